"""Housekeeping currents sampled at their own rates, interpolated onto the magnetometer's rows.

Telemetry carries each ``current_<name>_A`` only on the rows where that channel was sampled
(empty cells elsewhere; belsten sec. 3.4.2: housekeeping is not synchronised with the
magnetometer). A row gets the linear interpolation between the channel's samples just before and
just after it (a row at a sample gets the sample), if both lie in the row's session and are at
most ``max_gap_s`` apart; otherwise NaN (the row then cannot be used by a model with that current).

Streaming: blocks go in, blocks come out in the same order; rows after a channel's last sample
wait (at most ``max_gap_s`` of data) until the next sample arrives, so the memory is bounded and
the result does not depend on where blocks start. Time must be non-decreasing within a file.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence

import numpy as np

from magstack.data.telemetry import TelemetryBlock
from magstack.firmware.errors import InputDataError

MAX_GAP_S = 60.0


def _resolve(t, s, x, carry, max_gap_s):
    """Values for rows (t, s) from samples (finite x) plus the carried sample; and the index of the
    first row that still needs a later sample (len(t) if none)."""
    samp = np.flatnonzero(np.isfinite(x))
    st, sv, ss = t[samp], x[samp], s[samp]
    if carry is not None:
        st, sv, ss = np.r_[carry[0], st], np.r_[carry[1], sv], np.r_[carry[2], ss]
    n = t.size
    out = np.full(n, np.nan)
    if st.size == 0:
        return out, n
    ip = np.searchsorted(st, t, side="right") - 1
    inx = np.searchsorted(st, t, side="left")
    has_prev = ip >= 0
    ipc = np.clip(ip, 0, st.size - 1)
    inc = np.clip(inx, 0, st.size - 1)
    has_prev &= ss[ipc] == s
    has_next = (inx < st.size) & (ss[inc] == s)
    span = st[inc] - st[ipc]
    ok = has_prev & has_next & (span <= max_gap_s)
    w = np.divide(t - st[ipc], span, out=np.zeros(n), where=span > 0)
    out[ok] = (sv[ipc] + w * (sv[inc] - sv[ipc]))[ok]
    waiting = has_prev & (inx >= st.size) & (t - st[ipc] <= max_gap_s)
    first = int(np.flatnonzero(waiting)[0]) if waiting.any() else n
    return out, first


def interpolate_currents(blocks: Iterable[TelemetryBlock], names: Sequence[str],
                         max_gap_s: float = MAX_GAP_S) -> Iterator[TelemetryBlock]:
    """Blocks with ``currents_A[name]`` filled by interpolation for every name in ``names``."""
    if not max_gap_s > 0:
        raise InputDataError(f"max_gap_s must be > 0, got {max_gap_s}")
    carry: dict[str, tuple | None] = {k: None for k in names}
    pending: TelemetryBlock | None = None
    last_t = -np.inf
    for blk in blocks:
        if len(blk) and (blk.t_s[0] < last_t or np.any(np.diff(blk.t_s) < 0)):
            raise InputDataError(f"{blk.path}: time t_s decreases near data row {blk.first_row + 1}: "
                                 "telemetry must be in time order within a file")
        if len(blk):
            last_t = blk.t_s[-1]
        work = blk if pending is None else TelemetryBlock.concatenate([pending, blk])
        out, pending = _split(work, names, carry, max_gap_s, final=False)
        if out is not None:
            yield out
    if pending is not None and len(pending):
        out, _ = _split(pending, names, carry, max_gap_s, final=True)
        if out is not None:
            yield out


def _split(work: TelemetryBlock, names, carry, max_gap_s, final):
    """(rows resolved, with values; rows still waiting for a later sample)."""
    missing = [k for k in names if k not in work.currents_A]
    if missing:
        raise InputDataError(f"{work.path}: no current column(s) {['current_' + k + '_A' for k in missing]}")
    vals, first = {}, len(work)
    for k in names:
        v, f = _resolve(work.t_s, work.session, work.currents_A[k], carry[k], max_gap_s)
        vals[k] = v
        first = min(first, f)
    if final:
        first = len(work)
    for k in names:   # carry each channel's last sample before the cut
        x = work.currents_A[k][:first]
        idx = np.flatnonzero(np.isfinite(x))
        if idx.size:
            j = idx[-1]
            carry[k] = (work.t_s[j], x[j], work.session[j])
    head = np.arange(len(work)) < first
    pending = work.select(~head) if first < len(work) else None
    out = None
    if first > 0:
        out = work.select(head)
        out.currents_A = {**out.currents_A, **{k: vals[k][:first] for k in names}}
    return out, pending
