"""Posterior uncertainty of a calibration table: per-sample sd and the validity box it implies.

A table may carry the posterior covariance of its flight parameters (block ``posterior`` of the table
file, :mod:`magstack.firmware.cal_table`): per output axis the parameter names (``S[x,y]``, ``K_S[x,y]``,
``O[x]``, ``K_O[x]``, ``D_k[x]``, ``c3[x]``, ``P[x,xy]``) and their covariance ``C_i``. For an input
(field ``b`` uT, temperature, currents) the calibrated axis ``i`` is ``f_i(b, T, I)^T theta_i`` with the
features ``f_i`` named by the parameters, so its posterior predictive variance (parameter part) is
``f_i^T C_i f_i`` (uT^2). The sensor's own noise is not included: it is the noise floor, reported
beside it.

* :func:`predictive_sd_uT` (N, 3) per axis and :func:`norm_sd_uT` (N,), the sd of ``|B_cal|``
  (``sqrt(sum_i u_i^2 sd_i^2)`` with ``u = B/|B|``; the vector sd below 1 uT, where the direction is
  undefined).
* :func:`validity_box`: the temperature interval (and field limit) over which an upper bound of the
  worst-case vector sd stays below a bound, clipped to the part's operating range. Every feature is
  evaluated over fields of magnitude F (1000 directions), the nonlinear and current features bounded by
  the triangle inequality (|I| <= the current limits), ``C_i = L_i L_i^T``. The
  field limit is the largest F for which the bound holds at the data's centre temperature; the temperature
  interval is where it holds at the field magnitude the fit saw (not at the corners of the box, where a
  high field and a far temperature meet). The table stores the box; the fit, ``apply`` and the flight
  corrector all use it.

On board, evaluating ``f^T C f`` per sample costs k^2 + k multiply-adds per axis (k = 8 parameters per
axis for Eq. 3: about 220 per sample): optional, not done by the fixed-point applier (docs/cal-table.md).
"""
from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence

import numpy as np

AXES = ("x", "y", "z")
_NAME = re.compile(r"^(S|K_S2|K_S|O|K_O|c3|P|D_[A-Za-z0-9_]+)\[([xyz])(?:,(x|y|z|xy|xz|yz))?\]$")


def parse_name(name: str) -> tuple[str, int, str | None]:
    """``'K_S[x,y]'`` -> ("K_S", 0, "y"); ValueError for a name that is not a flight parameter."""
    m = _NAME.match(name)
    if not m:
        raise ValueError(f"not a flight parameter name: {name!r}")
    return m.group(1), AXES.index(m.group(2)), m.group(3)


def features(names: Sequence[str], b_uT: np.ndarray, dT: np.ndarray,
             currents_A: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
    """(N, k) values of the features that multiply the parameters ``names`` (one axis's)."""
    b = np.asarray(b_uT, dtype=float).reshape(-1, 3)
    n = b.shape[0]
    dT = np.broadcast_to(np.asarray(dT, dtype=float), (n,))
    out = np.empty((n, len(names)))
    for k, nm in enumerate(names):
        p, i, j = parse_name(nm)
        if p == "S":
            out[:, k] = b[:, AXES.index(j)]
        elif p == "K_S":
            out[:, k] = b[:, AXES.index(j)] * dT
        elif p == "K_S2":
            out[:, k] = b[:, i] * dT * dT
        elif p == "O":
            out[:, k] = 1.0
        elif p == "K_O":
            out[:, k] = dT
        elif p == "c3":
            out[:, k] = b[:, i] ** 3
        elif p == "P":
            a, c = ({"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)})[j]
            out[:, k] = b[:, a] * b[:, c]
        else:
            cur = (currents_A or {}).get(p[2:])
            if cur is None:
                raise ValueError(f"current {p[2:]!r} needed for {nm}")
            out[:, k] = np.broadcast_to(np.asarray(cur, dtype=float), (n,))
    return out


def predictive_sd_uT(posterior: Mapping, t0_c: float, b_uT, temp_c, currents_A=None) -> np.ndarray:
    """(N, 3) posterior sd of each calibrated axis (uT); NaN where an input is missing.

    ``posterior``: the table's block ``{"x": {"names": [...], "cov": [[...]]}, "y": ..., "z": ...}``."""
    b = np.asarray(b_uT, dtype=float).reshape(-1, 3)
    n = b.shape[0]
    t = np.full(n, t0_c) if temp_c is None else np.asarray(temp_c, dtype=float).reshape(n)
    out = np.empty((n, 3))
    with np.errstate(invalid="ignore"):
        for i, a in enumerate(AXES):
            blk = posterior[a]
            F = features(blk["names"], b, t - t0_c, currents_A)
            C = np.asarray(blk["cov"], dtype=float)
            out[:, i] = np.sqrt(np.maximum(np.einsum("nk,kl,nl->n", F, C, F), 0.0))
    return out


def norm_sd_uT(sd_axes_uT: np.ndarray, b_cal_uT: np.ndarray) -> np.ndarray:
    """(N,) sd of |B_cal| from per-axis sds: along the field direction, the vector sd below 1 uT."""
    b = np.asarray(b_cal_uT, dtype=float).reshape(-1, 3)
    s = np.asarray(sd_axes_uT, dtype=float).reshape(-1, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        mag = np.linalg.norm(b, axis=1)
        u2 = (b / mag[:, None]) ** 2
        along = np.sqrt(np.sum(u2 * s ** 2, axis=1))
    vec = np.sqrt(np.sum(s ** 2, axis=1))
    return np.where(mag >= 1.0, along, vec)


def _chol(C: np.ndarray) -> np.ndarray:
    C = 0.5 * (C + C.T)
    w, V = np.linalg.eigh(C)
    return V * np.sqrt(np.maximum(w, 0.0))          # L with L L^T = C (PSD, no jitter needed)


def _sphere(n: int = 1000) -> np.ndarray:
    """(n, 3) unit vectors spread evenly (Fibonacci sphere), both hemispheres."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5 ** 0.5) * k
    rho = np.sqrt(1.0 - z * z)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


_DIRS = _sphere()


def worst_sd_bound_uT(posterior: Mapping, t0_c: float, temp_c: float, field_uT: float,
                      currents_A: Mapping[str, tuple[float, float]] | None = None) -> float:
    """The largest vector sd ``sqrt(sum_i sd_i^2)`` (uT) over fields of magnitude ``field_uT`` (1000
    directions; the maximum of a convex quadratic over the ball lies on its surface), temperature
    ``temp_c``, currents inside their intervals; the cubic, cross-product and current features are bounded
    by the triangle inequality (see the module docstring)."""
    r = float(field_uT)
    dT = temp_c - t0_c
    b = r * _DIRS
    tot = np.zeros(b.shape[0])
    for a in AXES:
        blk = posterior[a]
        names = blk["names"]
        L = _chol(np.asarray(blk["cov"], dtype=float))
        lin_names = [k for k, nm in enumerate(names) if parse_name(nm)[0] in ("S", "K_S", "K_S2", "O", "K_O")]
        F = features([names[k] for k in lin_names], b, np.full(b.shape[0], dT))
        v = F @ L[lin_names]                         # L^T f for the linear features, per direction
        extra = 0.0
        for k, nm in enumerate(names):
            p = parse_name(nm)[0]
            if p == "c3":
                extra += r ** 3 * float(np.linalg.norm(L[k]))
            elif p == "P":
                extra += r ** 2 * float(np.linalg.norm(L[k]))
            elif p.startswith("D_"):
                lo, hi = (currents_A or {}).get(p[2:], (0.0, 0.0))
                extra += max(abs(lo), abs(hi)) * float(np.linalg.norm(L[k]))
        tot += (np.linalg.norm(v, axis=1) + extra) ** 2
    return float(np.sqrt(tot.max()))


def validity_box(posterior: Mapping, t0_c: float, bound_uT: float, temp_limits_c: tuple[float, float],
                 field_uT: float, centre_c: float, currents_A: Mapping[str, tuple[float, float]] | None = None,
                 step_c: float = 0.05) -> tuple[tuple[float, float] | None, float]:
    """``(temperature interval or None, worst bound at its centre)``: the interval around ``centre_c``
    (the fit data's mean temperature) where :func:`worst_sd_bound_uT` stays <= ``bound_uT`` at field
    ``field_uT``, inside ``temp_limits_c``, on a ``step_c`` grid (ends rounded inwards to 0.01 degC).
    None when even the centre exceeds the bound.

    Each end is the last grid point before the first one over the bound, walking out from the centre. The
    bound is quasi-convex in temperature (per axis the linear features are affine in ``dT``, so each
    axis's term is the square of a norm of an affine function plus a constant; their sum is convex, its
    maximum over directions too), so "over the bound" switches once along each walk: the end is found by
    bisection over the walk's grid points (~12 evaluations instead of one per 0.05 degC step)."""
    lo_lim, hi_lim = temp_limits_c
    c = min(max(centre_c, lo_lim), hi_lim)
    at_c = worst_sd_bound_uT(posterior, t0_c, c, field_uT, currents_A)
    if at_c > bound_uT:
        return None, at_c

    def over(t: float) -> bool:
        return worst_sd_bound_uT(posterior, t0_c, t, field_uT, currents_A) > bound_uT

    def edge(direction: int) -> float:
        walk = [c]                              # the grid points by repeated steps from the centre
        while True:
            nxt = walk[-1] + direction * step_c
            if (direction > 0 and nxt > hi_lim) or (direction < 0 and nxt < lo_lim):
                break
            walk.append(nxt)
        if len(walk) == 1 or not over(walk[-1]):
            return hi_lim if direction > 0 else lo_lim
        inside, outside = 0, len(walk) - 1      # walk[inside] within the bound, walk[outside] over it
        while outside - inside > 1:
            mid = (inside + outside) // 2
            if over(walk[mid]):
                outside = mid
            else:
                inside = mid
        return walk[inside]
    lo, hi = edge(-1), edge(+1)
    return (math.ceil(lo * 100 - 1e-9) / 100, math.floor(hi * 100 + 1e-9) / 100), at_c


def field_limit_uT(posterior: Mapping, t0_c: float, bound_uT: float, centre_c: float, f_max_uT: float,
                   currents_A: Mapping[str, tuple[float, float]] | None = None) -> float:
    """Largest per-axis field F <= ``f_max_uT`` (whole uT) whose worst-case bound at ``centre_c`` is
    <= ``bound_uT`` (0 when none)."""
    if worst_sd_bound_uT(posterior, t0_c, centre_c, f_max_uT, currents_A) <= bound_uT:
        return float(f_max_uT)
    lo, hi = 0.0, float(f_max_uT)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if worst_sd_bound_uT(posterior, t0_c, centre_c, mid, currents_A) <= bound_uT:
            lo = mid
        else:
            hi = mid
    return float(math.floor(lo))
