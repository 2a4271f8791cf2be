"""The executive: one tick source divided into rate groups (F' rate-group style).

Each :class:`RateGroup` has a period and an ordered list of components (anything with
``name`` and ``run(now_s)``); components own no timers. The executive calls a group's
components in their fixed order once per period and measures the group's execution time on
the group's clock against its period:

* execution longer than the period is an **overrun** (counted, event ``RATE_GROUP_OVERRUN``);
* slots that passed while the group ran are **skipped**, not run back-to-back: the schedule is
  re-anchored on the next future slot and the skipped slots are counted (``missed_slots``,
  event ``RATE_GROUP_SLIP``), so no interval between two runs is ever shorter than a period;
* a tick source that goes backwards re-anchors the group's schedule at once (event
  ``CLOCK_STEPPED_BACK``) instead of stalling for the step.

Before each run the group's ``boundary`` hooks are called: that is where commands are applied
and staged calibration tables are swapped in (``CalTableStore.cycle_boundary``), never mid-cycle.

Timelines. Every group runs on its own clock, the way each F' active rate group runs in its own
thread: a group that blocks (the HMC1053 front end converts for ~0.36 s per vector) delays only
itself. On hardware :meth:`Executive.run_threads` gives each group a thread on the shared system
clock (channels on one bus must be in one group, so a bus is never used by two threads). In
simulation :meth:`Executive.run_virtual` runs the groups as a discrete-event simulation over their
own virtual clocks: the group whose next slot is earliest runs next, so a simulated day takes
seconds and every run is reproducible.
"""
from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from magstack.firmware.flight.events import EventId, EventLog


class Component(Protocol):
    name: str

    def run(self, now_s: float) -> object: ...


@dataclass
class GroupStats:
    runs: int = 0
    overruns: int = 0
    missed_slots: int = 0
    clock_steps_back: int = 0
    exec_total_s: float = 0.0
    exec_max_s: float = 0.0
    min_interval_s: float = math.inf      # shortest interval between two consecutive runs

    def to_dict(self) -> dict:
        return {"runs": self.runs, "overruns": self.overruns, "missed_slots": self.missed_slots,
                "clock_steps_back": self.clock_steps_back, "exec_total_s": self.exec_total_s,
                "exec_max_s": self.exec_max_s,
                "min_interval_s": None if math.isinf(self.min_interval_s) else self.min_interval_s}


@dataclass
class RateGroup:
    """``period_s`` and the components run every period, in order, on ``clock``."""

    name: str
    period_s: float
    clock: object                                  # magstack.drivers.clock.Clock
    components: list[Component] = field(default_factory=list)
    boundary: list[Callable[[float], None]] = field(default_factory=list)
    stats: GroupStats = field(default_factory=GroupStats)
    next_due_s: float | None = None
    _last_start_s: float | None = None
    _last_seen_s: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise ValueError(f"rate group {self.name!r}: period must be a finite number > 0 s, got {self.period_s}")

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.period_s

    def _now(self) -> float:
        return self.clock.monotonic_s()

    def due_in_s(self) -> float:
        """Seconds until the next slot on this group's clock (<= 0: due now).

        A clock that went back since the last run makes the slot due at once (``run_once`` then counts
        the step and re-anchors): waiting for the old schedule would stall the group for the size of the
        step (the threaded runner and the virtual one both ask here)."""
        now = self._now()
        if self.next_due_s is None:
            return 0.0
        if self._last_seen_s is not None and now < self._last_seen_s:
            return 0.0
        return self.next_due_s - now

    def run_once(self, events: EventLog, epoch_of: Callable[[float], float]) -> None:
        """Run one slot now: boundary hooks, components in order, then schedule the next slot."""
        start = self._now()
        st = self.stats
        if self._last_seen_s is not None and start < self._last_seen_s:
            self._stepped_back(events, epoch_of, self._last_seen_s, start)
        if self.next_due_s is None:
            self.next_due_s = start
        if self._last_start_s is not None:
            st.min_interval_s = min(st.min_interval_s, start - self._last_start_s)
        self._last_start_s = start
        for hook in self.boundary:
            hook(start)
        for comp in self.components:
            comp.run(self._now())
        end = self._now()
        self._last_seen_s = end
        if end < start:                 # the clock went back while the group ran
            self._stepped_back(events, epoch_of, start, end)
            start = end
        took = end - start
        st.runs += 1
        st.exec_total_s += took
        st.exec_max_s = max(st.exec_max_s, took)
        if took > self.period_s:
            st.overruns += 1
            events.emit(epoch_of(end), EventId.RATE_GROUP_OVERRUN, self.name,
                        f"execution {took:.4f} s > period {self.period_s:.4f} s")
        nxt = self.next_due_s + self.period_s
        if end > nxt:   # slots passed while we ran: skip them, never catch up in a burst
            k = math.floor((end - nxt) / self.period_s) + 1
            st.missed_slots += k
            nxt += k * self.period_s
            events.emit(epoch_of(end), EventId.RATE_GROUP_SLIP, self.name, f"{k} slot(s) skipped")
        self.next_due_s = nxt

    def _stepped_back(self, events: EventLog, epoch_of: Callable[[float], float], before_s: float,
                      now_s: float) -> None:
        """Count a backward step of the clock and re-anchor the schedule at ``now_s`` (no stall)."""
        self.stats.clock_steps_back += 1
        events.emit(epoch_of(now_s), EventId.CLOCK_STEPPED_BACK, self.name,
                    f"clock went back {before_s - now_s:.6f} s: schedule re-anchored")
        self.next_due_s = now_s
        self._last_start_s = None


class Executive:
    """Rate groups + the event log; ``run_virtual`` (simulation) or ``run_threads`` (hardware)."""

    def __init__(self, groups: Sequence[RateGroup], events: EventLog,
                 epoch_of: Callable[[float], float] | None = None, stop: threading.Event | None = None) -> None:
        names = [g.name for g in groups]
        if len(set(names)) != len(names):
            raise ValueError(f"rate group names must be unique: {names}")
        self.groups = list(groups)
        self.events = events
        self.epoch_of = epoch_of or (lambda t: t)
        self._stop = stop if stop is not None else threading.Event()   # set by stop() or a signal handler

    def group(self, name: str) -> RateGroup:
        for g in self.groups:
            if g.name == name:
                return g
        raise KeyError(name)

    def stop(self) -> None:
        """Ask the executive to stop after the slots under way (thread-safe; signal handlers call it)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    # ------------------------------------------------------------------ simulation
    def run_virtual(self, duration_s: float, *, on_slot: Callable[[RateGroup], None] | None = None,
                    pauses: Sequence[tuple[float, Callable[[], None]]] = ()) -> None:
        """Discrete-event run over the groups' virtual clocks until each has reached ``duration_s``
        past its start (or :meth:`stop`). Each group's clock must be a VirtualClock of its own.

        ``pauses``: ``(t_s, action)`` pairs, ``t_s`` seconds after the start of this run: each action is called
        once every slot before ``t_s`` has run and before any slot at or after it (the whole application
        stands still meanwhile); the ones at ``duration_s`` after the last slot."""
        clocks = [g.clock for g in self.groups]
        if len({id(c) for c in clocks}) != len(clocks):
            raise ValueError("in virtual time every rate group needs a clock of its own")
        t_end = {g.name: g.clock.monotonic_s() + duration_s for g in self.groups}
        t0 = min(c.monotonic_s() for c in clocks)
        todo = sorted(pauses, key=lambda p: p[0])
        self.events.emit(self.epoch_of(t0), EventId.EXEC_STARTED, "executive",
                         f"{len(self.groups)} rate groups, virtual time, {duration_s:g} s")
        while not self._stop.is_set():
            live = [g for g in self.groups if _slot_time(g) < t_end[g.name] - 1e-6 * g.period_s]
            if not live:
                break
            g = min(live, key=lambda x: (_slot_time(x), -x.rate_hz))
            while todo and todo[0][0] <= _slot_time(g) - t0 and not self._stop.is_set():
                todo.pop(0)[1]()
            if self._stop.is_set():
                break
            wait = g.due_in_s()
            if wait > 0:
                g.clock.sleep_s(wait)
            g.run_once(self.events, self.epoch_of)
            if on_slot is not None:
                on_slot(g)
        while todo and todo[0][0] <= duration_s and not self._stop.is_set():
            todo.pop(0)[1]()
        self.events.emit(self.epoch_of(max(c.monotonic_s() for c in clocks)), EventId.EXEC_STOPPED, "executive",
                         "stopped" if self._stop.is_set() else "duration reached")

    # ------------------------------------------------------------------ hardware
    def run_threads(self, duration_s: float | None = None, *, poll_s: float = 0.05) -> None:
        """One thread per group on the (shared, real) clock until ``duration_s`` or :meth:`stop`."""
        t0 = {g.name: g.clock.monotonic_s() for g in self.groups}
        self.events.emit(self.epoch_of(min(t0.values())), EventId.EXEC_STARTED, "executive",
                         f"{len(self.groups)} rate groups, threads" + (f", {duration_s:g} s" if duration_s else ""))
        errors: list[BaseException] = []

        def worker(g: RateGroup) -> None:
            elapsed, last = 0.0, t0[g.name]     # forward progress only: a clock step back cannot extend the run
            try:
                while not self._stop.is_set():
                    now = g.clock.monotonic_s()
                    elapsed, last = elapsed + max(0.0, now - last), now
                    if duration_s is not None and elapsed >= duration_s:
                        return
                    wait = g.due_in_s()
                    if wait > 0:
                        # sleep in short steps so stop() is honoured promptly
                        self._stop.wait(min(wait, poll_s)) if wait > poll_s else g.clock.sleep_s(wait)
                        continue
                    g.run_once(self.events, self.epoch_of)
            except BaseException as exc:  # noqa: BLE001 - reported by the main thread
                errors.append(exc)
                self._stop.set()

        threads = [threading.Thread(target=worker, args=(g,), name=f"rg-{g.name}", daemon=True) for g in self.groups]
        for th in threads:
            th.start()
        try:
            for th in threads:
                while th.is_alive():
                    th.join(timeout=0.2)
        finally:
            self._stop.set()
            for th in threads:
                th.join(timeout=5.0)
        self.events.emit(self.epoch_of(max(g.clock.monotonic_s() for g in self.groups)), EventId.EXEC_STOPPED,
                         "executive", "stopped")
        if errors:
            raise errors[0]


def _slot_time(g: RateGroup) -> float:
    return g.clock.monotonic_s() if g.next_due_s is None else max(g.next_due_s, g.clock.monotonic_s())
