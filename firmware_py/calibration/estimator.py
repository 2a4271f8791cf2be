"""One linear-Gaussian (MAP) estimator behind every calibration fit: bench, streaming, on-orbit refit.

Per output axis ``i`` the model is ``y_i = X theta_i + e`` with ``e`` of variance ``sigma_i^2 kappa_i / w``
per row (``w`` the row weights, ``kappa_i >= 1`` the variance inflation of autocorrelated residuals), and a
Gaussian prior ``theta_i ~ N(mu_i, Sigma_i)`` (:class:`Prior`). The estimate maximises the posterior::

    theta_i = argmin  lambda_i ||R (theta; -e_i)||^2 + (theta - mu_i)^T Sigma_i^-1 (theta - mu_i),
    lambda_i = 1 / (sigma_i^2 kappa_i)

where ``R`` is the R factor of the weighted ``[X | Y]`` (so the batch fit, the streaming fit, the Dask
reduce and held-out folds all feed the same sufficient statistic). The posterior covariance
``(lambda_i R_x^T R_x + Sigma_i^-1)^-1`` is the parameter covariance. Directions the data cannot determine
return to the prior with the prior's variance: no rule has to decide. Conventions of the prior:

* variance ``inf`` on the diagonal: flat (no prior; only the data decide; ``--no-priors``);
* variance ``0``: fixed at the mean (a user-held parameter);
* otherwise a finite Gaussian; off-diagonal covariances allowed (a previous table's posterior).

``sigma_i`` is not known in advance: it starts from the unregularised (minimum-norm) residual and is
iterated with the MAP residual, ``sigma_i^2 = SSE_i / (n - tr H_i)`` (``tr H_i`` = the effective number of
parameters the data determine), until it changes by less than 0.1 %.

``data_share = 1 - var_post / var_prior`` per parameter says who determined it: near 1 the data, near 0 the
prior. Solved by QR of the stacked, column-equilibrated system (never normal equations), with BLAS limited
to one thread around these small solves (:mod:`magstack.firmware.blas`).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from magstack.firmware.calibration.model import AXES, CalModel
from magstack.firmware.errors import FitError

#: Relative rank tolerance of the stacked, equilibrated system (flat-prior directions below it are
#: undetermined): the one tolerance of the estimator.
RANK_RTOL = 1e-10
#: sigma iteration: stop when the relative change is below this, or after MAX_SIGMA_ITER.
SIGMA_RTOL = 1e-3
MAX_SIGMA_ITER = 8
#: Labels of who determined a parameter (posterior sd / prior sd).
DATA_SD_RATIO = 0.5      # at or below: "data"
PRIOR_SD_RATIO = 0.9     # at or above: "prior"


@dataclass(frozen=True)
class Prior:
    """Gaussian prior over a model's coefficients, per output axis.

    ``mean`` (3, p); ``cov`` (3, p, p) (diagonal ``inf`` = flat, ``0`` = fixed); ``source`` (3, p) strings.
    Entries of columns an axis does not use are ignored.
    """

    mean: np.ndarray
    cov: np.ndarray
    source: tuple[tuple[str, ...], ...]

    def __post_init__(self) -> None:
        m = np.asarray(self.mean, dtype=float)
        c = np.asarray(self.cov, dtype=float)
        p = m.shape[1]
        if m.shape != (3, p) or c.shape != (3, p, p):
            raise FitError(f"prior shapes {m.shape} / {c.shape} do not match (3, p) / (3, p, p)")
        if not np.all(np.isfinite(m)):
            raise FitError("prior means must be finite")
        d = np.diagonal(c, axis1=1, axis2=2)
        if np.any(np.isnan(c)) or np.any(d < 0):
            raise FitError("prior variances must be >= 0 (inf = flat)")
        object.__setattr__(self, "mean", m)
        object.__setattr__(self, "cov", c)

    @property
    def sd(self) -> np.ndarray:
        """(3, p) prior standard deviations (inf = flat, 0 = fixed)."""
        return np.sqrt(np.diagonal(self.cov, axis1=1, axis2=2))

    def with_values(self, i: int, c: int, mean: float, sd: float, source: str) -> Prior:
        """A copy with parameter (i, c) set to ``mean +- sd`` (its covariances with others cleared)."""
        m, cov = self.mean.copy(), self.cov.copy()
        m[i, c] = mean
        cov[i, c, :] = 0.0
        cov[i, :, c] = 0.0
        cov[i, c, c] = sd * sd if np.isfinite(sd) else np.inf
        src = [list(r) for r in self.source]
        src[i][c] = source
        return Prior(m, cov, tuple(tuple(r) for r in src))

    @classmethod
    def flat(cls, p: int) -> Prior:
        """No prior at all (the unregularised least squares of ``--no-priors``)."""
        cov = np.zeros((3, p, p))
        for i in range(3):
            np.fill_diagonal(cov[i], np.inf)
        return cls(np.zeros((3, p)), cov, tuple(tuple("none (flat)" for _ in range(p)) for _ in range(3)))


@dataclass
class AxisPosterior:
    """MAP solution of one output axis: ``theta`` (p,), ``cov`` (p, p) posterior covariance (0 rows for
    fixed or unused columns, NaN for undetermined flat ones), ``sse`` weighted residual sum of squares
    (uT^2), ``trace_h`` the number of parameters the data determine (tr H), ``cond`` condition number of
    the stacked equilibrated system."""

    theta: np.ndarray
    cov: np.ndarray
    sse: float
    trace_h: float
    cond: float
    undetermined: tuple[int, ...] = ()


@dataclass
class Posterior:
    """The estimate of all three axes plus what produced it."""

    model: CalModel
    prior: Prior
    theta: np.ndarray          # (3, p)
    cov: np.ndarray            # (3, p, p)
    sigma_uT: np.ndarray       # (3,) residual scale per axis
    kappa: np.ndarray          # (3,) variance inflation used (autocorrelated residuals)
    sse: np.ndarray            # (3,)
    dof: np.ndarray            # (3,) n - tr H
    cond: np.ndarray           # (3,)
    n: int
    undetermined: list[tuple[int, int]] = field(default_factory=list)
    gated: list[tuple[int, int]] = field(default_factory=list)    # prior only (data not used for them)
    #: per axis the (p, p) map of the design whose information the estimate used (None: the identity; see
    #: :func:`magstack.firmware.calibration.fit.weak_direction_maps`)
    design_maps: list[np.ndarray] | None = None

    @property
    def sd(self) -> np.ndarray:
        """(3, p) posterior standard deviations (NaN where undetermined or unused)."""
        with np.errstate(invalid="ignore"):
            return np.sqrt(np.diagonal(self.cov, axis1=1, axis2=2))

    @property
    def data_share(self) -> np.ndarray:
        """(3, p) ``1 - var_post / var_prior`` (NaN for flat, fixed or unused parameters)."""
        vp = np.diagonal(self.prior.cov, axis1=1, axis2=2)
        vq = np.diagonal(self.cov, axis1=1, axis2=2)
        with np.errstate(invalid="ignore", divide="ignore"):
            out = 1.0 - vq / vp
        out[~(np.isfinite(vp) & (vp > 0)) | ~self.model.axis_mask()] = np.nan
        return out

    def determined_by(self, i: int, c: int) -> str:
        """"data", "prior", "data+prior", "fixed", "data (flat prior)" or "undetermined"."""
        vp = self.prior.cov[i, c, c]
        if (i, c) in self.undetermined:
            return "undetermined"
        if vp == 0:
            return "fixed"
        if not np.isfinite(vp):
            return "data (flat prior)"
        ratio = np.sqrt(self.cov[i, c, c] / vp)
        if ratio <= DATA_SD_RATIO:
            return "data"
        if ratio >= PRIOR_SD_RATIO:
            return "prior"
        return "data+prior"


# ---------------------------------------------------------------------- building priors
#: Terms whose every parameter has the same prior: the CalPriors field that holds it.
_PRIOR_FIELD = {"offset": "offset_uT", "temperature_offset": "k_o_uT_per_c", "currents": "current_uT_per_A",
                "cubic": "cubic_per_uT2", "cross_products": "cross_products_per_uT", "time_skew": "time_skew_s",
                "session_offset": "session_offset_uT", "drift": "drift_uT_per_s"}


def model_prior(model: CalModel, chip, s_hint: np.ndarray | None = None) -> Prior:
    """Diagonal prior of ``model``'s coefficients from a chip's :class:`~magstack.drivers.cal_priors.CalPriors`.

    ``s_hint`` (3, 3): the gain matrix the sensitivity tempco is relative to (K_S[i,j] mean =
    k_s_rel x S[i,j] on the diagonal pattern of the part: ``k_s_rel * s_hint``; K_S2[i] mean =
    k_s2_rel x S[i,i]); identity when None.
    """
    p = model.n_columns
    mean = np.zeros((3, p))
    var = np.zeros((3, p))
    src = [["" for _ in range(p)] for _ in range(3)]
    S = np.eye(3) if s_hint is None else np.asarray(s_hint, dtype=float)
    for c, col in enumerate(model.columns):
        for i in range(3):
            j = col.index
            if col.term == "gain_matrix":
                pv = chip.gain_diag if i == j else chip.gain_offdiag
                m = pv.mean
            elif col.term == "temperature_gain":
                # relative tempco: the sensitivity of input axis j scales row i of S's column j
                pv = chip.k_s_rel_per_c if i == j else chip.k_s_offdiag_per_c
                m = chip.k_s_rel_per_c.mean * S[i, j]
            elif col.term == "temperature_gain2":
                # relative like K_S: K_S2[i] ~ k_s2_rel S[i,i] (only the on-axis column is used)
                pv = chip.k_s2_rel_per_c2
                m = pv.mean * S[i, i]
            elif col.term in _PRIOR_FIELD:
                pv = getattr(chip, _PRIOR_FIELD[col.term])
                m = pv.mean
            else:   # pragma: no cover - model.py asserts the term set
                raise FitError(f"no prior for term {col.term!r}")
            mean[i, c] = m
            var[i, c] = pv.sd ** 2
            src[i][c] = f"{chip.chip}: {pv.source}"
    cov = np.zeros((3, p, p))
    for i in range(3):
        cov[i][np.diag_indices(p)] = var[i]
    return Prior(mean, cov, tuple(tuple(r) for r in src))


def parse_override(text: str) -> tuple[str, float, float]:
    """``'K_S[x,x]=-2.7e-3+-0.5e-3'`` -> (name, mean, sd); ``'O[z]=0.3'`` fixes the value (sd 0);
    ``'O[z]=flat'`` removes the prior (sd inf)."""
    if "=" not in text:
        raise FitError(f"prior {text!r}: expected NAME=MEAN+-SD, NAME=VALUE or NAME=flat")
    name, rhs = (s.strip() for s in text.split("=", 1))
    if rhs.lower() == "flat":
        return name, 0.0, float("inf")
    parts = rhs.split("+-")
    try:
        mean = float(parts[0])
        sd = float(parts[1]) if len(parts) == 2 else 0.0
    except ValueError:
        raise FitError(f"prior {text!r}: MEAN and SD must be numbers") from None
    if len(parts) > 2 or not np.isfinite(mean) or not (np.isfinite(sd) and sd >= 0):
        raise FitError(f"prior {text!r}: expected NAME=MEAN+-SD with a finite mean and sd >= 0")
    return name, mean, sd


def apply_overrides(prior: Prior, model: CalModel, overrides: Mapping[str, tuple[float, float]],
                    source: str = "user") -> Prior:
    """Set named parameters (``K_S[x,x]``) to ``(mean, sd)``; unknown names raise FitError."""
    mask = model.axis_mask()
    names = {model.param_name(i, c): (i, c) for i in range(3) for c in range(model.n_columns) if mask[i, c]}
    for k, (m, s) in overrides.items():
        if k not in names:
            raise FitError(f"prior for unknown parameter {k!r} (model parameters: {', '.join(sorted(names))})")
        prior = prior.with_values(*names[k], float(m), float(s), source)
    return prior


# ---------------------------------------------------------------------- the solve
def _axis_map(R: np.ndarray, p: int, i: int, mask_i: np.ndarray, mean: np.ndarray, cov: np.ndarray,
              lam: float) -> AxisPosterior:
    """MAP of axis ``i`` from the R factor of the weighted ``[X | Y]`` at data precision ``lam``."""
    var = np.diag(cov)
    use = np.asarray(mask_i, dtype=bool)
    fixed = use & (var == 0)
    free = np.flatnonzero(use & ~fixed)
    theta = np.where(fixed, mean, 0.0)
    cov_post = np.zeros((p, p))
    y = R[:, p + i] - R[:, :p][:, fixed] @ mean[fixed]
    if free.size == 0:
        r = y
        return AxisPosterior(theta, cov_post, float(r @ r), 0.0, np.nan)
    fin = free[np.isfinite(var[free])]
    rows = [np.sqrt(lam) * R[:, free]]
    rhs = [np.sqrt(lam) * y]
    if fin.size:
        Linv = _inverse_sqrt(cov[np.ix_(fin, fin)])
        P = np.zeros((fin.size, free.size))
        P[:, np.searchsorted(free, fin)] = Linv
        rows.append(P)
        rhs.append(Linv @ mean[fin])
    A = np.vstack(rows)
    b = np.concatenate(rhs)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    As = A / scale
    Q2, R2 = np.linalg.qr(As)
    d = np.abs(np.diag(R2))
    undetermined: tuple[int, ...] = ()
    if d.min() <= RANK_RTOL * d.max():
        # only flat-prior directions can be undetermined: minimum-norm solution, those columns named
        U, sv, Vt = np.linalg.svd(As, full_matrices=False)
        keep = sv > RANK_RTOL * sv[0]
        z = Vt[keep].T @ ((U[:, keep].T @ b) / sv[keep])
        null = Vt[~keep]
        undetermined = tuple(int(free[k]) for k in np.flatnonzero(np.max(np.abs(null), axis=0) > 1e-6))
        Cz = (Vt[keep].T / sv[keep] ** 2) @ Vt[keep]
        cond = float(sv[0] / sv[keep][-1])
    else:
        z = scipy.linalg.solve_triangular(R2, Q2.T @ b)
        Rinv = scipy.linalg.solve_triangular(R2, np.eye(free.size))
        Cz = Rinv @ Rinv.T
        cond = float(np.linalg.cond(R2))
    theta[free] = z / scale
    cov_post[np.ix_(free, free)] = Cz / np.outer(scale, scale)
    for k in undetermined:
        cov_post[k, :] = np.nan
        cov_post[:, k] = np.nan
    res = R[:, :p] @ theta - R[:, p + i]
    sse = float(res @ res)
    # tr H: the data's share of the information, lam * tr(cov_post R_free^T R_free)
    Rf = R[:, free]
    with np.errstate(invalid="ignore"):
        trh = float(lam * np.nansum(cov_post[np.ix_(free, free)] * (Rf.T @ Rf)))
    return AxisPosterior(theta, cov_post, sse, trh, cond, undetermined)


def _inverse_sqrt(C: np.ndarray) -> np.ndarray:
    """``W`` with ``W^T W = C^-1`` (prior rows): Cholesky, or for a covariance that is only numerically
    positive semi-definite (a stored posterior) the eigen-decomposition with eigenvalues floored at 1e-12 of
    the largest (those directions then count as nearly fixed)."""
    try:
        L = np.linalg.cholesky(C)
        return scipy.linalg.solve_triangular(L, np.eye(C.shape[0]), lower=True)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (C + C.T))
        w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))
        return (V / np.sqrt(w)).T


def _min_norm_sse(R: np.ndarray, p: int, i: int, mask_i: np.ndarray, mean: np.ndarray,
                  var: np.ndarray) -> tuple[float, int]:
    """(SSE, rank) of the unregularised least squares (fixed parameters at their means): the start of sigma."""
    use = np.asarray(mask_i, dtype=bool)
    fixed = use & (var == 0)
    Rx = R[:, :p]
    A = Rx[:, use & ~fixed]
    y = R[:, p + i] - Rx[:, fixed] @ mean[fixed]
    if A.shape[1] == 0:
        return float(y @ y), 0
    sc = np.linalg.norm(A, axis=0)
    sc[sc == 0] = 1.0
    coef, _, rank, _ = np.linalg.lstsq(A / sc, y, rcond=RANK_RTOL)
    r = y - (A / sc) @ coef
    return float(r @ r), int(rank)


def map_solve(R: np.ndarray, n: int, model: CalModel, prior: Prior, kappa=None,
              sigma_uT: np.ndarray | None = None) -> Posterior:
    """MAP estimate of ``model`` from the accumulated R factor ``R`` ((p+3) x (p+3) or taller) of ``n`` rows.

    ``kappa`` (3,): variance inflation of autocorrelated residuals (1 = independent rows).
    ``sigma_uT`` (3,): a known residual scale (skips the sigma iteration).
    """
    from magstack.firmware.blas import single_thread

    p = model.n_columns
    if R.shape[1] != p + 3:
        raise FitError(f"R factor has {R.shape[1]} columns, model needs {p + 3}")
    if n <= 0:
        raise FitError("no rows to fit")
    mask = model.axis_mask()
    kap = np.ones(3) if kappa is None else np.maximum(np.asarray(kappa, dtype=float).reshape(3), 1.0)
    theta = np.zeros((3, p))
    cov = np.zeros((3, p, p))
    sig = np.zeros(3)
    sse = np.zeros(3)
    dof = np.zeros(3)
    cond = np.zeros(3)
    und: list[tuple[int, int]] = []
    with single_thread():
        for i in range(3):
            sol, s = _sigma_map(R, p, i, mask[i], prior.mean[i], prior.cov[i], n, kap[i],
                                None if sigma_uT is None else float(sigma_uT[i]))
            theta[i], cov[i], sse[i], cond[i] = sol.theta, sol.cov, sol.sse, sol.cond
            dof[i] = n - sol.trace_h
            sig[i] = s
            und += [(i, c) for c in sol.undetermined]
    return Posterior(model, prior, theta, cov, sig, kap, sse, dof, cond, int(n), und)


def map_solve_one(R: np.ndarray, n: int, mean: np.ndarray, cov: np.ndarray, kappa: float = 1.0,
                  sigma: float | None = None) -> tuple[AxisPosterior, float]:
    """MAP of a single output from the R factor of the weighted ``[X | y]`` ((q+1) columns) of ``n`` rows:
    the solve and sigma iteration of :func:`map_solve` for a problem whose parameters are not split by
    output axis (the attitude-independent fit: one magnitude residual per row couples all of them).
    ``mean`` (q,), ``cov`` (q, q) with the same conventions as :class:`Prior` (inf = flat, 0 = fixed).
    Returns the solution and the residual scale sigma used (same unit as y)."""
    from magstack.firmware.blas import single_thread

    q = R.shape[1] - 1
    if n <= 0:
        raise FitError("no rows to fit")
    mean = np.asarray(mean, dtype=float).reshape(q)
    cov = np.asarray(cov, dtype=float).reshape(q, q)
    mask = np.ones(q, dtype=bool)
    kap = max(float(kappa), 1.0)
    with single_thread():
        return _sigma_map(R, q, 0, mask, mean, cov, n, kap, None if sigma is None else float(sigma))


def _sigma_map(R: np.ndarray, p: int, i: int, mask: np.ndarray, mean: np.ndarray, cov: np.ndarray, n: int,
               kap: float, sigma: float | None):
    """One output's MAP (:func:`_axis_map`) with its residual scale: ``sigma`` when known, else started from the
    minimum-norm residual and iterated ``sigma^2 = SSE / (n - tr H)`` to ``SIGMA_RTOL``. Returns (solution,
    sigma)."""
    if sigma is None:
        s0, rank = _min_norm_sse(R, p, i, mask, mean, np.diag(cov))
        s = float(np.sqrt(s0 / max(n - rank, 1)))
    else:
        s = sigma
    s = s if s > 0 else 1e-9
    for _ in range(MAX_SIGMA_ITER):
        sol = _axis_map(R, p, i, mask, mean, cov, 1.0 / (s * s * kap))
        if sigma is not None:
            break
        new = float(np.sqrt(sol.sse / max(n - sol.trace_h, 1.0)))
        new = new if new > 0 else 1e-9
        if abs(new - s) <= SIGMA_RTOL * s:
            break
        s = new
    return sol, s


# ---------------------------------------------------------------------- residual autocorrelation
def autocorr_inflation(resid_uT: np.ndarray, t_s: np.ndarray, session: np.ndarray, min_blocks: int = 16,
                       cap: float = 1e4) -> np.ndarray:
    """(3,) variance inflation ``kappa >= 1`` of autocorrelated residuals (blocking method).

    Rows of each session in time order are cut into blocks of L = 2, 4, 8, ... rows; ``kappa(L) =
    L var(block means) / var(rows)`` estimates the integrated autocorrelation time; the largest over the
    L that leave at least ``min_blocks`` blocks is used (conservative: correlated misfit must not pass for
    independent evidence). A short session (fewer than ``2 min_blocks`` rows) gives 1. The accumulation
    is :class:`.blocking.BlockingInflation` (which the cross-fit feeds block by block).
    """
    from magstack.firmware.calibration.blocking import BlockingInflation

    r = np.asarray(resid_uT, dtype=float).reshape(-1, 3)
    s = np.asarray(session).reshape(-1)
    t = np.asarray(t_s, dtype=float).reshape(-1)
    if r.shape[0] < 2 * min_blocks:
        return np.ones(3)
    order = np.lexsort((t, s))
    acc = BlockingInflation()
    acc.add((r[order] - np.mean(r, axis=0)).T, s[order])
    return acc.kappa(min_blocks, cap)


def names_of(model: CalModel) -> list[tuple[int, int, str]]:
    """(axis, column, name) of every parameter the model uses, axis-major."""
    mask = model.axis_mask()
    return [(i, c, model.param_name(i, c)) for i in range(3) for c in range(model.n_columns) if mask[i, c]]


__all__ = ["Prior", "Posterior", "AxisPosterior", "model_prior", "apply_overrides", "parse_override", "map_solve",
           "map_solve_one",
           "autocorr_inflation", "names_of", "RANK_RTOL", "AXES"]
