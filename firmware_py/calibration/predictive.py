"""What a fit learns about its own accuracy: the pieces of a table's predictive uncertainty.

:mod:`magstack.firmware.cal_uncertainty` evaluates a table's predictive sd from three parts (parameters with the
terms the model leaves out, discrepancy, noise). This module estimates them from a fit, with accumulators fed
block by block by the passes of the cross-fit (or once with whole arrays by the refit path):

* **Slow noise and per-parameter inflation.** Per axis the residual is modelled as white (level ``a``, uT^2) plus
  exponentially correlated components with correlation times of 32, 128, 512 ... rows (variances ``v_k``) plus
  a random walk (rate ``q``, uT^2/s), fitted (:func:`slow_noise`) to the Allan-type differences of adjacent
  block means (:class:`.blocking.BlockingInflation`): for blocks of ``L`` rows lasting ``tau_L`` s,
  ``E[(m_{b+1} - m_b)^2] = 2 a / L + sum v_k D_k(L) + (2/3) q tau_L``. Differences of neighbouring blocks see a
  slow drift long before it spans a session and are not biased by the trends the fit removes; a flicker-like
  process spreads over the components and its growth stops with theirs, a random walk keeps growing. The
  parameter covariance under that noise is the sandwich ``C_s = C (lam^2 (a X'WX + sum v_k G_k + q G) + P) C``
  (``C`` the posterior, ``lam`` its data precision, ``P`` the prior precision, ``G_k``, ``G`` the components'
  score Grams: :class:`OUGram`, :class:`RandomWalkGram`); the
  table gets ``C + (C_s - C)_+`` (the positive part of the difference): never less than the posterior, at least
  the sandwich in every direction, each parameter inflated by its own amount and the combinations the data pin
  (a gain and an offset at one field) kept pinned.
* **Parameters the data were not allowed to inform** (gated: a gain whose axis saw no field of its own, a tempco
  column without temperature change) sit at their prior mean with the prior's variance, and the free
  parameters absorbed what the data said given that value: an error ``s - s_0`` of a gated parameter moves
  them by ``beta (s - s_0)``, ``beta = C lam X'W x_g`` (:func:`gated_absorption`). A gain held at its prior
  on a one-field run is then correlated with the offset as it should be: right at the field the data had,
  uncertain by the gain's prior away from it.
* **Terms the model leaves out** (:func:`left_out_terms`): catalogue terms not in the model (the sensitivity
  tempco's second and third order, the offset's second order in temperature, cubic nonlinearity, cross
  products), each with the part's prior. A left-out
  term ``c g(x)`` is partly absorbed by the fitted parameters, ``beta = C lam X'W g``; what remains at ``x`` is
  ``c h(x)``, ``h = g - f' beta``: small where the data pinned the model, growing beyond (two temperature
  plateaus absorb a tempco's curvature at the plateaus, not between or beyond them). The data cap ``c``: a term
  whose RMS over the fit rows, ``|c| sqrt(mean h^2)``, reached the residual's own sd (noise and discrepancy)
  would have shown in the held-out residuals, so ``c_eff^2 = min(prior mean^2 + sd^2, (n^2 + d0) / mean h^2)``,
  and an axis's terms together may not reach it either (their caps scaled down alike when they would).
  It enters the table's covariance as a rank-one extension over the features ``[f, g]``.
* **Discrepancy** (:class:`HeldOutBins`, :func:`discrepancy`): held-out residuals of the time-block folds,
  binned by field magnitude and temperature; in each bin the mean squared residual minus the noise and the
  parameter part expected there (the folds' posterior, ``tr(C M_bin)``) is what the model misses. A
  non-negative fit ``d0 + dB (|b|/50 uT)^2 + dT ((T - T_c)/10 degC)^2`` over the bins, weighted by their rows.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from magstack.firmware.calibration.model import AXES, CalModel

#: Reference scales of the discrepancy model's features.
FIELD_REF_uT = 50.0
TEMP_REF_C = 10.0
#: Bins of held-out residuals: field magnitude x temperature.
N_FIELD_BINS = 4
N_TEMP_BINS = 4
#: Adjacent-block pairs a level needs to enter the slow-noise fit.
MIN_PAIRS = 8


# ---------------------------------------------------------------------- random walk
def segment_sums(x: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Sums of the rows of ``x`` (m, p) over the consecutive segments that begin at ``starts`` (increasing, from 0):
    ``np.add.reduceat(x, starts, axis=0)`` to rounding, as a sparse matrix product (several times faster on a
    C-ordered ``x``)."""
    from scipy.sparse import csr_matrix

    m = x.shape[0]
    S = csr_matrix((np.ones(m), np.arange(m), np.r_[starts, m]), shape=(starts.size, m))
    return S @ x


def bin_rows(x: np.ndarray, t_s: np.ndarray, width_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``x`` (m, p) at times ``t_s`` (sorted) summed over bins of ``width_s`` from the first row, each bin at
    its rows' mean time: ``(sums (k, p), times (k,))``."""
    k = np.floor((t_s - t_s[0]) / width_s).astype(np.int64)
    starts = np.r_[0, np.flatnonzero(k[1:] != k[:-1]) + 1]
    if starts.size == t_s.size:
        return x, t_s
    counts = np.diff(np.r_[starts, t_s.size])
    return segment_sums(x, starts), np.add.reduceat(t_s, starts) / counts


def nested_bins(x: np.ndarray, t_s: np.ndarray, widths_s: Sequence[float]) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`bin_rows` of ``x`` at each of ``widths_s`` (ascending, each a power-of-two multiple of the previous, as
    the correlation times of :class:`SlowNoiseGrams`), each from the one before: a bin of a wider width is a union of
    bins of the narrower (``floor(u / 4) = floor(floor(u) / 4)``, and scaling by a power of two is exact), so its
    sums are sums of theirs (the same bins; sums to rounding) and the rows are summed once."""
    out = []
    if t_s.size < 2:
        return [(x, t_s)] * len(widths_s)
    cur_x, cur_t, cur_n = x, t_s, None          # the previous level's sums, times (sums), counts (None: rows)
    first = np.arange(t_s.size)                 # each current item's first row
    for w in widths_s:
        k = np.floor((t_s[first] - t_s[0]) / w).astype(np.int64)
        starts = np.r_[0, np.flatnonzero(k[1:] != k[:-1]) + 1]
        if starts.size < k.size:
            cur_x = segment_sums(cur_x, starts)
            cur_t = np.add.reduceat(cur_t, starts)
            cur_n = np.diff(np.r_[first[starts], t_s.size])
            first = first[starts]
        out.append((cur_x, cur_t if cur_n is None else cur_t / cur_n))
    return out


class RandomWalkGram:
    """``G = sum_sessions sum_k dt_k U_k U_k^T`` (p x p), ``U_k`` the tail sum of ``w x`` from row ``k`` to the
    session's end, ``dt_k`` the time since the previous row (0 at a session's first row): the covariance of the
    score ``X'W u`` per unit rate of a random walk ``u`` that starts at each session's first row. Rows arrive
    in (session, time) order, possibly over many calls; memory ``O(p^2)``. ``bin_s`` > 0: rows are first summed
    over bins of that width (at the bin's mean time), which moves each pair's shared time by less than a bin:
    relative error about ``bin_s`` over the session's span."""

    def __init__(self, p: int, bin_s: float = 0.0) -> None:
        self.p, self.bin_s = p, float(bin_s)
        self.G = np.zeros((p, p))
        self._session = None
        self._reset()

    def _reset(self) -> None:
        self._P = np.zeros(self.p)        # prefix sum of w x before the next row
        self._D = 0.0
        self._v = np.zeros(self.p)
        self._W = np.zeros((self.p, self.p))
        self._t = None

    def _close(self) -> None:
        T = self._P
        self.G += self._D * np.outer(T, T) - np.outer(T, self._v) - np.outer(self._v, T) + self._W
        self._reset()

    def add(self, xw: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> None:
        """Rows ``xw`` (m, p) = weights x design, their times (s) and sessions, in (session, time) order."""
        xw = np.asarray(xw, dtype=float).reshape(-1, self.p)
        t = np.asarray(t_s, dtype=float).reshape(-1)
        s = np.asarray(session).reshape(-1)
        if t.size == 0:
            return
        cuts = np.r_[0, np.flatnonzero(s[1:] != s[:-1]) + 1, s.size]
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            if self._session is None or s[a] != self._session:
                if self._session is not None:
                    self._close()
                self._session = s[a]
            x, tt = xw[a:b], t[a:b]
            if self.bin_s > 0 and tt.size > 1:
                x, tt = bin_rows(x, tt, self.bin_s)
            dt = np.diff(tt, prepend=tt[0] if self._t is None else self._t)
            excl = np.cumsum(x, axis=0) - x + self._P            # prefix before each row
            self._D += float(dt.sum())
            self._v += dt @ excl
            self._W += (excl * dt[:, None]).T @ excl
            self._P = self._P + x.sum(axis=0)
            self._t = float(tt[-1])

    def result(self) -> np.ndarray:
        """The Gram matrix (closes the last session)."""
        if self._session is not None:
            self._close()
            self._session = None
        return self.G


class OUGram:
    """``G_tau = sum_t sum_s x_t x_s^T exp(-|t_t - t_s| / tau)`` over each session's rows (``x`` = weights x design):
    the covariance of the score ``X'W u`` per unit variance of an exponentially correlated (Ornstein-Uhlenbeck)
    residual ``u`` with correlation time ``tau`` (s). Rows in (session, time) order, possibly over many calls;
    the causal sums ``h_t = sum_{s <= t} x_s exp(-(t_t - t_s)/tau)`` are formed by cumulative sums over stretches
    of at most ``STRETCH_TAUS`` tau (``exp`` stays far below overflow), carried between them and between calls;
    ``G = H + H^T - D`` with ``H = sum x_t h_t^T`` and ``D = sum x_t x_t^T``. Rows are first summed over bins of
    ``tau / BINS_PER_TAU`` (at the bin's mean time): pairs inside a bin count with correlation 1 instead of
    ``exp(-|dt|/tau) >= exp(-1/BINS_PER_TAU)``, so ``G`` is within about ``1/BINS_PER_TAU`` of the exact sum and
    costs a bin's rows less."""

    def __init__(self, p: int, tau_s: float) -> None:
        self.p, self.tau = p, float(tau_s)
        self.H = np.zeros((p, p))
        self.D = np.zeros((p, p))
        self._h = np.zeros(p)
        self._t: float | None = None
        self._session = None

    def add(self, xw: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> None:
        s = np.asarray(session).reshape(-1)
        t = np.asarray(t_s, dtype=float).reshape(-1)
        cuts = np.r_[0, np.flatnonzero(s[1:] != s[:-1]) + 1, s.size]
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            x, tt = xw[a:b], t[a:b]
            if tt.size > 1:
                x, tt = bin_rows(x, tt, self.bin_s)
            self.add_binned(x, tt, s[a])

    @property
    def bin_s(self) -> float:
        """Width (s) of the bins rows are summed over, from a run's first row."""
        return self.tau / BINS_PER_TAU

    def add_binned(self, x: np.ndarray, t: np.ndarray, session) -> None:
        """Rows of one session already summed over bins of :attr:`bin_s` (sums ``x``, mean times ``t``)."""
        if self._session is None or session != self._session:
            self._session, self._h, self._t = session, np.zeros(self.p), None
        self.D += x.T @ x
        i = 0
        while i < t.size:
            j = i + int(np.searchsorted(t[i:], t[i] + STRETCH_TAUS * self.tau, side="right"))
            j = max(j, i + 1)
            t0 = t[i]
            e = np.exp((t[i:j] - t0) / self.tau)[:, None]
            carry = 0.0 if self._t is None else np.exp(-(t0 - self._t) / self.tau)
            h = x[i:j] * e
            np.cumsum(h, axis=0, out=h)
            h += carry * self._h
            h /= e
            self.H += x[i:j].T @ h
            self._h, self._t = h[-1].copy(), float(t[j - 1])
            i = j

    def result(self) -> np.ndarray:
        return self.H + self.H.T - self.D


class SlowNoiseGrams:
    """The score Grams of every slow-noise component the fit can weigh: exponentially correlated residuals with
    correlation times ``tau_k`` = 32, 128, 512, ... rows (up to 4x the data's time span) and a random walk; the
    grid is set from the first rows' sampling interval; the random walk's rows are summed over ``RW_BINS`` bins of
    the span, each correlated component's over its :attr:`OUGram.bin_s`, all of those from one binning of the rows
    (:func:`nested_bins`). Feed rows with :meth:`add` in (session, time) order.

    A component whose variance the slow-noise fit leaves at 0 on every axis is weighed by 0 in the sandwich, so its
    Gram is not needed: a caller that knows the fit first feeds the rows' times (:meth:`add_times`, the grid and
    the mean interval), says which components it needs (:meth:`keep`), then feeds the rows (:meth:`add_rows`);
    the others' Grams stay 0."""

    def __init__(self, p: int, span_s: float) -> None:
        self.p, self.span_s = p, max(float(span_s), 0.0)
        self.rw = RandomWalkGram(p, self.span_s / RW_BINS)
        self.ou: list[OUGram] | None = None
        self._use_ou: list[bool] | None = None          # None: every component
        self._use_rw = True
        self._dt_sum, self._n, self._session, self._t_last = 0.0, 0, None, None

    @property
    def taus_s(self) -> list[float]:
        """The correlation times (s) of the grid (empty before the first rows)."""
        return [g.tau for g in self.ou or []]

    @property
    def mean_dt_s(self) -> float:
        """Mean sampling interval (s): each session's time span over the rows, less one."""
        return self._dt_sum / max(self._n - 1, 1)

    def add(self, xw: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> None:
        """Rows ``xw`` (m, p) = weights x design, their times (s) and sessions: :meth:`add_times` and
        :meth:`add_rows`."""
        self.add_times(t_s, session)
        self.add_rows(xw, t_s, session)

    def add_times(self, t_s: np.ndarray, session: np.ndarray) -> None:
        """The rows' times (s) and sessions, in (session, time) order: the grid (first rows) and the interval."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        s = np.asarray(session).reshape(-1)
        if t.size == 0:
            return
        if self.ou is None:
            dt = np.diff(t)
            dt = dt[dt > 0]
            dt0 = float(np.median(dt)) if dt.size else 1.0
            taus = [dt0 * 32.0 * 4.0 ** k for k in range(12)]
            self.ou = [OUGram(self.p, tau) for tau in taus if tau <= 4.0 * max(self.span_s, 32.0 * dt0)][:MAX_OU]
        cuts = np.r_[0, np.flatnonzero(s[1:] != s[:-1]) + 1, s.size]
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            if self._session is None or s[a] != self._session:
                self._session, self._t_last = s[a], None
            self._dt_sum += float(t[b - 1] - (t[a] if self._t_last is None else self._t_last))
            self._n += b - a
            self._t_last = float(t[b - 1])

    def keep(self, ou: Sequence[bool], rw: bool) -> None:
        """Accumulate only the correlated components ``ou`` (one flag per :attr:`taus_s`) and, ``rw``, the random
        walk (before any :meth:`add_rows`)."""
        self._use_ou, self._use_rw = [bool(u) for u in ou], bool(rw)

    def add_rows(self, xw: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> None:
        """Rows ``xw`` (m, p) = weights x design into the Grams of the components kept (times as given to
        :meth:`add_times`, in the same order)."""
        if self.ou is None:
            raise ValueError("add_rows before any add_times: the grid is set from the rows' times")
        if self._use_rw:
            self.rw.add(xw, t_s, session)
        live = [g for k, g in enumerate(self.ou) if self._use_ou is None or self._use_ou[k]]
        if not live:
            return
        s = np.asarray(session).reshape(-1)
        t = np.asarray(t_s, dtype=float).reshape(-1)
        cuts = np.r_[0, np.flatnonzero(s[1:] != s[:-1]) + 1, s.size]
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            for g, (x, tb) in zip(live, nested_bins(xw[a:b], t[a:b], [g.bin_s for g in live]), strict=True):
                g.add_binned(x, tb, s[a])

    def result(self) -> tuple[list[float], list[np.ndarray], np.ndarray, float]:
        """``(taus (s), OU Grams, random-walk Gram, mean sampling interval (s))``; the Grams of components not
        kept are 0."""
        ou = self.ou or []
        return [g.tau for g in ou], [g.result() for g in ou], self.rw.result(), self.mean_dt_s


#: Largest number of exponentially correlated components of the slow-noise model.
MAX_OU = 6
#: Bins per correlation time in which :class:`OUGram` sums rows before its kernel sums.
BINS_PER_TAU = 16
#: Bins over the data's time span in which :class:`SlowNoiseGrams` sums rows for the random-walk Gram.
RW_BINS = 4096
#: Longest stretch of one cumulative sum in :class:`OUGram`, in correlation times (``exp(200)`` ~ 7e86).
STRETCH_TAUS = 200.0


def ou_block_difference(L: int, dt_s: float, tau_s: float) -> float:
    """``E[(m_{b+1} - m_b)^2]`` of adjacent means of ``L`` rows ``dt_s`` apart of a unit-variance exponentially
    correlated series with correlation time ``tau_s``."""
    rho = math.exp(-dt_s / tau_s)
    if rho < 1e-300:
        return 2.0 / L
    one = 1.0 - rho
    s1 = rho * (L * one - 1.0 + rho ** L) / (one * one)          # sum_{k=1}^{L-1} (L - k) rho^k
    var = (L + 2.0 * s1) / (L * L)
    cov = rho * (1.0 - rho ** L) ** 2 / (one * one) / (L * L)
    return max(2.0 * (var - cov), 0.0)


@dataclass
class SlowNoise:
    """Per axis: white level ``a`` (uT^2), the variance of each exponentially correlated component (uT^2) and the
    random-walk rate ``q`` (uT^2/s)."""

    white_uT2: np.ndarray            # (3,)
    ou_uT2: np.ndarray               # (3, K)
    rw_uT2_per_s: np.ndarray         # (3,)
    taus_s: list[float]


def slow_noise(levels: Sequence[tuple[int, int, np.ndarray]], dt_s: float, taus_s: Sequence[float]) -> SlowNoise:
    """Fit the white level, the components' variances and the random-walk rate of each axis to the adjacent
    block-mean differences ``levels`` = [(L rows, pairs, mean squared difference (3,))] (non-negative least
    squares, each level weighted by its relative precision ``sqrt(pairs) / difference``). A flicker-like process
    spreads over the components and grows no further than they allow beyond the data's blocks; a random walk
    keeps growing."""
    from scipy.optimize import nnls

    K = len(taus_s)
    a, v, q = np.zeros(3), np.zeros((3, K)), np.zeros(3)
    use = [(L, k, d) for L, k, d in levels if k >= MIN_PAIRS]
    if not use or not dt_s > 0:
        return SlowNoise(a, v, q, list(taus_s))
    basis = np.array([[2.0 / L] + [ou_block_difference(L, dt_s, tau) for tau in taus_s] + [(2.0 / 3.0) * L * dt_s]
                      for L, _, _ in use])
    for i in range(3):
        y = np.array([d[i] for _, _, d in use])
        ok = y > 0
        if not ok.any():
            continue
        w = np.sqrt(np.array([k for _, k, _ in use], dtype=float))[ok] / y[ok]
        A = basis[ok] * w[:, None]
        sc = np.linalg.norm(A, axis=0)
        sc[sc == 0] = 1.0
        coef, _ = nnls(A / sc, y[ok] * w)
        coef = coef / sc
        a[i], v[i], q[i] = coef[0], coef[1:1 + K], coef[1 + K]
    return SlowNoise(a, v, q, list(taus_s))


def weighed_components(levels: Sequence[tuple[int, int, np.ndarray]], dt_s: float,
                       taus_s: Sequence[float]) -> list[bool]:
    """Per slow-noise component (the correlated ones, then the random walk) whether the slow-noise fit of
    ``levels`` (:func:`slow_noise`) gives it a variance on some axis: the Grams the sandwich weighs."""
    noise = slow_noise(levels, dt_s, taus_s)
    return [bool(u) for u in np.any(noise.ou_uT2 > 0, axis=0)] + [bool(np.any(noise.rw_uT2_per_s > 0))]


def weighed_grams(levels: Sequence[tuple[int, int, np.ndarray]], dt_s: float, taus_s: Sequence[float],
                  grams: Sequence[np.ndarray]) -> list[np.ndarray]:
    """``grams`` (the correlated components' then the random walk's) with those the slow-noise fit of ``levels``
    weighs by 0 on every axis set to 0 (:func:`weighed_components`): what :func:`sandwich_covariance` reads of
    them, however they were accumulated (:meth:`SlowNoiseGrams.keep`)."""
    used = weighed_components(levels, dt_s, taus_s)
    return [g if u else np.zeros_like(g) for g, u in zip(grams, used, strict=True)]


def sandwich_covariance(post, XtWX: np.ndarray, grams: Sequence[np.ndarray], noise: SlowNoise) -> np.ndarray:
    """(3, p, p) ``C + (C_s - C)_+`` of ``post`` (a :class:`.estimator.Posterior`) under the slow-noise model
    ``noise`` (white + exponentially correlated components + random walk, ``grams`` their score Grams: the OU
    ones then the random walk's; module docstring); fixed, gated, undetermined and unused parameters keep the
    posterior's entries."""
    p = post.model.n_columns
    mask = post.model.axis_mask()
    out = np.where(np.isfinite(post.cov), post.cov, 0.0) * (mask[:, :, None] & mask[:, None, :])
    for i in range(3):
        C = out[i]
        dC = np.diag(C)
        prior_var = np.diag(post.prior.cov[i])
        gated = {c for ax, c in post.gated if ax == i}
        free = np.array([mask[i, c] and np.isfinite(post.cov[i, c, c]) and dC[c] > 0 and prior_var[c] > 0
                         and c not in gated for c in range(p)])
        if not free.any():
            continue
        lam = 1.0 / (post.sigma_uT[i] ** 2 * post.kappa[i])
        idx = np.flatnonzero(free)
        Cf = C[np.ix_(idx, idx)]
        slow = sum(v * g for v, g in zip(list(noise.ou_uT2[i]) + [noise.rw_uT2_per_s[i]], grams, strict=True))
        A = noise.white_uT2[i] * XtWX + slow
        if post.design_maps is not None:      # the information the estimate used (weak directions removed)
            M = post.design_maps[i]
            A = M.T @ A @ M
        meat = lam * lam * A[np.ix_(idx, idx)]
        pv = prior_var[idx]
        meat += np.diag(np.where(np.isfinite(pv), 1.0 / np.where(np.isfinite(pv), pv, 1.0), 0.0))
        Cs = Cf @ meat @ Cf
        diff = 0.5 * ((Cs - Cf) + (Cs - Cf).T)
        w, V = np.linalg.eigh(diff)
        C[np.ix_(idx, idx)] = Cf + (V * np.maximum(w, 0.0)) @ V.T
    return out


def gated_absorption(post, XtWX: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(3, p, p) ``cov`` with each gated parameter's prior variance propagated into the free parameters
    (module docstring): ``C + sum_g v_g [beta_g; -e_g][beta_g; -e_g]^T`` over the gated columns ``g``."""
    p = post.model.n_columns
    mask = post.model.axis_mask()
    out = cov.copy()
    for i in range(3):
        gated = [c for ax, c in post.gated if ax == i and mask[i, c]]
        var = np.diag(post.prior.cov[i])
        gated = [c for c in gated if np.isfinite(var[c]) and var[c] > 0]
        if not gated:
            continue
        free = np.array([mask[i, c] and c not in gated and np.isfinite(post.cov[i, c, c]) for c in range(p)])
        A = XtWX
        if post.design_maps is not None:
            M = post.design_maps[i]
            A = M.T @ XtWX @ M
        lam = 1.0 / (post.sigma_uT[i] ** 2 * post.kappa[i])
        C = out[i]
        base = np.where(np.isfinite(post.cov[i]), post.cov[i], 0.0)
        Cf = base[np.ix_(free, free)]
        for c in gated:
            C[c, :] = 0.0
            C[:, c] = 0.0
        for c in gated:
            u = np.zeros(p)
            u[free] = Cf @ (lam * A[free, c])
            u[c] = -1.0
            C += var[c] * np.outer(u, u)
    return out


# ---------------------------------------------------------------------- left-out terms
@dataclass(frozen=True)
class LeftOut:
    """One left-out parameter: its name (``K_S2[x]``), output axis, prior mean and sd."""

    name: str
    axis: int
    mean: float
    sd: float

    @property
    def var(self) -> float:
        return self.mean ** 2 + self.sd ** 2


def left_out_terms(model: CalModel, chip, s_diag: np.ndarray) -> list[LeftOut]:
    """The catalogue terms ``model`` leaves out whose prior bounds its error beyond the data (see the module
    docstring); ``chip`` a :class:`~magstack.drivers.cal_priors.CalPriors`, ``s_diag`` the fitted gains (the
    tempco priors are relative to them)."""
    terms = set(model.terms)
    out: list[LeftOut] = []
    for i, a in enumerate(AXES):
        s = float(abs(s_diag[i])) if np.isfinite(s_diag[i]) else 1.0
        if "temperature_gain" in terms:
            if "temperature_gain2" not in terms:
                pv = chip.k_s2_rel_per_c2
                out.append(LeftOut(f"K_S2[{a}]", i, pv.mean * s, pv.sd * s))
            pv = chip.k_s3_rel_per_c3
            out.append(LeftOut(f"K_S3[{a}]", i, pv.mean * s, pv.sd * s))
        if "temperature_offset" in terms:
            pv = chip.k_o2_uT_per_c2
            out.append(LeftOut(f"K_O2[{a}]", i, pv.mean, pv.sd))
        if "cubic" not in terms:
            pv = chip.cubic_per_uT2
            out.append(LeftOut(f"c3[{a}]", i, pv.mean, pv.sd))
        if "cross_products" not in terms:
            pv = chip.cross_products_per_uT
            out += [LeftOut(f"P[{a},{pr}]", i, pv.mean, pv.sd) for pr in ("xy", "xz", "yz")]
    return out


class LeftOutMoments:
    """Weighted moments of the design and the left-out features over the fit rows: ``X'WG`` (p, m), the diagonal
    of ``G'WG`` (``g2`` (m,): ``sum w g_k^2``) and the sum of weights (NaN features count as 0)."""

    def __init__(self, p: int, m: int) -> None:
        self.XtWG = np.zeros((p, m))
        self.g2 = np.zeros(m)
        self.sum_w = 0.0

    def add_rows(self, X: np.ndarray, terms: Sequence[LeftOut], b_uT: np.ndarray, dT: np.ndarray,
                 w: np.ndarray | None = None) -> None:
        """Rows of design ``X`` (N, p), DUT field (N, 3) uT, ``dT = T - t0`` (N,) degC and weights: the features of
        ``terms`` (m of them) formed there, each distinct feature once (:func:`.cal_uncertainty.feature_key`)."""
        from magstack.firmware.cal_uncertainty import feature_key, features_t

        keys = [feature_key(t.name) for t in terms]
        first = {k: j for j, k in reversed(list(enumerate(keys)))}
        uniq = sorted(first.values())
        col = {keys[j]: q for q, j in enumerate(uniq)}
        at = np.array([col[k] for k in keys], dtype=np.intp)
        n = np.asarray(X).shape[0]
        if uniq:
            Gt = features_t([terms[j].name for j in uniq], b_uT, dT)                        # (u, N)
            if not np.isfinite(Gt).all():
                Gt = np.nan_to_num(Gt)
            Gw = Gt if w is None else Gt * w[None, :]
            self.XtWG += (Gw @ X).T[:, at]
            self.g2 += np.einsum("kn,kn->k", Gt, Gw)[at]
        self.sum_w += float(n if w is None else np.sum(w))

    def merge(self, other: LeftOutMoments) -> LeftOutMoments:
        self.XtWG += other.XtWG
        self.g2 += other.g2
        self.sum_w += other.sum_w
        return self


def absorbed(post, XtWG: np.ndarray, terms: Sequence[LeftOut]) -> np.ndarray:
    """(m, p) ``beta`` per left-out parameter: what the fitted parameters of its axis absorb of its feature
    (``C lam X'W g``, ``C`` the uninflated posterior: the absorption is a property of the estimator)."""
    p = post.model.n_columns
    mask = post.model.axis_mask()
    out = np.zeros((len(terms), p))
    for k, t in enumerate(terms):
        i = t.axis
        C = np.where(np.isfinite(post.cov[i]), post.cov[i], 0.0)
        lam = 1.0 / (post.sigma_uT[i] ** 2 * post.kappa[i])
        out[k] = np.where(mask[i], C @ (lam * XtWG[:, k]), 0.0)
    return out


def extended_covariance(C: np.ndarray, beta: np.ndarray, var: np.ndarray) -> np.ndarray:
    """The covariance over ``[f, g]`` (k + m) of one axis: ``C + sum s^2 beta beta'`` on ``f``, ``-s^2 beta`` between
    ``f`` and ``g``, ``s^2`` on ``g`` (``beta`` (m, k), ``var`` (m,))."""
    k, m = C.shape[0], beta.shape[0]
    E = np.zeros((k + m, k + m))
    E[:k, :k] = C + (beta.T * var) @ beta
    E[:k, k:] = -(beta.T * var)
    E[k:, :k] = E[:k, k:].T
    E[k:, k:] = np.diag(var)
    return E


# ---------------------------------------------------------------------- discrepancy
def _bin_index(edges: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``np.searchsorted(edges, x)`` (the number of the few ``edges`` below each ``x``; NaN after them all) by one
    comparison per edge, several times faster for a handful of edges."""
    k = np.zeros(x.shape, dtype=np.intp)
    for e in edges:
        k += x > e
    if edges.size:
        k[np.isnan(x)] = edges.size
    return k


@dataclass
class HeldOutBins:
    """Held-out residuals of the time-block folds, binned by field magnitude x temperature: per bin the row
    count, sum of squared residuals (3,), sums of ``(|b|/field_ref)^2`` and ``((T - T_c)/temp_ref)^2``, and the
    weighted second moments ``sum s_f x x^T`` of the full model's design row ``x`` (``s_f = N / N_train`` of the
    row's fold: a fold's posterior is the full one's times that)."""

    field_edges_uT: np.ndarray
    temp_edges_c: np.ndarray
    temp_centre_c: float
    q: int
    count: np.ndarray = field(init=False)
    sq: np.ndarray = field(init=False)
    u_b: np.ndarray = field(init=False)
    u_t: np.ndarray = field(init=False)
    M: np.ndarray = field(init=False)
    scale_sum: float = field(init=False, default=0.0)
    mag_max_uT: float = field(init=False, default=0.0)        # largest |b| of a binned row

    def __post_init__(self) -> None:
        nb = (len(self.field_edges_uT) + 1) * (len(self.temp_edges_c) + 1)
        self.count = np.zeros(nb)
        self.sq = np.zeros((nb, 3))
        self.u_b = np.zeros(nb)
        self.u_t = np.zeros(nb)
        self.M = np.zeros((nb, self.q, self.q))

    @classmethod
    def for_coverage(cls, cov, q: int) -> HeldOutBins:
        """Bins spanning the fit data's field magnitudes and temperatures (coverage ``cov``)."""
        fmax = float(np.linalg.norm(cov.field_max_uT)) if np.all(np.isfinite(cov.field_max_uT)) else 0.0
        fe = np.linspace(0.0, fmax, N_FIELD_BINS + 1)[1:-1] if fmax > 0 else np.zeros(0)
        has_t = np.isfinite(cov.temp_min_c) and cov.temp_max_c > cov.temp_min_c
        te = np.linspace(cov.temp_min_c, cov.temp_max_c, N_TEMP_BINS + 1)[1:-1] if has_t else np.zeros(0)
        tc = 0.5 * (cov.temp_min_c + cov.temp_max_c) if np.isfinite(cov.temp_min_c) else 0.0
        return cls(fe, te, float(tc), q)

    def add(self, z: np.ndarray, resid_uT: np.ndarray, b_uT: np.ndarray, temp_c: np.ndarray, scale: float) -> None:
        """Held-out rows: design ``z`` (m, p), residuals (3, m) uT, DUT field (m, 3), temperature (m,)."""
        k = self.add_residuals(resid_uT, b_uT, temp_c, scale)
        self.M += scale * self.design_moments(k, z)

    def add_residuals(self, resid_uT: np.ndarray, b_uT: np.ndarray, temp_c: np.ndarray, scale: float,
                      where: tuple | None = None) -> np.ndarray:
        """:meth:`add` without the design moments (add ``scale`` x :meth:`design_moments` to :attr:`M`); returns
        the rows' bins. ``where``: :meth:`locate` of the same rows, when another model's residuals there had it."""
        k, mag_max, per_bin = self.locate(b_uT, temp_c) if where is None else where
        nb = self.count.size
        self.mag_max_uT = max(self.mag_max_uT, mag_max)
        self.scale_sum += scale * k.size
        self.count += per_bin[0]
        self.u_b += per_bin[1]
        self.u_t += per_bin[2]
        r = np.asarray(resid_uT, dtype=float)
        self.sq += np.bincount((k + nb * np.arange(3)[:, None]).reshape(-1), weights=(r * r).reshape(-1),
                               minlength=3 * nb).reshape(3, nb).T
        return k

    def locate(self, b_uT: np.ndarray, temp_c: np.ndarray) -> tuple:
        """``(bin of each row, largest finite |b| (0 if none), per-bin (count, sum u_b, sum u_t))`` of rows with DUT
        field ``b_uT`` (m, 3) uT and temperature (m,) degC: what :meth:`add_residuals` adds besides the residuals."""
        b = np.asarray(b_uT, dtype=float)
        mag = np.sqrt(np.einsum("ij,ij->i", b, b))
        mag_max = float(np.nanmax(mag)) if mag.size and np.isfinite(mag).any() else 0.0
        t = np.where(np.isfinite(temp_c), temp_c, self.temp_centre_c)
        k = _bin_index(self.field_edges_uT, mag) * (len(self.temp_edges_c) + 1) + _bin_index(self.temp_edges_c, t)
        nb = self.count.size
        ub = (mag / FIELD_REF_uT) ** 2
        ut = ((t - self.temp_centre_c) / TEMP_REF_C) ** 2
        return k, mag_max, (np.bincount(k, minlength=nb), np.bincount(k, weights=ub, minlength=nb),
                            np.bincount(k, weights=ut, minlength=nb))

    def design_moments(self, k: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(bins, q, q) ``sum z z^T`` of design rows ``z`` (m, q) per bin ``k`` (m,) (any q: the rows of a design
        whose columns include the model's)."""
        out = np.zeros((self.count.size, z.shape[1], z.shape[1]))
        order = np.argsort(k, kind="stable")
        ks = k[order]
        cuts = np.r_[0, np.flatnonzero(ks[1:] != ks[:-1]) + 1, ks.size]
        for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
            zz = z[order[lo:hi]]
            out[ks[lo]] = zz.T @ zz
        return out


def discrepancy(bins: HeldOutBins, noise_uT: np.ndarray, cov: np.ndarray, temp_range_c: tuple[float, float],
                field_max_uT: float) -> dict:
    """The table's ``discrepancy`` block: per axis ``d0``, ``dB``, ``dT`` (uT^2) fitted (non-negative, weighted by
    rows) to each bin's mean squared held-out residual minus the noise and the parameter part there (``cov``
    (3, p, p) the full fit's inflated posterior)."""
    from scipy.optimize import nnls

    use = bins.count > 0
    n = bins.count[use]
    d0, dB, dT = np.zeros(3), np.zeros(3), np.zeros(3)
    excess_out = []
    for i in range(3):
        par = np.array([np.sum(cov[i] * bins.M[b]) for b in np.flatnonzero(use)]) / n
        excess = bins.sq[use, i] / n - noise_uT[i] ** 2 - par
        excess_out.append(excess)
        A = np.column_stack([np.ones(n.size), bins.u_b[use] / n, bins.u_t[use] / n])
        w = np.sqrt(n)
        sc = np.linalg.norm(A * w[:, None], axis=0)
        sc[sc == 0] = 1.0
        coef, _ = nnls(A * w[:, None] / sc, excess * w)
        d0[i], dB[i], dT[i] = coef / sc
    lo, hi = temp_range_c
    return {"d0_uT2": d0.tolist(), "dB_uT2": dB.tolist(), "dT_uT2": dT.tolist(), "field_ref_uT": FIELD_REF_uT,
            "temp_ref_c": TEMP_REF_C, "temp_centre_c": float(bins.temp_centre_c),
            "temp_range_c": [float(lo), float(hi)], "field_max_uT": float(field_max_uT),
            "held_out_rows": int(bins.count.sum())}


# ---------------------------------------------------------------------- assembling the parts
@dataclass
class Accumulated:
    """What the passes over the rows collected for the predictive parts of the full fit."""

    XtWX: np.ndarray                       # (p, p) weighted design Gram matrix
    taus_s: list                           # correlation times of the exponentially correlated components (s)
    grams: list                            # their score Grams, then the random walk's ((p, p) each)
    levels: list                           # BlockingInflation.adjacent_levels() of the full fit's residuals
    dt_s: float                            # mean sampling interval (s)
    terms: list[LeftOut]
    moments: LeftOutMoments                # design x left-out features over the fit rows
    bins: HeldOutBins | None               # held-out residuals of the time-block folds (None: no folds)


@dataclass
class Uncertainty:
    """The fit's predictive parts (see the module docstring)."""

    inflation: np.ndarray                  # (3, p) each parameter's variance over the posterior's
    cov: np.ndarray                        # (3, p, p) the posterior with the sandwich (0 where undetermined)
    slow: SlowNoise                        # the residual's noise model
    left_out: list[LeftOut]
    beta: np.ndarray                       # (m, p) what the fitted columns absorb of each left-out feature
    left_var: np.ndarray                   # (m,) c_eff^2 of each left-out parameter
    noise_uT: np.ndarray                   # (3,)
    discrepancy: dict | None
    typical_sd_uT: float | None = None     # RMS over the fit rows of the predictive vector sd

    def axis_block(self, i: int, cols: Sequence[int]) -> tuple[list[str], np.ndarray]:
        """Axis ``i``'s left-out names and the extended covariance over model columns ``cols`` + those."""
        lo = [k for k, t in enumerate(self.left_out) if t.axis == i]
        C = self.cov[i][np.ix_(cols, cols)]
        return ([self.left_out[k].name for k in lo],
                extended_covariance(C, self.beta[np.ix_(lo, cols)], self.left_var[lo]))

    def stats(self) -> dict:
        return {"white_uT2": self.slow.white_uT2.tolist(), "random_walk_uT2_per_s": self.slow.rw_uT2_per_s.tolist(),
                "correlated_uT2": {f"{tau:.4g} s": self.slow.ou_uT2[:, k].tolist()
                                   for k, tau in enumerate(self.slow.taus_s) if np.any(self.slow.ou_uT2[:, k] > 0)},
                "inflation_max": [float(np.max(r)) for r in self.inflation],
                "left_out": {t.name: {"prior_sd": float(np.sqrt(t.var)), "sd": float(np.sqrt(v))}
                             for t, v in zip(self.left_out, self.left_var, strict=True)},
                "noise_uT": self.noise_uT.tolist(),
                "typical_sd_uT": self.typical_sd_uT,
                **({"discrepancy": self.discrepancy} if self.discrepancy else {})}


def assemble(post, acc: Accumulated, noise_uT: np.ndarray, coverage, autocorr: bool = True) -> Uncertainty:
    """The :class:`Uncertainty` of the posterior ``post`` from what the passes accumulated."""
    mask = post.model.axis_mask()
    if autocorr:
        noise_model = slow_noise(acc.levels, acc.dt_s, acc.taus_s)
        C = sandwich_covariance(post, acc.XtWX, acc.grams, noise_model)
    else:
        noise_model = SlowNoise(np.zeros(3), np.zeros((3, len(acc.taus_s))), np.zeros(3), list(acc.taus_s))
        C = np.where(np.isfinite(post.cov), post.cov, 0.0) * (mask[:, :, None] & mask[:, None, :])
    C = gated_absorption(post, acc.XtWX, C)
    d0 = np.diagonal(np.where(np.isfinite(post.cov), post.cov, 0.0), axis1=1, axis2=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        infl = np.where(d0 > 0, np.diagonal(C, axis1=1, axis2=2) / np.where(d0 > 0, d0, 1.0), 1.0)
    noise = np.where(np.isfinite(noise_uT), noise_uT, 0.0)
    disc = None
    if acc.bins is not None and acc.bins.count.sum() > 0:
        trange = ((coverage.temp_min_c, coverage.temp_max_c) if np.isfinite(coverage.temp_min_c)
                  else (acc.bins.temp_centre_c, acc.bins.temp_centre_c))
        disc = discrepancy(acc.bins, noise, C, trange, acc.bins.mag_max_uT)
    typical = typical_sd(acc.XtWX, max(coverage.sum_w, 1e-300), C, noise, disc, acc.bins)
    mo = acc.moments
    beta = absorbed(post, mo.XtWG, acc.terms)
    resid2 = noise ** 2 + (np.asarray(disc["d0_uT2"], dtype=float) if disc else 0.0)
    var = capped_left_var(acc.terms, beta, mo, acc.XtWX, resid2)
    return Uncertainty(infl, C, noise_model, list(acc.terms), beta, var, noise, disc, typical)


def capped_left_var(terms: Sequence[LeftOut], beta: np.ndarray, mo: LeftOutMoments, XtWX: np.ndarray,
                    resid2_uT2: np.ndarray) -> np.ndarray:
    """(m,) ``c_eff^2`` of each left-out parameter: its prior's ``mean^2 + sd^2``, capped so that what the fitted
    terms leave of it, ``h = g - f'beta``, has an RMS over the fit rows no larger than the residual's own sd
    (``resid2_uT2`` per axis: noise and discrepancy) -- each term alone, then an axis's terms together (their
    parts add in the residual: together they may not reach more than it either)."""
    var = np.zeros(len(terms))
    h2 = np.zeros(len(terms))
    for k, t in enumerate(terms):
        b = beta[k]
        h2[k] = (mo.g2[k] - 2.0 * b @ mo.XtWG[:, k] + b @ XtWX @ b) / max(mo.sum_w, 1e-300)
        r2 = float(resid2_uT2[t.axis])
        var[k] = t.var if not h2[k] > 0 or r2 <= 0 else min(t.var, r2 / h2[k])
    for i in range(3):
        on = [k for k, t in enumerate(terms) if t.axis == i and h2[k] > 0]
        total = float(sum(var[k] * h2[k] for k in on))
        r2 = float(resid2_uT2[i])
        if r2 > 0 and total > r2:
            for k in on:
                var[k] *= r2 / total
    return var


def typical_sd(XtWX: np.ndarray, sum_w: float, cov: np.ndarray, noise_uT: np.ndarray, disc: dict | None,
               bins: HeldOutBins | None) -> float:
    """RMS over the fit rows of the full fit's predictive vector sd (uT): the parameter part ``tr(C X'WX) / sum w``,
    the discrepancy at the held-out bins' mean features (when there is one), the noise."""
    tot = 0.0
    for i in range(3):
        tot += float(np.sum(cov[i] * XtWX)) / sum_w + noise_uT[i] ** 2
        if disc is not None and bins is not None and bins.count.sum() > 0:
            n = bins.count.sum()
            tot += disc["d0_uT2"][i] + (disc["dB_uT2"][i] * bins.u_b.sum() + disc["dT_uT2"][i] * bins.u_t.sum()) / n
    return float(np.sqrt(tot))


def from_holdout(post, R_hold: np.ndarray, n_hold: int, coverage, terms: Sequence[LeftOut] = (),
                 moments: LeftOutMoments | None = None, R_fit: np.ndarray | None = None) -> Uncertainty | None:
    """The predictive parts of a fit whose held-out rows are summarised by their R factor ``R_hold`` of the
    unweighted ``[X | Y]`` (the on-orbit refit, which keeps no time-ordered residuals): the posterior as it is
    (no slow-noise sandwich), the noise the fit's residual scale, and one discrepancy level per axis: the
    held-out mean squared residual minus the noise and the posterior's part on those rows, ``tr(C X_h'X_h)/n``.
    ``terms`` the left-out terms with their ``moments`` over the fit rows and ``R_fit`` the fit rows' R factor:
    their absorption and data cap as in :func:`assemble`. None without held-out rows."""
    if n_hold <= 0:
        return None
    m = post.model
    p = m.n_columns
    mask = m.axis_mask()
    C = np.where(np.isfinite(post.cov), post.cov, 0.0) * (mask[:, :, None] & mask[:, None, :])
    Rx = R_hold[:, :p]
    XtX = Rx.T @ Rx
    th = np.where(mask, post.theta, 0.0)
    noise = np.asarray(post.sigma_uT, dtype=float)
    d0 = np.zeros(3)
    typical = 0.0
    for i in range(3):
        z = np.r_[th[i], np.zeros(3)]
        z[p + i] = -1.0
        ms = float(np.sum((R_hold @ z) ** 2)) / n_hold
        par = float(np.sum(C[i] * XtX)) / n_hold
        d0[i] = max(0.0, ms - noise[i] ** 2 - par)
        typical += noise[i] ** 2 + d0[i] + par
    t_lo = coverage.temp_min_c if np.isfinite(coverage.temp_min_c) else 0.0
    t_hi = coverage.temp_max_c if np.isfinite(coverage.temp_max_c) else t_lo
    disc = {"d0_uT2": d0.tolist(), "dB_uT2": [0.0] * 3, "dT_uT2": [0.0] * 3, "field_ref_uT": FIELD_REF_uT,
            "temp_ref_c": TEMP_REF_C, "temp_centre_c": float(0.5 * (t_lo + t_hi)),
            "temp_range_c": [float(t_lo), float(t_hi)], "field_max_uT": float(coverage.norm_max_uT),
            "held_out_rows": int(n_hold)}
    ones = np.ones((3, p))
    terms = list(terms) if moments is not None and R_fit is not None else []
    beta, var = np.zeros((len(terms), p)), np.zeros(len(terms))
    if terms:
        beta = absorbed(post, moments.XtWG, terms)
        Rf = R_fit[:, :p]
        var = capped_left_var(terms, beta, moments, Rf.T @ Rf, noise ** 2 + d0)
    return Uncertainty(ones, C, SlowNoise(noise ** 2, np.zeros((3, 0)), np.zeros(3), []), terms, beta, var, noise,
                       disc, float(np.sqrt(typical)))
