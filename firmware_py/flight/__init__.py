"""The flight application (``magstack run``): an executive dividing one tick source into rate groups,
a magnetometer channel per configured sensor, fixed-point calibration from the active table,
telemetry written as session files, events with stable ids, and commands applied at cycle
boundaries. Components own no timers: each exposes ``run(now_s)``. See docs/flight.md.
"""
