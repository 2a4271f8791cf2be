"""Attitude-independent calibration through the calibration estimator: MAP with the chip's priors.

The measurement equation is the bench fit's (:mod:`.model`, e.g. ``eq3``)::

    B_cal = (S + K_S dT) B_meas + O + K_O dT

but the data give only a magnitude per row: the local field's ``|B|`` (a constant from IGRF/WMM at the
site, a given value, a reference instrument's magnitude per row) or nothing (then the magnitude ``F`` is a
parameter, and the overall scale rests on the prior of the gains). The residual ``e_n = F_n - |B_cal,n|``
is non-linear in the parameters; each Gauss-Newton step linearises it, ``e(phi + d) ~ e(phi) - J d`` with
``J_n = u_n^T dB_cal,n/dphi`` (``u_n`` the calibrated field's direction), and solves for ``d`` with
:func:`.estimator.map_solve_one`: the same QR of the equilibrated stack, the same prior conventions (flat,
fixed, Gaussian), the same sigma iteration and the same residual-autocorrelation inflation as ``fit``. At
convergence the last linearisation's posterior is the parameter covariance (Laplace approximation).

**What the magnitude cannot determine.** ``|Q B_cal| = |B_cal|`` for every rotation ``Q``: a rotation of the
whole calibration (3 angles) and, with temperature terms, a rotation that changes with temperature (3 more)
are invisible. The fit therefore works in a stated gauge instead of letting the prior pick them: ``S`` and
``K_S`` symmetric (``soft_iron="symmetric"``, 6 + 6 parameters; the calibrated frame is the sensor's own
frame turned by the smallest rotation) or diagonal (``"diagonal"``: per-axis scale factors only). The prior
of a symmetric off-diagonal entry is the part's off-diagonal prior with its sd divided by sqrt(2) (the
symmetric part of a matrix with independent off-diagonal errors). Callers that have more information (a
level turn fixes the tilt, a reference vector the whole rotation) rotate the result afterwards.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magstack.firmware.calibration.estimator import DATA_SD_RATIO, PRIOR_SD_RATIO, Prior, map_solve_one
from magstack.firmware.calibration.linalg import qr_r
from magstack.firmware.calibration.model import AXES, CalModel
from magstack.firmware.errors import FitError

SOFT_IRON = ("symmetric", "diagonal")
#: Gauss-Newton stops when every step is below this fraction of the parameter's posterior sd.
STEP_RTOL = 1e-4
MAX_ITER = 40


@dataclass(frozen=True)
class ScalarParams:
    """How the free parameters ``phi`` (q,) map onto the model's coefficients: ``theta.ravel() = T @ phi[:m]``
    (axis-major, ``m`` = ``T.shape[1]``); ``groups[k]``: the coefficient indices parameter ``k`` sets;
    ``names[k]``: its name (``S[x,y]`` for the symmetric pair); ``magnitude``: the last parameter is the
    field magnitude ``F`` (uT)."""

    model: CalModel
    soft_iron: str
    T: np.ndarray
    groups: tuple[tuple[int, ...], ...]
    names: tuple[str, ...]
    magnitude: bool

    @property
    def n_model(self) -> int:
        return self.T.shape[1]

    @property
    def q(self) -> int:
        return self.n_model + int(self.magnitude)

    def theta(self, phi: np.ndarray) -> np.ndarray:
        """(3, p) model coefficients of ``phi``."""
        return (self.T @ np.asarray(phi, dtype=float)[:self.n_model]).reshape(3, self.model.n_columns)


def parametrise(model: CalModel, soft_iron: str = "symmetric", magnitude: bool = False) -> ScalarParams:
    """The gauge-fixed parameters of ``model`` (module docstring): matrices (``S``, ``K_S``) symmetric or
    diagonal, vectors (``O``, ``K_O``) free; ``magnitude`` adds ``F`` (uT) as the last parameter."""
    if soft_iron not in SOFT_IRON:
        raise FitError(f"unknown soft-iron form {soft_iron!r}; valid: {', '.join(SOFT_IRON)}")
    allowed = {"gain_matrix", "temperature_gain", "offset", "temperature_offset"}
    bad = [t for t in model.terms if t not in allowed]
    if bad:
        raise FitError(f"the attitude-independent fit takes the terms {sorted(allowed)}, not {bad}")
    p = model.n_columns
    groups: list[tuple[int, ...]] = []
    names: list[str] = []
    mats: dict[str, dict[int, int]] = {}
    for c, col in enumerate(model.columns):
        if col.param in ("S", "K_S"):
            mats.setdefault(col.param, {})[col.index] = c
        else:                                    # O, K_O: one per output axis
            for i in range(3):
                groups.append((i * p + c,))
                names.append(model.param_name(i, c))
    for cols in mats.values():
        for i in range(3):
            for j in range(i, 3):
                if soft_iron == "diagonal" and i != j:
                    continue
                idx = (i * p + cols[j],) if i == j else (i * p + cols[j], j * p + cols[i])
                groups.append(idx)
                names.append(model.param_name(i, cols[j]))
    order = sorted(range(len(groups)), key=lambda k: groups[k][0])
    groups = [groups[k] for k in order]
    names = [names[k] for k in order]
    T = np.zeros((3 * p, len(groups)))
    for k, g in enumerate(groups):
        T[list(g), k] = 1.0
    if magnitude:
        names.append("F")
    return ScalarParams(model, soft_iron, T, tuple(tuple(g) for g in groups), tuple(names), magnitude)


def phi_prior(par: ScalarParams, prior: Prior, magnitude: tuple[float, float] | None = None
              ) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """(mean (q,), covariance (q, q), sources) of ``phi`` from the model's prior ``prior`` (per axis, as
    ``fit`` builds it): a parameter that sets k coefficients takes their mean prior mean and their mean
    variance / k (symmetric pair: sd / sqrt(2)). ``magnitude``: (mean, sd) of ``F`` (sd inf = flat)."""
    p = par.model.n_columns
    var_theta = np.diagonal(prior.cov, axis1=1, axis2=2).reshape(-1)
    mean_theta = prior.mean.reshape(-1)
    q = par.q
    mean = np.zeros(q)
    var = np.zeros(q)
    src = []
    for k, g in enumerate(par.groups):
        mean[k] = float(np.mean(mean_theta[list(g)]))
        var[k] = float(np.mean(var_theta[list(g)])) / len(g)
        s = prior.source[g[0] // p][g[0] % p]
        src.append(s + (" (symmetric pair: sd / sqrt 2)" if len(g) == 2 and np.isfinite(var[k]) else ""))
    if par.magnitude:
        m, sd = magnitude if magnitude is not None else (0.0, np.inf)
        mean[-1] = m
        var[-1] = sd * sd if np.isfinite(sd) else np.inf
        src.append("given field magnitude" if np.isfinite(sd) else "none (flat): the field magnitude is estimated")
    cov = np.zeros((q, q))
    np.fill_diagonal(cov, var)
    return mean, cov, tuple(src)


@dataclass
class ScalarPosterior:
    """The MAP estimate of the gauge-fixed parameters and what produced it (uT, 1/degC, uT/degC)."""

    par: ScalarParams
    phi: np.ndarray
    cov: np.ndarray
    prior_mean: np.ndarray
    prior_cov: np.ndarray
    sources: tuple[str, ...]
    sigma_uT: float
    kappa: float
    n: int
    iterations: int
    undetermined: tuple[int, ...] = ()
    sse_uT2: float = float("nan")
    trace_h: float = float("nan")

    @property
    def theta(self) -> np.ndarray:
        return self.par.theta(self.phi)

    @property
    def sd(self) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            return np.sqrt(np.diag(self.cov))

    @property
    def prior_sd(self) -> np.ndarray:
        return np.sqrt(np.diag(self.prior_cov))

    def determined_by(self, k: int) -> str:
        """"data", "prior", "data+prior", "fixed", "data (flat prior)" or "undetermined" (estimator.Posterior)."""
        vp = self.prior_cov[k, k]
        if k in self.undetermined:
            return "undetermined"
        if vp == 0:
            return "fixed"
        if not np.isfinite(vp):
            return "data (flat prior)"
        ratio = np.sqrt(self.cov[k, k] / vp)
        return "data" if ratio <= DATA_SD_RATIO else "prior" if ratio >= PRIOR_SD_RATIO else "data+prior"

    def data_share(self, k: int) -> float:
        vp = self.prior_cov[k, k]
        if not (np.isfinite(vp) and vp > 0):
            return float("nan")
        return float(1.0 - self.cov[k, k] / vp)

    def theta_cov(self) -> np.ndarray:
        """(3p, 3p) covariance of the model coefficients (axis-major), ``F`` marginalised."""
        m = self.par.n_model
        C = np.nan_to_num(self.cov[:m, :m], nan=0.0)
        return self.par.T @ C @ self.par.T.T


def design(model: CalModel, b_meas_uT: np.ndarray, temp_c: np.ndarray | None) -> np.ndarray:
    """(N, p) design matrix of ``model`` (temperature only when the model has temperature terms)."""
    need_t = bool({"temperature_gain", "temperature_offset"} & set(model.terms))
    return model.design(b_meas_uT, temp_c if need_t else None)


def predict(par: ScalarParams, phi: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(N, 3) calibrated field."""
    return X @ par.theta(phi).T


def start_phi(par: ScalarParams, b_meas_uT: np.ndarray, r_uT: np.ndarray | None) -> np.ndarray:
    """A start from the closed-form quadric fit of :mod:`.scalar` (``S`` = sqrtm of the ellipsoid's matrix,
    ``O = -S c``, temperature terms 0); with no magnitude (``r_uT`` None) the ellipsoid is scaled to a
    unit-determinant gain and ``F`` starts at the mean calibrated magnitude. Identity when the data do not
    lie on an ellipsoid."""
    from scipy.linalg import sqrtm

    from magstack.firmware.calibration.scalar import closed_form_start, scalar_residual

    b = np.asarray(b_meas_uT, dtype=float)
    r = np.full(len(b), 50.0) if r_uT is None else np.asarray(r_uT, dtype=float)
    best = None
    try:
        cands = closed_form_start(b, r)
    except (np.linalg.LinAlgError, ValueError):
        cands = []
    for _, A, c, _ in cands:
        K = np.real(sqrtm(A))
        K = 0.5 * (K + K.T)
        if r_uT is None:
            K = K / np.cbrt(np.linalg.det(K))
        if par.soft_iron == "diagonal":
            K = np.diag(np.diag(K))
        k = K @ c
        res = scalar_residual(K, k, b, r) if r_uT is not None else (
            np.linalg.norm(b @ K.T - k, axis=1) - np.mean(np.linalg.norm(b @ K.T - k, axis=1)))
        cost = float(np.mean(res ** 2))
        if np.isfinite(cost) and (best is None or cost < best[0]):
            best = (cost, K, k)
    if best is None:
        K, k = np.eye(3), np.mean(b, axis=0)
    else:
        _, K, k = best
    m = par.model
    p = m.n_columns
    theta = np.zeros((3, p))
    for c, col in enumerate(m.columns):
        if col.param == "S":
            theta[:, c] = K[:, col.index]
        elif col.param == "O":
            theta[:, c] = -k
    phi = np.linalg.lstsq(par.T, theta.ravel(), rcond=None)[0]
    if par.magnitude:
        phi = np.r_[phi, float(np.mean(np.linalg.norm(b @ K.T - k, axis=1)))]
    return phi


def residual(par: ScalarParams, phi: np.ndarray, X: np.ndarray, r_uT: np.ndarray | None) -> np.ndarray:
    """(N,) ``F_n - |B_cal,n|`` (uT); ``F`` is ``r_uT`` or the parameter."""
    mag = np.linalg.norm(predict(par, phi, X), axis=1)
    return (phi[-1] if r_uT is None else r_uT) - mag


def _jacobian(par: ScalarParams, phi: np.ndarray, X: np.ndarray, r_uT) -> tuple[np.ndarray, np.ndarray]:
    """(design (N, q) of the linearised residual, residual (N,)): ``e(phi + d) ~ e - D d``."""
    f = predict(par, phi, X)
    nf = np.linalg.norm(f, axis=1)
    u = f / np.where(nf > 0, nf, 1.0)[:, None]
    n, p = X.shape
    J = np.einsum("ni,nc->nic", u, X).reshape(n, 3 * p) @ par.T
    e = ((phi[-1] if r_uT is None else r_uT) - nf)
    if par.magnitude:
        J = np.hstack([J, -np.ones((n, 1))])
    return J, e


def _objective(e: np.ndarray, w: np.ndarray, phi: np.ndarray, mean: np.ndarray, cov: np.ndarray, lam: float) -> float:
    var = np.diag(cov)
    fin = np.isfinite(var) & (var > 0)
    d = phi[fin] - mean[fin]
    return float(lam * np.sum(w * e * e) + np.sum(d * d / var[fin]))


def _solve(R, n, mean, cov, kappa, floor):
    sol, sigma = map_solve_one(R, n, mean, cov, kappa)
    if sigma < floor:
        sol, sigma = map_solve_one(R, n, mean, cov, kappa, sigma=floor)
    return sol, sigma


def fit_magnitude(par: ScalarParams, X: np.ndarray, r_uT: np.ndarray | None, prior_mean: np.ndarray,
                  prior_cov: np.ndarray, sources: tuple[str, ...], *, weights: np.ndarray | None = None,
                  start: np.ndarray | None = None, kappa: float = 1.0, max_iter: int = MAX_ITER,
                  sigma_floor_uT: float = 0.0) -> ScalarPosterior:
    """Gauss-Newton MAP of ``phi`` (module docstring) from the design ``X`` (N, p) and magnitudes ``r_uT``
    ((N,) uT, or None when ``par.magnitude``); ``weights`` (N,) >= 0; ``kappa`` the residual
    autocorrelation inflation; ``sigma_floor_uT`` a lower bound of the residual scale (the sensor's own noise:
    where the rows admit an exact fit, e.g. a zero gain and an offset as long as the field, the sigma iteration
    would otherwise shrink to nothing and the prior would stop counting). Raises FitError when it does not
    converge to a finite answer."""
    n = X.shape[0]
    if n <= par.q:
        raise FitError(f"{n} rows for {par.q} parameters: not enough data")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    sw = np.sqrt(w)[:, None]
    phi = np.array(start if start is not None else start_phi(par, X[:, :3], r_uT), dtype=float)
    fixed = np.diag(prior_cov) == 0
    phi[fixed] = prior_mean[fixed]
    sol = None
    sigma = None
    it = 0
    for _ in range(max_iter):
        it += 1
        J, e = _jacobian(par, phi, X, r_uT)
        R = qr_r(np.hstack([J, e[:, None]]) * sw)
        sol, sigma = _solve(R, n, prior_mean - phi, prior_cov, kappa, sigma_floor_uT)
        d = sol.theta
        if not np.all(np.isfinite(d)):
            raise FitError("the attitude-independent fit diverged (non-finite step)")
        lam = 1.0 / (sigma * sigma * kappa)
        f0 = _objective(e, w, phi, prior_mean, prior_cov, lam)
        step = 1.0
        for _ in range(8):          # halve the step while the MAP objective does not decrease
            trial = phi + step * d
            e1 = residual(par, trial, X, r_uT)
            if _objective(e1, w, trial, prior_mean, prior_cov, lam) <= f0 * (1 + 1e-12):
                break
            step *= 0.5
        phi = phi + step * d
        sd = np.sqrt(np.abs(np.diag(sol.cov)))
        scale = np.where(sd > 0, sd, np.maximum(np.abs(phi), 1e-12))
        if np.all(np.abs(step * d) <= STEP_RTOL * scale):
            break
    # the posterior at the solution (one more linearisation there)
    J, e = _jacobian(par, phi, X, r_uT)
    R = qr_r(np.hstack([J, e[:, None]]) * sw)
    sol, sigma = _solve(R, n, prior_mean - phi, prior_cov, kappa, sigma_floor_uT)
    if not np.all(np.isfinite(phi)):
        raise FitError("the attitude-independent fit did not converge to a finite answer")
    return ScalarPosterior(par, phi, sol.cov, prior_mean, prior_cov, sources, float(sigma), float(kappa), n, it,
                           tuple(sol.undetermined), float(np.sum(w * e * e)), float(sol.trace_h))


@dataclass
class ParameterRow:
    """One row of the report's parameter table."""

    name: str
    value: float
    sd: float
    prior_mean: float
    prior_sd: float
    data_share: float
    determined_by: str
    unit: str = ""
    extra: dict = field(default_factory=dict)


def parameter_rows(post: ScalarPosterior) -> list[ParameterRow]:
    """Value, posterior sd, prior and who determined each free parameter."""
    units = {"S": "1", "K_S": "1/degC", "O": "uT", "K_O": "uT/degC", "F": "uT"}
    out = []
    for k, name in enumerate(post.par.names):
        out.append(ParameterRow(name, float(post.phi[k]), float(post.sd[k]), float(post.prior_mean[k]),
                                float(post.prior_sd[k]), post.data_share(k), post.determined_by(k),
                                units.get(name.split("[")[0], "")))
    return out


__all__ = ["SOFT_IRON", "ScalarParams", "ScalarPosterior", "ParameterRow", "parametrise", "phi_prior", "design",
           "predict", "start_phi", "residual", "fit_magnitude", "parameter_rows", "AXES"]
