"""Serial transport: plain pyserial opened by URL.

``open_serial("/dev/ttyUSB0")`` and ``open_serial("fvm400sim://?seed=1")`` return the same
kind of object. Simulated instruments register their URL scheme as a pyserial protocol
handler package through the ``magstack.plugins`` entry point (see
:func:`magstack.drivers.registry.load_plugins`), so no driver code changes between them and this
layer never names the simulator.
"""
from __future__ import annotations

import serial

from magstack.drivers.errors import BusError


def open_serial(url: str, *, baudrate: int = 9600, timeout_s: float = 2.0, **kwargs) -> serial.SerialBase:
    """Open ``url`` (device path or ``scheme://``) with 8N1 framing."""
    if "://" in url:
        from magstack.drivers.registry import load_plugins

        load_plugins()
    try:
        return serial.serial_for_url(url, baudrate=baudrate, bytesize=8, parity="N", stopbits=1,
                                     timeout=timeout_s, **kwargs)
    except (serial.SerialException, ValueError, OSError) as exc:
        raise BusError(f"cannot open serial port {url!r}: {exc}", address=url, operation="open") from exc
