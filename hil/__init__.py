"""Hardware in the loop: the bench runner (a DUT and a reference side by side into a session file)
and the Raspberry Pi wiring notes (hil/README.md). Uses drivers, data and, for the simulated bench,
sim; only the CLI imports it.
"""
