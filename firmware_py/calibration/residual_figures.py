"""The fit's figures that need every residual, from residuals that arrive in blocks of rows.

In-sample and raw sums of squares, the noise floor (:func:`.fit.noise_floor`: MAD of residual differences
``lag_s`` apart within a session) and the step diagnosis (:func:`.steps.diagnose_steps`: a median threshold
on row-to-row reference changes, then the squared residual split at steps), equal to those functions on the
whole residual array, in memory independent of the row count. Rows must be ordered by (session, time). The
medians are exact (:mod:`.rank_select`): the step threshold is taken from the reference alone before any
residual arrives (so the step split rides on the first pass); the noise floor's median and median of absolute
deviations are bracketed about a guess from the first residuals, which decides them in that one pass on
stationary residuals. Otherwise the caller replays the same residuals while :attr:`ResidualFigures.pending`
(typically two more passes).
"""
from __future__ import annotations

import math

import numpy as np

from magstack.firmware.calibration.rank_select import ExactMedian, MedianAbsDeviation
from magstack.firmware.calibration.steps import STEP_NOISE_FACTOR, StepDiagnosis

#: Rows per block of the reference-only passes that find the step threshold.
THRESHOLD_ROWS = 1 << 16


class LagPairs:
    """The residual differences ``r[later] - r[earlier]`` of the row pairs :func:`.fit.noise_floor` forms
    (nearest row to ``t + lag_s`` in the session, within ``lag_s / 2``), for rows ordered by (session, time)
    arriving in consecutive blocks: each block gives the pairs whose later row it holds. Waiting: the
    residuals of earlier rows whose partner has not arrived (rows within ``1.5 lag_s`` of the block's end).
    A block's session runs whose every row pairs with the row a fixed number of rows later (regular
    sampling) are remembered as that shift: replays of the block then pair by slicing, and the next block is
    first checked at the same shift (no search)."""

    def __init__(self, t_s: np.ndarray, session: np.ndarray, lag_s: float) -> None:
        self.t_s, self.session, self.lag_s = t_s, session, lag_s
        self._shift: dict[tuple[int, int], int] = {}       # rows (from, to) -> their partners' offset
        self._last_shift: int | None = None                 # the offset of the last run that had one
        self.restart()

    def restart(self) -> None:
        """A new pass from the first row."""
        self._r = np.empty((3, 0))
        self._later = np.empty(0, dtype=np.int64)

    def _pairs(self, start: int, a: int, b: int, s) -> tuple[np.ndarray, np.ndarray]:
        """Block-relative (earlier, later) rows of the pairs of block rows ``a .. b`` (session ``s``). Only the
        session's times from row ``start + a`` up to the first row past the last target time are read (a
        window grown by doubling): the same pairs as searching the whole session."""
        lo = int(self.session.searchsorted(s, side="left"))
        hi = int(self.session.searchsorted(s, side="right"))
        if hi - lo < 2:
            return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
        w_lo, lag = start + a, self.lag_s
        t_last = float(self.t_s[start + b - 1]) + lag
        w_hi = min(hi, w_lo + 2 * (b - a) + 1)
        while True:
            t = self.t_s[w_lo:w_hi]
            if w_hi >= hi or t[-1] > t_last:
                break
            w_hi = min(hi, w_lo + 2 * (w_hi - w_lo))
        i = np.arange(b - a)
        ti = t[:b - a]
        x = ti + lag                    # sorted: search the window of t that can hold the answers
        j = np.clip(np.searchsorted(t, x), 1, t.size - 1)
        j = np.where(np.abs(t[j - 1] - ti - lag) < np.abs(t[j] - ti - lag), j - 1, j)  # nearest to t + lag
        good = (np.abs((t[j] - ti) - lag) <= 0.5 * lag) & (j > i)
        return a + i[good], a + j[good]

    def _at_shift(self, lo: int, hi: int, s, k: int) -> bool:
        """Whether every row ``lo .. hi`` (of session ``s``) pairs with the row ``k`` later, as :meth:`_pairs` would
        find (the same nearest-row rule and tolerance, checked for that offset alone: no search)."""
        end = int(self.session.searchsorted(s, side="right"))
        if k < 1 or hi + k + 1 > end:
            return False
        t, lag = self.t_s, self.lag_s
        ti = t[lo:hi]
        x = ti + lag
        t0, t1, t2 = t[lo + k - 1:hi + k - 1], t[lo + k:hi + k], t[lo + k + 1:hi + k + 1]
        d0, d1, d2 = np.abs(t0 - ti - lag), np.abs(t1 - ti - lag), np.abs(t2 - ti - lag)
        found_at = (t0 < x) & (x <= t1) & ~(d0 < d1)          # the search lands on the row, nearer than the one before
        found_after = (t1 < x) & (x <= t2) & (d1 < d2)        # the search lands after it, and it is nearer
        return bool(np.all((found_at | found_after) & (np.abs((t1 - ti) - lag) <= 0.5 * lag)))

    def diffs(self, start: int, r: np.ndarray) -> np.ndarray:
        """(3, k) differences completed by the block of rows ``start ..`` with residuals ``r`` (3, m)."""
        m = r.shape[1]
        s = self.session[start:start + m]
        cuts = np.r_[0, np.flatnonzero(s[1:] != s[:-1]) + 1, s.size]
        due = self._later < start + m
        out = [np.take(r, self._later[due] - start, axis=1) - self._r[:, due]]
        wait_r, wait_later = [self._r[:, ~due]], [self._later[~due]]
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            k = self._shift.get((start + a, start + b))
            if k is None and self._last_shift is not None and self._at_shift(start + a, start + b, s[a],
                                                                            self._last_shift):
                k = self._shift[(start + a, start + b)] = self._last_shift
            if k is None:
                e, lt = self._pairs(start, a, b, s[a])
                if e.size == b - a and e.size and np.all(lt - e == lt[0] - e[0]):
                    k = self._shift[(start + a, start + b)] = int(lt[0] - e[0])
            if k is not None:           # rows a .. b pair with a + k .. b + k
                self._last_shift = k
                c = max(a, min(b, m - k))
                out.append(r[:, a + k:c + k] - r[:, a:c])
                wait_r.append(r[:, c:b])
                wait_later.append(np.arange(c, b) + (start + k))
            else:
                now = lt < m
                out.append(np.take(r, lt[now], axis=1) - np.take(r, e[now], axis=1))
                wait_r.append(np.take(r, e[~now], axis=1))
                wait_later.append(lt[~now] + start)
        self._r, self._later = np.hstack(wait_r), np.concatenate(wait_later)
        return np.hstack(out)


def _changes(b_ref_uT: np.ndarray, session: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """Absolute reference change (uT, (hi - lo - 1, 3)) between consecutive rows of ``lo .. hi`` and whether
    the two rows share a session (as :func:`.steps.step_threshold_uT` and :func:`.steps.reference_steps`)."""
    return np.abs(np.diff(b_ref_uT[lo:hi], axis=0)), session[lo + 1:hi] == session[lo:hi - 1]


class ResidualFigures:
    """Feed the full fit's residuals block by block with :meth:`add` (rows ``start ..`` in order, every row
    once per pass), close each pass with :meth:`end_pass`, replay while :attr:`pending`; then
    :attr:`sse_uT2`, :attr:`raw_sse_uT2`, :meth:`noise_floor_uT` and :attr:`steps`.

    ``b_meas_uT``, ``b_ref_uT``, ``t_s``, ``session``: the fit rows, ordered by (session, time);
    ``steps``: whether to diagnose reference steps (the fit does unless it excluded them)."""

    def __init__(self, b_meas_uT, b_ref_uT, t_s, session, lag_s: float, steps: bool = True) -> None:
        self.b_meas_uT, self.b_ref_uT, self.session = b_meas_uT, b_ref_uT, session
        self.n = len(session)
        self._pairs = LagPairs(t_s, session, lag_s)
        self._pass = 0
        self.sse_uT2 = np.zeros(3)
        self.raw_sse_uT2 = np.zeros(3)
        self._mad = [MedianAbsDeviation(expected_n=self.n) for _ in range(3)]    # of the pair differences, per axis
        self._threshold = self._step_threshold() if steps else None     # of the non-zero reference changes
        self._split: np.ndarray | None = None                       # (2, 4): at steps / not: sums of r^2, count
        self._split_pass: int | None = None
        self.steps: StepDiagnosis | None = None
        self._start_pass()

    def _step_threshold(self) -> ExactMedian:
        """The median of the non-zero reference changes (max over axes) between rows of a session, found before
        any residual arrives (the reference alone decides it), so the step split rides on the first pass."""
        med = ExactMedian(expected_n=self.n)
        while med.pending:
            for a in range(0, self.n, THRESHOLD_ROWS):
                d, same = _changes(self.b_ref_uT, self.session, max(a - 1, 0), min(a + THRESHOLD_ROWS, self.n))
                d = np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2])          # max over axes
                med.feed(np.compress(same & np.isfinite(d) & (d > 0), d))
            med.end_pass()
        return med

    def _start_pass(self) -> None:
        self._pairs.restart()
        if self._threshold is not None and not self._threshold.pending and self._split is None:
            thr = STEP_NOISE_FACTOR * self._threshold.value
            if math.isfinite(thr) and thr > 0:
                self._split, self._split_pass = np.zeros((2, 4)), self._pass

    @property
    def pending(self) -> bool:
        """Another pass over the same residuals is needed."""
        return any(m.pending for m in self._mad) or self._split_pass == self._pass

    def add(self, start: int, r_uT: np.ndarray) -> None:
        """Residuals ``r_uT`` (3, m: one contiguous row per axis) of rows ``start .. start + m``."""
        stop = start + r_uT.shape[1]
        if self._pass == 0:
            self.sse_uT2 += np.einsum("ij,ij->i", r_uT, r_uT)
            raw = self.b_ref_uT[start:stop] - self.b_meas_uT[start:stop]
            self.raw_sse_uT2 += np.einsum("ij,ij->j", raw, raw)
        if self._split_pass == self._pass:
            self._add_split(start, r_uT)
        if any(m.pending for m in self._mad):
            diff = self._pairs.diffs(start, r_uT)
            for a in range(3):
                self._mad[a].feed(diff[a])

    def _add_split(self, start: int, r_uT: np.ndarray) -> None:
        stop = start + r_uT.shape[1]
        lo, hi = max(start - 1, 0), min(stop + 1, self.n)
        d, same = _changes(self.b_ref_uT, self.session, lo, hi)
        thr = STEP_NOISE_FACTOR * self._threshold.value
        big = ((d[:, 0] > thr) | (d[:, 1] > thr) | (d[:, 2] > thr)) & same     # any axis; NaN compares False
        at = np.zeros(hi - lo, dtype=bool)             # rows lo .. hi
        at[1:] |= big
        at[:-1] |= big
        at = at[start - lo:stop - lo]
        sq = r_uT ** 2
        for k, rows in enumerate((at, ~at)):
            self._split[k, :3] += np.compress(rows, sq, axis=1).sum(axis=1)
            self._split[k, 3] += np.count_nonzero(rows)

    def end_pass(self) -> None:
        """Close a pass over every row."""
        for m in self._mad:
            if m.pending:
                m.end_pass()
        if self._split_pass == self._pass:
            self._split_pass = -1
            self.steps = self._diagnosis()
        self._pass += 1
        self._start_pass()

    def _diagnosis(self) -> StepDiagnosis | None:
        s = self._split
        if s[0, 3] < 10 or s[1, 3] < 10:
            return None
        total = float(s[:, :3].sum())
        return StepDiagnosis(STEP_NOISE_FACTOR * self._threshold.value, int(s[0, 3]), int(s[1, 3]),
                             np.sqrt(s[0, :3] / s[0, 3]), np.sqrt(s[1, :3] / s[1, 3]),
                             float(s[0, :3].sum()) / total if total > 0 else 0.0)

    def noise_floor_uT(self) -> np.ndarray:
        """(3,) as :func:`.fit.noise_floor` (NaN for fewer than 10 pairs)."""
        if self._mad[0].center.n < 10:
            return np.full(3, np.nan)
        return np.array([1.4826 * m.value / np.sqrt(2.0) for m in self._mad])
