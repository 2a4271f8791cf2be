"""Is one model better than another on held-out data? A paired test over held-out time blocks.

Both models predict the same held-out rows (each row by the fold that did not see it). Per time block the
difference of their squared errors is one paired observation. Neighbouring blocks are not independent (a slow
drift or a thermal transient spans several), so the blocks are grouped into consecutive batches (at least
``MIN_BATCHES``, the batch means of a correlated series are close to independent once a batch spans the
correlation) and the mean difference is tested against zero with a one-sided t test on the batch means.
A candidate is adopted only when its improvement is significant at ``ALPHA`` *and* at least ``MIN_GAIN`` of the
base's held-out sum of squares: within the noise, the simpler model stays.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

#: One-sided significance level of an adopted improvement.
ALPHA = 0.01
#: Smallest relative improvement of the held-out sum of squares worth a change.
MIN_GAIN = 0.01
#: Fewest batches the blocks are grouped into (fewer blocks: one block per batch).
MIN_BATCHES = 10
#: Largest number of batches (more blocks: batches of several blocks).
MAX_BATCHES = 40


@dataclass(frozen=True)
class PairedTest:
    """``gain``: relative reduction of the held-out sum of squares (candidate vs base); ``t``, ``p``: the one-sided
    batch-means t test; ``batches`` used; ``significant``: p <= ALPHA and gain >= MIN_GAIN."""

    gain: float
    t: float
    p: float
    batches: int
    blocks: int
    significant: bool

    def describe(self) -> str:
        return (f"held-out sum of squares {self.gain:+.1%} over {self.blocks} time blocks in {self.batches} batches, "
                f"one-sided p = {self.p:.3g} (adopted when p <= {ALPHA:g} and the gain >= {MIN_GAIN:.0%})")


class BlockSSE:
    """Squared held-out residuals summed per time block, keyed by (session index, block number)."""

    def __init__(self) -> None:
        self.sse: dict[tuple[int, int], float] = {}

    def add(self, session_index: np.ndarray, block: np.ndarray, sq: np.ndarray) -> None:
        """Rows' session index and block number, and their squared residual (summed over axes), uT^2."""
        if not sq.size:
            return
        key = np.asarray(session_index, dtype=np.int64) * (1 << 32) + np.asarray(block, dtype=np.int64)
        u, inv = np.unique(key, return_inverse=True)
        sums = np.bincount(inv, weights=sq)
        for k, v in zip(u.tolist(), sums.tolist(), strict=True):
            kk = (k >> 32, k & 0xFFFFFFFF)
            self.sse[kk] = self.sse.get(kk, 0.0) + v


def paired_block_test(base: Mapping[tuple[int, int], float], cand: Mapping[tuple[int, int], float]) -> PairedTest:
    """The paired test of ``cand`` against ``base`` over the blocks both predicted (see the module docstring)."""
    from scipy.stats import t as student_t

    keys = sorted(set(base) & set(cand))
    if len(keys) < 3:
        return PairedTest(0.0, 0.0, 1.0, 0, len(keys), False)
    b = np.array([base[k] for k in keys])
    c = np.array([cand[k] for k in keys])
    d = b - c
    total = float(b.sum())
    gain = float(d.sum() / total) if total > 0 else 0.0
    nb = min(MAX_BATCHES, max(MIN_BATCHES, 1), len(keys))
    batches = np.array([x.sum() for x in np.array_split(d, nb)])
    sd = float(np.std(batches, ddof=1))
    mean = float(batches.mean())
    if sd == 0.0:
        t = np.inf if mean > 0 else (0.0 if mean == 0 else -np.inf)
    else:
        t = mean / (sd / np.sqrt(nb))
    p = float(student_t.sf(t, nb - 1)) if np.isfinite(t) else (0.0 if t > 0 else 1.0)
    return PairedTest(gain, float(t), p, int(nb), len(keys), bool(p <= ALPHA and gain >= MIN_GAIN))


class BlockGrams:
    """Per held-out time block the Gram matrix ``Z'Z`` of its rows ``Z = [X | Y]`` (design and targets), so the
    block's sum of squared residuals of *any* coefficient set follows later without another pass over the data
    (:meth:`sse`). Keyed like :class:`BlockSSE`; mergeable (a map-reduce over files adds them)."""

    def __init__(self) -> None:
        self.gram: dict[tuple[int, int], np.ndarray] = {}

    def add(self, session_index: np.ndarray, block: np.ndarray, X: np.ndarray, Y: np.ndarray) -> None:
        """Rows' session index and block number, design ``X`` (N, p) and targets ``Y`` (N, 3), uT."""
        if not len(X):
            return
        Z = np.hstack([np.asarray(X, dtype=float), np.asarray(Y, dtype=float)])
        key = np.asarray(session_index, dtype=np.int64) * (1 << 32) + np.asarray(block, dtype=np.int64)
        order = np.argsort(key, kind="stable")
        ks = key[order]
        cuts = np.r_[0, np.flatnonzero(np.diff(ks)) + 1, ks.size]
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            zz = Z[order[a:b]]
            k = int(ks[a])
            kk = (k >> 32, k & 0xFFFFFFFF)
            g = zz.T @ zz
            self.gram[kk] = self.gram[kk] + g if kk in self.gram else g

    def merge(self, other: BlockGrams) -> BlockGrams:
        for k, g in other.gram.items():
            self.gram[k] = self.gram[k] + g if k in self.gram else g.copy()
        return self

    def sse(self, theta: np.ndarray) -> dict[tuple[int, int], float]:
        """Sum over the three axes of the squared residuals ``y_i - X theta_i`` per block (uT^2); ``theta``
        (3, p) with the columns an axis does not use set to 0."""
        th = np.asarray(theta, dtype=float)
        p = th.shape[1]
        Zc = np.zeros((p + 3, 3))
        Zc[:p, :] = th.T
        Zc[p:, :] = -np.eye(3)
        return {k: float(max(np.einsum("ji,jk,ki->", Zc, g, Zc), 0.0)) for k, g in self.gram.items()}
