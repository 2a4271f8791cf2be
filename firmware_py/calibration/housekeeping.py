"""Housekeeping currents sampled at their own rates, interpolated onto the magnetometer's rows.

Telemetry carries each ``current_<name>_A`` only on the rows where that channel was sampled
(empty cells elsewhere; belsten sec. 3.4.2: housekeeping is not synchronised with the
magnetometer). The rule (one function, :func:`fill_channel`, used by ``refit`` through
:func:`interpolate_currents` and by ``apply`` through :func:`merge_currents`): in time order, a row
gets the linear interpolation between the channel's sample at or before it and the sample at or
after it (a row with a sample gets the sample), if both lie in the row's session and are at most
``max_gap_s`` apart; otherwise NaN (the row then cannot be used by a model with that current).

Streaming (:func:`interpolate_currents`): the blocks come out as they went in (same rows, no
copies); a block is held back only until every channel has a sample after it, or until the
data has run ``max_gap_s`` past the channel's last sample (at most ``max_gap_s`` of data plus one
block), so memory is bounded and the result does not depend on where blocks start. Time must be
non-decreasing within a file.
"""
from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Iterable, Iterator, Mapping, Sequence

import numpy as np

from magstack.data.telemetry import TelemetryBlock
from magstack.firmware.errors import InputDataError

MAX_GAP_S = 60.0

#: A sample outside the rows (the carry before a block, the first sample after it): (t_s, value, session).
Sample = tuple[float, float, int]


def fill_channel(t_s: np.ndarray, session: np.ndarray, x: np.ndarray, max_gap_s: float = MAX_GAP_S,
                 before: Sample | None = None, after: Sample | None = None, finite: np.ndarray | None = None
                 ) -> np.ndarray:
    """(N,) values of one channel on rows in time order: its samples (finite ``x``), interpolated
    between neighbouring samples of the same session at most ``max_gap_s`` apart, else NaN.
    ``before``/``after``: the channel's last sample before the rows and first one after them;
    ``finite``: ``np.isfinite(x)`` if the caller has it."""
    fin = np.isfinite(x) if finite is None else finite
    if fin.all():
        return x.copy()
    st, sv = t_s[fin], x[fin]
    if before is not None:
        st, sv = np.r_[before[0], st], np.r_[before[1], sv]
    if after is not None:
        st, sv = np.r_[st, after[0]], np.r_[sv, after[1]]
    if st.size == 0:
        return np.full(t_s.size, np.nan)
    out = np.interp(t_s, st, sv)
    steps = np.diff(st)
    if np.any(steps == 0):
        out[fin] = x[fin]                      # a row with a sample gets that sample (ties in time)
    s0 = session[0]
    if (np.all(steps <= max_gap_s) and all(smp is None or smp[2] == s0 for smp in (before, after))
            and np.all(session == s0)):
        # common case, one session and no long gap: only rows before the first / after the last sample lack one
        has = fin.any()
        if before is None:
            out[:int(np.argmax(fin)) if has else t_s.size] = np.nan
        if after is None:
            out[t_s.size - int(np.argmax(fin[::-1])) if has else 0:] = np.nan
        return out
    ss = session[fin]
    if before is not None:
        ss = np.r_[before[2], ss]
    if after is not None:
        ss = np.r_[ss, after[2]]
    # k: the sample at or before each row (-1: none); the pair (k, k + 1) must share the row's
    # session and lie at most max_gap_s apart
    k = np.cumsum(fin) - (1 if before is None else 0)
    pair_ok = np.zeros(st.size + 1, bool)
    pair_ok[1:-1] = (ss[1:] == ss[:-1]) & (steps <= max_gap_s)
    ok = pair_ok[k + 1] & (ss[np.maximum(k, 0)] == session)
    ok |= fin
    out[~ok] = np.nan
    return out


def merge_currents(t_s, session, currents_A: Mapping[str, np.ndarray], names: Sequence[str],
                   max_gap_s: float = MAX_GAP_S) -> dict[str, np.ndarray]:
    """``{name: values}`` for whole arrays (a session in memory; ``apply``): :func:`fill_channel`
    in time order (rows are sorted by time, stably, and put back), the same rule as ``refit``."""
    if not max_gap_s > 0:
        raise InputDataError(f"max_gap_s must be > 0, got {max_gap_s}")
    t = np.asarray(t_s, float)
    sess = np.asarray(session, np.int64)
    order = None if t.size < 2 or np.all(t[1:] >= t[:-1]) else np.argsort(t, kind="stable")
    out = {}
    for k in names:
        x = np.asarray(currents_A[k], float)
        if order is None:
            out[k] = fill_channel(t, sess, x, max_gap_s)
        else:
            v = np.empty_like(x)
            v[order] = fill_channel(t[order], sess[order], x[order], max_gap_s)
            out[k] = v
    return out


class _Buffered:
    """A block with, per channel, its finite mask and the rows of its first and last sample (-1: none)."""

    def __init__(self, blk: TelemetryBlock, names: Sequence[str]) -> None:
        self.blk = blk
        self.finite = {k: np.isfinite(blk.currents_A[k]) for k in names}
        self.first = {k: int(np.argmax(f)) if f.any() else -1 for k, f in self.finite.items()}
        self.last = {k: f.size - 1 - int(np.argmax(f[::-1])) if self.first[k] >= 0 else -1
                     for k, f in self.finite.items()}

    def sample(self, name: str, row: int) -> Sample:
        return float(self.blk.t_s[row]), float(self.blk.currents_A[name][row]), int(self.blk.session[row])


def _first_after(buf: Iterable[_Buffered], name: str) -> Sample | None:
    for b in buf:
        if b.first[name] >= 0:
            return b.sample(name, b.first[name])
    return None


def _waits(buf: deque[_Buffered], name: str, carry: Sample | None, max_gap_s: float) -> bool:
    """True if rows of ``buf[0]`` may still get a value from a sample not read yet."""
    head = buf[0]
    last_row = head.last[name]
    if last_row == len(head.blk) - 1:          # the block ends on a sample: nothing waits
        return False
    last = head.sample(name, last_row) if last_row >= 0 else carry
    if last is None or any(b.first[name] >= 0 for b in list(buf)[1:]):
        return False
    return buf[-1].blk.t_s[-1] - last[0] <= max_gap_s


def interpolate_currents(blocks: Iterable[TelemetryBlock], names: Sequence[str],
                         max_gap_s: float = MAX_GAP_S) -> Iterator[TelemetryBlock]:
    """The same blocks with ``currents_A[name]`` filled by :func:`fill_channel` for every name in ``names``."""
    if not max_gap_s > 0:
        raise InputDataError(f"max_gap_s must be > 0, got {max_gap_s}")
    carry: dict[str, Sample | None] = {k: None for k in names}
    buf: deque[_Buffered] = deque()
    last_t = -np.inf

    def emit() -> TelemetryBlock:
        b = buf.popleft()
        vals = {}
        for k in names:
            vals[k] = fill_channel(b.blk.t_s, b.blk.session, b.blk.currents_A[k], max_gap_s, carry[k],
                                   _first_after(buf, k), b.finite[k])
            if b.last[k] >= 0:
                carry[k] = b.sample(k, b.last[k])
        return dataclasses.replace(b.blk, currents_A={**b.blk.currents_A, **vals})

    for blk in blocks:
        if len(blk) and (blk.t_s[0] < last_t or np.any(np.diff(blk.t_s) < 0)):
            raise InputDataError(f"{blk.path}: time t_s decreases near data row {blk.first_row + 1}: "
                                 "telemetry must be in time order within a file")
        missing = [k for k in names if k not in blk.currents_A]
        if missing:
            raise InputDataError(f"{blk.path}: no current column(s) {['current_' + k + '_A' for k in missing]}")
        if not len(blk):
            continue
        last_t = blk.t_s[-1]
        buf.append(_Buffered(blk, names))
        while buf and not any(_waits(buf, k, carry[k], max_gap_s) for k in names):
            yield emit()
    while buf:
        yield emit()
