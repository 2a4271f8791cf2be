"""Residual autocorrelation by the blocking method, accumulated block by block (memory flat in rows).

Residuals of each session, in time order, are cut into blocks of ``L = 2, 4, 8, ...`` rows from the
session's start; ``kappa(L) = L var(block means) / var(rows)`` estimates the integrated autocorrelation
time. Blocks of ``2L`` rows are pairs of blocks of ``L`` rows, so the block means of every ``L`` are built
by pairwise averaging as the rows arrive; per level only the count, sum and sum of squares of the
complete block means are kept, plus at most one pending (odd) block mean per level. A session's last,
incomplete blocks are dropped, as in the one-shot definition (:func:`.estimator.autocorr_inflation`).

Beside the spread, each level (and the rows themselves) keeps the sum of squared differences of *adjacent* block
means within a session (an Allan-type statistic, :meth:`BlockingInflation.adjacent_levels`): it sees a slow
random walk from short blocks on, which the spread about the mean does only once blocks span the session
(:mod:`.predictive` turns it into white and random-walk levels).
"""
from __future__ import annotations

import numpy as np


class BlockingInflation:
    """Accumulate residuals with :meth:`add`, then :meth:`kappa`.

    Residuals arrive series-first, ``(k, m)`` uT (``k`` = 3 output axes by default, or the axes of several fits of
    the same rows stacked: each series is accumulated on its own, exactly as alone; a contiguous row per series: the
    reductions run along memory), ordered by (session, time): a session's rows contiguous, possibly over several
    calls.
    The spread is taken about the accumulated mean, so any centre gives the same result up to rounding;
    callers subtract (an estimate of) the mean first so that rounding stays at the level of the spread.
    """

    def __init__(self, k: int = 3, adjacent: bool = True) -> None:
        self.k = k
        self.adjacent = adjacent             # False: kappa only (no adjacent_levels), at less cost
        self.n = 0
        self._sum = np.zeros(k)
        self._sum_sq = np.zeros(k)
        self._count: list[int] = []              # level j: blocks of 2**(j+1) rows
        self._s1: list[np.ndarray] = []
        self._s2: list[np.ndarray] = []
        self._carry: list[np.ndarray | None] = []
        self._last: list[np.ndarray | None] = []    # per level (0 = rows): the session's last complete item
        self._dcount: list[int] = []
        self._d2: list[np.ndarray] = []
        self._session = None

    def add(self, resid_uT, session) -> None:
        """Residuals ``resid_uT`` (k, m) of rows of sessions ``session`` (m,), in (session, time) order."""
        r = np.asarray(resid_uT, dtype=float).reshape(self.k, -1)
        s = np.asarray(session).reshape(-1)
        if r.shape[1] == 0:
            return
        self.n += r.shape[1]
        self._sum += r.sum(axis=1)
        self._sum_sq += np.einsum("ij,ij->i", r, r)
        cuts = np.r_[0, np.flatnonzero(s[1:] != s[:-1]) + 1, s.size]
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            if self._session is None or s[a] != self._session:
                self._session = s[a]
                self._carry = []
                self._last = []
            if self.adjacent:
                self._adjacent(0, r[:, a:b])
            self._climb(r[:, a:b])

    def _climb(self, items: np.ndarray) -> None:
        """Pair up ``items`` (k, n: means of 2**j rows) level by level, keeping an odd one pending."""
        j = 0
        while items.shape[1]:
            if j == len(self._carry):
                self._carry.append(None)
            if self._carry[j] is not None:
                items = np.hstack([self._carry[j], items])
            k = items.shape[1] // 2
            self._carry[j] = items[:, -1:].copy() if items.shape[1] % 2 else None
            pairs = np.add(items[:, 0:2 * k:2], items[:, 1:2 * k:2])
            pairs *= 0.5
            items = pairs
            if k:
                if self.adjacent:
                    self._adjacent(j + 1, items)
                if j == len(self._count):
                    self._count.append(0)
                    self._s1.append(np.zeros(self.k))
                    self._s2.append(np.zeros(self.k))
                self._count[j] += k
                self._s1[j] += items.sum(axis=1)
                self._s2[j] += np.einsum("ij,ij->i", items, items)
            j += 1

    def _adjacent(self, level: int, items: np.ndarray) -> None:
        """Squared differences of adjacent items (k, n) of ``level`` (means of 2**level rows), this session."""
        while len(self._last) <= level:
            self._last.append(None)
        while len(self._dcount) <= level:
            self._dcount.append(0)
            self._d2.append(np.zeros(self.k))
        prev = self._last[level]
        if prev is not None:                 # the pair across calls
            e = items[:, 0] - prev[:, 0]
            self._dcount[level] += 1
            self._d2[level] += e * e
        if items.shape[1] > 1:
            d = np.subtract(items[:, 1:], items[:, :-1])
            self._dcount[level] += d.shape[1]
            self._d2[level] += np.einsum("ij,ij->i", d, d)
        self._last[level] = items[:, -1:].copy()

    def adjacent_levels(self) -> list[tuple[int, int, np.ndarray]]:
        """``[(L rows per block, number of adjacent pairs, mean squared difference (k,) uT^2)]``, L = 1, 2, 4...
        (empty for an accumulator made with ``adjacent=False``)."""
        return [(2 ** j, k, self._d2[j] / k) for j, k in enumerate(self._dcount) if k]

    def kappa(self, min_blocks: int = 16, cap: float = 1e4) -> np.ndarray:
        """(k,) ``kappa >= 1``: the largest ``kappa(L)`` over the ``L`` that leave at least ``min_blocks``
        blocks, capped at ``cap``; 1 for fewer than ``2 min_blocks`` rows."""
        out = np.ones(self.k)
        if self.n < 2 * min_blocks:
            return out
        mean = self._sum / self.n
        v = self._sum_sq / self.n - mean ** 2
        v = np.where(v > 0, v, 1.0)
        for j, k in enumerate(self._count):
            if k < min_blocks:
                break
            spread = self._s2[j] / k - 2.0 * mean * self._s1[j] / k + mean ** 2
            out = np.maximum(out, 2 ** (j + 1) * spread / v)
        return np.minimum(np.maximum(out, 1.0), cap)
