"""A magnetometer channel: one sensor read, checked, corrected and published per ``run(now_s)``.

The channel owns no timer: the executive calls :meth:`MagChannel.run` from its rate group. Each
call reads the driver once through the common :class:`~magstack.drivers.magnetometer.Magnetometer`
interface and publishes exactly one :class:`TelemetryRecord`, good or not. Faults never escape:

* typed driver errors are counted per class (bus, timeout, stale, self-test, other) with an event;
* any other exception raised inside the driver is caught here, counted as ``exceptions`` and
  logged with its type (the flight loop must survive a driver bug);
* a sample is **good** only if it is new (the chip's data-ready said so and it does not repeat the
  previous sample bit for bit), no axis overflowed, it is within the sensor's range, and its change
  since the last good sample is physically possible (:meth:`ChannelLimits.allowed_change_uT`: noise +
  ``max_rate_uT_per_s`` over at most one period, not growing with the gap; a step that the very next
  read confirms is accepted, a one-sample spike is not);
* a good sample is **calibrated** only inside the active table's validity (:mod:`.corrector`).

After ``reinit_after`` consecutive faults the driver's ``reinit()`` is called (a failure there is
counted under its own class, never hidden); after ``degrade_after`` re-initialisations without a
good sample in between the channel is marked degraded (it keeps trying at its rate); the first
good sample clears it.
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import IntFlag

import numpy as np

from magstack.data.dictionary import DISQUALIFYING, FLIGHT, flags_of
from magstack.data.dictionary import INFORMATIONAL as _INFORMATIONAL_BITS
from magstack.drivers.errors import BusError, BusTimeout, MagError, SelfTestFailed, StaleData
from magstack.drivers.magnetometer import Magnetometer, MagSample
from magstack.firmware.corrector import Correction, TableCorrector
from magstack.firmware.flight.events import EventId, EventLog
from magstack.firmware.health import HealthCounters

#: Bits of a telemetry record's ``flags`` (and of the telemetry file's ``flag`` column): the flight
#: channel's bits of the one flag definition, :data:`magstack.data.dictionary.FLAG_BITS`.
TlmFlag = IntFlag("TlmFlag", flags_of(FLIGHT), module=__name__)


#: Longest run of exact repeats ever accepted as new data (a very coarse sensor in a static field).
STALE_MAX_REPEATS = 5
#: Accepted chance per sample of calling new data stale (one false flag in ~17 min at 10 Hz).
STALE_FALSE_ALARM = 1e-4

#: Flags that make a sample not good (its field must not be used).
BAD = TlmFlag(DISQUALIFYING & sum(TlmFlag))
#: Flags that describe a good raw sample without disqualifying it (the dictionary's non-disqualifying bits:
#: ground tools such as ``refit`` keep such rows). Every other bit disqualifies the row.
INFORMATIONAL = TlmFlag(sum(TlmFlag) & _INFORMATIONAL_BITS)


@dataclass(frozen=True)
class TelemetryRecord:
    """What a channel publishes each cycle."""

    channel: str
    t_s: float                                     # sample time (epoch s of the channel's clock)
    raw_uT: tuple[float, float, float] | None      # sensor output, None when no sample
    cal_uT: tuple[float, float, float] | None      # calibrated field, None unless good and calibrated
    temp_c: float | None
    table_crc32: int | None                        # active table when the sample was corrected
    flags: int
    error_count: int
    fault: str = ""                                # short reason when not good

    @property
    def good(self) -> bool:
        return not (self.flags & BAD)

    @property
    def calibrated(self) -> bool:
        return self.cal_uT is not None


@dataclass
class ChannelLimits:
    """Plausibility limits of a channel (from the flight configuration)."""

    max_field_uT: float = 1000.0          # |B_i| beyond this cannot be real for this sensor/mounting
    max_rate_uT_per_s: float = 2000.0     # fastest physical change (rotation + torquer switching)
    reinit_after: int = 3                 # consecutive faults before re-initialising the driver
    degrade_after: int = 3                # re-initialisations without a good sample before "degraded"
    rate_horizon_s: float = 1.0           # longest gap the rate bound is extrapolated over (the app: one period)
    noise_uT: float = 2.0                 # sample-to-sample noise allowed on top of the rate bound

    def allowed_change_uT(self, dt_s: float, range_uT: float) -> float:
        """Largest plausible change of a component between two samples ``dt_s`` apart.

        ``noise_uT + max_rate_uT_per_s * min(dt_s, rate_horizon_s)``, at most the sensor range: the
        allowance does not grow with the gap beyond one horizon (a sample after an outage that moved
        further is accepted once the next sample confirms it)."""
        return min(self.noise_uT + self.max_rate_uT_per_s * min(max(dt_s, 1e-3), self.rate_horizon_s), range_uT)

    def __post_init__(self) -> None:
        for name in ("max_field_uT", "max_rate_uT_per_s", "rate_horizon_s", "noise_uT"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        for name in ("reinit_after", "degrade_after"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")


@dataclass
class MagChannel:
    """One sensor, its corrector and its telemetry sink; ``run(now_s)`` is one cycle."""

    name: str
    mag: Magnetometer
    corrector: TableCorrector | None
    events: EventLog
    sink: Callable[[TelemetryRecord], None] | None = None
    limits: ChannelLimits = field(default_factory=ChannelLimits)
    epoch_of: Callable[[float], float] | None = None    # monotonic -> epoch seconds (the clock's)
    currents_A: Callable[[], Mapping[str, float]] | None = None
    health: HealthCounters = field(default_factory=HealthCounters)
    degraded: bool = False
    cycles: int = 0
    _last_good: tuple[float, tuple[float, float, float]] | None = None
    _rejected: tuple[float, tuple[float, float, float], int] | None = None   # (t, field, cycle)
    _last_raw: tuple[float, float, float] | None = None
    _reinits_since_good: int = 0
    _repeat_run: int = 0
    _last_counts: tuple[int, int, int] | None = None
    _diffs: deque = field(default_factory=lambda: deque(maxlen=256))
    _diffs_new: int = 0
    _threshold: int | None = None

    def stale_threshold(self) -> int:
        """Consecutive exact repeats that mean frozen data.

        ``p`` = chance that a new sample repeats the previous one on all three axes, from the width of
        this channel's own sample-to-sample differences in ADC counts (``extra["raw"]``): per axis
        P(d = 0) ~ 1 / (sqrt(2 pi) sigma_d) for a difference spread of sigma_d counts (robust: median of
        |d| over non-repeating pairs, so frozen data cannot inflate it). The threshold is the shortest
        run whose chance of occurring in new data is below ``STALE_FALSE_ALARM`` per sample: 1 for a sensor
        whose noise spans many counts, 2-3 for a coarse range in a quiet field. Without raw counts (24-bit
        front end, floats) it is 1.
        """
        if self._diffs_new < 32 and self._threshold is not None:
            return self._threshold                  # re-estimated every 32 new differences (cheap per cycle)
        self._diffs_new = 0
        self._threshold = self._estimate_threshold()
        return self._threshold

    def _estimate_threshold(self) -> int:
        if len(self._diffs) < 32:
            return 1
        d = np.asarray(self._diffs, dtype=float)
        sigma = np.median(d, axis=0) / 0.6745
        p = float(np.prod(np.minimum(1.0, 1.0 / (math.sqrt(2 * math.pi) * np.maximum(sigma, 1e-9)))))
        if p >= 0.5:
            return STALE_MAX_REPEATS
        if p <= STALE_FALSE_ALARM:
            return 1
        return max(1, min(STALE_MAX_REPEATS, math.ceil(math.log(STALE_FALSE_ALARM) / math.log(p))))

    # ------------------------------------------------------------------ one cycle
    def run(self, now_s: float) -> TelemetryRecord:
        self.cycles += 1
        try:
            sample = self.mag.read()
        except BusTimeout as exc:
            rec = self._fault(now_s, "timeouts", EventId.CHAN_TIMEOUT, exc)
        except StaleData as exc:
            rec = self._fault(now_s, "stale", EventId.CHAN_STALE, exc)
        except BusError as exc:
            rec = self._fault(now_s, "bus_errors", EventId.CHAN_BUS_ERROR, exc)
        except SelfTestFailed as exc:
            rec = self._fault(now_s, "other_errors", EventId.CHAN_SELF_TEST_FAILED, exc)
        except MagError as exc:
            rec = self._fault(now_s, "other_errors", EventId.CHAN_OTHER_ERROR, exc)
        except Exception as exc:  # noqa: BLE001 - the component boundary: a driver bug must not stop the loop
            rec = self._fault(now_s, "exceptions", EventId.CHAN_EXCEPTION, exc)
        else:
            try:
                rec = self._check_and_correct(now_s, sample)
            except Exception as exc:  # noqa: BLE001 - a malformed sample (wrong types) is a fault, not a crash
                rec = self._fault(now_s, "exceptions", EventId.CHAN_EXCEPTION, exc)
        if self.sink is not None:
            try:
                self.sink(rec)
            except Exception as exc:  # noqa: BLE001 - a full disk must not stop sampling
                self.health.telemetry_errors += 1
                self.events.emit(rec.t_s, EventId.TLM_WRITE_ERROR, self.name, f"{type(exc).__name__}: {exc}"[:200])
        return rec

    # ------------------------------------------------------------------ faults
    def _epoch(self, t_s: float) -> float:
        return self.epoch_of(t_s) if self.epoch_of is not None else t_s

    def _fault(self, now_s: float, counter: str, eid: EventId, exc: Exception | None,
               sample: MagSample | None = None, flags: int = TlmFlag.NO_SAMPLE) -> TelemetryRecord:
        setattr(self.health, counter, getattr(self.health, counter) + 1)
        self.health.consecutive_faults += 1
        reason = f"{type(exc).__name__}: {exc}" if exc is not None else eid.name.lower()
        self.events.emit(self._epoch(now_s), eid, self.name, reason[:200])
        if self.health.consecutive_faults >= self.limits.reinit_after:
            self._reinit(now_s)
        if self.degraded:
            flags |= TlmFlag.DEGRADED
        raw = None if sample is None else tuple(float(v) for v in sample.b_uT)
        t = now_s if sample is None else sample.t_s
        temp = None if sample is None else sample.temp_c
        return TelemetryRecord(self.name, self._epoch(t), raw, None, temp, None, int(flags),
                               self.health.error_count, reason[:120])

    def _reinit(self, now_s: float) -> None:
        self.health.consecutive_faults = 0
        reinit = getattr(self.mag, "reinit", None)
        if reinit is None:
            return
        try:
            reinit()
        except BusError as exc:            # a NACK during re-initialisation is a bus error
            self.health.bus_errors += 1
            self.health.reinit_failures += 1
            self.events.emit(self._epoch(now_s), EventId.CHAN_REINIT_FAILED, self.name, f"{type(exc).__name__}: {exc}")
        except Exception as exc:  # noqa: BLE001 - same boundary as read()
            self.health.reinit_failures += 1
            if isinstance(exc, MagError):
                self.health.other_errors += 1
            else:
                self.health.exceptions += 1
            self.events.emit(self._epoch(now_s), EventId.CHAN_REINIT_FAILED, self.name, f"{type(exc).__name__}: {exc}")
        else:
            self.health.reinits += 1
            self.events.emit(self._epoch(now_s), EventId.CHAN_REINIT, self.name, "driver re-initialised")
        self._reinits_since_good += 1
        if not self.degraded and self._reinits_since_good >= self.limits.degrade_after:
            self.degraded = True
            self.events.emit(self._epoch(now_s), EventId.CHAN_DEGRADED, self.name,
                             f"{self._reinits_since_good} re-initialisations without a good sample")

    # ------------------------------------------------------------------ checks
    def _check_and_correct(self, now_s: float, s: MagSample) -> TelemetryRecord:
        b = tuple(float(v) for v in s.b_uT)
        if len(b) != 3:
            raise ValueError(f"sample has {len(b)} axes")
        overrun = bool(s.extra.get("overrun", False)) if isinstance(s.extra, Mapping) else False
        extra_flags = TlmFlag.OVERRUN if overrun else 0
        if s.overflow:
            self._last_raw = b
            return self._fault(now_s, "overflows", EventId.CHAN_OVERFLOW, None, s,
                               TlmFlag.OVERFLOW | extra_flags)
        repeats = s.extra.get("repeats") if isinstance(s.extra, Mapping) else None
        # new data? an exact repeat of all three axes (or the driver's bit-identical register count)
        same = (isinstance(repeats, int) and repeats > 0) or b == self._last_raw
        self._last_raw = b
        self._repeat_run = self._repeat_run + 1 if same else 0
        k = self.stale_threshold()
        counts = s.extra.get("raw") if isinstance(s.extra, Mapping) else None
        if isinstance(counts, tuple) and len(counts) == 3 and all(isinstance(c, int) for c in counts):
            if self._last_counts is not None and not same:
                self._diffs.append(tuple(abs(a - b0) for a, b0 in zip(counts, self._last_counts, strict=True)))
                self._diffs_new += 1
            self._last_counts = counts
        if self._repeat_run >= k:
            return self._fault(now_s, "stale", EventId.CHAN_STALE, None, s, TlmFlag.STALE | extra_flags)
        if same:
            extra_flags |= TlmFlag.REPEATED
        why = self._implausible(s.t_s, b)
        if why:
            return self._fault(now_s, "implausible", EventId.CHAN_IMPLAUSIBLE, ValueError(why), s,
                               TlmFlag.IMPLAUSIBLE | (extra_flags & ~TlmFlag.REPEATED))
        # a good sample
        self._last_good = (s.t_s, b)
        self.health.consecutive_faults = 0
        self.health.samples_ok += 1
        self._reinits_since_good = 0
        if self.degraded:
            self.degraded = False
            self.events.emit(self._epoch(now_s), EventId.CHAN_RECOVERED, self.name, "good sample after degradation")
        corr = self._correct(b, s.temp_c)
        flags = int(extra_flags)
        if corr.status != "ok":
            flags |= TlmFlag.UNCALIBRATED
            self.health.uncalibrated += 1
            if corr.status == "out_of_validity":
                flags |= TlmFlag.OUT_OF_VALIDITY
                self.health.out_of_validity += 1
        return TelemetryRecord(self.name, self._epoch(s.t_s), b, corr.b_uT, s.temp_c, corr.table_crc32, flags,
                               self.health.error_count, "" if corr.status == "ok" else corr.status)

    def _implausible(self, t_s: float, b: tuple[float, float, float]) -> str:
        lim = self.limits
        rng = getattr(self.mag, "range_uT", None)
        max_field = min(lim.max_field_uT, float(rng)) if isinstance(rng, (int, float)) else lim.max_field_uT
        if not all(math.isfinite(v) for v in b):
            return "non-finite field"
        if max(abs(v) for v in b) > max_field:
            return f"|B| component {max(abs(v) for v in b):.1f} uT beyond {max_field:g} uT"
        if self._last_good is None:
            return ""
        t0, b0 = self._last_good
        dt = t_s - t0
        jump = max(abs(x - y) for x, y in zip(b, b0, strict=True))
        allowed = lim.allowed_change_uT(dt, max_field)
        if jump <= allowed:
            self._rejected = None
            return ""
        # a step the very next read confirms is real (torquer switched, field moved during an outage); a lone
        # spike is not, nor are two corruptions with failed reads between them
        if self._rejected is not None:
            tr, br, cycle = self._rejected
            if cycle == self.cycles - 1 and \
                    max(abs(x - y) for x, y in zip(b, br, strict=True)) <= lim.allowed_change_uT(t_s - tr, max_field):
                self._rejected = None
                return ""
        self._rejected = (t_s, b, self.cycles)
        return (f"change of {jump:.1f} uT in {dt:.3f} s exceeds {allowed:.1f} uT ({lim.max_rate_uT_per_s:g} uT/s "
                f"over at most {lim.rate_horizon_s:g} s + {lim.noise_uT:g} uT noise)")

    def _correct(self, b, temp_c) -> Correction:
        if self.corrector is None:
            return Correction(None, "no_table")
        cur = self.currents_A() if self.currents_A is not None else None
        return self.corrector.correct(b, temp_c, cur)

    # ------------------------------------------------------------------ housekeeping
    def counters(self) -> dict[str, int | bool]:
        d: dict[str, int | bool] = dict(self.health.snapshot())
        d["degraded"] = self.degraded
        d["cycles"] = self.cycles
        return d
