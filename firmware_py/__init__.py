"""On-board side (``magstack.firmware``): calibration model and fit, calibration tables, fixed-point
applier, sampling loop, health counters, effect catalogue.

Uses chips only through :class:`magstack.drivers.magnetometer.Magnetometer`; never an address.
"""
