"""Attitude-independent ("scalar checking") calibration against the reference field magnitude.

Model (riwanto eq. 2b, belsten Eq. 3 without temperature terms)::

    b_hat = K @ b_meas - k          |b_hat| = |b_ref|

``K`` (3x3, unitless) and ``k`` (same unit as the data) are what a calibration table stores
as ``S = K`` and ``O = -k`` (term ``gain_matrix`` + ``offset``).

Only the magnitude is checked, so ``(Q K, Q k)`` fits exactly as well for every rotation
``Q``: the data fix ``A = K^T K`` and the centre ``c = K^-1 k`` (9 numbers), never the
rotation. The answer is therefore reported in a stated *gauge* (:data:`GAUGES`):

* ``"symmetric"``        ``K`` symmetric positive definite (``K = sqrtm(A)``), the smallest
  rotation away from the raw sensor frame; the default.
* ``"lower_triangular"`` ``K`` lower triangular with positive diagonal: calibrated x lies
  along sensor x, calibrated y in the sensor x-y plane (the usual "one axis is aligned"
  assumption of TWOSTEP-style papers).
* ``"prior"``            the rotation that brings ``K`` closest to a given matrix (e.g. the
  active table's ``S``), so a scalar refit keeps the active table's alignment.
* ``"reference"``        the rotation that best maps the calibrated vectors onto given
  reference vectors (Wahba's problem; needs ``b_ref`` as (N, 3) vectors).
* ``"axes"``             the rotation that turns the oriented plane normals of calibrated
  rotation loci onto ``-omega`` (the riwanto rotation-axis information; see ``pso.py``).

Closed-form start: an algebraic ellipsoid/quadric fit, chosen because it needs no prior
(TWOSTEP's centring step needs an a-priori small-misalignment assumption to split off the
scale factors; the quadric fit gives the full ``A`` and ``c`` directly). Two linear
variants are computed and the one with the lower magnitude residual is kept:

1. "magnitude" quadric: ``b^T A b - 2 g^T b + d = |b_ref|^2`` solved by linear least squares
   (10 unknowns, ``d`` relaxed as in TWOSTEP); needs ``|b_ref|`` to vary, otherwise the
   constant column and the target are collinear and the scale is lost.
2. "shape" quadric: the algebraic ellipsoid through the points (smallest right singular vector
   of the 10-column design), scaled so that the mean ``(b-c)^T A (b-c)`` equals the mean
   ``|b_ref|^2``; exact for constant ``|b_ref|``.

The start is refined by :func:`scipy.optimize.least_squares` on the residual
``|K b_meas - k| - |b_ref|`` (same unit as the data) with an analytic Jacobian, in the
9-parameter symmetric gauge, then rotated into the requested gauge.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.linalg import cholesky, polar, sqrtm
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from magstack.firmware.calibration.pso import area_vector
from magstack.firmware.errors import FitError

GAUGES = ("symmetric", "lower_triangular", "prior", "reference", "axes")

_IU = np.triu_indices(3)          # the 6 free entries of a symmetric K
#: Candidate starts along the least-determined quadric direction (gauge "axes", degenerate loci).
N_PENCIL = 24
#: Best starts refined by the joint least squares (gauge "axes").
N_AXES_STARTS = 2


@dataclass(frozen=True)
class ScalarFit:
    """Result of :func:`fit_scalar`. ``k`` is in the unit of the input data.

    ``rms_residual`` = RMS of ``|K b_meas - k| - |b_ref|`` after the fit, ``rms_raw`` the same
    for the raw data (K = I, k = 0); ``start`` names the closed-form variant that won.
    ``se_params``: 1-sigma standard errors in the fit's own parametrisation, before the gauge
    rotation: ``[K11 K12 K13 K22 K23 K33 k1 k2 k3]`` (symmetric fit) or ``[K row-major, k]``
    (gauge ``axes``). A direction the data cannot see gets an error that does not shrink with
    the noise (two great circles, magnitudes only: about 0.04 on K at any noise level).
    """

    K: np.ndarray
    k: np.ndarray
    gauge: str
    rms_residual: float
    rms_raw: float
    n_used: int
    start: str
    nfev: int
    runtime_s: float
    se_params: np.ndarray = field(default_factory=lambda: np.full(9, np.nan))

    def apply(self, b_meas: np.ndarray) -> np.ndarray:
        """Calibrated vectors ``K b - k`` for (N, 3) input."""
        return np.asarray(b_meas, float) @ self.K.T - self.k


def scalar_residual(K: np.ndarray, k: np.ndarray, b_meas: np.ndarray, b_ref_norm: np.ndarray) -> np.ndarray:
    """``|K b_meas - k| - |b_ref|`` per sample (unit of the data)."""
    return np.linalg.norm(b_meas @ np.asarray(K).T - k, axis=1) - b_ref_norm


def _as_inputs(b_meas, b_ref) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    b = np.asarray(b_meas, dtype=float)
    if b.ndim != 2 or b.shape[1] != 3:
        raise FitError(f"b_meas must have shape (N, 3), got {b.shape}")
    r = np.asarray(b_ref, dtype=float)
    vec = None
    if r.ndim == 2 and r.shape == b.shape:
        vec = r
        r = np.linalg.norm(r, axis=1)
    elif r.ndim == 0:
        r = np.full(len(b), float(r))
    elif r.shape != (len(b),):
        raise FitError(f"b_ref must be a scalar, (N,) magnitudes or (N, 3) vectors with N = {len(b)}, got {r.shape}")
    if not (np.isfinite(b).all() and np.isfinite(r).all()):
        raise FitError("non-finite value in b_meas or b_ref")
    if (r <= 0).any():
        raise FitError("reference magnitude must be positive")
    if len(b) < 12:
        raise FitError(f"scalar calibration needs at least 12 samples (9 unknowns), got {len(b)}")
    return b, r, vec


def _quad_design(b: np.ndarray) -> np.ndarray:
    x, y, z = b.T
    return np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, -2 * x, -2 * y, -2 * z,
                            np.ones(len(b))])


def _from_quadric(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(A, c, d) from ``[a11 a22 a33 a12 a13 a23 g1 g2 g3 d]``; None if A is not definite."""
    a11, a22, a33, a12, a13, a23 = theta[:6]
    A = np.array([[a11, a12, a13], [a12, a22, a23], [a13, a23, a33]])
    if np.trace(A) < 0:
        A, theta = -A, -theta
    w = np.linalg.eigvalsh(A)
    if w[0] <= 0 or not np.isfinite(w).all():
        return None
    c = np.linalg.solve(A, theta[6:9])
    return A, c, float(theta[9])


def _quadric_candidates(b: np.ndarray, r: np.ndarray, ts, phis) -> list[tuple[str, float, np.ndarray]]:
    """Quadric coefficient vectors (scaled units) ``(name, pencil parameter, theta)`` of both
    closed-form variants, plus points ``ts`` / ``phis`` along each one's least-determined
    direction (see :func:`closed_form_start`)."""
    D = _quad_design(b)
    col = np.linalg.norm(D, axis=0)
    Dn = D / col
    out = []
    # 1. magnitude quadric (TWOSTEP-like relaxation: d free), plus particular + t * null direction
    theta, *_ = np.linalg.lstsq(D, r ** 2, rcond=None)
    out.append(("magnitude_quadric", 0.0, theta))
    _, _, vt = np.linalg.svd(Dn, full_matrices=False)
    v = vt[-1] / col
    scale = np.linalg.norm(theta[:6]) / max(np.linalg.norm(v[:6]), 1e-300)
    for t in ts:
        out.append(("magnitude_quadric_pencil", t, theta + t * scale * v))
    # 2. shape quadric (algebraic ellipsoid, unit norm), plus the pencil of the two smallest directions
    out.append(("shape_quadric", 0.0, vt[-1] / col))
    for phi in phis:
        out.append(("shape_quadric_pencil", phi, (np.cos(phi) * vt[-1] + np.sin(phi) * vt[-2]) / col))
    return out


def closed_form_start(b: np.ndarray, r: np.ndarray, n_pencil: int = 0, *, ts=None, phis=None
                      ) -> list[tuple[str, np.ndarray, np.ndarray, float]]:
    """Closed-form candidates ``(name, A, c, pencil parameter)`` with ``|K(b - c)| ~ r`` for ``K^T K = A``.

    When the loci do not determine an ellipsoid (e.g. two circles: every quadric
    ``sphere + mu * plane_1 * plane_2`` contains both), the design has a (near) null direction;
    ``n_pencil > 0`` adds candidates along it (``t`` in [-1, 1] for the magnitude variant, angle
    ``phi`` in [0, pi) between the two smallest singular directions for the shape variant), or
    explicit ``ts`` / ``phis``; they are to be chosen by a cost that sees more than the magnitude
    (the rotation-axis residual)."""
    if ts is None:
        ts = np.linspace(-1.0, 1.0, n_pencil) if n_pencil else ()
    if phis is None:
        phis = np.linspace(0.0, np.pi, n_pencil, endpoint=False) if n_pencil else ()
    # scale data and reference to O(1) for conditioning: A is scale-free, c scales by s
    s = float(np.median(r))
    bs, rs = b / s, r / s
    out = []
    for name, param, theta in _quadric_candidates(bs, rs, ts, phis):
        q = _from_quadric(theta)
        if q is None:
            continue
        A, c, _ = q
        if name.startswith("shape"):
            # the ellipsoid's scale is free: match the mean squared reference magnitude
            u = bs - c
            m = np.einsum("ni,ij,nj->n", u, A, u)
            lam = np.mean(rs ** 2) / np.mean(m)
            if not (np.isfinite(lam) and lam > 0):
                continue
            A = lam * A
        out.append((name, A, c * s, float(param)))
    return out


def _K_sym(p: np.ndarray) -> np.ndarray:
    K = np.zeros((3, 3))
    K[_IU] = p[:6]
    return K + np.triu(K, 1).T


def _refine(b: np.ndarray, r: np.ndarray, K0: np.ndarray, k0: np.ndarray, loss: str, f_scale: float):
    """Least squares in the symmetric gauge: 6 entries of K, 3 of k."""
    def fun(p):
        return np.linalg.norm(b @ _K_sym(p).T - p[6:], axis=1) - r

    def jac(p):
        u = b @ _K_sym(p).T - p[6:]
        n = np.linalg.norm(u, axis=1, keepdims=True)
        e = u / np.where(n > 0, n, 1.0)                   # d|u|/du
        J = np.empty((len(b), 9))
        for col, (i, j) in enumerate(zip(*_IU, strict=True)):
            J[:, col] = e[:, i] * b[:, j] + (e[:, j] * b[:, i] if i != j else 0.0)
        J[:, 6:] = -e
        return J

    p0 = np.concatenate([K0[_IU], k0])
    res = least_squares(fun, p0, jac=jac, method="trf" if loss != "linear" else "lm", loss=loss,
                        f_scale=f_scale, x_scale="jac")
    return _K_sym(res.x), res.x[6:].copy(), res


def oriented_normal(points: np.ndarray) -> np.ndarray:
    """Unit normal of the orthogonal-regression plane through ``points`` (n, 3), signed by the
    right-hand rule of the sample order (oriented area of the centred polygon)."""
    u = points - points.mean(axis=0)
    _, vecs = np.linalg.eigh(u.T @ u)
    n = vecs[:, 0]
    return n if n @ area_vector(u) >= 0 else -n


def rotation_from_axes(b_cal: np.ndarray, groups, omega_hat: np.ndarray) -> np.ndarray:
    """Rotation ``Q`` (3x3) that best turns each calibrated locus's oriented plane normal onto
    ``-omega_l`` (the field turns opposite to the body); ``groups`` are index arrays per locus."""
    normals = np.array([oriented_normal(b_cal[g]) for g in groups])
    rot, _ = Rotation.align_vectors(-omega_hat, normals)
    return rot.as_matrix()


def axis_residuals(b_cal: np.ndarray, groups, omega_hat: np.ndarray) -> np.ndarray:
    """Per locus ``w_l (n_l + omega_l)`` (3 values each, unit of the data). ``w_l = R_l sqrt(n_l / 2)``
    with ``R_l`` the RMS distance of the calibrated points from their centroid: for points spread
    round a circle, the fitted normal's angular error has standard deviation ~ sigma / w_l, so
    these residuals carry the same noise sigma as the magnitude residuals (no tuning weight)."""
    out = []
    for g, om in zip(groups, omega_hat, strict=True):
        pts = b_cal[g]
        radius = np.sqrt(np.mean(np.sum((pts - pts.mean(axis=0)) ** 2, axis=1)))
        out.append(radius * np.sqrt(len(g) / 2.0) * (oriented_normal(pts) + om))
    return np.concatenate(out)


def _check_loci(locus, omega, n: int) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    """(index arrays per locus, unit axes per locus)."""
    if locus is None or omega is None:
        raise FitError("gauge 'axes' needs locus labels and rotation axes omega")
    lab = np.asarray(locus)
    om = np.asarray(omega, dtype=float)
    if lab.shape != (n,) or not np.issubdtype(lab.dtype, np.integer):
        raise FitError(f"locus must be (N,) integer labels, got {lab.shape} {lab.dtype}")
    if om.ndim != 2 or om.shape[1] != 3 or lab.min() < 0 or lab.max() >= len(om):
        raise FitError(f"omega must be (L, 3) with one row per locus label 0..{int(lab.max())}")
    if not np.isfinite(om).all() or (np.linalg.norm(om, axis=1) == 0).any():
        raise FitError("rotation axes must be finite and non-zero")
    used = np.unique(lab)
    if len(used) < 2:
        raise FitError("the rotation-axis gauge needs at least two loci")
    groups = tuple(np.flatnonzero(lab == u) for u in used)
    if any(len(g) < 3 for g in groups):
        raise FitError("every locus needs at least 3 samples to fit its plane")
    axes = om[used] / np.linalg.norm(om[used], axis=1, keepdims=True)
    if np.linalg.matrix_rank(axes, tol=1e-6) < 2:
        raise FitError("the rotation axes of the loci are parallel: they do not fix the rotation")
    return groups, axes


def _refine_axes(b, r, K0, k0, groups, axes, loss, f_scale):
    """Joint least squares over all 12 parameters: magnitude residuals + axis residuals."""
    def fun(p):
        K = p[:9].reshape(3, 3)
        bc = b @ K.T - p[9:]
        return np.r_[np.linalg.norm(bc, axis=1) - r, axis_residuals(bc, groups, axes)]

    res = least_squares(fun, np.r_[K0.ravel(), k0], method="trf", loss=loss, f_scale=f_scale, x_scale="jac")
    return res.x[:9].reshape(3, 3), res.x[9:].copy(), res


def fit_scalar(b_meas, b_ref, *, gauge: str = "symmetric", K_prior=None, locus=None, omega=None,
               loss: str = "linear", f_scale: float = 1.0) -> ScalarFit:
    """Scalar calibration of ``b_meas`` (N, 3) against ``b_ref`` (scalar, (N,) magnitudes or
    (N, 3) vectors; only magnitudes are fitted). ``gauge`` picks the rotation (module doc);
    ``K_prior`` for ``"prior"``; ``locus`` (N,) ints and ``omega`` (L, 3) for ``"axes"``.
    With ``"axes"`` the rotation-axis residuals (:func:`axis_residuals`) join the magnitude
    residuals in one 12-parameter least squares, which also fixes what the magnitude alone
    cannot (e.g. two great-circle loci). ``loss``/``f_scale`` go to least_squares (e.g.
    ``"soft_l1"`` for outliers; f_scale in data units). Raises FitError when the data do not
    determine the calibration."""
    if gauge not in GAUGES:
        raise FitError(f"unknown gauge {gauge!r}; valid: {', '.join(GAUGES)}")
    t0 = time.perf_counter()
    b, r, vec = _as_inputs(b_meas, b_ref)
    if gauge == "prior":
        if K_prior is None:
            raise FitError("gauge 'prior' needs K_prior")
        if np.shape(K_prior) != (3, 3) or not np.isfinite(np.asarray(K_prior, dtype=float)).all():
            raise FitError(f"K_prior must be a finite 3x3 matrix, got shape {np.shape(K_prior)}")
    if gauge == "reference" and vec is None:
        raise FitError("gauge 'reference' needs b_ref as (N, 3) vectors")
    groups, axes = _check_loci(locus, omega, len(b)) if gauge == "axes" else ((), np.zeros((0, 3)))

    def start_cost(A, c):
        K0 = np.real(sqrtm(A))
        K0 = (K0 + K0.T) / 2
        k0 = K0 @ c
        res0 = scalar_residual(K0, k0, b, r)
        if gauge == "axes":
            Q = rotation_from_axes(b @ K0.T - k0, groups, axes)
            K0, k0 = Q @ K0, Q @ k0
            res0 = np.r_[res0, axis_residuals(b @ K0.T - k0, groups, axes)]
        return float(np.sum(res0 ** 2)), K0, k0

    scored = []
    for name, A, c, _ in closed_form_start(b, r, n_pencil=N_PENCIL if gauge == "axes" else 0):
        cost, K0, k0 = start_cost(A, c)
        if np.isfinite(cost):
            scored.append((cost, name, K0, k0))
    if not scored:
        raise FitError("closed-form start failed: the data do not lie on an ellipsoid (too little attitude "
                       "coverage or degenerate loci)")
    scored.sort(key=lambda x: x[0])
    _, start_name, K0, k0 = scored[0]
    if gauge == "axes":
        # the joint cost can have a narrow valley along the pencil of degenerate loci: refine the
        # best few starts and keep the best proper (det > 0) answer
        best = None
        for _, name, K0, k0 in scored[:N_AXES_STARTS]:
            Ki, ki, ri = _refine_axes(b, r, K0, k0, groups, axes, loss, f_scale)
            if np.linalg.det(Ki) > 0 and (best is None or ri.cost < best[2].cost):
                best = (Ki, ki, ri, name)
        if best is None:
            raise FitError("rotation-axis fit converged to a reflection (loci do not fix the handedness)")
        K, k, res, start_name = best
    else:
        K, k, res = _refine(b, r, K0, k0, loss, f_scale)
        # The magnitude is blind to any orthogonal factor: K = U P (polar) fits exactly like
        # (P, U^T k). Taking P keeps the symmetric gauge positive definite (U may be a reflection).
        U, P = polar(K)
        K, k = P, U.T @ k
    if np.linalg.svd(K, compute_uv=False)[-1] <= 1e-9 * np.abs(K).max():
        raise FitError("scalar fit is singular: the data do not determine all three axes")
    se = _standard_errors(res)
    if not np.isfinite(se).all():
        raise FitError("the data do not determine the calibration (singular Jacobian at the solution): "
                       "too little attitude coverage (e.g. a single rotation plane)")
    Q = np.eye(3)
    if gauge == "lower_triangular":
        A = K.T @ K
        J = np.eye(3)[::-1]
        L = cholesky(J @ A @ J, lower=True)        # J A J = L L^T
        Kl = J @ L.T @ J                            # lower triangular, Kl^T Kl = A
        Q = Kl @ np.linalg.inv(K)
    elif gauge == "prior":
        P = np.asarray(K_prior, float).reshape(3, 3)
        rot, _ = Rotation.align_vectors(P.T, K.T)    # columns of R K ~ columns of P
        Q = rot.as_matrix()
    elif gauge == "reference":
        rot, _ = Rotation.align_vectors(vec, b @ K.T - k)
        Q = rot.as_matrix()
    K, k = Q @ K, Q @ k
    if gauge == "lower_triangular":
        K = np.tril(K)
    rms = float(np.sqrt(np.mean(scalar_residual(K, k, b, r) ** 2)))
    raw = float(np.sqrt(np.mean(scalar_residual(np.eye(3), np.zeros(3), b, r) ** 2)))
    return ScalarFit(K=K, k=k, gauge=gauge, rms_residual=rms, rms_raw=raw, n_used=len(b), start=start_name,
                     nfev=int(res.nfev), runtime_s=time.perf_counter() - t0, se_params=se)


def _standard_errors(res) -> np.ndarray:
    """1-sigma standard errors of the fitted parameters from the Jacobian at the solution,
    ``s^2 (J^T J)^-1`` with ``s^2 = sum r^2 / (m - n)`` (inf where J^T J is singular)."""
    J = np.asarray(res.jac, dtype=float)
    m, n = J.shape
    s2 = float(np.sum(res.fun ** 2)) / max(m - n, 1)
    sv = np.linalg.svd(J, compute_uv=False)
    if sv[-1] <= sv[0] * 1e-12:
        return np.full(n, np.inf)
    return np.sqrt(s2 * np.diag(np.linalg.pinv(J.T @ J)))


# ---------------------------------------------------------------------- on-orbit refit entry point
REFIT_METHODS = ("scalar", "pso")


@dataclass(frozen=True)
class ScalarRefit:
    """Attitude-independent refit, ready for a calibration table: ``B_cal = S B_meas + O`` with
    ``S = K`` (unitless) and ``O_uT = -k`` (terms ``gain_matrix`` + ``offset``, model ``gain_offset``).

    ``rms_residual_uT`` / ``rms_raw_uT``: RMS of ``|B_cal| - |b_ref|`` after / before (K = I, k = 0).
    ``fitness`` is the PSO's eq. (10) value (computed in nT), NaN for ``method="scalar"``.
    ``field_max_uT``: largest |component| of the input, the table's default validity field."""

    method: str
    gauge: str
    S: np.ndarray
    O_uT: np.ndarray
    rms_residual_uT: float
    rms_raw_uT: float
    n_used: int
    runtime_s: float
    field_max_uT: float
    fitness: float = float("nan")
    seed: int | None = None
    se_params: np.ndarray | None = None

    def fit_stats(self) -> dict[str, Any]:
        """Statistics for the table's ``fit`` block (informational)."""
        st: dict[str, Any] = {"method": f"attitude-independent {self.method}", "gauge": self.gauge,
                              "n_used": self.n_used, "raw_rmse_scalar_uT": self.rms_raw_uT,
                              "rmse_scalar_uT": self.rms_residual_uT, "runtime_s": self.runtime_s}
        if self.se_params is not None:
            st["se_params"] = [float(x) for x in self.se_params]
        if self.method == "pso":
            st["pso_fitness_nT"] = self.fitness
            st["pso_seed"] = self.seed
        return st

    def to_table(self, device_id: str, *, description: str = "", created_utc: str = "",
                 validity_field_uT: float | None = None):
        """A :class:`magstack.firmware.cal_table.CalTable` (not yet validated: run ``validate``)."""
        from magstack.firmware.cal_table import CalTable

        return CalTable(device_id=device_id, terms=("gain_matrix", "offset"), S=self.S, O=self.O_uT,
                        validity_field_uT=float(np.ceil(self.field_max_uT)) if validity_field_uT is None
                        else float(validity_field_uT),
                        model_name="gain_offset", description=description or f"{self.method} refit ({self.gauge})",
                        created_utc=created_utc, fit_stats=self.fit_stats())


def refit_scalar(b_meas_uT, b_ref_uT, *, method: str = "scalar", locus=None, omega_body=None,
                 gauge: str | None = None, K_prior=None, seed: int = 0, pso_options=None,
                 loss: str = "linear", f_scale_uT: float = 1.0) -> ScalarRefit:
    """Attitude-independent calibration for the on-orbit refit (docs/refit-pso.md).

    ``b_meas_uT`` (N, 3) sensor output; ``b_ref_uT`` the reference field: (N,) magnitudes or (N, 3)
    vectors (only the magnitude is fitted; vectors serve ``gauge="reference"``); ``locus`` (N,)
    integer labels of single-axis rotation segments and ``omega_body`` (L, 3) their rotation axes
    in the body frame (row ``l`` for label ``l``).

    ``method="scalar"``: closed form + least squares (:func:`fit_scalar`). ``gauge`` defaults to
    ``"axes"`` when loci are given, else ``"prior"`` when ``K_prior`` (e.g. the active table's S)
    is given, else ``"symmetric"``.
    ``method="pso"``: the riwanto PSO (needs loci; it fixes the rotation by the axes itself), run in
    nT as tuned by the paper, its initial box centred on ``K_prior`` (offset 0) when given.
    """
    if method not in REFIT_METHODS:
        raise FitError(f"unknown refit method {method!r}; valid: {', '.join(REFIT_METHODS)}")
    b, r, vec = _as_inputs(b_meas_uT, b_ref_uT)
    has_loci = locus is not None or omega_body is not None
    field_max = float(np.abs(b).max())
    if method == "scalar":
        g = gauge or ("axes" if has_loci else "prior" if K_prior is not None else "symmetric")
        fit = fit_scalar(b, vec if vec is not None else r, gauge=g, K_prior=K_prior, locus=locus, omega=omega_body,
                         loss=loss, f_scale=f_scale_uT)
        return ScalarRefit("scalar", g, fit.K, -fit.k, fit.rms_residual, fit.rms_raw, fit.n_used, fit.runtime_s,
                           field_max, se_params=fit.se_params)
    from magstack.firmware.calibration import pso as _pso

    if gauge not in (None, "axes"):
        raise FitError("method 'pso' fixes the rotation by the rotation axes: gauge must be 'axes' or None")
    if not has_loci:
        raise FitError("method 'pso' needs locus labels and rotation axes (omega_body)")
    t0 = time.perf_counter()
    prob = _pso.Problem.build(b * 1e3, r * 1e3, locus, omega_body)
    center = None if K_prior is None else np.r_[np.asarray(K_prior, float).reshape(9), np.zeros(3)]
    res = _pso.run_pso(prob, seed=seed, options=pso_options, center=center)
    k_uT = res.k_nT / 1e3
    rms = float(np.sqrt(np.mean(scalar_residual(res.K, k_uT, b, r) ** 2)))
    raw = float(np.sqrt(np.mean(scalar_residual(np.eye(3), np.zeros(3), b, r) ** 2)))
    return ScalarRefit("pso", "axes", res.K, -k_uT, rms, raw, len(b), time.perf_counter() - t0, field_max,
                       fitness=res.fitness, seed=seed)
