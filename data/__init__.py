"""Data layer: the session / telemetry file format (the project's data contract), merging several
files, splitting DUT and reference rows, atomic writes and NumPy-safe JSON.

Sits beneath the on-board code (the flight application writes telemetry as session files and the
refitter reads them), the simulators and ground analysis; imports only ``magstack.drivers`` and
``magstack.errors``.
"""
