"""A null model for slow residual noise: surrogate sessions with the residual's own spectrum.

The block sign-flip test (:mod:`.search`) assumes held-out blocks are exchangeable; slow noise (1/f,
random walk) is real slow structure that offset-like columns (per-session offsets, drift, temperature
offset, a hysteresis state) partly absorb, on held-out blocks too. This module asks the question
directly: *could noise with this session's spectrum, and nothing unmodelled, shrink the held-out gap
as much as the candidate did?*

Surrogates (:class:`SurrogateSource`). The template is the held-out residual of the best description
found (lowest held-out RMSE: the one closest to the noise). Not the baseline's: an unmodelled effect
is itself slow power, and surrogates carrying it hide it (tried: the validation then missed
temperature offset, drift, per-session offsets and hysteresis at realistic strength). The rows, in
session-then-time order, are one series (slow noise runs on across power cycles; for sessions
recorded apart this only adds slow power, the conservative side), mirrored (``x, x reversed``: no
jump at the wrap) and Fourier transformed. Components faster than ``LOW_CYCLES`` cycles per record
keep the template's amplitudes with random phases, the *same* phase on the three axes (the
cross-spectrum is kept; Prichard & Theiler 1994). The slower ones are where the best candidate's fit
may have taken slow noise out of the template, so they are drawn from a noise model instead: white +
power law with one exponent in [0, 2] (:func:`fit_spectrum`, Whittle likelihood) fitted to the
template's periodogram from ``LOW_CYCLES`` to ``FIT_SPAN`` x that, extrapolated down, with the
coherence between axes measured in the fit band; their total is capped at ``LOW_CAP`` x the
template's own slow power (a steep band edge, e.g. pairing noise, would otherwise extrapolate to
hundreds of times the data's slow power). A surrogate is a stationary Gaussian series with that
spectrum and no relation to any candidate's columns.

Statistic. ``T`` = total held-out SSE reduction over all blocks and axes (uT^2), base against base +
candidate, with the same folds. For surrogate ``y`` and design ``Z`` it needs only ``Z_f^T y`` per
fold (``y^T y`` cancels), so the held-out fits of hundreds of surrogates are a few matrix products.
The observed ``T`` comes from the same code on the session's own target, so both sides of the test
use one statistic. Linear candidates and hysteresis (its threshold and initial sign chosen per fold
by training SSE among the same options the search offers) and the thermal lag (its time constant chosen
per fold among the coarse grid and the chosen value) are exact; the per-axis delay and the mount
rotation, whose estimators are not per-axis linear, enter through per-axis linear proxies (the
reference's rate of change mapped into DUT units, every axis' proxy for every output axis; the
rotation's angle columns with a free coefficient per output axis), so their surrogate test is of a
slightly richer model than the one ranked - for both sides alike.

Rows. On a session longer than ``MAX_TEST_ROWS`` the test runs on every m-th row (:func:`test_rows`): template,
folds and every design thinned alike, fixed before any outcome, so the test stays exact; slow noise, what the
test is for, survives thinning (only white-noise power per row is fewer rows; the block test, on all rows,
covers it). Memory and time then stop growing with the session beyond building the candidates' columns.

p-value. Monte Carlo ``(1 + hits) / (1 + k)``, one set of surrogates for every candidate, with
sequential stopping per candidate (Besag & Clifford 1991): stop
at ``STOP_HITS`` hits (``p = hits / k``), at ``max_surrogates`` (by a row budget, at most 1999), or,
with no hit after ``MIN_SURROGATES``, when Cantelli's one-sided bound ``1 / (1 + z^2)`` (z of the
observed ``T`` against the surrogates' mean and standard deviation; valid for any distribution) is
already below ``p_needed`` (the smallest level Holm can ask for): then ``p`` is that bound.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.optimize

from magstack.ground.diagnose import nonlinear as nl
from magstack.ground.diagnose.gap import Block, Gap, solve_normal

#: Upper limit of surrogates per candidate (p resolution 5e-4 < 0.05 / 14 effects).
MAX_SURROGATES = 1999
#: Surrogates drawn before Cantelli's bound may end a candidate's test early.
MIN_SURROGATES = 199
#: Hits (surrogate T >= observed T) that end a candidate's test: its p is then hits / k.
STOP_HITS = 10
#: Rows x surrogates: limits the surrogate count on very long data (at least MIN_SURROGATES).
ROW_BUDGET = 1.5e8
#: Components slower than 1/LOW_CYCLES of the record are drawn from the fitted noise model, not the template.
LOW_CYCLES = 8
#: The slow power drawn is at most this multiple of the template's own below k_a (per axis).
LOW_CAP = 4.0
#: The noise model is fitted between LOW_CYCLES and FIT_SPAN x LOW_CYCLES cycles per record.
FIT_SPAN = 64
#: Rows x 3 axes x surrogates in one batch (32 MB; the transforms' intermediates are one surrogate's).
BATCH_FLOATS = 4e6
#: Complex spectrum bins transformed in one call (draw): ~1 MB, so a group's phases, spectrum and transform
#: stay in the cache (a 4 x 900-row draw of 199 surrogates took 0.083 s in groups of 1e6 bins, 0.060 s in
#: groups of 5e4; the values do not depend on the grouping).
TRANSFORM_BINS = 65536
#: Floats of the candidates' own columns tested together on one set of surrogate batches.
DESIGN_FLOATS = 1e7
#: Bounds of the noise model's log levels relative to the mean periodogram ordinate (e^-30 ~ 1e-13: none).
LOG_LEVEL_MIN, LOG_LEVEL_MAX = -30.0, 30.0
#: Rows the surrogate test uses at most (every m-th row beyond: :func:`test_rows`).
MAX_TEST_ROWS = 2 ** 16


@dataclass
class AxisDesign:
    """Axis i: the candidate's own columns ``O`` (n,q) and its options, each an index array into them
    (one option unless the candidate chooses per fold). The base columns are shared (:class:`Shared`)."""

    O: np.ndarray
    options: list[np.ndarray]


@dataclass
class SurrogateResult:
    p_value: float
    n_surrogates: int
    t_observed_uT2: float
    t_null_mean_uT2: float
    t_null_sd_uT2: float
    stopped: str          # "hits", "cantelli", "limit" or "no shrink"


# ----------------------------------------------------------------------------- surrogates
def fit_spectrum(power: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Whittle fit of ``P_j(k) = w_j + a_j k^-beta`` to periodogram ordinates ``power`` (m,3) at bins ``k``
    (m,): white level ``w`` (3,), power-law level ``a`` (3,) and one exponent ``beta`` in [0, 2] shared
    by the axes (white to random walk). Maximises the Whittle likelihood
    ``-sum(log P + I / P)`` (exponentially distributed ordinates) by scipy.optimize's L-BFGS-B with the
    analytic gradient from three starting exponents; the exponent is a bounded variable and the levels'
    logarithms (relative to the mean ordinate) lie in [LOG_LEVEL_MIN, LOG_LEVEL_MAX], so an optimum on a
    bound (a random walk, beta = 2; no power law, a = 0) is reached exactly instead of approached without
    end."""
    power = np.maximum(power, 1e-300)
    lk = np.log(k)
    scale = np.mean(power, axis=0)
    power_t = np.ascontiguousarray(power.T)            # (3,m): every elementwise pass runs along the bins

    def unpack(x):
        return scale * np.exp(x[0:3]), scale * np.exp(x[3:6]), float(x[6])

    add = np.add.reduce

    def nll(x):
        """Negative Whittle log-likelihood and its analytic gradient in ``x``."""
        w, a, beta = unpack(x)
        kb = np.exp(-beta * lk)                         # (m,)
        P = np.multiply.outer(a, kb)
        P += w[:, None]                                 # (3,m): w + a k^-beta
        q = 1.0 / P
        r = power_t * q                                 # I / P
        f = float(add(np.log(P), axis=None) + add(r, axis=None))
        d = q - r * q                                   # d nll / d P = 1/P - I/P^2
        g = np.empty(7)
        g[0:3] = w * add(d, axis=1)
        g[3:6] = a * (d @ kb)
        g[6] = -float(a @ (d @ (kb * lk)))              # d P / d beta = -a k^-beta log k
        return f, g

    bounds = [(LOG_LEVEL_MIN, LOG_LEVEL_MAX)] * 6 + [(0.0, 2.0)]
    best = None
    for b0 in (0.25, 1.0, 1.75):      # the likelihood is not convex in beta
        x0 = np.r_[np.log(0.5) * np.ones(6), b0]
        r = scipy.optimize.minimize(nll, x0, jac=True, method="L-BFGS-B", bounds=bounds,
                                    options={"maxiter": 2000, "ftol": 1e-12, "gtol": 1e-8})
        if best is None or r.fun < best.fun:
            best = r
    return unpack(best.x)


class SurrogateSource:
    """Surrogates of ``template`` (N,3), rows in session-then-time order taken as one series.

    The template is a residual *after* a fit, and a candidate fitted to it may have removed slow noise
    from its slowest components. So components slower than ``1/LOW_CYCLES`` of the record are drawn
    afresh from a noise model fitted to the faster ones; faster components keep the template's own
    Fourier amplitudes with random phases (the same phase on the three axes: the cross-spectrum is
    kept). Model: white + power law with one exponent (:func:`fit_spectrum`) on the periodogram of
    the mirrored template (no jump at the wrap) between ``LOW_CYCLES`` and ``FIT_SPAN`` x that many
    cycles per record; the slow components are complex Gaussian with that power and the coherence
    between axes measured in the fit band, the mean with the power of the lowest bin."""

    def __init__(self, template_uT: np.ndarray, seed: int = 0):
        x = np.where(np.isfinite(template_uT), template_uT, 0.0).astype(float)
        self.n = x.shape[0]
        mirrored = np.concatenate([x, x[::-1]], axis=0)          # no jump at the wrap
        # the noise model is fitted on the mirrored series itself (bins of 1/(2n) cycles per row) ...
        F0 = scipy.fft.rfft(mirrored, axis=0)
        # ... surrogates are drawn at a length the FFT does fast (a length with a large prime factor is
        # up to 20x slower), the mirrored series padded with its end value (a few % of it)
        self.L = scipy.fft.next_fast_len(2 * self.n, real=True)
        self.F = scipy.fft.rfft(np.concatenate([mirrored, np.repeat(x[:1], self.L - 2 * self.n, axis=0)]), axis=0)
        self.FT = np.ascontiguousarray(self.F.T)                  # (3, bins): one axis' spectrum contiguous
        nf0, nf = F0.shape[0], self.F.shape[0]
        k_a0 = int(min(2 * LOW_CYCLES, max(nf0 - 1, 0)))
        k_c = int(min(nf0 - 1, FIT_SPAN * k_a0))
        stretch = self.L / (2.0 * self.n)                         # padded bins per fitted bin (>= 1)
        self.k_a = int(min(nf - 1, np.ceil(k_a0 * stretch))) if k_a0 else 0
        self.p_low = np.zeros((self.k_a, 3))
        self.chol = np.eye(3, dtype=complex)
        self.beta = 0.0
        self.capped = np.zeros(3, bool)
        if k_a0 >= 1 and k_c - k_a0 >= 8:
            k = np.arange(k_a0, k_c + 1)
            band = F0[k]
            w, a, self.beta = fit_spectrum(np.abs(band) ** 2, k.astype(float))
            kk = np.arange(self.k_a, dtype=float) / stretch       # padded bin -> fitted bin
            kk[0] = 1.0                                           # the mean: the lowest bin's power
            kk = np.maximum(kk, 1.0)
            self.p_low = (w[None, :] + a[None, :] * kk[:, None] ** -self.beta) * stretch
            # an exponent fitted above k_a can explode below it (a steep or ill-determined band edge,
            # pairing noise): the slow power drawn is at most LOW_CAP x the template's own (per axis)
            own = np.sum(np.abs(F0[:k_a0]) ** 2, axis=0) * (self.k_a / k_a0) * stretch
            tot = np.sum(self.p_low, axis=0)
            self.capped = LOW_CAP * own < tot
            self.p_low *= np.minimum(1.0, LOW_CAP * own / np.maximum(tot, 1e-300))[None, :]
            model = w[None, :] + a[None, :] * k[:, None].astype(float) ** -self.beta
            u = band / np.sqrt(model)
            C = (u.T @ u.conj()) / k.size
            d = np.sqrt(np.maximum(np.real(np.diag(C)), 1e-300))
            C = C / np.outer(d, d) + 1e-9 * np.eye(3)
            self.chol = np.linalg.cholesky(C)
        elif self.k_a >= 1:                                 # too short to fit: the template's own mean power
            self.p_low[:] = np.mean(np.abs(self.F[1:]) ** 2, axis=0) if nf > 1 else 0.0
        self.rng = np.random.default_rng(seed)

    def summary(self) -> dict:
        """The noise model for the JSON: exponent, slow components replaced, capped axes."""
        return {"slow_noise_exponent": float(self.beta), "replaced_below_cycles_per_record": LOW_CYCLES,
                "slow_power_capped_axes": [a for a, c in zip("xyz", self.capped, strict=True) if c],
                "slow_power_cap": LOW_CAP}

    def draw(self, k: int, pos: np.ndarray | None = None) -> np.ndarray:
        """(3,k,n) surrogates: axis, surrogate, row (rows ``pos`` of the series in that order, all by default).
        The random numbers of the batch are drawn first; the transforms run on groups of surrogates of at most
        TRANSFORM_BINS complex bins (a few surrogates of a short session at once, one of a long one), so the
        transient complex spectrum stays bounded whatever the batch."""
        L, nf = self.L, self.F.shape[0]
        u = self.rng.random((k, nf))
        nyq = np.where(self.rng.random(k) < 0.5, 1.0, -1.0) if L % 2 == 0 else None
        if self.k_a:
            z = (self.rng.standard_normal((k, 3, self.k_a)) + 1j * self.rng.standard_normal((k, 3, self.k_a)))
            z /= np.sqrt(2)
            z = np.einsum("ij,kjm->kim", self.chol, z)               # coherent across axes as measured
            z[:, :, 0] = np.real(z[:, :, 0]) * np.sqrt(2)            # the mean is real
            z *= np.sqrt(self.p_low).T[None, :, :]
        out = np.empty((3, k, self.n if pos is None else pos.size))
        step = max(1, int(TRANSFORM_BINS // (3 * nf)))               # surrogates per transform call
        for a in range(0, k, step):
            b = min(a + step, k)
            ph = unit_phasors(u[a:b])                                 # (m, bins)
            if nyq is not None:
                ph[:, -1] = nyq[a:b]                                  # the Nyquist bin stays real
            G = ph[:, None, :] * self.FT[None, :, :]                  # (m, 3, bins)
            if self.k_a:
                G[:, :, :self.k_a] = z[a:b]
            y = scipy.fft.irfft(G, n=L, axis=-1, overwrite_x=True)
            for i in range(3):                                         # gathered straight into place
                if pos is None:
                    out[i, a:b, :] = y[:, i, :self.n]
                else:
                    np.take(y[:, i, :], pos, axis=1, out=out[i, a:b, :])
        return out


#: Table size of :func:`unit_phasors` (64 kB of complex roots of unity: stays in the cache).
PHASOR_TABLE = 4096
_ROOTS = np.exp(2j * np.pi * np.arange(PHASOR_TABLE) / PHASOR_TABLE)


def unit_phasors(u: np.ndarray) -> np.ndarray:
    """``exp(2 pi i u)`` for ``u`` in [0, 1), equal to numpy's complex exponential to a few ulp (<= 2e-15
    absolute, tested) at ~3x its speed: a root of unity from a table of PHASOR_TABLE times the short Taylor
    series of the remaining angle (< 2 pi / PHASOR_TABLE = 1.5e-3 rad; the first omitted terms are < 1e-23)."""
    x = u * PHASOR_TABLE
    j = x.astype(np.intp)
    th = x - j                                                     # exact: PHASOR_TABLE is a power of 2
    th *= 2.0 * np.pi / PHASOR_TABLE
    t2 = th * th
    out = np.empty(u.shape, complex)
    np.multiply(t2, -0.5 + t2 * (1.0 / 24.0 - t2 / 720.0), out=out.real)
    out.real += 1.0                                                # cos th
    np.multiply(th, 1.0 - t2 * (1.0 / 6.0 - t2 / 120.0), out=out.imag)   # sin th
    out *= np.take(_ROOTS, j)
    return out


# ----------------------------------------------------------------------------- held-out algebra
class Shared:
    """What every candidate's test shares: the rows tested (:func:`test_rows`) in the order grouping the
    folds, the base columns per axis in that order with their fold Gram matrices, and ``B_f^T y`` of the
    current batch (computed once)."""

    def __init__(self, gap: Gap, base: Block, fold: np.ndarray, rows: np.ndarray):
        self.pos = np.argsort(fold[rows], kind="stable")           # tested rows, fold-grouped, in ``rows``
        self.order = rows[self.pos]                                 # the same as row numbers
        _, counts = np.unique(fold[rows], return_counts=True)
        ends = np.cumsum(counts)
        self.counts = counts
        self.slices = [slice(int(e - c), int(e)) for e, c in zip(ends, counts, strict=True)]
        self.B = [np.ascontiguousarray(c[self.order]) for c in base_axis_columns(gap, base)]
        self.BB = [[B[s].T @ B[s] for s in self.slices] for B in self.B]
        self._key = None
        self._cache: dict = {}

    def base_products(self, Y: np.ndarray, i: int) -> list[np.ndarray]:
        """Per fold ``B_f^T y_f`` (p_base,k) of axis i for targets ``Y`` (3,k,n) in fold order."""
        if self._key is not Y:
            self._key, self._cache = Y, {}
        if i not in self._cache:
            self._cache[i] = [(Y[i][:, s] @ self.B[i][s]).T for s in self.slices]
        return self._cache[i]


class HeldOut:
    """Held-out SSE (minus ``y_f^T y_f``, which cancels between models) per fold for one axis' design
    (shared base columns + the candidate's own), from the fold Gram matrices and ``Z_f^T y`` of many
    right-hand sides at once. The Gram matrices do not depend on ``y``: each fold's and option's solve
    (``solve_normal`` of the training Gram matrix, a linear map) is formed once, so a batch of surrogates
    costs the products ``Z_f^T y`` and a few small matrix products per fold and option."""

    def __init__(self, shared: Shared, i: int, design: AxisDesign):
        self.sh, self.i, self.d = shared, i, design
        B, O = shared.B[i], design.O
        self.nb = B.shape[1]
        P = self.nb + O.shape[1]
        n = B.shape[0]
        Gf = []
        for f, s in enumerate(shared.slices):
            BO = B[s].T @ O[s]
            Gf.append(np.block([[shared.BB[i][f], BO], [BO.T, O[s].T @ O[s]]]))
        G = sum(Gf) if Gf else np.zeros((P, P))
        base = np.arange(self.nb)
        #: per usable fold: (base solve, [option solves]); a solve: (index, training inverse, held-out Gram)
        self.plans = []
        for f, c in enumerate(shared.counts):
            if not ((n - c) > P and c > 0):
                self.plans.append(None)
                continue
            Gt = G - Gf[f]
            plan = [self._plan(base, Gt, Gf[f])]
            plan += [self._plan(np.r_[base, self.nb + o].astype(np.int64), Gt, Gf[f]) for o in design.options]
            self.plans.append(plan)

    @staticmethod
    def _plan(idx, Gt, Gf):
        if idx.size == 0:
            return None
        sub = np.ix_(idx, idx)
        return idx, solve_normal(Gt[sub], np.eye(idx.size)), Gf[sub]

    def reduction(self, Y: np.ndarray) -> np.ndarray:
        """(k,) held-out SSE(base) - SSE(base + candidate), summed over folds, for targets Y (3,k,n)
        in fold order."""
        cb = self.sh.base_products(Y, self.i)
        O, Yi = self.d.O, Y[self.i]
        cf = [np.vstack([cb[f], (Yi[:, s] @ O[s]).T]) for f, s in enumerate(self.sh.slices)]
        c = sum(cf)
        out = np.zeros(Yi.shape[0])
        for f, plan in enumerate(self.plans):
            if plan is None:
                continue
            ct = c - cf[f]
            h0 = self._h(plan[0], ct, cf[f])[0]
            best_h, best_e = None, None
            for p in plan[1:]:
                h, e = self._h(p, ct, cf[f])
                if best_h is None:
                    best_h, best_e = h, e
                else:   # the option with the largest explained training sum of squares (lowest training SSE)
                    take = e > best_e
                    best_h, best_e = np.where(take, h, best_h), np.where(take, e, best_e)
            out += h0 - best_h
        return out

    @staticmethod
    def _h(plan, ct, cf):
        if plan is None:
            z = np.zeros(ct.shape[1])
            return z, z
        idx, inv, Gf = plan
        c_t, c_f = ct[idx], cf[idx]
        th = inv @ c_t
        held = np.sum(th * (Gf @ th - 2.0 * c_f), axis=0)
        explained = np.sum(th * c_t, axis=0)
        return held, explained


def test_rows(n: int) -> np.ndarray:
    """Rows the surrogate test uses: all up to ``MAX_TEST_ROWS``, else every m-th row (m = ceil(n /
    MAX_TEST_ROWS)). A fixed thinning, chosen before any outcome, keeps the test exact (observed and
    surrogate statistics on the same rows); the slow noise it is about survives thinning, white noise stays
    white; it costs power against white noise only, where the block test already decides."""
    m = -(-n // MAX_TEST_ROWS)
    return np.arange(0, n, max(m, 1))


# ----------------------------------------------------------------------------- designs
def _axis_cols(blk: Block, i: int) -> np.ndarray:
    return blk.X[:, np.flatnonzero(blk.mask[i])]


def _per_axis(blk: Block) -> list[np.ndarray]:
    """Each output axis' columns of ``blk``; axes using the same columns share one array (the temperature
    terms of every axis are the same 4 columns: a third of the memory)."""
    seen: dict[bytes, np.ndarray] = {}
    out = []
    for i in range(3):
        key = blk.mask[i].tobytes()
        if key not in seen:
            seen[key] = np.ascontiguousarray(_axis_cols(blk, i))
        out.append(seen[key])
    return out


def base_axis_columns(gap: Gap, base: Block) -> list[np.ndarray]:
    """Per output axis the base columns (with a modelled mount rotation: its angle columns, a free
    coefficient per output axis)."""
    out = [_axis_cols(base, i) for i in range(3)]
    if gap.rotation is not None:
        mc = gap.rotation[0]
        out = [np.hstack([out[i], _nonzero(mc.axis_columns(i))]) for i in range(3)]
    return out


def _nonzero(X: np.ndarray) -> np.ndarray:
    return X[:, np.any(X != 0, axis=0)]


def candidate_designs(gap: Gap, cand, order: np.ndarray) -> list[AxisDesign]:
    """Per output axis the surrogate test's design for candidate ``cand`` (search.Candidate), on rows
    ``order`` (each block's columns are taken down to them as soon as it is built)."""
    from magstack.ground.diagnose import rotation as rot
    from magstack.ground.diagnose import search as sr
    own: list[list[np.ndarray]]
    if cand.kind == "linear":       # row-wise terms (surrogates test no delay here): built on the tested rows
        blk = sr.linear_block(gap.rows_view(order), cand.effect, cand.terms)
        own = [[c] for c in _per_axis(blk)]
    elif cand.kind == "hysteresis":
        hist, idx = gap.history()
        extra = gap.rows_view(order).term_design(("offset",)) if "offset" not in gap.base_terms else None
        own = []
        for j in range(3):
            fixed = _axis_cols(extra, j) if extra is not None else np.zeros((order.size, 0))
            opts = []
            for c in cand.thresholds[j]:
                for s0 in (-1.0, 1.0):
                    thr, init = np.full(3, np.inf), np.ones(3)
                    thr[j], init[j] = c, s0
                    col = nl.hysteresis_state(hist, thr, init)[idx[order]][:, j:j + 1]
                    opts.append(np.hstack([fixed, col]))
            own.append(opts or [fixed])
    elif cand.kind == "lag":
        # the time constant is searched on the data, so it is searched on every surrogate too: one option per
        # coarse-grid tau (plus the one chosen), chosen per fold by training SSE as the search does (a fixed tau
        # fitted on the data alone made the test anti-conservative: 1 of 4 orbit null sessions named a lag)
        # each option on the die temperature of the data's own fit at that time constant (its starting offsets per
        # stretch, lag.py, held: a few numbers on thousands of rows; free per-axis transients on every surrogate
        # widen the statistic's spread so far that the test runs to its 1999 surrogates and loses power)
        from magstack.ground.diagnose import lag as lg
        base = gap.base_design()
        taus = np.unique(np.r_[nl.lag_grid(gap.session.t_s, gap.session.session), cand.lag_tau_s])
        own = [[], [], []]
        for tau in taus:
            die = lg.die_temperature_on(gap, base, float(tau), order)          # on the tested rows
            for i, c in enumerate(_per_axis(sr.lag_block(gap, float(tau), order, temp=die, temp_on_rows=True))):
                own[i].append(c)
    elif cand.kind == "joint":
        mc = rot.mount_columns(gap)
        own = [[_nonzero(mc.axis_columns(i))[order]] for i in range(3)]
    else:   # delay: first-order proxy, the reference's rate of change in DUT units (per DUT axis)
        t = gap.session.t_s
        dt = np.diff(t)
        h = 0.25 * float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1e-3
        u = (gap.skew_columns(np.full(3, h), nl.shift_axes) - gap.skew_columns(np.full(3, -h), nl.shift_axes)) / (2 * h)
        u = u[order]
        own = [[u] for _ in range(3)]
    out = []
    stacked: dict[tuple, np.ndarray] = {}      # axes with the same pieces share one stacked array
    for i in range(3):
        opts, k = [], 0
        for o in own[i]:
            opts.append(np.arange(k, k + o.shape[1]))
            k += o.shape[1]
        key = tuple(id(o) for o in own[i])
        if key not in stacked:
            stacked[key] = np.ascontiguousarray(np.hstack(own[i])) if own[i] else np.zeros((order.size, 0))
        out.append(AxisDesign(stacked[key], opts))
    del own
    return out


# ----------------------------------------------------------------------------- the test
def prepare(gap: Gap, cand, shared: Shared):
    """(observed T, function mapping surrogates (3,k,n) in fold order to their T (k,), floats its own
    columns hold)."""
    designs = candidate_designs(gap, cand, shared.order)
    held = [HeldOut(shared, i, d) for i, d in enumerate(designs)]

    def statistic(Ys: np.ndarray) -> np.ndarray:
        return sum(held[i].reduction(Ys) for i in range(3))
    t_obs = float(statistic(np.ascontiguousarray(gap.target[shared.order].T[:, None, :]))[0])
    return t_obs, statistic, sum(O.size for O in {id(d.O): d.O for d in designs}.values())


class _Test:
    """One candidate's running Monte Carlo test."""

    def __init__(self, t_obs: float, statistic):
        self.t_obs, self.statistic = t_obs, statistic
        self.tol = 1e-12 * abs(t_obs)
        self.vals: list[np.ndarray] = []
        self.hits = 0
        self.result: SurrogateResult | None = None

    def cantelli(self) -> float:
        allv = np.concatenate(self.vals)
        sd = float(np.std(allv, ddof=1))
        z = (self.t_obs - float(np.mean(allv))) / sd if sd > 0 else np.inf
        return 1.0 / (1.0 + z * z) if z > 0 else 1.0

    def update(self, Ys: np.ndarray, k: int, kmax: int, p_needed: float) -> bool:
        """Add a batch (k surrogates drawn so far, with it); True when the test has ended."""
        t = self.statistic(Ys)
        self.vals.append(t)
        self.hits += int(np.sum(t >= self.t_obs - self.tol))
        if self.hits >= STOP_HITS:
            self.result = _result(self.hits / k, k, self.t_obs, self.vals, "hits")
        elif self.hits == 0 and k >= MIN_SURROGATES and self.cantelli() < p_needed:
            self.result = _result(self.cantelli(), k, self.t_obs, self.vals, "cantelli")
        elif k >= kmax:
            p = (1 + self.hits) / (1 + k)
            if self.hits == 0:   # with a row budget below 1999 surrogates the bound may be the sharper one
                p = min(p, self.cantelli())
            self.result = _result(p, k, self.t_obs, self.vals, "limit")
        return self.result is not None


def surrogate_tests(gap: Gap, cands: list, base: Block, fold: np.ndarray, template_uT: np.ndarray,
                    p_needed: float, seed: int = 0, max_surrogates: int | None = None
                    ) -> tuple[list[SurrogateResult], dict]:
    """One-sided p-values of the candidates' held-out SSE reductions against surrogates of
    ``template_uT`` (see the module docs). Each batch of surrogates is drawn once and serves every
    candidate still under test; candidates are prepared in groups of at most ``DESIGN_FLOATS`` design
    floats (memory bounded for any number of rows). Also returns the noise model's summary."""
    rows = test_rows(gap.n)
    n = rows.size
    src = SurrogateSource(np.asarray(template_uT)[rows], seed)
    kmax = max_surrogates or int(min(MAX_SURROGATES, max(MIN_SURROGATES, ROW_BUDGET // max(n, 1))))
    batch = int(max(1, min(199, BATCH_FLOATS // (3 * n))))
    out: list[SurrogateResult | None] = [None] * len(cands)
    group: list[tuple[int, _Test]] = []
    floats = 0

    def run(group):
        src.rng = np.random.default_rng(seed)
        active = [(i, t) for i, t in group]
        k = 0
        while active:
            m = min(batch, kmax - k)
            Ys = src.draw(m, shared.pos)                                # (3,k,n) in fold order
            k += m
            active = [(i, t) for i, t in active if not t.update(Ys, k, kmax, p_needed)]
        for i, t in group:
            out[i] = t.result

    shared = Shared(gap, base, fold, rows)
    for i, c in enumerate(cands):
        t_obs, statistic, size = prepare(gap, c, shared)
        if not t_obs > 0:
            out[i] = SurrogateResult(1.0, 0, t_obs, np.nan, np.nan, "no shrink")
            continue
        if group and floats + size > DESIGN_FLOATS:
            run(group)
            group, floats = [], 0
        group.append((i, _Test(t_obs, statistic)))
        floats += size
    if group:
        run(group)
    return out, src.summary()


def _result(p, k, t_obs, vals, why) -> SurrogateResult:
    allv = np.concatenate(vals) if vals else np.array([np.nan])
    sd = float(np.std(allv, ddof=1)) if allv.size > 1 else float("nan")
    return SurrogateResult(float(p), int(k), t_obs, float(np.mean(allv)), sd, why)
