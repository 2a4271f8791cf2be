"""HMC1053 AMR bridge triple as the analog inputs of the simulated ADS1248.

Per axis i (differential output wired to an AIN pair):

    V_i = G_ext * V_exc * (p * S_i * 1e-3 * B_i / 100 + O_i * 1e-3 * (1 + k_O * (T - 25)))

with ``p`` = +1 after a SET pulse and -1 after a RESET pulse (the field term flips, the
bridge offset ``O_i`` in mV/V does not; hardware-facts 5.3), ``S_i`` in mV/V/G
(1 G = 100 uT), ``B_i`` the sensed field in uT from the shared error model (noise, gain,
cross-axis, temperature, offsets that are real field...), ``V_exc`` the bridge excitation
and ``G_ext`` an optional amplifier gain in front of the ADC.

The set/reset strap is driven by one GPIO line through a pulse circuit: a rising edge
gives a SET pulse, a falling edge a RESET pulse (``strap_line``; ``set_on_rising_edge=False``
models the inverted circuit, as the front-end table's switch of the same name). The board temperature is
``truth.temp_c`` (read by the ADC's internal diode, or by an optional linear sensor on an AIN pair).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from magstack.drivers.errors import BusError, ConfigurationError
from magstack.firmware.effects import EFFECT_NAMES
from magstack.sim.gpio import SimOutputLine
from magstack.sim.i2c_register_model import IdealSensor  # noqa: F401  (re-exported: the noise-free bridge)

#: Bridge samples per field vector of the front end (X, Y, Z after SET, then after RESET).
CONVERSIONS_PER_VECTOR = 6

#: Effects the ADC model does itself (sequential skew, quantisation, clipping): off in the default sensor.
ADC_SIDE_EFFECTS = ("time_skew", "quantization", "saturation")


def default_sensor(seed: int = 0):
    """The shared error model with the ``hmc1053`` preset, minus the ADC-side effects.

    The preset's white noise describes the *reported* value (belsten Table 1), which is the
    set/reset half-difference of two independent conversions, i.e. sigma_conv / sqrt(2).
    The bridge draws noise once per conversion, so the white sigma is scaled by sqrt(2) here
    to make the front end's output reproduce the preset figure.
    """
    import dataclasses

    from magstack.sim.error_model import ErrorModel
    from magstack.sim.presets import preset

    params = preset("hmc1053")
    params = dataclasses.replace(params, noise_white_uT=np.asarray(params.noise_white_uT) * math.sqrt(2.0))
    return ErrorModel(params, seed=seed, effects=[n for n in EFFECT_NAMES if n not in ADC_SIDE_EFFECTS])


class HMC1053Bridge:
    """Bridge model implementing :class:`magstack.sim.ads1248_model.AnalogInputs`.

    ``offset_mV_per_V``: bridge offsets (default: drawn uniformly in +-1.25 mV/V from ``seed``);
    ``offset_tempco_per_c``: relative offset change per degC (does not flip, removed by set/reset);
    ``axis_pins``: (pos, neg) AIN pair per axis; ``temp_pins`` + ``temp_v_at_25c_V`` /
    ``temp_V_per_c``: an optional linear temperature sensor on an AIN pair;
    ``initial_polarity``: magnetisation state at power-on (+1 set, -1 reset);
    ``set_on_rising_edge``: pulse-circuit polarity (False: a falling edge fires SET).
    """

    def __init__(self, truth: Any, *, sensor: Any = None, seed: int = 0, excitation_V: float = 3.3,
                 sensitivity_mV_per_V_per_G: Sequence[float] = (1.0, 1.0, 1.0),
                 offset_mV_per_V: Sequence[float] | None = None, offset_tempco_per_c: float = 0.0,
                 external_gain: float = 1.0,
                 axis_pins: Sequence[tuple[int, int]] = ((0, 1), (2, 3), (4, 5)),
                 temp_pins: tuple[int, int] | None = None, temp_v_at_25c_V: float = 0.0,
                 temp_V_per_c: float = 0.0, initial_polarity: int = 1, set_on_rising_edge: bool = True) -> None:
        self.truth = truth
        self.sensor = sensor if sensor is not None else default_sensor(seed)
        if not callable(getattr(self.sensor, "sense", None)):
            raise ConfigurationError("sensor must have a sense(t_s, truth) method")
        sens = np.asarray(sensitivity_mV_per_V_per_G, dtype=float)
        if sens.shape != (3,) or not np.all(np.isfinite(sens)) or np.any(sens <= 0):
            raise ConfigurationError(f"sensitivity_mV_per_V_per_G must be 3 positive values, got {sens}")
        if offset_mV_per_V is None:
            offset_mV_per_V = np.random.default_rng(seed).uniform(-1.25, 1.25, 3)
        off = np.asarray(offset_mV_per_V, dtype=float)
        if off.shape != (3,) or not np.all(np.isfinite(off)):
            raise ConfigurationError(f"offset_mV_per_V must be 3 finite values, got {off}")
        for label, v in (("excitation_V", excitation_V), ("external_gain", external_gain)):
            if not (math.isfinite(v) and v > 0):
                raise ConfigurationError(f"{label} must be finite and > 0, got {v!r}")
        for label, v in (("offset_tempco_per_c", offset_tempco_per_c), ("temp_v_at_25c_V", temp_v_at_25c_V),
                         ("temp_V_per_c", temp_V_per_c)):
            if not math.isfinite(v):
                raise ConfigurationError(f"{label} must be finite, got {v!r}")
        if temp_pins is not None and temp_V_per_c == 0:
            raise ConfigurationError("a temperature sensor on temp_pins needs a nonzero temp_V_per_c")
        if initial_polarity not in (1, -1):
            raise ConfigurationError("initial_polarity must be +1 (set) or -1 (reset)")
        pins = [tuple(p) for p in axis_pins] + ([tuple(temp_pins)] if temp_pins is not None else [])
        flat = [x for p in pins for x in p]
        if len(set(flat)) != len(flat) or not all(0 <= x <= 7 for x in flat):
            raise ConfigurationError(f"AIN pins must be distinct and in 0..7, got {pins}")
        self.excitation_V = float(excitation_V)
        self.external_gain = float(external_gain)
        # volts of bridge output per uT of field (before polarity)
        self._v_per_uT = external_gain * excitation_V * sens * 1e-3 / 100.0
        self._offset_V = external_gain * excitation_V * off * 1e-3
        self.offset_mV_per_V = off
        self.offset_tempco_per_c = float(offset_tempco_per_c)
        self._pins = {tuple(p): i for i, p in enumerate(axis_pins)}
        self._temp_pins = tuple(temp_pins) if temp_pins is not None else None
        self._temp_v25 = float(temp_v_at_25c_V)
        self._temp_slope = float(temp_V_per_c)
        self.polarity = initial_polarity
        self.set_on_rising_edge = bool(set_on_rising_edge)
        self.set_pulses = 0
        self.reset_pulses = 0
        # the line idles at the level from which the SET edge starts
        self.strap_line = SimOutputLine("SR", self._on_strap, initial=not self.set_on_rising_edge)
        self._last_t: float | None = None
        self.sense_calls = 0
        self._recent: list[float] = []     # instants of the last CONVERSIONS_PER_VECTOR bridge samples

    def _on_strap(self, level: bool) -> None:
        if level == self.set_on_rising_edge:
            self.polarity = 1
            self.set_pulses += 1
        else:
            self.polarity = -1
            self.reset_pulses += 1

    def bridge_offset_V(self, axis: int, t_s: float) -> float:
        """The true (non-flipping) bridge offset of ``axis`` at ``t_s`` (for tests)."""
        dt = self.truth.temp_c(t_s) - 25.0
        return float(self._offset_V[axis] * (1.0 + self.offset_tempco_per_c * dt))

    def v_per_uT(self, axis: int) -> float:
        return float(self._v_per_uT[axis])

    def differential_V(self, pos: int, neg: int, t_s: float) -> float:
        key = (pos, neg)
        sign = 1.0
        if key not in self._pins and (neg, pos) in self._pins:
            key, sign = (neg, pos), -1.0
        if key in self._pins:
            axis = self._pins[key]
            # a premature read can ask for an instant before the last sample; the sensor model
            # needs non-decreasing time
            t = t_s if self._last_t is None or t_s >= self._last_t else self._last_t
            self._last_t = t
            self.sense_calls += 1
            self._prefetch(t)
            b_uT = self.sensor.sense(t, self.truth)[axis]
            v = self.polarity * self._v_per_uT[axis] * b_uT + self.bridge_offset_V(axis, t)
            return sign * float(v)
        if self._temp_pins is not None and key in (self._temp_pins, self._temp_pins[::-1]):
            s = 1.0 if key == self._temp_pins else -1.0
            return s * (self._temp_v25 + self._temp_slope * (self.truth.temp_c(t_s) - 25.0))
        raise BusError(f"AIN{pos}/AIN{neg} is not a wired pair on the simulated HMC1053 board",
                       address="sim-hmc1053", operation="convert")

    def temp_c(self, t_s: float) -> float:
        return float(self.truth.temp_c(t_s))

    def _prefetch(self, t: float) -> None:
        """With a memoising truth (:class:`~magstack.sim.truth_memo.TruthMemo`): at an instant it does not hold
        (the first conversion of a vector), evaluate this vector's conversions in one call, predicted as this
        instant plus the previous vector's offsets (the front end's timing repeats; a wrong guess costs one
        evaluation, never a wrong value)."""
        known = getattr(self.truth, "known", None)
        ahead = getattr(self.sensor, "prefetch", None)
        if known is None or ahead is None:
            return
        recent = self._recent
        if not known(t) and len(recent) == CONVERSIONS_PER_VECTOR:
            ahead([t] + [t + (r - recent[0]) for r in recent[1:]], self.truth)
        recent.append(t)
        if len(recent) > CONVERSIONS_PER_VECTOR:
            del recent[0]



@dataclass
class SimHMC1053Rig:
    """Everything of one simulated HMC1053 + ADS1248 board, for tests and benchmarks."""

    clock: Any
    truth: Any
    bridge: HMC1053Bridge
    adc_model: Any  # magstack.sim.ads1248_model.ADS1248Model
    spi: Any  # magstack.sim.spi_bus.SimSpiBus
    adc: Any  # magstack.drivers.ads1248.ADS1248
    front_end: Any  # magstack.drivers.hmc1053.HMC1053


def build_sim_hmc1053(clock: Any = None, *, truth: Any = None, sensor: Any = None, seed: int = 0,
                      table: Any = "hf8.2", bridge_kwargs: dict | None = None, adc_kwargs: dict | None = None,
                      spi_hz: int | None = None, reset: bool = True) -> SimHMC1053Rig:
    """Wire truth -> bridge -> ADS1248 model -> SimSpiBus/GPIO -> ADS1248 driver -> HMC1053 front end.

    The bridge's pins, excitation and gain follow ``table``; its sensitivity defaults to the
    table's nominal value (pass ``bridge_kwargs`` to make the simulated part differ).
    ``sensor`` defaults to the shared error model (:func:`default_sensor`).
    """
    from magstack.drivers.ads1248 import ADS1248, DEFAULT_SPI_HZ, SPI_MODE, lookup
    from magstack.drivers.clock import VirtualClock
    from magstack.drivers.hmc1053 import FRONT_ENDS, HMC1053
    from magstack.sim.ads1248_model import ADS1248Model
    from magstack.sim.spi_bus import SimSpiBus
    from magstack.sim.truth_source import StaticTruth

    clock = clock if clock is not None else VirtualClock()
    truth = truth if truth is not None else StaticTruth()
    tab = lookup(FRONT_ENDS, table, "front-end table") if isinstance(table, str) else table
    tab.validate()
    kw = dict(sensitivity_mV_per_V_per_G=tab.sensitivity_mV_per_V_per_G, excitation_V=tab.excitation_V,
              external_gain=tab.external_gain, axis_pins=tab.axis_pins, set_on_rising_edge=tab.set_on_rising_edge)
    if tab.temperature.kind == "linear":
        kw.update(temp_pins=(tab.temperature.pos, tab.temperature.neg),
                  temp_v_at_25c_V=tab.temperature.v_at_25c_V, temp_V_per_c=tab.temperature.V_per_c)
    kw.update(bridge_kwargs or {})
    bridge = HMC1053Bridge(truth, sensor=sensor, seed=seed, **kw)
    refs = {"REF0": "ref0_V", "REF1": "ref1_V"}
    ref_kw = {refs[tab.reference]: bridge.excitation_V} if tab.reference in refs else {}
    model = ADS1248Model(clock, bridge, seed=seed, **{**ref_kw, **(adc_kwargs or {})})
    spi = SimSpiBus(model, mode=SPI_MODE, max_speed_hz=spi_hz or DEFAULT_SPI_HZ, name="sim-spi0.0")
    adc = ADS1248(spi, clock, start=model.start_line, reset=model.reset_line, drdy=model.drdy_line, **ref_kw)
    fe = HMC1053(adc, bridge.strap_line, clock, tab, reset_adc=reset)
    return SimHMC1053Rig(clock, truth, bridge, model, spi, adc, fe)
