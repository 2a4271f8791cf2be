"""Per-session mount rotations: the bench mount as a nuisance, fitted jointly with the sensor.

On a bench the DUT is remounted between sessions, a little differently each time. That is a
property of the bench, not of the sensor, and must not be baked into a flight table. Model
(effect ``mount_rotation`` of the catalogue)::

    R_s^T B_ref = (S + K_S dT) B_meas + O + ...        for every row of session s

``R_s`` is session s's mount rotation relative to the *frame session* (``R_frame = I``): the
first session, or one named (``FitOptions.mount_frame``). The table's parameters are the
sensor's, in the frame session's mount; the rotations are reported (with standard errors) and
never written into the table. A new session (or a left-out one) gets the identity.

Solver: Gauss-Newton on the stacked three-axis problem (the angles couple the output axes, so
the per-axis problems of :mod:`fit` do not separate). With the current rotations,
``b' = R_s^T B_ref`` is linear in a small correction ``delta_s``: ``b' = X theta + delta_s x b'``;
the stacked system (rows of axis i weighted by 1/sigma_i, the per-axis residual RMS) is solved
by least squares and ``R_s <- R_s R(delta_s)`` (``scipy.spatial.transform.Rotation``) until the
correction is below 1e-12 rad. Standard errors come from the final linearised system.

Identifiability of the angles (held at 0 with the reason, or refused):
1. rotation about axis a in session s needs field perpendicular to a: its RMS in the session
   must reach ``min_field_rms_uT`` (a single-axis sweep does not see rotation about its axis);
2. the degeneracy rule (module :mod:`degeneracy`) on the stacked design with the angles as the
   holdable columns: an angle the sensor's own parameters can absorb (e.g. the only session
   sweeping X rotated about Z looks exactly like the gain coupling S[y,x]) is held.
Sessions for which the frame is not determined (e.g. a near-zero-field frame session) show up
in rule 2: a common rotation of all other sessions is then the same as changing S.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from scipy.spatial.transform import Rotation

from magstack.firmware.calibration.model import AXES, CalModel
from magstack.firmware.errors import FitError

#: Gauss-Newton stops when the largest angle correction is below this (rad) ...
TOL_RAD = 1e-12
#: ... or after this many iterations.
MAX_ITER = 30


@dataclass
class MountSolution:
    """Fitted mount rotations (rotation vectors, rad) per session relative to ``frame``."""

    frame: int
    rotvec_rad: dict[int, np.ndarray]
    se_rad: dict[int, np.ndarray]
    held: list[tuple[int, int, str]] = field(default_factory=list)   # (session, axis, reason)
    iterations: int = 0
    sigma_uT: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    frame_note: str | None = None

    def rotate_to_frame(self, b_ref_uT: np.ndarray, session: np.ndarray) -> np.ndarray:
        """``R_s^T B_ref`` per row (sessions without a fitted mount: unchanged)."""
        out = np.array(b_ref_uT, dtype=float, copy=True).reshape(-1, 3)
        s = np.asarray(session).reshape(-1)
        for k, rv in self.rotvec_rad.items():
            m = s == k
            if m.any() and np.any(rv != 0):
                out[m] = Rotation.from_rotvec(rv).inv().apply(out[m])
        return out

    def stats(self) -> dict:
        return {"frame_session": self.frame, "iterations": self.iterations,
                "angles_rad": {str(k): [float(x) for x in v] for k, v in sorted(self.rotvec_rad.items())},
                "angles_se_rad": {str(k): [float(x) for x in v] for k, v in sorted(self.se_rad.items())},
                "held": [f"session {s} about {AXES[a]}: {r}" for s, a, r in self.held],
                **({"frame_note": self.frame_note} if self.frame_note else {})}

    def report_lines(self) -> list[str]:
        L = [f"mount rotations relative to session {self.frame} (mrad, +- standard error; nuisance, not in the "
             "table):"]
        held = {(s, a) for s, a, _ in self.held}
        for k in sorted(self.rotvec_rad):
            if k == self.frame:
                continue
            cells = []
            for a in range(3):
                v, e = self.rotvec_rad[k][a] * 1e3, self.se_rad[k][a] * 1e3
                cells.append(f"{AXES[a]} {'held' if (k, a) in held else f'{v:+.3f} +- {e:.3f}'}")
            L.append(f"  session {k}: " + ", ".join(cells))
        for s, a, r in self.held:
            L.append(f"  held: session {s} about {AXES[a]} = 0: {r}")
        if self.frame_note:
            L.append(f"  note: {self.frame_note}")
        return L


def perpendicular_rms(Y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(3,) uT: RMS of the field perpendicular to each axis (what a rotation about it moves)."""
    sq = Y ** 2
    return np.sqrt(np.array([np.average(sq.sum(axis=1) - sq[:, a], weights=w) for a in range(3)]))


def choose_frame(Y: np.ndarray, session: np.ndarray, w: np.ndarray, requested: int | None,
                 min_rms_uT: float) -> tuple[int, str | None]:
    """``(frame session, note)``: ``requested`` (must be present), else the first session in which a
    rotation about every axis is observable (field perpendicular to each axis >= ``min_rms_uT``),
    else the first session; the note says when the first session was passed over or cannot pin
    the frame."""
    ids = sorted(int(k) for k in np.unique(session))
    if not ids:
        raise FitError("mount_rotation: no sessions")
    if len(ids) == 1 and requested in (None, ids[0]):
        return ids[0], "one session: no mount rotation to fit (the frame is the session itself)"
    if requested is not None:
        if int(requested) not in ids:
            raise FitError(f"mount frame session {requested} is not in the data (sessions {ids})")
        return int(requested), None
    ok = [k for k in ids if np.all(perpendicular_rms(Y[session == k], w[session == k]) >= min_rms_uT)]
    if ok and ok[0] != ids[0]:
        return ok[0], (f"frame: session {ok[0]}, the first whose field makes a rotation about every axis "
                       f"observable (session {ids[0]} does not); name another with --mount-frame")
    if not ok:
        return ids[0], (f"frame: session {ids[0]} (first); no session has field perpendicular to every axis "
                        f">= {min_rms_uT:g} uT, so the frame is not fully pinned by the data and the "
                        "degeneracy rule holds the angles the sensor's gains absorb")
    return ids[0], None


def _cross_cols(b: np.ndarray, a: int) -> np.ndarray:
    """(N, 3): (e_a x b) per row -- the derivative of delta x b w.r.t. delta_a."""
    e = np.zeros(3)
    e[a] = 1.0
    return np.cross(e, b)


def solve_mount(X: np.ndarray, Y: np.ndarray, session: np.ndarray, weights: np.ndarray | None,
                model: CalModel, held_params: dict[tuple[int, int], float], theta0: np.ndarray,
                options) -> tuple[np.ndarray, np.ndarray, MountSolution]:
    """Joint fit of the sensor parameters and per-session mount rotations.

    ``X`` (N, p) design, ``Y`` (N, 3) reference, ``held_params`` {(axis, column): value} from the
    sensor's identifiability rules, ``theta0`` (3, p) the fit without mounts (start and sigma).
    Returns ``(theta (3, p), se (3, p), MountSolution)``.

    The sensor parameters are eliminated per output axis (QR of each axis's weighted active
    columns, computed once): each iteration solves only the small angle system of the columns'
    parts orthogonal to the sensor's (Schur complement), then back-substitutes the sensor's.
    """
    n, p = X.shape
    mask = model.axis_mask()
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    sw = np.sqrt(w)
    s = np.asarray(session).reshape(n)
    ids = sorted(int(k) for k in np.unique(s))
    frame, frame_note = choose_frame(Y, s, w, options.mount_frame, options.min_field_rms_uT)
    act = [[c for c in range(p) if mask[i, c] and (i, c) not in held_params] for i in range(3)]
    hv = np.zeros((3, p))
    for (i, c), v in held_params.items():
        hv[i, c] = v
    resid0 = Y - X @ np.where(mask, theta0, 0.0).T
    sigma = np.sqrt(np.average(resid0 ** 2, axis=0, weights=w))
    sigma = np.where(sigma > 0, sigma, 1.0)
    # per-axis QR of the weighted active sensor columns (fixed across iterations)
    QR = []
    for i in range(3):
        if act[i]:
            Q, R = np.linalg.qr(X[:, act[i]] * sw[:, None])
            if np.any(np.abs(np.diag(R)) <= np.abs(np.diag(R)).max() * 1e-12):
                raise FitError(f"axis {AXES[i]}: sensor design is rank deficient in the mount fit")
        else:
            Q, R = np.zeros((n, 0)), np.zeros((0, 0))
        QR.append((Q, R))

    # angle identifiability 1: field perpendicular to the rotation axis within the session
    held: list[tuple[int, int, str]] = []
    free: list[tuple[int, int]] = []
    for k in ids:
        if k == frame:
            continue
        m = s == k
        perp = perpendicular_rms(Y[m], w[m])
        for a in range(3):
            if perp[a] < options.min_field_rms_uT:
                held.append((k, a, f"field perpendicular to {AXES[a]} in the session has RMS {perp[a]:.3g} uT "
                                   f"(need {options.min_field_rms_uT:g} uT)"))
            else:
                free.append((k, a))
    rot = {k: Rotation.identity() for k in ids}
    theta = np.where(mask, theta0, 0.0)
    it = 0
    first = True
    while True:
        bp = Y.copy()
        for k in ids:
            if k != frame:
                bp[s == k] = rot[k].inv().apply(Y[s == k])
        C, T = _angle_system(X, bp, s, sw, hv, free)          # (3, N, m), (3, N) weighted
        Ct, Tt = _project(QR, C, T)
        if first and free:
            drop = _degenerate_angles(Ct, C, QR, sigma, free, act, model, options, held)
            if drop:
                free = [f for q, f in enumerate(free) if q not in drop]
                C, T = _angle_system(X, bp, s, sw, hv, free)
                Ct, Tt = _project(QR, C, T)
            first = False
        if held and options.on_unidentifiable == "refuse":
            raise FitError("data cannot determine mount angles: " + "; ".join(
                f"session {k} about {AXES[a]} ({r})" for k, a, r in held))
        M = np.vstack([Ct[i] / sigma[i] for i in range(3)])
        v = np.concatenate([Tt[i] / sigma[i] for i in range(3)])
        if free:
            sc = np.linalg.norm(M, axis=0)
            sc[sc == 0] = 1.0
            delta = np.linalg.lstsq(M / sc, v, rcond=None)[0] / sc
        else:
            delta = np.zeros(0)
        resid = np.empty((n, 3))
        for i in range(3):
            Q, R = QR[i]
            rhs = T[i] - C[i] @ delta
            if act[i]:
                theta[i, act[i]] = scipy.linalg.solve_triangular(R, Q.T @ rhs)
                resid[:, i] = (rhs - Q @ (Q.T @ rhs)) / np.where(sw > 0, sw, 1.0)
            else:
                resid[:, i] = rhs / np.where(sw > 0, sw, 1.0)
        for (i, c), val in held_params.items():
            theta[i, c] = val
        for q, (k, a) in enumerate(free):
            rot[k] = rot[k] * Rotation.from_rotvec(np.eye(3)[a] * delta[q])
        it += 1
        if it <= 3:   # settle the per-axis weights on the first iterations, then keep them fixed
            sigma = np.sqrt(np.average(resid ** 2, axis=0, weights=w))
            sigma = np.where(sigma > 0, sigma, 1.0)
        step = float(np.max(np.abs(delta))) if delta.size else 0.0
        if (step < TOL_RAD and it > 3) or it >= MAX_ITER or not free:
            break
    # covariance (Schur complement), scaled by the weighted residual variance
    k_par = sum(len(a) for a in act) + len(free)
    dof = 3 * n - k_par
    s2 = float(np.sum(w[:, None] * resid ** 2 / sigma ** 2)) / dof if dof > 0 else np.nan
    M = np.vstack([Ct[i] / sigma[i] for i in range(3)])
    Minv = _inv(M.T @ M) if free else np.zeros((0, 0))
    se = np.full((3, p), np.nan)
    for i in range(3):
        if not act[i]:
            continue
        Q, R = QR[i]
        Rinv = scipy.linalg.solve_triangular(R, np.eye(R.shape[0]))
        var = np.sum(Rinv ** 2, axis=1) * sigma[i] ** 2
        if free:
            G = Rinv @ (Q.T @ C[i])                        # d theta_i / d delta
            var = var + np.einsum("ij,jk,ik->i", G, Minv, G)
        se[i, act[i]] = np.sqrt(s2 * var)
    rv = {k: rot[k].as_rotvec() for k in ids}
    ang_se = {k: np.full(3, np.nan) for k in ids}
    ang_se[frame] = np.zeros(3)
    for q, (k, a) in enumerate(free):
        ang_se[k][a] = float(np.sqrt(s2 * Minv[q, q]))
    return theta, se, MountSolution(frame, rv, ang_se, held, it, sigma, frame_note)


def _inv(G: np.ndarray) -> np.ndarray:
    try:
        out = np.linalg.inv(G)
        if np.all(np.isfinite(out)):
            return out
    except np.linalg.LinAlgError:
        pass
    return np.linalg.pinv(G)


def _angle_system(X, bp, s, sw, hv, free):
    """Weighted angle columns ``C`` (3, N, m) (``e_a x b'`` in the rows of session k, per output
    axis) and weighted targets ``T`` (3, N) (``b'`` minus the held sensor parameters)."""
    n = X.shape[0]
    C = np.zeros((3, n, len(free)))
    for q, (k, a) in enumerate(free):
        m = s == k
        C[:, m, q] = _cross_cols(bp[m], a).T
    C *= sw[None, :, None]
    T = ((bp - X @ hv.T) * sw[:, None]).T
    return C, T


def _project(QR, C, T):
    """Parts of C and T orthogonal to each axis's sensor columns."""
    Ct, Tt = np.empty_like(C), np.empty_like(T)
    for i, (Q, _) in enumerate(QR):
        Ct[i] = C[i] - Q @ (Q.T @ C[i])
        Tt[i] = T[i] - Q @ (Q.T @ T[i])
    return Ct, Tt


def _degenerate_angles(Ct, C, QR, sigma, free, act, model, options, held) -> set[int]:
    """Angles the sensor's parameters (or other angles) absorb: variance inflation of each angle
    column in the whole stacked design >= ``options.max_vif``, held one at a time (worst first)."""
    live = list(range(len(free)))
    drop: set[int] = set()
    full = np.vstack([C[i] / sigma[i] for i in range(3)])
    norms2 = np.sum(full ** 2, axis=0)
    while live:
        M = np.vstack([Ct[i][:, live] / sigma[i] for i in range(3)])
        Minv = _inv(M.T @ M)
        vif = np.diag(Minv) * norms2[live]
        worst = int(np.argmax(vif))
        if not vif[worst] >= options.max_vif:
            return drop
        q = live[worst]
        k, a = free[q]
        # its strongest partner: the sensor parameter (or angle) whose estimate correlates most
        best, name = 0.0, None
        for i in range(3):
            Q, R = QR[i]
            if not act[i]:
                continue
            Rinv = scipy.linalg.solve_triangular(R, np.eye(R.shape[0]))
            G = Rinv @ (Q.T @ C[i][:, live]) / sigma[i]
            cov_td = -G @ Minv[:, worst]
            var_t = np.sum(Rinv ** 2, axis=1) / sigma[i] ** 2 + np.einsum("ij,jk,ik->i", G, Minv, G)
            corr = cov_td / np.sqrt(var_t * Minv[worst, worst])
            j = int(np.argmax(np.abs(corr)))
            if abs(corr[j]) > abs(best):
                best, name = float(corr[j]), model.param_name(i, act[i][j])
        held.append((k, a, f"degenerate with the sensor parameters: variance inflation {vif[worst]:.3g} >= "
                           f"{options.max_vif:g}" + (f" (estimate correlates at {best:+.4f} with {name})"
                                                      if name else "")))
        drop.add(q)
        live.remove(q)
    return drop
