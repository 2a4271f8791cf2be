"""The rows of a fit's input that a mask keeps, without copying them (fit memory flat in rows).

A fit drops rows (NaN, a disqualifying flag, zero weight, a saturated reference, a reference step). Copying the
kept rows of every column costs ~90 B per row; :class:`KeptRows` instead numbers the kept rows 0 .. n-1 and
resolves a range of them to the parent's row numbers block by block (per BLOCK_ROWS block of the parent only its
count of kept rows is stored). :class:`KeptColumn` is one column seen through it: indexing by a slice or by an
integer array gathers just those rows, ``searchsorted`` works on a sorted column, and anything else gets the
gathered column (``__array__``). The cross-fit (:mod:`.crossfit`) and the streamed figures
(:mod:`.residual_figures`) touch their rows only through such indexing, block by block.
"""
from __future__ import annotations

import numpy as np

#: Parent rows per block of the kept-row count table (the same blocks as the fit's passes).
BLOCK_ROWS = 65536
#: Resolved row ranges and parent blocks kept (the passes read each block's columns together).
RECENT = 4


class KeptRows:
    """Row numbering of the rows of a parent where ``mask`` (N,) is True. Memory: the mask (the caller's, not
    copied, never written) and N / BLOCK_ROWS counts; the last RECENT ranges and parent blocks resolved are
    kept (a block's columns are read one after another, with a row of overlap)."""

    def __init__(self, mask: np.ndarray) -> None:
        self.mask = np.asarray(mask, dtype=bool).reshape(-1)
        counts = [np.count_nonzero(self.mask[a:a + BLOCK_ROWS]) for a in range(0, self.mask.size, BLOCK_ROWS)]
        self.cum = np.r_[0, np.cumsum(counts, dtype=np.int64)]
        self.n = int(self.cum[-1])
        self._recent: dict[tuple[int, int], np.ndarray] = {}
        self._blocks: dict[int, np.ndarray] = {}

    def parent_range(self, lo: int, hi: int) -> np.ndarray:
        """Parent row numbers (hi - lo,) of kept rows ``lo .. hi`` (0 <= lo <= hi <= n)."""
        got = self._recent.get((lo, hi))
        if got is not None:
            return got
        if hi <= lo:
            return np.empty(0, dtype=np.intp)
        j0 = int(np.searchsorted(self.cum, lo, side="right")) - 1
        j1 = int(np.searchsorted(self.cum, hi - 1, side="right")) - 1
        parts = [self._block(j) for j in range(j0, j1 + 1)]
        first = int(self.cum[j0])
        rows = (parts[0] if len(parts) == 1 else np.concatenate(parts))[lo - first:hi - first]
        if len(self._recent) >= RECENT:
            del self._recent[next(iter(self._recent))]           # the oldest
        self._recent[(lo, hi)] = rows
        return rows

    def _block(self, j: int) -> np.ndarray:
        """Parent row numbers of the kept rows of parent block ``j`` (the last RECENT blocks kept: the passes
        sweep the blocks in order, each range touching one or two)."""
        got = self._blocks.get(j)
        if got is None:
            got = j * BLOCK_ROWS + np.flatnonzero(self.mask[j * BLOCK_ROWS:(j + 1) * BLOCK_ROWS])
            if len(self._blocks) >= RECENT:
                del self._blocks[next(iter(self._blocks))]
            self._blocks[j] = got
        return got

    def parent_span(self, lo: int, hi: int) -> tuple[int, int]:
        """Parent rows ``p0 .. p1`` whose kept ones are exactly kept rows ``lo .. hi`` (lo < hi)."""
        rows = self.parent_range(lo, hi)
        return int(rows[0]), int(rows[-1]) + 1

    def parent_rows(self, idx) -> np.ndarray:
        """Parent row numbers of kept rows ``idx``: a slice, an integer array or an integer."""
        if isinstance(idx, slice):
            lo, hi, step = idx.indices(self.n)
            if step == 1:
                return self.parent_range(lo, max(lo, hi))
            idx = np.arange(lo, hi, step)
        idx = np.asarray(idx)
        if idx.dtype == bool:
            raise TypeError("KeptRows: boolean indexing is not supported (use the row numbers)")
        if idx.size == 0:
            return np.empty(idx.shape, dtype=np.intp)
        idx = np.where(idx < 0, idx + self.n, idx)
        lo, hi = int(idx.min()), int(idx.max()) + 1
        if lo < 0 or hi > self.n:
            raise IndexError(f"kept row {hi - 1 if hi > self.n else lo} out of range 0 .. {self.n - 1}")
        return self.parent_range(lo, hi)[idx - lo]


class KeptColumn:
    """Column ``base`` (N, ...) of a parent seen through :class:`KeptRows`: ``len``, ``shape``, indexing by
    row slices and integer arrays (gathered), ``searchsorted`` of a sorted column; ``np.asarray`` gathers it
    all."""

    def __init__(self, rows: KeptRows, base: np.ndarray) -> None:
        self.rows, self.base = rows, base
        self.shape = (rows.n,) + base.shape[1:]
        self.ndim, self.dtype = base.ndim, base.dtype
        # a C-ordered 2-D column as one record per row: a row range's kept rows are then gathered by the mask
        # itself (~3x faster than taking the rows of an (N,3) float array by their numbers)
        self._records = (base.reshape(base.shape[0], -1).view(np.dtype((np.void, base.itemsize * int(
            np.prod(base.shape[1:]))))).reshape(-1) if base.ndim > 1 and base.flags.c_contiguous else None)
        self._found: dict[tuple, int] = {}

    def __len__(self) -> int:
        return self.rows.n

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __getitem__(self, idx):
        rest = ()
        if isinstance(idx, tuple):
            idx, rest = idx[0], idx[1:]
        if isinstance(idx, slice) and idx.step in (None, 1):        # a row range: gathered by the mask
            lo, hi, _ = idx.indices(self.rows.n)
            out = self._range(lo, hi)
            return out[(slice(None),) + rest] if rest else out
        scalar = isinstance(idx, (int, np.integer))
        out = np.take(self.base, self.rows.parent_rows(np.array([idx]) if scalar else idx), axis=0)
        if scalar:
            out = out[0]
        return out[(slice(None),) * (not scalar) + rest] if rest else out

    def _range(self, lo: int, hi: int) -> np.ndarray:
        if hi <= lo:
            return self.base[:0]
        p0, p1 = self.rows.parent_span(lo, hi)
        keep = self.rows.mask[p0:p1]
        if self._records is None:
            return self.base[p0:p1][keep]
        return self._records[p0:p1][keep].view(self.dtype).reshape((hi - lo,) + self.base.shape[1:])

    def searchsorted(self, v, side: str = "left") -> int:
        """Index where scalar ``v`` would go in this (sorted) column: a bisection over the kept rows (answers
        kept: the streamed figures ask for the same session's bounds on every block and pass)."""
        key = (v.item() if isinstance(v, np.generic) else v, side)
        if key not in self._found:
            self._found[key] = self._bisect(v, side)
        return self._found[key]

    def _bisect(self, v, side: str) -> int:
        lo, hi = 0, self.rows.n
        while lo < hi:
            mid = (lo + hi) // 2
            x = self[mid]
            if x < v or (side == "right" and x == v):
                lo = mid + 1
            else:
                hi = mid
        return lo

    def __array__(self, dtype=None, copy=None):
        out = self._range(0, self.rows.n)
        return out if dtype is None else out.astype(dtype, copy=False)
