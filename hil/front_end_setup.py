"""Factory for the HMC1053 + ADS1248 front end: ``open_hmc1053(bus_spec, clock)``.

``bus_spec``:

* ``"sim"`` - simulated board (:func:`sim.hmc1053_bridge.build_sim_hmc1053`): truth source
  (default :class:`sim.truth_source.StaticTruth`) -> shared error model -> bridge -> ADS1248
  model on a simulated SPI bus and GPIO lines, in virtual time.
* ``"spiB.C"`` optionally followed by ``,key=value`` items, e.g.
  ``"spi0.0,start=6,reset=13,drdy=19,sr=5,chip=0,hz=1000000"`` - real ``/dev/spidevB.C``
  (:class:`drivers.bus.spi.SpidevSpiBus`, mode 1) and lgpio lines (BCM numbers). START=6,
  RESET=13, DRDY=19 are the MagEval wiring (hardware-facts 7.1); the set/reset strap pin is
  not in any source: ``sr=5`` is this project's bench wiring (docs/hmc1053-front-end.md).
"""
from __future__ import annotations

import re
from typing import Any

from drivers.errors import ConfigurationError

#: Default BCM pins: START/RESET/DRDY from the MagEval runMe.py wiring [F:MIT-DRV]; SR is ours.
DEFAULT_PINS = {"start": 6, "reset": 13, "drdy": 19, "sr": 5}
_SPI_RE = re.compile(r"^spi(\d+)\.(\d+)((?:,[a-z]+=\d+)*)$")
_KEYS = set(DEFAULT_PINS) | {"chip", "hz"}


def parse_spi_spec(bus_spec: str) -> tuple[int, int, dict[str, int]]:
    """``"spi0.0,sr=5"`` -> (0, 0, {pins..., "chip": 0, "hz": 1000000}); bad specs raise ConfigurationError."""
    from drivers.ads1248 import DEFAULT_SPI_HZ

    m = _SPI_RE.match(str(bus_spec).strip().lower())
    if not m:
        raise ConfigurationError(f"bad HMC1053 bus {bus_spec!r}; valid: 'sim' or "
                                 f"'spiB.C[,start=N][,reset=N][,drdy=N][,sr=N][,chip=N][,hz=N]'")
    opts: dict[str, int] = {**DEFAULT_PINS, "chip": 0, "hz": DEFAULT_SPI_HZ}
    for item in filter(None, m.group(3).split(",")):
        key, _, value = item.partition("=")
        if key not in _KEYS:
            raise ConfigurationError(f"unknown option {key!r} in {bus_spec!r}; valid: {', '.join(sorted(_KEYS))}")
        opts[key] = int(value)
    pins = [opts[k] for k in DEFAULT_PINS]
    if len(set(pins)) != len(pins):
        raise ConfigurationError(f"GPIO pins must be distinct, got {dict((k, opts[k]) for k in DEFAULT_PINS)}")
    return int(m.group(1)), int(m.group(2)), opts


def open_hmc1053(bus_spec: str, clock: Any = None, *, table: Any = "hf8.2", truth: Any = None,
                 sensor: Any = None, seed: int = 0, **kwargs: Any):
    """Open the HMC1053 front end on ``bus_spec`` (see module doc); returns a Magnetometer.

    Simulation only: ``truth``, ``sensor`` (default: shared error model, preset ``hmc1053``),
    ``seed`` and ``bridge_kwargs``/``adc_kwargs`` for :func:`sim.hmc1053_bridge.build_sim_hmc1053`.
    """
    if str(bus_spec).strip().lower() == "sim":
        from sim.hmc1053_bridge import build_sim_hmc1053

        rig = build_sim_hmc1053(clock, truth=truth, sensor=sensor, seed=seed, table=table, **kwargs)
        front_end = rig.front_end
        front_end.sim_rig = rig  # access to the simulated board for tools and tests
        return front_end
    if kwargs:
        raise ConfigurationError(f"options {sorted(kwargs)} only apply to the simulated bus")
    bus, dev, opts = parse_spi_spec(bus_spec)
    from drivers.ads1248 import ADS1248, SPI_MODE, lookup
    from drivers.bus.gpio import LgpioInputLine, LgpioOutputLine
    from drivers.bus.spi import SpidevSpiBus
    from drivers.hmc1053 import FRONT_ENDS, HMC1053

    if clock is None:
        from drivers.clock import SystemClock

        clock = SystemClock()
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
