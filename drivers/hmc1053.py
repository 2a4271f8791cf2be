"""HMC1053 AMR front end on an ADS1248: set/reset acquisition cycle -> :class:`MagSample`.

Cycle (one :meth:`HMC1053.read`): SET pulse, convert X, Y, Z; RESET pulse, convert X, Y, Z;
convert temperature (or, with ``temp_in_both_states``, temperature after each axis triple,
i.e. 8 conversions, the 0.4 s cycle of belsten 2.1). Per axis::

    field_uT  = (V_set - V_reset) / 2 / (G_ext * V_exc * S * 1e-3 / 100)   # S in mV/V/G
    offset_V  = (V_set + V_reset) / 2                                     # health telemetry

Times: every conversion has its own window (filter restart -> DRDY); its instant is the
window centre. The per-axis instant reported in ``MagSample.axis_t_s`` is the **mean of the
set-state and reset-state conversion instants** of that axis (for a field changing
linearly in time, (V_set - V_reset)/2 measures the field at exactly that instant); both
instants are kept in ``extra["axis_t_set_s"]`` / ``extra["axis_t_reset_s"]``.
``MagSample.t_s`` is the mean of the three axis instants.

Channel layout, excitation, sensitivity and gains come from a frozen :class:`FrontEndTable`
(:data:`FRONT_ENDS`); hardware-facts 8.2 is only the default layout.

Temperature: the table's :class:`TempChannel` is the ADS1248 internal diode (its coefficients are
unverified forum figures, ``verified=False``) or an external sensor with its own linear transfer
function on a mux pair (the belsten bench read an external sensor). :class:`TempCalibration` fits
the reported temperature against a reference thermometer (two points or a linear least-squares
fit over a bench session) and :meth:`HMC1053.calibrate_temperature` folds it into the board
table; every sample says whether its temperature is calibrated (``extra["temp_verified"]``).
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from types import MappingProxyType

import numpy as np

from magstack.drivers.ads1248 import (
    ADS1248,
    DATA_RATES,
    PGA_CODES,
    TEMP_DIODE_V_AT_25C,
    TEMP_DIODE_V_PER_C,
    ChannelConfig,
    Conversion,
    diode_temp_c,
    lookup,
)
from magstack.drivers.bus.gpio import OutputLine
from magstack.drivers.clock import Clock
from magstack.drivers.errors import ConfigurationError
from magstack.drivers.magnetometer import MagSample

#: Temperature channel kinds: the ADC's internal diode (MUXCAL=011) or a linear sensor on an AIN pair.
TEMP_KINDS = ("adc_diode", "linear")


@dataclass(frozen=True)
class TempChannel:
    """``linear``: T = 25 + (V - v_at_25c_V) / V_per_c on AIN ``pos``/``neg``; ``adc_diode``: the ADS1248
    diode, by the same formula with the forum coefficients (118 mV, 405 uV/degC [F2], unverified) while
    both constants are 0.0 (default), or with a per-board calibration when both are given.

    ``verified``: the transfer function was calibrated against a reference on this board;
    ``source``: where the coefficients come from (shown in sample metadata)."""

    kind: str = "adc_diode"
    pos: int = 6
    neg: int = 7
    pga: int = 1
    v_at_25c_V: float = 0.0
    V_per_c: float = 0.0
    verified: bool = False
    source: str = "ADS1248 internal diode, forum coefficients (E2E 249199), unverified"

    def coefficients(self) -> tuple[float, float]:
        """(volts at 25 degC, volts per degC) in use."""
        if self.kind == "adc_diode" and (self.v_at_25c_V, self.V_per_c) == (0.0, 0.0):
            return TEMP_DIODE_V_AT_25C, TEMP_DIODE_V_PER_C
        return self.v_at_25c_V, self.V_per_c

    def temp_c(self, volts: float) -> float:
        v25, slope = self.coefficients()
        if self.kind == "adc_diode":
            return diode_temp_c(volts, v25, slope)
        return 25.0 + (volts - v25) / slope


@dataclass(frozen=True)
class TempCalibration:
    """A linear correction of a temperature channel: ``T_ref = gain * T_reported + offset_c`` (degC).

    Fitted from pairs of reported and reference temperatures: two points give the line through
    them, more a least-squares line (``rms_c`` its residual). :meth:`fit_session` pairs a bench
    session's temperature column with reference readings taken at other instants.
    """

    gain: float
    offset_c: float
    n_points: int
    rms_c: float
    span_c: float
    source: str = ""

    @classmethod
    def fit(cls, reported_c: Sequence[float], reference_c: Sequence[float], *, source: str = "",
            min_span_c: float = 1.0) -> TempCalibration:
        """Least-squares line through (reported, reference); ConfigurationError when the data cannot
        determine it (fewer than two finite pairs, or a reported span below ``min_span_c``)."""
        x = np.asarray(reported_c, dtype=float).ravel()
        y = np.asarray(reference_c, dtype=float).ravel()
        if x.shape != y.shape:
            raise ConfigurationError(f"temperature calibration: {x.size} reported vs {y.size} reference values")
        ok = np.isfinite(x) & np.isfinite(y)
        x, y = x[ok], y[ok]
        if x.size < 2:
            raise ConfigurationError(f"temperature calibration needs at least 2 finite pairs, got {x.size}")
        span = float(np.ptp(x))
        if not span >= min_span_c:
            raise ConfigurationError(f"temperature calibration: reported temperatures span {span:.3g} degC, "
                                     f"need at least {min_span_c:g} degC to determine a slope")
        gain, offset = np.polyfit(x, y, 1)
        # a negative gain is legitimate: a diode read with a slope of the wrong sign (the forum's own
        # measurement fell when the board warmed) reports temperatures that fall as the truth rises
        if not (math.isfinite(gain) and abs(gain) > 1e-9):
            raise ConfigurationError(f"temperature calibration: fitted gain {gain!r} cannot be inverted")
        rms = float(np.sqrt(np.mean((gain * x + offset - y) ** 2)))
        return cls(float(gain), float(offset), int(x.size), rms, span, source)

    @classmethod
    def fit_session(cls, t_s: Sequence[float], temp_c: Sequence[float], ref_t_s: Sequence[float],
                    ref_temp_c: Sequence[float], *, source: str = "", **kw) -> TempCalibration:
        """Fit from a bench session's ``(t_s, temp_c)`` rows and reference readings ``(ref_t_s, ref_temp_c)``
        (same clock): the session temperature is interpolated at each reference instant inside it."""
        t = np.asarray(t_s, dtype=float)
        tc = np.asarray(temp_c, dtype=float)
        ok = np.isfinite(t) & np.isfinite(tc)
        t, tc = t[ok], tc[ok]
        if t.size < 2:
            raise ConfigurationError("temperature calibration: the session has fewer than 2 rows with a temperature")
        order = np.argsort(t)
        t, tc = t[order], tc[order]
        rt = np.asarray(ref_t_s, dtype=float)
        rc = np.asarray(ref_temp_c, dtype=float)
        if rt.shape != rc.shape:
            raise ConfigurationError(f"temperature calibration: {rt.size} reference times vs {rc.size} values")
        inside = np.isfinite(rt) & (rt >= t[0]) & (rt <= t[-1])
        return cls.fit(np.interp(rt[inside], t, tc), rc[inside], source=source, **kw)

    def apply(self, temp_c: float | None) -> float | None:
        """Corrected degC (None stays None)."""
        return None if temp_c is None else self.gain * temp_c + self.offset_c

    def apply_to_channel(self, ch: TempChannel) -> TempChannel:
        """The channel whose transfer function reports ``apply(old reported)``: same volts, new coefficients.

        Reported T = 25 + (V - v25) / k; calibrated T' = g T + o. Then k' = k / g, and v25' is the
        voltage at which T' = 25, i.e. where the old channel reported (25 - o) / g.
        """
        v25, k = ch.coefficients()
        k_new = k / self.gain
        t_rep_at_25 = (25.0 - self.offset_c) / self.gain
        v25_new = v25 + k * (t_rep_at_25 - 25.0)
        return replace(ch, v_at_25c_V=float(v25_new), V_per_c=float(k_new), verified=True,
                       source=self.describe())

    def describe(self) -> str:
        return (f"calibrated T = {self.gain:.6g} * T_reported + {self.offset_c:.6g} degC from {self.n_points} "
                f"points over {self.span_c:.3g} degC (rms {self.rms_c:.3g} degC)"
                + (f"; {self.source}" if self.source else ""))


@dataclass(frozen=True)
class FrontEndTable:
    """One board configuration. ``axis_pins``: (AIN+, AIN-) for X, Y, Z; ``reference``: ADS1248
    REFSELT name ("internal" 2.048 V, or "REF0"/"REF1" with the voltage given to the ADC driver);
    ``external_gain``: amplifier gain between bridge and ADC; ``strap_settle_s``: wait after a
    set/reset pulse before the next conversion starts; ``set_on_rising_edge``: strap circuit polarity.
    """

    name: str
    axis_pins: tuple[tuple[int, int], tuple[int, int], tuple[int, int]] = ((0, 1), (2, 3), (4, 5))
    excitation_V: float = 3.3
    sensitivity_mV_per_V_per_G: tuple[float, float, float] = (1.0, 1.0, 1.0)
    external_gain: float = 1.0
    pga: int = 128
    data_rate_sps: int = 20
    reference: str = "internal"
    temperature: TempChannel = field(default_factory=TempChannel)
    temp_in_both_states: bool = False
    strap_settle_s: float = 50e-6
    set_on_rising_edge: bool = True

    def validate(self) -> FrontEndTable:
        """Raise ConfigurationError naming the bad entry; return self."""
        if len(self.axis_pins) != 3:
            raise ConfigurationError(f"{self.name}: axis_pins needs 3 (pos, neg) pairs")
        pins = [p for pair in self.axis_pins for p in pair]
        if self.temperature.kind not in TEMP_KINDS:
            raise ConfigurationError(f"{self.name}: temperature kind {self.temperature.kind!r}; "
                                     f"valid: {', '.join(TEMP_KINDS)}")
        tv, ts = self.temperature.v_at_25c_V, self.temperature.V_per_c
        if self.temperature.kind == "adc_diode" and (tv, ts) != (0.0, 0.0) and not (
                math.isfinite(tv) and tv != 0.0 and math.isfinite(ts) and ts != 0.0):
            raise ConfigurationError(f"{self.name}: a diode calibration needs both v_at_25c_V and V_per_c "
                                     f"(finite, nonzero), got {tv!r}, {ts!r}; 0.0 and 0.0 = forum values")
        if self.temperature.kind == "linear":
            pins += [self.temperature.pos, self.temperature.neg]
            if not self.temperature.V_per_c or not math.isfinite(self.temperature.V_per_c):
                raise ConfigurationError(f"{self.name}: linear temperature sensor needs a nonzero V_per_c")
            if not math.isfinite(self.temperature.v_at_25c_V):
                raise ConfigurationError(f"{self.name}: linear temperature sensor needs a finite v_at_25c_V, "
                                         f"got {self.temperature.v_at_25c_V!r}")
        if len(set(pins)) != len(pins) or not all(isinstance(p, int) and 0 <= p <= 7 for p in pins):
            raise ConfigurationError(f"{self.name}: AIN pins must be distinct integers 0..7, got {pins}")
        sens = self.sensitivity_mV_per_V_per_G
        if len(sens) != 3 or not all(math.isfinite(s) and s > 0 for s in sens):
            raise ConfigurationError(f"{self.name}: sensitivity_mV_per_V_per_G must be 3 positive values")
        for nm in ("excitation_V", "external_gain"):
            v = getattr(self, nm)
            if not (math.isfinite(v) and v > 0):
                raise ConfigurationError(f"{self.name}: {nm} must be > 0, got {v!r}")
        if not (math.isfinite(self.strap_settle_s) and self.strap_settle_s >= 0):
            raise ConfigurationError(f"{self.name}: strap_settle_s must be >= 0")
        lookup(PGA_CODES, self.pga, "PGA gain")
        lookup(PGA_CODES, self.temperature.pga, "temperature PGA gain")
        lookup(DATA_RATES, self.data_rate_sps, "data rate (SPS)")
        for ch in self.channels():
            ch.register_bytes()
        return self

    def axis_channel(self, axis: int) -> ChannelConfig:
        pos, neg = self.axis_pins[axis]
        return ChannelConfig(pos=pos, neg=neg, pga=self.pga, data_rate_sps=self.data_rate_sps,
                             reference=self.reference, vrefcon="on")

    def temp_channel(self) -> ChannelConfig:
        t = self.temperature
        if t.kind == "adc_diode":  # the diode needs the internal reference
            return ChannelConfig(pos=0, neg=1, pga=t.pga, data_rate_sps=self.data_rate_sps,
                                 reference="internal", vrefcon="on", muxcal="temperature")
        return ChannelConfig(pos=t.pos, neg=t.neg, pga=t.pga, data_rate_sps=self.data_rate_sps,
                             reference=self.reference, vrefcon="on")

    def channels(self) -> tuple[ChannelConfig, ...]:
        return tuple(self.axis_channel(i) for i in range(3)) + (self.temp_channel(),)

    def v_per_uT(self, axis: int) -> float:
        """Bridge volts at the ADC input per uT of field (1 G = 100 uT)."""
        return self.external_gain * self.excitation_V * self.sensitivity_mV_per_V_per_G[axis] * 1e-3 / 100.0

    def conversions_per_cycle(self) -> int:
        return 8 if self.temp_in_both_states else 7

    def nominal_cycle_s(self) -> float:
        """Datasheet arithmetic: conversions x first-result-after-MUX-write + 2 strap settles."""
        rate = DATA_RATES[self.data_rate_sps]
        return self.conversions_per_cycle() * rate.first_after_write_s + 2 * self.strap_settle_s


#: Board tables. "hf8.2": the hardware-facts 8.2 layout (X AIN0/1, Y AIN2/3, Z AIN4/5), internal
#: 2.048 V reference, PGA 128 (+-16 mV), 3.3 V bridge, nominal 1 mV/V/G, internal temperature
#: diode, 7-conversion cycle. "hf8.2-8conv": same, temperature read in both states (8 conversions).
FRONT_ENDS: Mapping[str, FrontEndTable] = MappingProxyType({
    "hf8.2": FrontEndTable("hf8.2").validate(),
    "hf8.2-8conv": FrontEndTable("hf8.2-8conv", temp_in_both_states=True).validate(),
    # an external linear sensor on AIN6/AIN7, as the belsten bench read its temperature on a mux
    # channel; the coefficients are placeholders of a typical analog sensor (0.75 V at 25 degC,
    # 10 mV/degC) [I]: calibrate them on the bench (TempCalibration) before trusting the reading
    "hf8.2-ext-temp": FrontEndTable("hf8.2-ext-temp", temperature=TempChannel(
        "linear", pos=6, neg=7, pga=1, v_at_25c_V=0.75, V_per_c=0.010, verified=False,
        source="external linear sensor on AIN6/AIN7, placeholder coefficients, unverified")).validate(),
})
DEFAULT_FRONT_END = "hf8.2"


class HMC1053:
    """Magnetometer front end. ``adc`` is an :class:`ADS1248` driver, ``strap`` the GPIO line
    that fires the set/reset pulse circuit (edge-triggered), ``table`` a :class:`FrontEndTable`
    or the name of one in :data:`FRONT_ENDS`. ``reset_adc`` resets and brings up the ADC now.
    """

    name = "hmc1053"

    def __init__(self, adc: ADS1248, strap: OutputLine, clock: Clock,
                 table: FrontEndTable | str = DEFAULT_FRONT_END, *, reset_adc: bool = True) -> None:
        if isinstance(table, str):
            table = lookup(FRONT_ENDS, table, "front-end table")
        self.table = table.validate()
        self.adc = adc
        self.strap = strap
        self.clock = clock
        self._axis_ch = tuple(table.axis_channel(i) for i in range(3))
        self._temp_ch = table.temp_channel()
        self._v_per_uT = tuple(table.v_per_uT(i) for i in range(3))
        self._idle_level = not table.set_on_rising_edge  # the level from which the SET edge starts
        self.strap.set(self._idle_level)
        self._strap_level = self._idle_level
        self.cycles = 0
        if reset_adc:
            self.adc.reset()

    def reinit(self) -> None:
        """Recover after persistent faults (the sampling loop calls this): reset and bring up the ADC
        again, and return the strap line to its idle level so the next cycle's SET edge is clean.
        The ADC's bus errors propagate (typed) so the caller can count them."""
        self.strap.set(self._idle_level)
        self._strap_level = self._idle_level
        self.adc.reset()

    def with_table(self, **changes) -> FrontEndTable:
        """A validated copy of the current table with ``changes`` (does not apply it)."""
        return replace(self.table, **changes).validate()

    def data_ready(self) -> bool:
        """Always True: the front end converts on demand, :meth:`read` runs one full cycle."""
        return True

    def _pulse(self, set_pulse: bool) -> None:
        level = (not self._idle_level) if set_pulse else self._idle_level
        if self._strap_level == level:  # left there by an aborted cycle: make the edge possible
            self.strap.set(not level)
            self._strap_level = not level
            self.clock.sleep_s(self.table.strap_settle_s)
        self.strap.set(level)
        self._strap_level = level
        self.clock.sleep_s(self.table.strap_settle_s)

    def _temperature(self, conv: Conversion) -> float:
        if conv.clipped:
            return math.nan
        return self.table.temperature.temp_c(conv.volts)

    def calibrate_temperature(self, cal: TempCalibration) -> FrontEndTable:
        """Fold ``cal`` into the board table's temperature channel (same conversions, new transfer
        function, ``verified=True``); returns the new table."""
        self.table = replace(self.table, temperature=cal.apply_to_channel(self.table.temperature)).validate()
        return self.table

    def acquire(self) -> tuple[list[Conversion], list[Conversion], list[Conversion]]:
        """Run one cycle; return (set X/Y/Z, reset X/Y/Z, temperature conversions)."""
        adc = self.adc
        temps: list[Conversion] = []
        if self._strap_level != self._idle_level:  # previous cycle aborted mid-way
            self._pulse(set_pulse=False)
        self._pulse(set_pulse=True)
        v_set = [adc.convert(ch) for ch in self._axis_ch]
        if self.table.temp_in_both_states:
            temps.append(adc.convert(self._temp_ch))
        self._pulse(set_pulse=False)
        v_reset = [adc.convert(ch) for ch in self._axis_ch]
        temps.append(adc.convert(self._temp_ch))
        self.cycles += 1
        return v_set, v_reset, temps

    def read(self) -> MagSample:
        """One set/reset cycle -> field (uT), temperature (degC) and per-axis times."""
        t_cycle0 = self.clock.monotonic_s()
        v_set, v_reset, temps = self.acquire()
        b, axis_t, overflow, offset_V = [], [], [], []
        for i in range(3):
            s, r = v_set[i], v_reset[i]
            axis_t.append(0.5 * (s.t_s + r.t_s))
            if s.clipped or r.clipped:
                overflow.append(i)
                b.append(math.nan)
                offset_V.append(math.nan)
                continue
            b.append(0.5 * (s.volts - r.volts) / self._v_per_uT[i])
            offset_V.append(0.5 * (s.volts + r.volts))
        temp_vals = [self._temperature(c) for c in temps]
        temp_c = None if any(math.isnan(v) for v in temp_vals) else sum(temp_vals) / len(temp_vals)
        scale = self.table.external_gain * self.table.excitation_V * 1e-3
        extra = {
            "axis_time_rule": "mean of set and reset conversion instants (window centres)",
            "axis_t_set_s": tuple(c.t_s for c in v_set),
            "axis_t_reset_s": tuple(c.t_s for c in v_reset),
            "v_set_V": tuple(c.volts for c in v_set),
            "v_reset_V": tuple(c.volts for c in v_reset),
            "code_set": tuple(c.code for c in v_set),
            "code_reset": tuple(c.code for c in v_reset),
            "bridge_offset_V": tuple(offset_V),
            "bridge_offset_mV_per_V": tuple(v / scale for v in offset_V),
            "temp_t_s": tuple(c.t_s for c in temps),
            "temp_V": tuple(c.volts for c in temps),
            "temp_verified": self.table.temperature.verified,
            "temp_overflow": temp_c is None,
            "cycle_start_s": t_cycle0,
            "cycle_end_s": self.clock.monotonic_s(),
        }
        return MagSample(t_s=sum(axis_t) / 3.0, b_uT=(b[0], b[1], b[2]), temp_c=temp_c,
                         axis_t_s=(axis_t[0], axis_t[1], axis_t[2]), overflow=tuple(overflow), extra=extra)
