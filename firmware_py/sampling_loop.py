"""The on-board sampling loop: one cyclic executive step per sample period.

Each :meth:`SamplingLoop.step` reads one sample through the common
:class:`~magstack.drivers.magnetometer.Magnetometer` interface, applies the active calibration
(if any) and publishes a :class:`PublishedSample`. Faults never escape: every
:class:`~magstack.drivers.errors.MagError` is counted in :class:`HealthCounters` and the loop
keeps running; after ``reinit_after`` consecutive faults it calls the driver's
``reinit()`` (if it has one). Time comes only from the injected clock.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from magstack.drivers.clock import Clock
from magstack.drivers.errors import BusError, BusTimeout, MagError, StaleData
from magstack.drivers.magnetometer import Magnetometer, MagSample
from magstack.firmware.health import HealthCounters


class Corrector(Protocol):
    """Maps a raw sample to calibrated field in uT; returns None if it cannot (no table, out of range)."""

    def __call__(self, sample: MagSample) -> tuple[float, float, float] | None: ...


@dataclass(frozen=True)
class PublishedSample:
    """What the loop publishes each cycle (telemetry)."""

    t_s: float
    raw_uT: tuple[float, float, float] | None
    b_uT: tuple[float, float, float] | None   # calibrated field, None if unavailable
    temp_c: float | None
    calibrated: bool
    error_count: int
    fault: str | None = None


class SamplingLoop:
    def __init__(self, mag: Magnetometer, clock: Clock, *, period_s: float,
                 corrector: Corrector | None = None, reinit_after: int = 5,
                 sink: Callable[[PublishedSample], None] | None = None) -> None:
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"period_s must be a positive finite number, got {period_s}")
        if int(reinit_after) < 1:
            raise ValueError(f"reinit_after must be >= 1 consecutive faults, got {reinit_after}")
        self.mag = mag
        self.clock = clock
        self.period_s = float(period_s)
        self.corrector = corrector
        self.reinit_after = int(reinit_after)
        self.sink = sink
        self.health = HealthCounters()
        self._next_s: float | None = None

    def _count(self, exc: MagError) -> str:
        """Count ``exc`` in its fault class (the same classes for reads and re-initialisations)."""
        if isinstance(exc, BusTimeout):
            self.health.timeouts += 1
            return "timeout"
        if isinstance(exc, StaleData):
            self.health.stale += 1
            return "stale"
        if isinstance(exc, BusError):
            self.health.bus_errors += 1
            return "bus"
        self.health.other_errors += 1
        return type(exc).__name__

    def _fault(self, t_s: float, kind: str, exc: Exception | None) -> PublishedSample:
        self.health.consecutive_faults += 1
        if self.health.consecutive_faults >= self.reinit_after and hasattr(self.mag, "reinit"):
            try:
                self.mag.reinit()
                self.health.reinits += 1
                self.health.consecutive_faults = 0
            except MagError as rexc:   # e.g. a NACK during the re-initialisation: a bus error
                self.health.reinit_failures += 1
                self._count(rexc)
        return PublishedSample(t_s, None, None, None, False, self.health.error_count,
                               f"{kind}: {exc}" if exc else kind)

    def step(self) -> PublishedSample:
        """Wait for the next cycle boundary, read, correct, publish. Never raises MagError."""
        now = self.clock.monotonic_s()
        if self._next_s is None or now < self._next_s - self.period_s:
            self._next_s = now        # first cycle, or the clock went back: re-anchor, never stall
        if self._next_s > now:
            self.clock.sleep_s(self._next_s - now)
        elif now - self._next_s >= self.period_s:
            # slots passed while the last read blocked: skip them (counted), no catch-up burst
            k = int((now - self._next_s) // self.period_s)
            self.health.missed_slots += k
            self._next_s += k * self.period_s
            if self._next_s < now:
                self._next_s += self.period_s
                self.health.missed_slots += 1
                self.clock.sleep_s(self._next_s - now)
        self._next_s += self.period_s
        t_s = self.clock.monotonic_s()
        try:
            sample = self.mag.read()
        except MagError as exc:
            out = self._fault(t_s, self._count(exc), exc)
        else:
            out = self._publish(sample)
        if self.sink is not None:
            self.sink(out)
        return out

    def _publish(self, sample: MagSample) -> PublishedSample:
        if sample.overflow:
            self.health.overflows += 1
            self.health.consecutive_faults += 1
            return PublishedSample(sample.t_s, sample.b_uT, None, sample.temp_c, False, self.health.error_count,
                                   f"overflow on axes {sample.overflow}")
        self.health.consecutive_faults = 0
        self.health.samples_ok += 1
        b = self.corrector(sample) if self.corrector is not None else None
        if b is None:
            self.health.uncalibrated += 1
        return PublishedSample(sample.t_s, sample.b_uT, b, sample.temp_c, b is not None, self.health.error_count)

    def run(self, n: int) -> list[PublishedSample]:
        """Run ``n`` cycles and return what was published."""
        return [self.step() for _ in range(n)]
