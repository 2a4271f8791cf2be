"""Chip name -> driver factory, imported lazily.

Each entry is a ``"module:function"`` string naming a factory
``open_<chip>(bus_spec: str, clock) -> Magnetometer``. ``bus_spec`` is ``"sim"`` (the
default simulated bench, :mod:`sim.i2c_bench`) or a real bus (``"/dev/i2c-1"`` or ``"1"``).
The real I2C adapter (:class:`drivers.bus.i2c.SMBus2I2CBus`) is created here, never in a
driver. Modules are only imported when a chip is opened, so a missing optional component
does not break the others.
"""
from __future__ import annotations

import importlib
import re
from collections.abc import Callable
from typing import Any

from drivers.errors import ConfigurationError

CHIP_FACTORIES: dict[str, str] = {
    "lis3mdl": "hil.chip_registry:open_lis3mdl",
    "hmc5983": "hil.chip_registry:open_hmc5983",
    "lsm303dlhc": "hil.chip_registry:open_lsm303dlhc",
    "hmc1053": "hil.front_end_setup:open_hmc1053",
}


def chip_names() -> list[str]:
    """Registered chip names (for CLI ``choices``)."""
    return sorted(CHIP_FACTORIES)


def factory(chip: str) -> Callable[..., Any]:
    """Resolve the factory of ``chip`` (imports its module now)."""
    try:
        target = CHIP_FACTORIES[chip]
    except KeyError:
        raise ConfigurationError(f"unknown chip {chip!r}; valid: {', '.join(chip_names())}") from None
    module_name, _, func_name = target.partition(":")
    module = importlib.import_module(module_name)
    return getattr(module, func_name)


def open_chip(chip: str, bus_spec: str, clock, **kwargs):
    """Open ``chip`` on ``bus_spec`` with ``clock``; extra keyword arguments go to the factory."""
    return factory(chip)(bus_spec, clock, **kwargs)


_BUS_RE = re.compile(r"^(?:/dev/i2c-)?(\d+)$")


def parse_i2c_bus(bus_spec: str) -> int:
    """``"/dev/i2c-1"`` or ``"1"`` -> 1; anything else raises ConfigurationError."""
    m = _BUS_RE.match(str(bus_spec).strip())
    if not m:
        raise ConfigurationError(f"bad I2C bus {bus_spec!r}; valid: 'sim', 'N' or '/dev/i2c-N'")
    return int(m.group(1))


def open_i2c_bus(bus_spec: str):
    """The real smbus2 adapter for ``bus_spec`` (``"1"`` or ``"/dev/i2c-1"``)."""
    from drivers.bus.i2c import SMBus2I2CBus

    return SMBus2I2CBus(parse_i2c_bus(bus_spec))


def _bus_clock_address(chip: str, bus_spec: str, clock, bench):
    """(bus, clock, address or None) for ``chip`` on ``bus_spec``."""
    if str(bus_spec).strip().lower() == "sim":
        from sim.i2c_bench import default_bench

        b = bench if bench is not None else default_bench(clock=clock)
        return b.bus_for(chip), b.clock, b.address(chip)
    if clock is None:
        from drivers.clock import SystemClock

        clock = SystemClock()
    return open_i2c_bus(bus_spec), clock, None


def _open(cls, chip: str, bus_spec: str, clock, bench, config):
    bus, clk, address = _bus_clock_address(chip, bus_spec, clock, bench)
    if address is not None:
        config.setdefault("address", address)
    return cls(bus, clk, **config)


def open_lis3mdl(bus_spec: str, clock=None, *, bench=None, **config):
    """LIS3MDL driver on ``bus_spec`` ("sim" or an I2C bus); ``config`` goes to the driver
    (address, range_uT, odr_hz, performance, mode, ...)."""
    from drivers.lis3mdl import LIS3MDL

    return _open(LIS3MDL, "lis3mdl", bus_spec, clock, bench, config)


def open_hmc5983(bus_spec: str, clock=None, *, bench=None, **config):
    """HMC5983 driver on ``bus_spec``; ``config`` goes to the driver (range_uT, odr_hz, averaging, ...)."""
    from drivers.hmc5983 import HMC5983

    return _open(HMC5983, "hmc5983", bus_spec, clock, bench, config)


def open_lsm303dlhc(bus_spec: str, clock=None, *, bench=None, **config):
    """LSM303DLHC magnetometer driver on ``bus_spec``; ``config`` goes to the driver."""
    from drivers.lsm303dlhc import LSM303DLHC

    return _open(LSM303DLHC, "lsm303dlhc", bus_spec, clock, bench, config)
