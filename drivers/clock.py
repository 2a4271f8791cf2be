"""Injected clocks. No component owns time.

Every wait and timestamp in magstack goes through a :class:`Clock`, so the same code
runs against the wall clock on hardware and in virtual time in simulation and tests.
"""
from __future__ import annotations

import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """Time source used by drivers, simulators and the flight loop."""

    def monotonic_s(self) -> float:
        """Monotonic seconds since an arbitrary origin."""

    def epoch_s(self) -> float:
        """UTC Unix time in seconds (for session timestamps)."""

    def sleep_s(self, dt_s: float) -> None:
        """Wait ``dt_s`` seconds (advances virtual time in simulation)."""


class SystemClock:
    """Real time: ``time.monotonic``, ``time.time`` and ``time.sleep``."""

    def monotonic_s(self) -> float:
        return time.monotonic()

    def epoch_s(self) -> float:
        return time.time()

    def sleep_s(self, dt_s: float) -> None:
        if dt_s > 0:
            time.sleep(dt_s)


class VirtualClock:
    """Deterministic simulated time. ``sleep_s`` advances time instantly.

    ``start_epoch_s`` anchors :meth:`epoch_s` (default 2026-01-01T00:00:00Z).
    """

    def __init__(self, start_epoch_s: float = 1767225600.0, start_monotonic_s: float = 0.0) -> None:
        self._t_s = float(start_monotonic_s)
        self._epoch0_s = float(start_epoch_s) - float(start_monotonic_s)

    def monotonic_s(self) -> float:
        return self._t_s

    def epoch_s(self) -> float:
        return self._epoch0_s + self._t_s

    def sleep_s(self, dt_s: float) -> None:
        if dt_s < 0:
            raise ValueError(f"cannot sleep a negative duration: {dt_s} s")
        self._t_s += float(dt_s)

    def advance_s(self, dt_s: float) -> None:
        """Alias of :meth:`sleep_s` for test code that moves time explicitly."""
        self.sleep_s(dt_s)
