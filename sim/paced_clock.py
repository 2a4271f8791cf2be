"""A virtual clock that keeps pace with a wall clock: simulated hardware at the speed a person watches it.

:class:`PacedClock` is a :class:`~magstack.drivers.clock.VirtualClock` (simulated chips and the bench runner
treat it as one: exact, repeatable sample instants) whose ``sleep_s`` also waits on an injected wall clock
until the wall clock has caught up with ``virtual time / speed``. Work that takes longer than the virtual
time it covers (drawing a screen) makes the virtual clock lag; it then runs without waiting until it is level
again, so no simulated sample is skipped, only delivered late. ``lag_s()`` says by how much.
"""
from __future__ import annotations

from magstack.drivers.clock import Clock, VirtualClock


class PacedClock(VirtualClock):
    """Virtual time paced to ``wall`` at ``speed`` (1 = real time, 2 = twice as fast)."""

    def __init__(self, wall: Clock, speed: float = 1.0, start_epoch_s: float | None = None) -> None:
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed!r}")
        super().__init__(wall.epoch_s() if start_epoch_s is None else start_epoch_s)
        self.wall = wall
        self.speed = float(speed)
        self._wall0 = wall.monotonic_s()

    def lag_s(self) -> float:
        """How far virtual time is behind the wall clock (s of virtual time; <= 0 when on pace)."""
        return (self.wall.monotonic_s() - self._wall0) * self.speed - self.monotonic_s()

    def sleep_s(self, dt_s: float) -> None:
        super().sleep_s(dt_s)
        ahead = -self.lag_s() / self.speed
        if ahead > 0:
            self.wall.sleep_s(ahead)
