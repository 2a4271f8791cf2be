"""Rotation-axis loci from attitude telemetry, for the attitude-independent refit (riwanto PSO, ``axes`` gauge).

The rotation-axis objective needs segments ("loci") in which the spacecraft turns about one fixed body
axis while the inertial field stays (nearly) constant, and that axis in the body frame. Both follow from
the attitude quaternions ``q_body_eci`` (scalar first; ``b_body = R b_eci``, docs/refit.md): between two
samples the same inertial vector's body components turn by ``R_rel = R_{k+1} R_k^-1``, whose rotation
vector is ``-omega_body dt`` (the field turns opposite to the body), so

    omega_body_k = -rotvec(R_{k+1} R_k^-1) / (t_{k+1} - t_k)        (rad/s, body frame)

A locus is a run of consecutive samples whose rate direction stays within ``max_axis_dev_deg`` of the
run's first direction, that turns at least ``min_rate_deg_s`` deg/s, without a time gap, and that sweeps
between ``min_arc_deg`` and ``max_arc_deg`` (longer runs are cut, so the inertial field direction changes
little within one locus: in LEO it turns by up to ~0.13 deg/s). Its axis is the mean rate direction.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def body_rates(t_s: np.ndarray, q_body_eci_wxyz: np.ndarray) -> np.ndarray:
    """(N-1, 3) body angular velocity in rad/s between consecutive samples (see the module docstring)."""
    q = np.asarray(q_body_eci_wxyz, dtype=float)
    r = Rotation.from_quat(q[:, [1, 2, 3, 0]])          # scipy is scalar-last
    rel = r[1:] * r[:-1].inv()
    dt = np.diff(np.asarray(t_s, dtype=float))
    with np.errstate(divide="ignore", invalid="ignore"):
        return -rel.as_rotvec() / dt[:, None]


def loci_from_attitude(t_s, q_body_eci_wxyz, *, max_axis_dev_deg: float = 5.0, min_rate_deg_s: float = 0.5,
                       min_arc_deg: float = 90.0, max_arc_deg: float = 360.0, max_gap_s: float = 10.0,
                       min_samples: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """``(labels, omega_hat_body)``: per sample a locus label (-1 = in no locus) and per locus its unit axis."""
    t = np.asarray(t_s, dtype=float)
    n = t.size
    labels = np.full(n, -1, dtype=np.int64)
    if n < min_samples:
        return labels, np.zeros((0, 3))
    w = body_rates(t, q_body_eci_wxyz)
    rate = np.linalg.norm(w, axis=1)
    dt = np.diff(t)
    ok = np.isfinite(rate) & (rate >= np.radians(min_rate_deg_s)) & (dt > 0) & (dt <= max_gap_s)
    u = np.where(ok[:, None], w / np.where(rate > 0, rate, 1.0)[:, None], 0.0)
    cos_dev = np.cos(np.radians(max_axis_dev_deg))
    axes: list[np.ndarray] = []
    k = 0
    while k < n - 1:
        if not ok[k]:
            k += 1
            continue
        start, arc, j = k, 0.0, k
        while j < n - 1 and ok[j] and float(u[j] @ u[start]) >= cos_dev and arc < np.radians(max_arc_deg):
            arc += rate[j] * dt[j]
            j += 1
        if arc >= np.radians(min_arc_deg) and j + 1 - start >= min_samples:
            mean = u[start:j].sum(axis=0)
            axes.append(mean / np.linalg.norm(mean))
            labels[start:j + 1] = len(axes) - 1
        k = max(j, k + 1)
    return labels, np.asarray(axes).reshape(-1, 3)
