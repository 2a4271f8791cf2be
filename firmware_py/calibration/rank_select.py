"""Exact medians of a stream that can be replayed, in memory bounded independently of its length.

Radix selection on the bits of the values: float64 values map to unsigned 64-bit keys in the same order
(:func:`order_keys`). The first pass counts the keys' top 16 bits (65,536 bins) and finds the bin holding the
wanted rank; each further pass either counts the next 16 bits of the keys in that bin or, once the bin holds at
most ``cap`` values, collects them and takes the rank with ``np.partition``. Ties need nothing special: at most
four counting passes fix all 64 bits. The answer is the element ``np.median`` would pick (the mean of the two
middle elements for an even count, computed as ``np.median`` does), so equal to it, not an approximation.

Given the number of values a pass will carry, the first values fed also set a guess (:class:`Bracket`): the values
in a few intervals about the guessed median (and, for the deviations, about the median plus and minus the guessed
deviation) are collected and the others counted per gap. Where the wanted ranks fall inside (stationary data), the
answer is exact after that one pass; where they do not, the passes above follow, from the next pass on.
"""
from __future__ import annotations

import numpy as np

#: Values collected at most per wanted rank (8 bytes each): above it, another counting pass narrows the bin.
COLLECT_CAP = 1 << 18
#: Share of :data:`COLLECT_CAP` a guessed :class:`Bracket` is sized to hold (the rest is headroom).
GUESS_FILL = 0.75
#: Fewest first values a guess is made from.
GUESS_MIN_VALUES = 2000
_BITS = 16
_SIGN = np.uint64(1 << 63)


def order_keys(values: np.ndarray) -> np.ndarray:
    """Unsigned 64-bit keys of float64 ``values`` (no NaN) in the values' order (-0.0 just below +0.0)."""
    u = np.ascontiguousarray(values, dtype=np.float64).view(np.uint64)
    return np.where(u & _SIGN, ~u, u | _SIGN)


def key_values(keys: np.ndarray) -> np.ndarray:
    """The float64 values of :func:`order_keys` keys."""
    k = np.asarray(keys, dtype=np.uint64)
    return np.where(k & _SIGN, k & ~_SIGN, ~k).view(np.float64)


def _prefix_range(prefix, known: int) -> np.ndarray:
    """(2, ...) smallest and largest value whose key's top ``known`` bits are ``prefix``."""
    p = np.asarray(prefix, dtype=np.uint64) << np.uint64(64 - known)
    return key_values(np.stack([p, p | np.uint64((1 << (64 - known)) - 1)]))


def _weighted_rank(x: np.ndarray, w: np.ndarray, rank: int) -> float:
    """The ``rank``-th (0-based) smallest of values ``x`` each repeated ``w`` times."""
    o = np.argsort(x, kind="stable")
    return float(x[o][np.searchsorted(np.cumsum(w[o]), rank, side="right")])


class _Target:
    """One wanted rank: the keys' top ``known`` bits are ``prefix``; ``below`` values have smaller keys,
    ``count`` share the prefix."""

    def __init__(self, rank: int) -> None:
        self.rank, self.prefix, self.known, self.below, self.count = rank, 0, 0, 0, 0
        self.hist: np.ndarray | None = None
        self.got: list[np.ndarray] = []
        self.value: float | None = None

    def start_pass(self) -> None:
        self.got = []
        self.hist = None if self.count <= COLLECT_CAP else np.zeros(1 << _BITS, dtype=np.int64)

    def feed(self, v: np.ndarray, k: np.ndarray) -> None:
        inside = (k >> np.uint64(64 - self.known)) == np.uint64(self.prefix)
        v, k = v[inside], k[inside]
        if self.hist is None:
            self.got.append(v)
        else:
            self.hist += np.bincount(((k >> np.uint64(64 - self.known - _BITS)) & np.uint64(0xFFFF)).astype(np.intp),
                                     minlength=1 << _BITS)

    def end_pass(self) -> None:
        if self.hist is not None:
            self.narrow(self.hist)
            return
        v = np.concatenate(self.got) if self.got else np.empty(0)
        self.got = []
        if v.size != self.count:
            raise RuntimeError(f"stream replayed {v.size} values where {self.count} were counted")
        self.take(v)

    def take(self, v: np.ndarray) -> None:
        """The value from all ``v`` sharing the prefix."""
        r = self.rank - self.below
        self.value = float(np.partition(v, r)[r])

    def narrow(self, hist: np.ndarray) -> None:
        """Fix the next 16 bits from ``hist``, their counts among the keys sharing the prefix."""
        c = np.cumsum(hist)
        b = int(np.searchsorted(c, self.rank - self.below, side="right"))
        self.below += int(c[b - 1]) if b else 0
        self.prefix, self.known, self.count = (self.prefix << _BITS) | b, self.known + _BITS, int(hist[b])
        if self.known == 64:            # every bit fixed: the value is the key
            self.value = float(key_values(np.array([self.prefix]))[0])


class Bracket:
    """The values of one pass that fall in a few intervals ``[lo, hi)`` collected, the others counted below each
    edge: any rank whose value falls in an interval is then known exactly (:meth:`rank_value`), and so is any
    rank of the deviations from a point whose value is decided by collected values alone
    (:meth:`deviation_rank_value`). More than ``cap`` collected values: the bracket gives up (:attr:`full`)."""

    def __init__(self, intervals: list[tuple[float, float]], cap: int) -> None:
        merged: list[list[float]] = []
        for lo, hi in sorted((float(a), float(b)) for a, b in intervals if b > a):
            if merged and lo <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], hi)
            else:
                merged.append([lo, hi])
        self.edges = np.array([e for pair in merged for e in pair], dtype=np.float64)
        self.below = np.zeros(self.edges.size, dtype=np.int64)     # values below each edge
        self.n = 0
        self.cap = cap
        self.full = False
        self._got: list[np.ndarray] = []
        self._n_got = 0
        self._values: np.ndarray | None = None

    def feed(self, v: np.ndarray) -> None:
        self.n += v.size
        if self.full or not self.edges.size:
            return
        lt = [v < e for e in self.edges]
        self.below += np.array([np.count_nonzero(x) for x in lt], dtype=np.int64)
        inside = lt[0] ^ lt[1]                  # below an odd number of edges: inside an interval
        for x in lt[2:]:
            inside ^= x
        keep = np.compress(inside, v)                 # (several times faster than v[inside] on scattered rows)
        self._n_got += keep.size
        if self._n_got > self.cap:
            self.full, self._got = True, []
        else:
            self._got.append(keep)

    def _collected(self) -> np.ndarray:
        if self._values is None:
            self._values = np.concatenate(self._got) if self._got else np.empty(0)
            self._got = []
        return self._values

    def rank_value(self, rank: int) -> float | None:
        """The ``rank``-th (0-based) smallest value fed, or None where it is not in an interval."""
        if self.full:
            return None
        off = 0
        for i in range(0, self.edges.size, 2):
            lo, hi = int(self.below[i]), int(self.below[i + 1])
            if lo <= rank < hi:
                return _kth(self._collected(), off + rank - lo)
            off += hi - lo
        return None

    def deviation_rank_value(self, c: float, rank: int) -> float | None:
        """The ``rank``-th smallest of ``|x - c|`` over every value ``x`` fed, or None where a gap between the
        intervals (values only counted) may hold deviations equal to it. ``fl(|x - c|)`` is monotone in ``x`` on
        either side of ``c``, so a gap's deviations lie between those of its edges: away from those ranges a gap
        counts whole or not at all, and the answer is the collected deviations' element of rank ``rank`` less
        the gaps' rows below it (each distinct such count tried)."""
        if self.full:
            return None
        dev = np.abs(self._collected() - c)
        edges = np.r_[-np.inf, self.edges, np.inf]
        counts = np.diff(np.r_[0, self.below, self.n])[0::2]                    # per gap
        lo, hi = edges[0::2], edges[1::2]
        with np.errstate(invalid="ignore"):
            dl, dh = np.abs(lo - c), np.abs(hi - c)
        used = counts > 0
        dmin = np.where((lo <= c) & (c <= hi), 0.0, np.minimum(dl, dh))[used]
        dmax, counts = np.maximum(dl, dh)[used], counts[used]
        for below in sorted({int(counts[dmax < m].sum()) for m in np.r_[dmax, np.inf]}):
            r = rank - below
            if not 0 <= r < dev.size:
                continue
            m = _kth(dev, r)
            if int(counts[dmax < m].sum()) == below and not np.any((dmin <= m) & (m <= dmax)):
                return m
        return None


def _kth(a: np.ndarray, k: int) -> float:
    """The ``k``-th (0-based) smallest element of ``a``."""
    return float(np.partition(a, k)[k])


def _ranked(v: np.ndarray, shares: list[float]) -> list[float]:
    """The elements of ``v`` at the given shares of its sorted order (nearest rank; one partition)."""
    k = [min(int(round(q * (v.size - 1))), v.size - 1) for q in shares]
    part = np.partition(v, sorted(set(k)))
    return [float(part[i]) for i in k]


def guess_intervals(v: np.ndarray, share: float, deviations: bool) -> tuple[float, list[tuple[float, float]]]:
    """Intervals expected to hold about ``share`` of a stream like ``v`` (its first values) and the ranks that
    decide its median (and, ``deviations``, the median of its absolute deviations from the median): the middle
    ``share / 3`` of ``v`` and the middle ``2 share / 3`` of its deviations on either side (or the middle
    ``share`` alone), by nearest rank. Returns the guessed median and the intervals."""
    q = share / 3.0 if deviations else share
    c, lo, hi = _ranked(v, [0.5, max(0.5 - q / 2, 0.0), min(0.5 + q / 2, 1.0)])
    iv = [(lo, hi)]
    if deviations:
        d_lo, d_hi = _ranked(np.abs(v - c), [max(0.5 - q, 0.0), min(0.5 + q, 1.0)])
        iv += [(c - d_hi, c - d_lo), (c + d_lo, c + d_hi)]
    iv = [(lo, float(np.nextafter(hi, np.inf))) for lo, hi in iv]             # the upper quantile inside
    return c, iv


def open_guess(v: np.ndarray, expected_n: int | None, deviations: bool) -> Bracket | None:
    """The :class:`Bracket` of a pass of about ``expected_n`` values whose first values are ``v``: everything when
    :data:`COLLECT_CAP` holds them all, else intervals about the guess from ``v`` (:func:`guess_intervals`), or
    None when ``v`` is too few to guess from."""
    if expected_n is None:
        return None
    share = GUESS_FILL * COLLECT_CAP / max(expected_n, 1)
    if share >= 1.0:
        return Bracket([(-np.inf, np.inf)], COLLECT_CAP)
    if v.size < GUESS_MIN_VALUES:
        return None
    return Bracket(guess_intervals(v, share, deviations)[1], COLLECT_CAP)


def _fed_guess(stat, v: np.ndarray, deviations: bool) -> bool:
    """Feed ``v`` to the guessed bracket of ``stat`` (an :class:`ExactMedian` or :class:`MedianAbsDeviation` in
    its first pass, ``expected_n`` given), opening it from these first values; False where there is none (no
    ``expected_n``, or too few values to guess from: then none is tried again)."""
    if stat._expected_n is None:
        return False
    if stat._guess is None:
        stat._guess = open_guess(v, stat._expected_n, deviations)
        if stat._guess is None:
            stat._expected_n = None
            return False
    stat._guess.feed(v)
    return True


def _median_ranks(n: int) -> list[int]:
    return sorted({(n - 1) // 2, n // 2})


def _mean_of(values: list[float]) -> float:
    """The mean of the middle values, as ``np.median`` takes it."""
    return float(np.mean(np.array(values)))


class ExactMedian:
    """``np.median`` of all values passed to :meth:`feed` during one pass; while :attr:`pending` after
    :meth:`end_pass`, the same values are fed again (any chunking and order) and the pass closed again.
    :attr:`value` is then the median (NaN for no values). A first pass of at most :data:`COLLECT_CAP`
    values is the only one, and so is one whose median falls in the guessed bracket when ``expected_n`` (about the
    number of values per pass) is given (module docstring)."""

    def __init__(self, expected_n: int | None = None) -> None:
        self.n = 0
        self.top_hist = np.zeros(1 << _BITS, dtype=np.int64)                   # first pass: top 16 bits
        self._first: list[np.ndarray] | None = []                              # ... and the values, if few
        self._targets: list[_Target] | None = None
        self._known: float | None = None
        self._expected_n = expected_n
        self._guess: Bracket | None = None          # the first pass's guess (counting starts a pass later if wrong)
        self.passes = 0

    @property
    def pending(self) -> bool:
        return self._known is None and (self._targets is None or any(t.value is None for t in self._targets))

    def settle(self, value: float, n: int) -> None:
        """The median ``value`` of the ``n`` values of a pass, found otherwise (no more passes)."""
        self._known, self.n, self._targets = value, n, []
        self.passes = max(self.passes, 1)

    def feed(self, values: np.ndarray) -> None:
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if not v.size or not self.pending:
            return
        if _fed_guess(self, v, deviations=False):
            return
        k = order_keys(v)
        if self._targets is None:
            self.n += v.size
            self.top_hist += np.bincount((k >> np.uint64(64 - _BITS)).astype(np.intp), minlength=1 << _BITS)
            if self._first is not None and self.n <= COLLECT_CAP:
                self._first.append(v.copy())
            else:
                self._first = None
            return
        for t in self._targets:
            if t.value is None:
                t.feed(v, k)

    def end_pass(self) -> None:
        """Close a pass over all values; replay them while :attr:`pending`."""
        if self._guess is not None:
            g, self._guess, self._expected_n = self._guess, None, None
            got = [g.rank_value(r) for r in _median_ranks(g.n)] if g.n else []
            if g.n and None not in got:
                self.settle(_mean_of(got), g.n)
            return                                   # else the counting passes start with the next pass
        self.passes += 1
        if self._targets is None:
            self._targets = [_Target(r) for r in _median_ranks(self.n)] if self.n else []
            v = np.concatenate(self._first) if self._first else None
            for t in self._targets:
                t.count = self.n
                if v is not None:
                    t.take(v)
                else:
                    t.narrow(self.top_hist)
            self._first = None
        else:
            for t in self._targets:
                if t.value is None:
                    t.end_pass()
        for t in self._targets:
            if t.value is None:
                t.start_pass()

    @property
    def value(self) -> float:
        if self._known is not None:
            return self._known
        if not self._targets:
            return float("nan")
        return _mean_of([t.value for t in self._targets])

    def interval(self) -> tuple[float, float]:
        """Bounds of the median after the first pass (the values sharing the wanted ranks' key prefixes)."""
        if not self.pending:
            return self.value, self.value
        r = _prefix_range([t.prefix for t in self._targets], self._targets[0].known)
        return float(r[0].min()), float(r[1].max())


class MedianAbsDeviation:
    """``np.median(np.abs(x - np.median(x)))`` of a stream replayed as for :class:`ExactMedian`, exactly, in
    three passes as a rule: (1) the median's first pass (:class:`ExactMedian`); (2) its bin collected, and
    the deviations ``|x - c|`` from a point ``c`` of that bin counted in 65,536 bins over the range the first
    pass's counts allow them; (3) once the median ``m`` is exact, the deviations ``|x - m|`` within the
    counted bin of the wanted rank, widened by ``|m - c|``, are collected (order statistics move by at most
    ``|m - c|``). When that bin would hold more than :data:`COLLECT_CAP` values, the deviations' median is
    found by :class:`ExactMedian` from pass 3 on. ``center`` is the median, :attr:`value` the result.

    With ``expected_n`` (about the number of values per pass), the first pass is a guess instead
    (:func:`open_guess`): both medians are exact after it where their ranks fall in the bracket; where only the
    median's do, the deviations' median is found by counting (:class:`ExactMedian`, two more passes as a rule:
    the first block that misled the guess would mislead a second one); where neither, the passes above start
    with the next pass."""

    def __init__(self, expected_n: int | None = None) -> None:
        self._expected_n = expected_n
        self._guess: Bracket | None = None
        self.center = ExactMedian()
        self._scan: tuple | None = None         # c, lo, width, counts (below lo / per bin / above), counted
        self._bracket: tuple | None = None      # lo, hi, count below, collected
        self._exact: ExactMedian | None = None     # the fall-back, fed once the median is exact
        self._fall_back = False
        self.value: float | None = None

    @property
    def pending(self) -> bool:
        return self.value is None

    def feed(self, values: np.ndarray) -> None:
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.size and _fed_guess(self, v, deviations=True):
            return
        if self.center.pending:
            self.center.feed(v)
        if self._scan is not None and self._scan[-1] is None:
            c, lo, width, counts, _ = self._scan
            with np.errstate(over="ignore"):            # far beyond the bins: inf, clipped to "above"
                k = np.floor((np.abs(v - c) - lo) / width)
            counts += np.bincount((np.clip(k, -1, 1 << _BITS) + 1).astype(np.intp), minlength=(1 << _BITS) + 2)
        elif self._bracket is not None:
            lo, hi, below, got = self._bracket
            y = np.abs(v - self.center.value)
            self._bracket = (lo, hi, below + int(np.count_nonzero(y < lo)), got + [y[(y >= lo) & (y <= hi)]])
        elif self._exact is not None:             # created once the median was exact
            self._exact.feed(np.abs(v - self.center.value))

    def end_pass(self) -> None:
        """Close a pass over all values; replay them while :attr:`pending`."""
        if self._guess is not None:
            self._close_guess()
            return
        first = self.center.passes == 0
        if self.center.pending:
            self.center.end_pass()
        n = self.center.n
        if n == 0:
            self.value = float("nan")
            return
        ranks = sorted({(n - 1) // 2, n // 2})
        if self._exact is not None:
            self._exact.end_pass()
            if not self._exact.pending:
                self.value = self._exact.value
        elif self._bracket is not None:
            self._close_bracket(ranks)
        elif self._scan is not None:
            self._scan = (*self._scan[:4], True)
        elif first:                                 # a median from few values is exact already
            self._fall_back = not self.center.pending or not self._start_scan(ranks)
        if self._scan is not None and self._scan[-1] and not self.center.pending:
            self._fall_back = not self._open_bracket(ranks)
        if self._fall_back and self._exact is None and not self.center.pending:
            self._exact = ExactMedian()

    def _start_scan(self, ranks: list[int]) -> bool:
        """Bins for the deviations from ``c``: ranks bounded by the first pass's bins of the values."""
        c, hi_c = self.center.interval()
        h = self.center.top_hist
        used = np.flatnonzero(h)
        edge = _prefix_range(used, _BITS)
        far = np.maximum(np.abs(edge[0] - c), np.abs(edge[1] - c))
        near = np.where((edge[0] <= c) & (c <= edge[1]), 0.0, np.minimum(np.abs(edge[0] - c), np.abs(edge[1] - c)))
        a, b = _weighted_rank(near, h[used], ranks[0]), _weighted_rank(far, h[used], ranks[-1])
        if not (np.isfinite(hi_c - c) and np.isfinite(a) and np.isfinite(b)):
            return False
        width = max((b - a) / (1 << _BITS), float(np.spacing(max(b, 1e-300))))
        self._scan = (c, a, width, np.zeros((1 << _BITS) + 2, dtype=np.int64), None)
        return True

    def _open_bracket(self, ranks: list[int]) -> bool:
        """Whether the deviations of the wanted ranks are bracketed in few enough values to collect."""
        c, a, width, counts, _ = self._scan
        self._scan = None
        cum = np.cumsum(counts)                       # bin 0: below a, then the bins, then above
        k = np.searchsorted(cum, ranks, side="right")
        m = self.center.value
        w = abs(m - c) + 4 * float(np.spacing(abs(m) + abs(c) + a + (k[-1] + 2) * width))
        if k[0] == 0 or k[-1] == counts.size - 1 or not np.isfinite(w):      # outside the counted range
            return False
        lo, hi = a + (k[0] - 2) * width - w, a + (k[-1] + 1) * width + w     # a bin of margin each side
        reach = np.ceil(w / width) + 1
        if cum[min(int(k[-1] + reach), counts.size - 1)] - cum[max(int(k[0] - reach) - 1, 0)] > COLLECT_CAP:
            return False
        self._bracket = (lo, hi, 0, [])
        return True

    def _close_bracket(self, ranks: list[int]) -> None:
        _, _, below, got = self._bracket
        self._bracket = None
        y = np.concatenate(got) if got else np.empty(0)
        if not (below <= ranks[0] and ranks[-1] < below + y.size):
            self._fall_back = True                   # cannot happen (the bracket holds the ranks); stay exact
            return
        y = np.partition(y, [r - below for r in ranks])
        self.value = float(np.mean(np.array([y[r - below] for r in ranks])))

    def _close_guess(self) -> None:
        g, self._guess, self._expected_n = self._guess, None, None
        if g.n == 0:
            self.center.settle(float("nan"), 0)
            self.value = float("nan")
            return
        ranks = _median_ranks(g.n)
        got = [g.rank_value(r) for r in ranks]
        if None in got:
            return                                   # the counting passes start with the next pass
        c = _mean_of(got)
        self.center.settle(c, g.n)
        dev = [g.deviation_rank_value(c, r) for r in ranks]
        if None in dev:
            self._fall_back, self._exact = True, ExactMedian()       # counting: a second guess would miss alike
        else:
            self.value = _mean_of(dev)
