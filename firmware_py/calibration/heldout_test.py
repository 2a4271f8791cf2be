"""Is one model better than another on held-out data? A paired test over held-out time blocks.

Both models predict the same held-out rows (each row by the fold that did not see it). Per time block the
difference of their squared errors is one paired observation. Neighbouring blocks are not independent (a slow
drift or a thermal transient spans several), so the blocks are grouped into consecutive batches (at least
``MIN_BATCHES``, the batch means of a correlated series are close to independent once a batch spans the
correlation) and the mean difference is tested against zero with a one-sided t test on the batch means.
A candidate is adopted only when its improvement is significant at ``ALPHA`` *and* at least ``MIN_GAIN`` of the
base's held-out sum of squares: within the noise, the simpler model stays.

``scale_free=True`` (the refit's comparison of a candidate with the active table) adds the same t test on the log
ratio of the batches' sums of squares: where the error's scale differs from block to block (an orbit's attitude and
field change along it) the differences are dominated by the largest blocks, and with a handful of blocks a large but
uneven improvement is not significant on them; the log ratios are. The two p values are combined by Bonferroni
(twice the smaller), so the level stays ``ALPHA``.

With fewer than ``MIN_BATCHES`` held-out blocks (an orbit refit over an hour or two) the blocks alone cannot carry
the test; :func:`paired_test_over_parts` then pairs the blocks' ``PARTS_PER_BLOCK`` consecutive parts instead and the
result says so (``parts_of``): the parts of one block are not independent, so such a result speaks for these blocks,
not for time in general.
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
#: Parts a held-out block is scored in, so a test over few blocks can pair their parts.
PARTS_PER_BLOCK = 10


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
    scale_free: bool = False
    parts_of: int = 0

    def describe(self) -> str:
        how = "differences and log ratios, Bonferroni" if self.scale_free else "differences"
        over = (f"{self.blocks} parts of {self.parts_of} time blocks" if self.parts_of
                else f"{self.blocks} time blocks")
        return (f"held-out sum of squares {self.gain:+.1%} over {over} in {self.batches} batches, "
                f"one-sided p = {self.p:.3g} ({how}; adopted when p <= {ALPHA:g} and the gain >= {MIN_GAIN:.0%})")


class BlockSSE:
    """Squared held-out residuals summed per time block, keyed by (session index, block number)."""

    def __init__(self) -> None:
        self.sse: dict[tuple[int, int], float] = {}

    def add(self, session_index: np.ndarray, block: np.ndarray, sq: np.ndarray) -> None:
        """Rows' session index and block number, and their squared residual (summed over axes), uT^2."""
        self.add_grouped(self.group(session_index, block), sq)

    @staticmethod
    def group(session_index: np.ndarray, block: np.ndarray) -> tuple[list, np.ndarray | None, np.ndarray | None]:
        """``(keys, starts, inverse)`` of rows' (session index, block number), for :meth:`add_grouped` (rows of
        several models' residuals share it): ``starts`` of runs of one key when the rows come in key order, else
        ``inverse`` (each row's key)."""
        key = np.asarray(session_index, dtype=np.int64) * (1 << 32) + np.asarray(block, dtype=np.int64)
        if key.size and np.all(key[1:] >= key[:-1]):
            starts = np.r_[0, np.flatnonzero(key[1:] != key[:-1]) + 1]
            u, inv = key[starts], None
        else:
            u, inv = np.unique(key, return_inverse=True)
            starts = None
        return [(int(k) >> 32, int(k) & 0xFFFFFFFF) for k in u.tolist()], starts, inv

    def add_grouped(self, group: tuple, sq: np.ndarray) -> None:
        """:meth:`add` with the rows' keys grouped by :meth:`group`."""
        if not sq.size:
            return
        keys, starts, inv = group
        sums = np.add.reduceat(sq, starts) if inv is None else np.bincount(inv, weights=sq)
        sse = self.sse
        for kk, v in zip(keys, sums.tolist(), strict=True):
            sse[kk] = sse.get(kk, 0.0) + v


def _one_sided_t(x: np.ndarray) -> tuple[float, float]:
    """t statistic of mean(x) > 0 and its one-sided p (Student, len(x) - 1 degrees of freedom)."""
    from scipy.special import stdtr

    sd, mean, n = float(np.std(x, ddof=1)), float(x.mean()), x.size
    if sd == 0.0:
        t = np.inf if mean > 0 else (0.0 if mean == 0 else -np.inf)
    else:
        t = mean / (sd / np.sqrt(n))
    p = float(stdtr(n - 1, -t)) if np.isfinite(t) else (0.0 if t > 0 else 1.0)
    return float(t), p


def paired_block_test(base: Mapping[tuple[int, int], float], cand: Mapping[tuple[int, int], float],
                      scale_free: bool = False) -> PairedTest:
    """The paired test of ``cand`` against ``base`` over the blocks both predicted (see the module docstring)."""
    keys = sorted(set(base) & set(cand))
    if len(keys) < 3:
        return PairedTest(0.0, 0.0, 1.0, 0, len(keys), False, scale_free)
    b = np.array([base[k] for k in keys])
    c = np.array([cand[k] for k in keys])
    d = b - c
    total = float(b.sum())
    gain = float(d.sum() / total) if total > 0 else 0.0
    nb = min(MAX_BATCHES, max(MIN_BATCHES, 1), len(keys))
    parts = np.array_split(np.arange(len(keys)), nb)
    t, p = _one_sided_t(np.array([d[i].sum() for i in parts]))
    if scale_free:
        tiny = np.finfo(float).tiny
        ratio = np.array([np.log(max(b[i].sum(), tiny) / max(c[i].sum(), tiny)) for i in parts])
        t2, p2 = _one_sided_t(ratio)
        if p2 < p:
            t = t2
        p = min(1.0, 2.0 * min(p, p2))
    return PairedTest(gain, t, p, int(nb), len(keys), bool(p <= ALPHA and gain >= MIN_GAIN), scale_free)


def paired_test_over_parts(base: Mapping[tuple[int, int], float], cand: Mapping[tuple[int, int], float],
                           scale_free: bool = False) -> PairedTest:
    """:func:`paired_block_test` on sums of squares keyed by block *part* (``(session, part)``, ``part //
    PARTS_PER_BLOCK`` the block): over whole blocks when there are at least ``MIN_BATCHES`` of them, else over
    their parts (``parts_of`` then holds the number of blocks)."""
    def by_block(d: Mapping[tuple[int, int], float]) -> dict[tuple[int, int], float]:
        out: dict[tuple[int, int], float] = {}
        for (sess, part), v in d.items():
            k = (sess, part // PARTS_PER_BLOCK)
            out[k] = out.get(k, 0.0) + v
        return out

    b, c = by_block(base), by_block(cand)
    n_blocks = len(set(b) & set(c))
    if n_blocks >= MIN_BATCHES:
        return paired_block_test(b, c, scale_free)
    r = paired_block_test(base, cand, scale_free)
    return PairedTest(r.gain, r.t, r.p, r.batches, r.blocks, r.significant, r.scale_free, n_blocks)


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
