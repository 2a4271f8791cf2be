"""Does a mount rotation explain the differences between sessions? Compare with a general map.

The general alternative gives every session except the frame its own linear map on top of the
sensor model: ``B_ref = X theta + dA_s B_meas + dc_s`` (per output axis; ``dA_s`` only for input
axes the session excites, ``min_field_rms_uT`` about the session mean, and never for columns the
degeneracy rule finds the sensor's own parameters can absorb). The mount model
``B_ref = R_s (X theta)`` is a special case (``dA_s = (R_s - I) S``, ``dc_s = (R_s - I) O``), so
the two are nested:

* F-test on the pooled, per-axis noise-weighted residuals (weights 1/sigma_i^2 from the general
  map), ``F = ((SSE_r - SSE_f)/(p_f - p_r)) / (SSE_f/(3N - p_f))``;
* AIC ``3N ln(SSE/3N) + 2p`` of both;
* held-out RMS of both on the same interleaved time blocks as the fit's.

Verdict: the rotation explains the session differences when the general map is not better by
AIC, or its held-out error is within ``HOLDOUT_TOL`` of the mount model's.
"""
from __future__ import annotations

import numpy as np

from magstack.firmware.calibration.degeneracy import degenerate_groups
from magstack.firmware.calibration.linalg import qr_r
from magstack.firmware.calibration.model import AXES

#: Relative held-out margin within which the general map counts as "no better".
HOLDOUT_TOL = 0.02


def _extras(b: np.ndarray, s: np.ndarray, frame: int, min_rms: float, sessions) -> list[tuple[int, int | None]]:
    out: list[tuple[int, int | None]] = []
    for k in sessions:
        if k == frame:
            continue
        m = s == k
        if not m.any():
            continue
        out.append((k, None))                       # dc_s
        for j in range(3):
            bj = b[m, j]
            if np.sqrt(np.mean((bj - bj.mean()) ** 2)) >= min_rms:
                out.append((k, j))                  # dA_s[:, j]
    return out


def _extra_cols(b, s, extras) -> np.ndarray:
    E = np.zeros((b.shape[0], len(extras)))
    for q, (k, j) in enumerate(extras):
        m = s == k
        E[m, q] = 1.0 if j is None else b[m, j]
    return E


def _fit_map(X, Y, b, s, w, act, hv, extras, options):
    """Per-axis LS of the general map; returns (coefficients per axis, kept extras per axis)."""
    E = _extra_cols(b, s, extras)
    sw = np.sqrt(w)
    out = []
    for i in range(3):
        A = np.hstack([X[:, act[i]], E]) * sw[:, None]
        keep = list(range(A.shape[1]))
        hold = [c >= len(act[i]) for c in keep]
        # one column at a time (group_corr 1): only what the sensor's own columns absorb is dropped
        for g in degenerate_groups(qr_r(A), hold, None, options.max_vif, 1.0):
            keep = [c for c in keep if c not in g.members]
        A = A[:, keep]
        t = (Y[:, i] - X @ hv[i]) * sw
        sc = np.linalg.norm(A, axis=0)
        sc[sc == 0] = 1.0
        z, *_ = np.linalg.lstsq(A / sc, t, rcond=None)
        out.append((keep, z / sc))
    return out


def _predict_map(X, b, s, act, hv, extras, coefs) -> np.ndarray:
    E = _extra_cols(b, s, extras)
    P = np.zeros((X.shape[0], 3))
    for i in range(3):
        keep, z = coefs[i]
        P[:, i] = X @ hv[i] + np.hstack([X[:, act[i]], E])[:, keep] @ z
    return P


def compare(X, Y, b_meas, session, weights, model, held, mount, resid_mount, options,
            folds: np.ndarray | None = None, holdout_mount_uT: np.ndarray | None = None) -> dict:
    """Nested comparison (module docstring). ``resid_mount``: (N, 3) in-sample residual of the mount
    model; ``folds``: fold index per row (the fit's time blocks) for the held-out figures."""
    n, p = X.shape
    mask = model.axis_mask()
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    hv = np.zeros((3, p))
    for h in held:
        hv[h.axis, h.column] = h.value
    heldset = {(h.axis, h.column) for h in held}
    act = [[c for c in range(p) if mask[i, c] and (i, c) not in heldset] for i in range(3)]
    sessions = sorted(int(k) for k in np.unique(session))
    extras = _extras(b_meas, session, mount.frame, options.min_field_rms_uT, sessions)
    coefs = _fit_map(X, Y, b_meas, session, w, act, hv, extras, options)
    r_map = Y - _predict_map(X, b_meas, session, act, hv, extras, coefs)
    sig = np.sqrt(np.average(r_map ** 2, axis=0, weights=w))
    sig = np.where(sig > 0, sig, 1.0)
    sse_f = float(np.sum(w[:, None] * r_map ** 2 / sig ** 2))
    sse_r = float(np.sum(w[:, None] * resid_mount ** 2 / sig ** 2))
    n_ang = sum(1 for k in mount.se_rad for a in range(3) if k != mount.frame and np.isfinite(mount.se_rad[k][a]))
    p_r = sum(len(a) for a in act) + n_ang
    p_f = sum(len(c[0]) for c in coefs)
    nt = 3 * n
    out: dict = {"n_rows": n, "params_mount": p_r, "params_session_map": p_f,
                 "rms_mount_uT": [float(x) for x in np.sqrt(np.average(resid_mount ** 2, axis=0, weights=w))],
                 "rms_session_map_uT": [float(x) for x in np.sqrt(np.average(r_map ** 2, axis=0, weights=w))],
                 "aic_mount": nt * np.log(sse_r / nt) + 2 * p_r, "aic_session_map": nt * np.log(sse_f / nt) + 2 * p_f}
    if p_f > p_r and nt > p_f:
        F = ((sse_r - sse_f) / (p_f - p_r)) / (sse_f / (nt - p_f))
        out.update({"F": float(F), "F_dof": [p_f - p_r, nt - p_f],
                    "F_p_value": _f_sf(max(F, 0.0), p_f - p_r, nt - p_f)})
    if folds is not None:
        sq, cnt = np.zeros(3), 0
        for f in np.unique(folds):
            te = folds == f
            tr = ~te
            ex = _extras(b_meas[tr], session[tr], mount.frame, options.min_field_rms_uT, sessions)
            try:
                c = _fit_map(X[tr], Y[tr], b_meas[tr], session[tr], w[tr], act, hv, ex, options)
            except np.linalg.LinAlgError:
                continue
            r = Y[te] - _predict_map(X[te], b_meas[te], session[te], act, hv, ex, c)
            sq += np.sum(r ** 2, axis=0)
            cnt += r.shape[0]
        if cnt:
            out["holdout_session_map_uT"] = [float(x) for x in np.sqrt(sq / cnt)]
    if holdout_mount_uT is not None:
        out["holdout_mount_uT"] = [float(x) for x in holdout_mount_uT]
    better_aic = out["aic_session_map"] < out["aic_mount"]
    ho_m, ho_f = out.get("holdout_mount_uT"), out.get("holdout_session_map_uT")
    within = ho_m is not None and ho_f is not None and np.linalg.norm(ho_f) >= (1 - HOLDOUT_TOL) * np.linalg.norm(ho_m)
    out["n_free_angles"] = n_ang
    out["rotation_explains"] = None if (n_ang == 0 or p_f <= p_r) else bool(not better_aic or within)
    return out


def comparison_lines(c: dict) -> list[str]:
    """Report lines for :func:`compare`'s result."""
    def nt(v):
        return "n/a" if v is None else f"{np.linalg.norm(v) * 1e3:.1f} nT (" + " / ".join(
            f"{AXES[i]} {x * 1e3:.1f}" for i, x in enumerate(v)) + ")"
    L = ["mount rotation vs a general per-session linear map (nested; noise-weighted):",
         f"  parameters {c['params_mount']} vs {c['params_session_map']}; in-sample {nt(c['rms_mount_uT'])} vs "
         f"{nt(c['rms_session_map_uT'])}",
         f"  held-out time blocks {nt(c.get('holdout_mount_uT'))} vs {nt(c.get('holdout_session_map_uT'))}",
         f"  AIC {c['aic_mount']:.1f} vs {c['aic_session_map']:.1f}"
         + (f"; F({c['F_dof'][0]}, {c['F_dof'][1]}) = {c['F']:.3g}, p = {c['F_p_value']:.3g}" if "F" in c else "")]
    if c["rotation_explains"] is None:
        L.append("  verdict: undecided -- " + (
            "no mount angle is determined by these data (see the held angles)" if c.get("n_free_angles") == 0 else
            "the general map has no parameter the data determine beyond the mount model")
            + "; a remount can only be told from the sensor when some input axis is swept in two or more "
              "sessions, or a session excites two or more axes")
        return L
    L.append("  verdict: " + ("a rotation per session explains the session differences (the general map is "
                              "not better by AIC, or not better held out)" if c["rotation_explains"] else
                              "a rotation does NOT explain all session differences: the general per-session map "
                              "is better by AIC and held out; look for other per-session effects"))
    return L


def _f_sf(f: float, d1: int, d2: int) -> float:
    """Survival function of the F distribution (scipy.stats imported here: it costs ~2 s at start-up)."""
    import scipy.stats

    return float(scipy.stats.f.sf(f, d1, d2))
