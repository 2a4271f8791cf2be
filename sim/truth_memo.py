"""A truth source that evaluates instants it will be asked for in one vectorised call, ahead of time.

A register-level chip model converting continuously knows its next conversion instants (its period on the
virtual clock); :meth:`TruthMemo.prefetch` evaluates the wrapped source's series methods over a block of them
in one call, and :meth:`TruthMemo.sample_floats` (the fast path of
:func:`magstack.sim.error_truth.sample_truth_floats`) answers from that block when an instant is in it, by exact
float equality; any other instant is evaluated as before. The values are the wrapped source's: its series
methods compute element by element (coil programmes), so a block gives the same bits as one instant at a time
(``tests/test_truth_memo.py``, and the telemetry digest of ``tests/test_flight_sim_digest.py``).
"""
from __future__ import annotations

from typing import Any

from magstack.sim.error_truth import sample_truth_floats

#: Instants kept; the oldest half is dropped beyond this (consumers move forward in time).
CAPACITY = 4096


class TruthMemo:
    """Wraps a TruthSource with series methods; the scalar and series protocols pass through unchanged."""

    def __init__(self, truth: Any, capacity: int = CAPACITY) -> None:
        self.truth = truth
        self.capacity = int(capacity)
        self._rows: dict[float, tuple] = {}
        self.hits = 0
        self.misses = 0

    def __getattr__(self, name: str):
        # field_uT, temp_c, series methods, duration_s ...: the wrapped source's
        return getattr(self.truth, name)

    def known(self, t_s: float) -> bool:
        """True when the values at ``t_s`` are held (evaluated ahead, or asked for before)."""
        return t_s in self._rows

    def prefetch(self, ts: list[float]) -> None:
        """Evaluate the instants ``ts`` (non-decreasing) in one call and keep their values."""
        todo = [t for t in ts if t not in self._rows]
        if not todo:
            return
        got = sample_truth_floats(self.truth, todo)
        if got is None:                      # non-finite truth: evaluated (and refused) when asked for
            return
        self._keep(todo, got)

    def _keep(self, ts: list[float], got) -> None:
        bs, temps, cur, sessions = got
        keys = list(cur)
        for i, t in enumerate(ts):
            self._rows[t] = (bs[i], temps[i], tuple(cur[k][i] for k in keys), sessions[i], keys)
        if len(self._rows) > self.capacity:
            for t in list(self._rows)[:len(self._rows) // 2]:
                del self._rows[t]

    def sample_floats(self, ts: list[float]):
        rows = self._rows
        hit = [rows.get(t) for t in ts]
        if any(h is None for h in hit):
            self.misses += 1
            got = sample_truth_floats(self.truth, ts)
            if got is not None:             # kept too: the same instant's temperature is often asked next
                self._keep(ts, got)
            return got
        self.hits += 1
        keys = hit[0][4]
        return ([list(h[0]) for h in hit], [h[1] for h in hit],
                {k: [h[2][j] for h in hit] for j, k in enumerate(keys)}, [h[3] for h in hit])

    def temp_c(self, t_s: float) -> float:
        row = self._rows.get(t_s)
        return row[1] if row is not None else self.truth.temp_c(t_s)
