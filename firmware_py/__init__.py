"""On-board side: sampling loop, calibration tables and applier, batch refitter, health counters.

Uses chips only through :class:`drivers.magnetometer.Magnetometer`; never an address.
"""
