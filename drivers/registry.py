"""Chip factory: chip name + bus spec -> a :class:`~magstack.drivers.magnetometer.Magnetometer`.

``open_chip(chip, bus_spec, clock, **config)``. The bus spec chooses a *backend*:

* a real bus: I2C ``"1"`` or ``"/dev/i2c-1"`` (smbus2), HMC1053 ``"spiB.C[,start=N,...]"``
  (spidev + lgpio) - the ``linux`` backend defined here;
* ``"sim"`` (or ``"sim:<anything>"``) - the simulated bench, a backend that the simulator
  registers through the ``magstack.plugins`` entry point (``magstack.sim.backends``), so this
  layer never imports or names the simulator's modules.

The real adapters (smbus2, spidev, lgpio) are created here, never in a driver, and only when a
chip is opened, so a missing optional package does not break the others.
"""
from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from magstack.drivers.errors import ConfigurationError

#: Chips every backend must know (the CLI's ``--chip`` choices).
CHIPS = ("hmc1053", "hmc5983", "lis3mdl", "lsm303dlhc")


@dataclass(frozen=True)
class Backend:
    """What a backend provides.

    ``open_chip(chip, bus_spec, clock, **config) -> Magnetometer``; ``i2c_buses(bus_spec)`` -> list of
    ``(name, I2CBus)`` to scan; ``make_clock()`` -> the clock its devices run on (system or virtual).
    """

    open_chip: Callable[..., Any]
    i2c_buses: Callable[[str], list[tuple[str, Any]]]
    make_clock: Callable[[], Any]


_BACKENDS: dict[str, Backend] = {}
_PLUGINS_LOADED = False


def register_backend(name: str, backend: Backend) -> None:
    """Register ``backend`` for bus specs ``name`` and ``name:...`` (a plugin calls this)."""
    _BACKENDS[name] = backend


def load_plugins() -> None:
    """Load every ``magstack.plugins`` entry point once (each registers its backends/URL schemes)."""
    global _PLUGINS_LOADED
    if _PLUGINS_LOADED:
        return
    _PLUGINS_LOADED = True
    from importlib.metadata import entry_points

    for ep in entry_points(group="magstack.plugins"):
        ep.load()()


def backend_name(bus_spec: str) -> str:
    """``"sim"``/``"sim:x"`` -> ``"sim"``; every real bus spec -> ``"linux"``."""
    head = str(bus_spec).strip().lower().partition(":")[0]
    if head in _BACKENDS:
        return head
    load_plugins()
    return head if head in _BACKENDS else "linux"


def is_simulated(bus_spec: str) -> bool:
    """True when ``bus_spec`` names a registered non-hardware backend."""
    return backend_name(bus_spec) != "linux"


def chip_names() -> list[str]:
    """Chip names (for CLI ``choices``)."""
    return sorted(CHIPS)


def open_chip(chip: str, bus_spec: str, clock: Any = None, **config: Any):
    """Open ``chip`` on ``bus_spec`` with ``clock``; ``config`` goes to the backend and driver."""
    if chip not in CHIPS:
        raise ConfigurationError(f"unknown chip {chip!r}; valid: {', '.join(chip_names())}")
    return _BACKENDS[backend_name(bus_spec)].open_chip(chip, bus_spec, clock, **config)


def i2c_buses(bus_spec: str) -> list[tuple[str, Any]]:
    """The I2C bus(es) ``bus_spec`` names, as ``(name, bus)`` pairs (the caller closes real ones)."""
    return _BACKENDS[backend_name(bus_spec)].i2c_buses(bus_spec)


def clock_for(bus_spec: str):
    """A new clock of the kind devices on ``bus_spec`` run on (``SystemClock``, or virtual in simulation)."""
    return _BACKENDS[backend_name(bus_spec)].make_clock()


# ----------------------------------------------------------------------------- linux backend
_I2C_RE = re.compile(r"^(?:/dev/i2c-)?(\d+)$")


def parse_i2c_bus(bus_spec: str) -> int:
    """``"/dev/i2c-1"`` or ``"1"`` -> 1; anything else raises ConfigurationError."""
    m = _I2C_RE.match(str(bus_spec).strip())
    if not m:
        raise ConfigurationError(f"bad I2C bus {bus_spec!r}; valid: 'sim', 'N' or '/dev/i2c-N'")
    return int(m.group(1))


def open_i2c_bus(bus_spec: str):
    """The real smbus2 adapter for ``bus_spec`` (``"1"`` or ``"/dev/i2c-1"``)."""
    from magstack.drivers.bus.i2c import SMBus2I2CBus

    return SMBus2I2CBus(parse_i2c_bus(bus_spec))


#: Default BCM pins: START/RESET/DRDY from the MagEval runMe.py wiring [F:MIT-DRV]; SR is ours.
DEFAULT_PINS = {"start": 6, "reset": 13, "drdy": 19, "sr": 5}
_SPI_RE = re.compile(r"^spi(\d+)\.(\d+)((?:,[a-z]+=\d+)*)$")
_SPI_KEYS = set(DEFAULT_PINS) | {"chip", "hz"}


def parse_spi_spec(bus_spec: str) -> tuple[int, int, dict[str, int]]:
    """``"spi0.0,sr=5"`` -> (0, 0, {pins..., "chip": 0, "hz": 1000000}); bad specs raise ConfigurationError."""
    from magstack.drivers.ads1248 import DEFAULT_SPI_HZ

    m = _SPI_RE.match(str(bus_spec).strip().lower())
    if not m:
        raise ConfigurationError(f"bad HMC1053 bus {bus_spec!r}; valid: 'sim' or "
                                 f"'spiB.C[,start=N][,reset=N][,drdy=N][,sr=N][,chip=N][,hz=N]'")
    opts: dict[str, int] = {**DEFAULT_PINS, "chip": 0, "hz": DEFAULT_SPI_HZ}
    for item in filter(None, m.group(3).split(",")):
        key, _, value = item.partition("=")
        if key not in _SPI_KEYS:
            raise ConfigurationError(f"unknown option {key!r} in {bus_spec!r}; valid: {', '.join(sorted(_SPI_KEYS))}")
        opts[key] = int(value)
    pins = [opts[k] for k in DEFAULT_PINS]
    if len(set(pins)) != len(pins):
        raise ConfigurationError(f"GPIO pins must be distinct, got {dict((k, opts[k]) for k in DEFAULT_PINS)}")
    return int(m.group(1)), int(m.group(2)), opts


def _system_clock(clock):
    if clock is not None:
        return clock
    from magstack.drivers.clock import SystemClock

    return SystemClock()


def _driver_class(chip: str) -> Callable[..., Any]:
    if chip == "lis3mdl":
        from magstack.drivers.lis3mdl import LIS3MDL

        return LIS3MDL
    if chip == "hmc5983":
        from magstack.drivers.hmc5983 import HMC5983

        return HMC5983
    from magstack.drivers.lsm303dlhc import LSM303DLHC

    return LSM303DLHC


def i2c_driver_class(chip: str) -> Callable[..., Any]:
    """The driver class of an I2C chip (``lis3mdl``, ``hmc5983``, ``lsm303dlhc``)."""
    if chip not in ("lis3mdl", "hmc5983", "lsm303dlhc"):
        raise ConfigurationError(f"{chip!r} is not an I2C chip")
    return _driver_class(chip)


def open_hmc1053_linux(bus_spec: str, clock: Any = None, *, table: Any = "hf8.2", **kwargs: Any):
    """HMC1053 + ADS1248 on ``/dev/spidevB.C`` (mode 1) with lgpio lines (BCM numbers)."""
    if kwargs:
        raise ConfigurationError(f"options {sorted(kwargs)} only apply to the simulated bus")
    bus, dev, opts = parse_spi_spec(bus_spec)
    from magstack.drivers.ads1248 import ADS1248, SPI_MODE, lookup
    from magstack.drivers.bus.gpio import LgpioInputLine, LgpioOutputLine
    from magstack.drivers.bus.spi import SpidevSpiBus
    from magstack.drivers.hmc1053 import FRONT_ENDS, HMC1053

    clock = _system_clock(clock)
    tab = (lookup(FRONT_ENDS, table, "front-end table") if isinstance(table, str) else table).validate()
    # a ratiometric board uses the bridge excitation as the ADC reference
    ref_kw = {{"REF0": "ref0_V", "REF1": "ref1_V"}[tab.reference]: tab.excitation_V} \
        if tab.reference in ("REF0", "REF1") else {}
    spi = SpidevSpiBus(bus, dev, mode=SPI_MODE, max_speed_hz=opts["hz"])
    chip = opts["chip"]
    start = LgpioOutputLine(opts["start"], chip=chip, initial=False)
    reset = LgpioOutputLine(opts["reset"], chip=chip, initial=True)
    drdy = LgpioInputLine(opts["drdy"], chip=chip)
    sr = LgpioOutputLine(opts["sr"], chip=chip, initial=False)
    adc = ADS1248(spi, clock, start=start, reset=reset, drdy=drdy, **ref_kw)
    return HMC1053(adc, sr, clock, tab)


def _open_linux(chip: str, bus_spec: str, clock: Any = None, **config: Any):
    if chip == "hmc1053":
        return open_hmc1053_linux(bus_spec, clock, **config)
    return _driver_class(chip)(open_i2c_bus(bus_spec), _system_clock(clock), **config)


def _linux_i2c_buses(bus_spec: str) -> list[tuple[str, Any]]:
    bus = open_i2c_bus(bus_spec)
    return [(bus.name, bus)]


register_backend("linux", Backend(_open_linux, _linux_i2c_buses, lambda: _system_clock(None)))
