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
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType

from magstack.drivers.ads1248 import ADS1248, DATA_RATES, PGA_CODES, ChannelConfig, Conversion, diode_temp_c, lookup
from magstack.drivers.bus.gpio import OutputLine
from magstack.drivers.clock import Clock
from magstack.drivers.errors import ConfigurationError
from magstack.drivers.magnetometer import MagSample

#: Temperature channel kinds: the ADC's internal diode (MUXCAL=011) or a linear sensor on an AIN pair.
TEMP_KINDS = ("adc_diode", "linear")


@dataclass(frozen=True)
class TempChannel:
    """``linear``: T = 25 + (V - v_at_25c_V) / V_per_c on AIN ``pos``/``neg``; ``adc_diode``: the ADS1248
    diode, by the same formula with the forum coefficients (118 mV, 405 uV/degC [F2]) while both constants
    are 0.0 (default), or with a per-board calibration when both are given."""

    kind: str = "adc_diode"
    pos: int = 6
    neg: int = 7
    pga: int = 1
    v_at_25c_V: float = 0.0
    V_per_c: float = 0.0


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
        t = self.table.temperature
        if t.kind == "adc_diode":
            if (t.v_at_25c_V, t.V_per_c) == (0.0, 0.0):
                return diode_temp_c(conv.volts)
            return diode_temp_c(conv.volts, t.v_at_25c_V, t.V_per_c)
        return 25.0 + (conv.volts - t.v_at_25c_V) / t.V_per_c

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
            "temp_overflow": temp_c is None,
            "cycle_start_s": t_cycle0,
            "cycle_end_s": self.clock.monotonic_s(),
        }
        return MagSample(t_s=sum(axis_t) / 3.0, b_uT=(b[0], b[1], b[2]), temp_c=temp_c,
                         axis_t_s=(axis_t[0], axis_t[1], axis_t[2]), overflow=tuple(overflow), extra=extra)
