"""Riwanto et al. (2017) multi-objective PSO with rotation-axis fitting (12 parameters).

Calibration model (paper eq. 2b): ``b_hat = K b_meas - k``; a particle is
``p = [K11 K12 K13 K21 K22 K23 K31 K32 K33 k1 k2 k3]`` (eq. 7). Fitness (eq. 10)::

    F = c_f1 sqrt(F1) / n_s + c_f2 sqrt(F2) / n_l
    F1 = sum_s (|b_s| - |K b_meas_s - k|)^2                        (eq. 8b)
    F2 = sum_l (1 - n_l . (-omega_l))^2                             (eq. 9)

``n_l`` is the unit normal of the orthogonal-regression plane through calibrated locus ``l``
(Algorithm 3), signed by the right-hand rule of the sample order; ``omega_l`` is the known
rotation axis of the body during that locus (the field turns the other way in the sensor
frame, hence the minus). The weights are the paper's (c_f1 = 1, c_f2 = 4e4) and were tuned
for data in **nT**, so this module works in nT.

Optimizer (section III-B, Table I): global-best PSO, 35 particles, 500 iterations, greedy
personal/global bests, per-component uniform random numbers (eq. 3), initial positions
uniform in ``[-pmax, pmax]`` (K entries 1, k entries 5000 nT) and velocities uniform in
``[-vmax, vmax]`` (eq. 5) with ``vmax = 2 pmax / v_lim``, ``v_lim = 50`` (eq. 6). The only
boundary condition is the velocity clamp (Algorithm 1): positions are never clamped, so the
swarm can leave the initial box (the paper's own truth has k1 = 12 600 nT, outside it).

Inertia/acceleration schedule (Fig. 2; its shape is not given in numbers, our reading, see
docs/refit-pso.md): one cycle is ``w`` ramping linearly ``w_s -> w_f`` over ``w_v`` iterations
(``c1 = c1_s``, ``c2 = c2_s``), then ``c1: c1_s -> c_f`` and ``c2: c2_s -> c_f`` linearly over
``c_v`` iterations (``w = w_f``); the cycle repeats ``n_cycles`` times, after which the end
values ``w_e``, ``c_e`` hold to ``k_max``. Table I: w_s 5, w_f 0.5, w_e 0.382, c1_s 4, c2_s 0,
c_f 2, c_e 2.5, w_v = c_v in (0.05 .. 0.4) k_max; we use 0.1 k_max and 3 cycles.

Mirror solutions: ``(-K, -k)`` gives ``b_hat -> -b_hat``, which leaves |b_hat|, the fitted
plane and the right-hand-rule sign of the normal unchanged, so both fitness terms are equal.
Eq. (11) flips ``K`` only; flipping ``K`` without ``k`` would leave a wrong offset, so the fix
here is ``(K, k) <- sign(det K) (K, k)``, applied to the returned global best.

Everything is vectorised over particles and seeded by a ``numpy.random.Generator``: the same
seed and inputs give bit-identical results.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from magstack.firmware.errors import FitError

N_PARAMS = 12
SIGN_RULES = ("area", "pair")


@dataclass(frozen=True)
class PsoOptions:
    """PSO settings; defaults are the paper's Table I (reading documented in the module doc)."""

    n_particles: int = 35
    k_max: int = 500
    w_s: float = 5.0
    w_f: float = 0.5
    w_e: float = 0.382
    c1_s: float = 4.0
    c2_s: float = 0.0
    c_f: float = 2.0
    c_e: float = 2.5
    w_v_frac: float = 0.1
    c_v_frac: float = 0.1
    n_cycles: int = 3
    pmax_K: float = 1.0            # initial box half-width of the K entries (unitless)
    pmax_k_nT: float = 5000.0      # initial box half-width of the k entries (nT)
    v_lim: float = 50.0
    cf1: float = 1.0
    cf2: float = 4e4
    sign_rule: str = "area"        # "area" (oriented polygon area) or "pair" (paper: b_1 x b_q)

    def __post_init__(self) -> None:
        if self.n_particles < 2 or self.k_max < 1 or self.n_cycles < 0:
            raise FitError("PSO needs n_particles >= 2, k_max >= 1, n_cycles >= 0")
        if self.v_lim <= 0 or self.pmax_K <= 0 or self.pmax_k_nT <= 0:
            raise FitError("v_lim, pmax_K and pmax_k_nT must be positive")
        if self.sign_rule not in SIGN_RULES:
            raise FitError(f"unknown sign_rule {self.sign_rule!r}; valid: {', '.join(SIGN_RULES)}")

    @property
    def pmax(self) -> np.ndarray:
        return np.r_[np.full(9, self.pmax_K), np.full(3, self.pmax_k_nT)]

    @property
    def vmax(self) -> np.ndarray:
        """Velocity limit per component, eq. (6) with pmax = [-pmax, pmax]."""
        return 2 * self.pmax / self.v_lim


def schedule(opt: PsoOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(w, c1, c2)``, each of length ``k_max`` (iteration 1..k_max)."""
    k_max = opt.k_max
    n_w = max(1, round(opt.w_v_frac * k_max))
    n_c = max(1, round(opt.c_v_frac * k_max))
    ramp_w = np.linspace(0.0, 1.0, n_w)
    ramp_c = np.linspace(0.0, 1.0, n_c)
    w_cyc = np.r_[opt.w_s + (opt.w_f - opt.w_s) * ramp_w, np.full(n_c, opt.w_f)]
    c1_cyc = np.r_[np.full(n_w, opt.c1_s), opt.c1_s + (opt.c_f - opt.c1_s) * ramp_c]
    c2_cyc = np.r_[np.full(n_w, opt.c2_s), opt.c2_s + (opt.c_f - opt.c2_s) * ramp_c]
    w = np.full(k_max, opt.w_e)
    c1 = np.full(k_max, opt.c_e)
    c2 = np.full(k_max, opt.c_e)
    n = min(k_max, opt.n_cycles * len(w_cyc))
    w[:n] = np.tile(w_cyc, opt.n_cycles)[:n]
    c1[:n] = np.tile(c1_cyc, opt.n_cycles)[:n]
    c2[:n] = np.tile(c2_cyc, opt.n_cycles)[:n]
    return w, c1, c2


def area_vector(u: np.ndarray) -> np.ndarray:
    """``sum_s u_s x u_s+1`` over the sample axis of ``u`` (..., n, 3): twice the oriented area of
    the polygon (from the antisymmetric part of ``u[:-1]^T u[1:]``, one matrix product)."""
    m = np.swapaxes(u[..., :-1, :], -1, -2) @ u[..., 1:, :]
    return np.stack([m[..., 1, 2] - m[..., 2, 1], m[..., 2, 0] - m[..., 0, 2], m[..., 0, 1] - m[..., 1, 0]], axis=-1)


def plane_normals(points: np.ndarray, sign_rule: str = "area", pair_index: int | None = None) -> np.ndarray:
    """Algorithm 3 for a batch: ``points`` (P, n, 3) -> oriented unit normals (P, 3).

    The normal is the direction of least scatter about the centroid (the left singular vector of
    the paper's centred 3 x n matrix for the smallest singular value, computed as the first
    eigenvector of the 3 x 3 scatter matrix). Its sign follows the right-hand rule of the sample
    order: ``"area"`` (default) uses the oriented area of the centred polygon, sum of
    ``u_s x u_s+1``, which needs no hand-picked sample; ``"pair"`` is the paper's step 6,
    ``sign(n . (b_1 x b_q))`` with uncentred vectors and ``q = pair_index``.
    """
    pts = np.asarray(points, dtype=float)
    u = pts - pts.mean(axis=1, keepdims=True)
    ut = u.transpose(0, 2, 1)
    _, vecs = np.linalg.eigh(ut @ u)
    n = vecs[:, :, 0]
    if sign_rule == "area":
        ref = area_vector(u)
    elif sign_rule == "pair":
        q = pts.shape[1] // 4 if pair_index is None else pair_index
        ref = np.cross(pts[:, 0], pts[:, q])
    else:
        raise FitError(f"unknown sign_rule {sign_rule!r}")
    s = np.sign(np.einsum("pi,pi->p", n, ref))
    return n * np.where(s == 0, 1.0, s)[:, None]


def pair_indices(b_meas: np.ndarray, groups: list[np.ndarray]) -> list[int]:
    """For the paper's pair rule: per locus, the first sample at which the centred raw vector has
    turned 90 degrees from the first one (summing the angles between consecutive samples), or
    the last sample of a shorter arc. The paper asks for a hand-picked point between 0 and 180
    degrees; a linear map with det > 0 keeps that half-turn, so the choice on raw data holds
    after calibration. (Picking the largest |u_1 x u_q| instead can land at 270 degrees, where
    the sign is reversed.)"""
    out = []
    for idx in groups:
        u = b_meas[idx] - b_meas[idx].mean(axis=0)
        u = u / np.linalg.norm(u, axis=1, keepdims=True)
        turn = np.cumsum(np.arccos(np.clip(np.sum(u[:-1] * u[1:], axis=1), -1.0, 1.0)))
        out.append(int(min(np.searchsorted(turn, np.pi / 2) + 1, len(idx) - 1)))
    return out


@dataclass(frozen=True)
class Problem:
    """Data of one calibration problem (nT). ``groups`` are the sample indices of each locus in
    time order; ``omega_hat`` the unit rotation axes (L, 3)."""

    b_meas_nT: np.ndarray
    b_ref_norm_nT: np.ndarray
    groups: tuple[np.ndarray, ...]
    omega_hat: np.ndarray
    sign_rule: str = "area"
    pair_index: tuple[int, ...] = ()

    @classmethod
    def build(cls, b_meas_nT, b_ref_nT, locus, omega, sign_rule: str = "area") -> Problem:
        if sign_rule not in SIGN_RULES:
            raise FitError(f"unknown sign_rule {sign_rule!r}; valid: {', '.join(SIGN_RULES)}")
        b = np.asarray(b_meas_nT, dtype=float)
        if b.ndim != 2 or b.shape[1] != 3 or len(b) < 12:
            raise FitError(f"b_meas must have shape (N >= 12, 3), got {b.shape}")
        r = np.asarray(b_ref_nT, dtype=float)
        if r.ndim == 2 and r.shape == b.shape:
            r = np.linalg.norm(r, axis=1)
        elif r.ndim == 0:
            r = np.full(len(b), float(r))
        elif r.shape != (len(b),):
            raise FitError(f"b_ref must be a scalar, (N,) or (N, 3); got {r.shape}")
        lab = np.asarray(locus)
        om = np.asarray(omega, dtype=float)
        if lab.shape != (len(b),) or not np.issubdtype(lab.dtype, np.integer):
            raise FitError(f"locus must be (N,) integer labels, got shape {lab.shape} dtype {lab.dtype}")
        if om.ndim != 2 or om.shape[1] != 3 or lab.min() < 0 or lab.max() >= len(om):
            raise FitError("omega must be (L, 3) with one row per locus label 0..L-1")
        if not (np.isfinite(b).all() and np.isfinite(r).all() and np.isfinite(om).all()):
            raise FitError("non-finite value in b_meas, b_ref or omega")
        labels = np.unique(lab)
        if len(labels) < 2:
            raise FitError("rotation-axis fitting needs at least two loci (one leaves scale/offset free)")
        groups = tuple(np.flatnonzero(lab == u) for u in labels)
        if any(len(g) < 3 for g in groups):
            raise FitError("every locus needs at least 3 samples")
        norms = np.linalg.norm(om[labels], axis=1, keepdims=True)
        if (norms == 0).any():
            raise FitError("rotation axes must be non-zero")
        pairs = tuple(pair_indices(b, list(groups))) if sign_rule == "pair" else ()
        return cls(b, r, groups, om[labels] / norms, sign_rule, pairs)


def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 12) -> K (..., 3, 3), k (..., 3)."""
    p = np.asarray(p, dtype=float)
    return p[..., :9].reshape(*p.shape[:-1], 3, 3), p[..., 9:]


def fitness_terms(P: np.ndarray, prob: Problem) -> tuple[np.ndarray, np.ndarray]:
    """``F1``, ``F2`` (eqs. 8b, 9) for particles ``P`` (n_p, 12)."""
    K, k = unpack(P)
    b_hat = prob.b_meas_nT @ K.transpose(0, 2, 1) - k[:, None, :]          # (P, N, 3)
    f1 = np.sum((prob.b_ref_norm_nT - np.linalg.norm(b_hat, axis=2)) ** 2, axis=1)
    f2 = np.zeros(len(P))
    for l, idx in enumerate(prob.groups):
        q = prob.pair_index[l] if prob.pair_index else None
        n = plane_normals(b_hat[:, idx], prob.sign_rule, q)
        f2 += (1.0 - n @ (-prob.omega_hat[l])) ** 2
    return f1, f2


def fitness(P: np.ndarray, prob: Problem, opt: PsoOptions) -> np.ndarray:
    """Eq. (10) per particle; non-finite values (degenerate K) become +inf."""
    P = np.atleast_2d(P)
    with np.errstate(invalid="ignore", over="ignore"):
        f1, f2 = fitness_terms(P, prob)
        f = opt.cf1 * np.sqrt(f1) / len(prob.b_meas_nT) + opt.cf2 * np.sqrt(f2) / len(prob.groups)
    return np.where(np.isfinite(f), f, np.inf)


def mirror_fix(K: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """``sign(det K) (K, k)``: the right-handed member of the mirror pair (matrix AND offset)."""
    if np.linalg.det(K) < 0:
        return -K, -k, True
    return K, k, False


@dataclass(frozen=True)
class PsoResult:
    """Global best after ``k_max`` iterations, mirror-fixed. ``k_nT`` is the offset k_m = off_mc."""

    K: np.ndarray
    k_nT: np.ndarray
    fitness: float
    f1_term: float                 # c_f1 sqrt(F1) / n_s, nT
    f2_term: float                 # c_f2 sqrt(F2) / n_l
    mirrored: bool
    history: np.ndarray = field(repr=False)   # best fitness after each iteration
    n_evaluations: int = 0
    runtime_s: float = 0.0
    seed: int | None = None

    @property
    def S_mc(self) -> np.ndarray:
        """The paper's reported matrix S_mc = K^-1."""
        return np.linalg.inv(self.K)


def run_pso(prob: Problem, *, seed: int | np.random.SeedSequence | None = 0,
            options: PsoOptions | None = None, center: np.ndarray | None = None,
            progress=None) -> PsoResult:
    """Run the PSO on ``prob``. The initial box is ``center +- pmax`` (``center`` (12,) in the
    layout of eq. 7, default 0 as in the paper); with a ``center`` one random particle starts
    on it (Algorithm 2, step 9). ``progress(k, best)`` is called every iteration if given."""
    opt = options or PsoOptions()
    if opt.sign_rule != prob.sign_rule:
        raise FitError(f"options.sign_rule {opt.sign_rule!r} differs from the problem's {prob.sign_rule!r}")
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    n_p = opt.n_particles
    pmax, vmax = opt.pmax, opt.vmax
    c0 = np.zeros(N_PARAMS) if center is None else np.asarray(center, dtype=float).reshape(N_PARAMS)
    pos = c0 - pmax + rng.random((n_p, N_PARAMS)) * 2 * pmax             # eq. (5a)
    vel = -vmax + rng.random((n_p, N_PARAMS)) * 2 * vmax                  # eq. (5b)
    if center is not None:
        pos[rng.integers(n_p)] = c0
    f = fitness(pos, prob, opt)
    pbest, f_pbest = pos.copy(), f.copy()
    g = int(np.argmin(f_pbest))
    gbest, f_g = pbest[g].copy(), float(f_pbest[g])
    w, c1, c2 = schedule(opt)
    hist = np.empty(opt.k_max)
    for it in range(opt.k_max):
        r1 = rng.random((n_p, N_PARAMS))
        r2 = rng.random((n_p, N_PARAMS))
        vel = w[it] * vel + r1 * c1[it] * (pbest - pos) + r2 * c2[it] * (gbest - pos)   # eq. (3a)
        np.clip(vel, -vmax, vmax, out=vel)                                               # Algorithm 1
        pos = pos + vel                                                                  # eq. (3b)
        f = fitness(pos, prob, opt)
        better = f < f_pbest                                                             # eq. (4a)
        pbest[better] = pos[better]
        f_pbest[better] = f[better]
        g = int(np.argmin(f_pbest))                                                      # eq. (4b)
        if f_pbest[g] < f_g:
            gbest, f_g = pbest[g].copy(), float(f_pbest[g])
        hist[it] = f_g
        if progress is not None:
            progress(it + 1, f_g)
    K, k = unpack(gbest)
    K, k, mirrored = mirror_fix(K, k)
    f1, f2 = fitness_terms(np.r_[K.ravel(), k][None, :], prob)
    return PsoResult(K=K, k_nT=k, fitness=f_g,
                     f1_term=float(opt.cf1 * np.sqrt(f1[0]) / len(prob.b_meas_nT)),
                     f2_term=float(opt.cf2 * np.sqrt(f2[0]) / len(prob.groups)),
                     mirrored=mirrored, history=hist, n_evaluations=n_p * (opt.k_max + 1),
                     runtime_s=time.perf_counter() - t0,
                     seed=seed if isinstance(seed, int) else None)
