"""Executive: rate groups on their own timelines, overruns, skipped slots (no catch-up bursts), clock steps."""
from __future__ import annotations

import math
import threading

import pytest

from magstack.drivers.clock import SystemClock, VirtualClock
from magstack.firmware.flight.events import EventId, EventLog
from magstack.firmware.flight.executive import Executive, RateGroup


class Recorder:
    """A component that records when it ran and can block for a while (a slow read)."""

    def __init__(self, name, clock, block_s=0.0):
        self.name, self.clock, self.block_s = name, clock, block_s
        self.starts: list[float] = []
        self.block_at: dict[int, float] = {}

    def run(self, now_s):
        self.starts.append(now_s)
        self.clock.sleep_s(self.block_at.get(len(self.starts), self.block_s))


def _exec(*groups):
    ev = EventLog()
    return Executive(list(groups), ev), ev


def test_groups_run_at_their_rates_in_virtual_time():
    fast_clk, slow_clk = VirtualClock(), VirtualClock()
    fast, slow = Recorder("a", fast_clk, 0.01), Recorder("b", slow_clk, 0.3)
    ex, ev = _exec(RateGroup("fast", 0.05, fast_clk, [fast]), RateGroup("slow", 1.0, slow_clk, [slow]))
    ex.run_virtual(10.0)
    assert len(fast.starts) == 200 and len(slow.starts) == 10
    assert all(b - a == pytest.approx(0.05) for a, b in zip(fast.starts, fast.starts[1:], strict=False))
    # the slow group's 0.3 s blocking read delays only itself (its own timeline)
    assert ex.group("fast").stats.missed_slots == 0 and ex.group("fast").stats.overruns == 0
    assert ex.group("slow").stats.exec_max_s == pytest.approx(0.3)
    assert ev.count(EventId.EXEC_STARTED) == 1 and ev.count(EventId.EXEC_STOPPED) == 1


def test_overrun_skips_slots_and_never_bursts():
    """A read that blocks 3.5 periods: the missed slots are skipped and counted, the schedule
    re-anchors, and no interval between two runs is shorter than the period."""
    clk = VirtualClock()
    comp = Recorder("c", clk, 0.001)
    comp.block_at = {5: 0.35, 12: 0.35}
    ex, ev = _exec(RateGroup("g", 0.1, clk, [comp]))
    ex.run_virtual(3.0)
    gaps = [b - a for a, b in zip(comp.starts, comp.starts[1:], strict=False)]
    assert min(gaps) >= 0.1 - 1e-9
    st = ex.group("g").stats
    assert st.overruns == 2 and ev.count(EventId.RATE_GROUP_OVERRUN) == 2
    assert st.missed_slots == 2 * 3 and ev.count(EventId.RATE_GROUP_SLIP) == 2
    assert st.min_interval_s >= 0.1 - 1e-9
    # after the overrun the schedule is back on the original grid
    assert comp.starts[-1] == pytest.approx(round(comp.starts[-1] / 0.1) * 0.1)


class SteppedSystemClock(SystemClock):
    """The system clock plus an offset the test can step back: real sleeps, a monotonic time that jumps."""

    offset_s = 0.0

    def monotonic_s(self):
        return super().monotonic_s() + self.offset_s


def test_threaded_runner_reanchors_after_a_clock_step_back():
    """The threaded runner itself (not a hand-forced slot) meets a clock stepped back an hour: it re-anchors and
    counts the step, rather than waiting it out (a 5 s step would be a 5.1 s gap)."""
    clk = SteppedSystemClock()

    class Stepper:
        name = "stepper"
        runs = after = 0

        def run(self, now_s):
            self.runs += 1
            if self.runs == 5:
                clk.offset_s -= 3600.0
            elif self.runs > 5:
                self.after += 1
                if self.after == 10:
                    ex.stop()

    comp = Stepper()
    g = RateGroup("g", 0.02, clk, [comp])
    ex, ev = _exec(g)
    watchdog = threading.Timer(30.0, ex.stop)      # ends an hour-long wait, should the runner wait out the step
    watchdog.start()
    try:
        ex.run_threads(None)
    finally:
        watchdog.cancel()
    assert comp.after == 10
    assert g.stats.clock_steps_back == 1 and ev.count(EventId.CLOCK_STEPPED_BACK) == 1


def test_threaded_duration_counts_forward_progress_only():
    """A clock step back cannot stretch ``run_threads(duration_s)`` by the size of the step."""
    clk = SteppedSystemClock()

    class Stepper:
        name = "stepper"
        runs = 0

        def run(self, now_s):
            self.runs += 1
            if self.runs == 3:
                clk.offset_s -= 3600.0

    comp = Stepper()
    g = RateGroup("g", 0.02, clk, [comp])
    ex, ev = _exec(g)
    watchdog = threading.Timer(30.0, ex.stop)
    watchdog.start()
    try:
        ex.run_threads(0.3)
    finally:
        stopped_by_watchdog = not watchdog.is_alive() or watchdog.finished.is_set()
        watchdog.cancel()
    assert not stopped_by_watchdog and g.stats.clock_steps_back == 1


def test_stop_and_validation():
    clk = VirtualClock()
    comp = Recorder("c", clk)
    ex, _ = _exec(RateGroup("g", 0.1, clk, [comp]))
    ex.stop()
    ex.run_virtual(100.0)
    assert comp.starts == []
    with pytest.raises(ValueError, match="period"):
        RateGroup("bad", 0.0, clk)
    with pytest.raises(ValueError, match="unique"):
        Executive([RateGroup("g", 1, clk), RateGroup("g", 1, VirtualClock())], EventLog())
    with pytest.raises(ValueError, match="clock of its own"):
        Executive([RateGroup("a", 1, clk), RateGroup("b", 1, clk)], EventLog()).run_virtual(1.0)


def test_threads_on_the_system_clock_keep_their_rates():
    from magstack.drivers.clock import SystemClock

    clk = SystemClock()
    a, b = Recorder("a", clk), Recorder("b", clk, 0.12)
    ex, _ = _exec(RateGroup("fast", 0.02, clk, [a]), RateGroup("slow", 0.25, clk, [b]))
    ex.run_threads(0.6)
    # the slow group's blocking (0.12 s, six fast periods) does not hold up the fast one (its own thread):
    # on a single shared timeline the fast group could run at most ~18 times in 0.6 s; allow for a loaded host
    assert len(a.starts) >= 19
    # slots stay on their grid, at most one run per slot: a run the OS woke late may be followed closely by the
    # next slot's (on a busy host), but a catch-up burst would put a second run into the late run's slot
    slot = [math.floor((t - a.starts[0]) / 0.02 + 1e-3) for t in a.starts]
    assert all(k1 > k0 for k0, k1 in zip(slot, slot[1:], strict=False)), slot
    assert 2 <= len(b.starts) <= 4
