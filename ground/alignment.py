"""Align two independently clocked vector streams (device under test and reference).

Conventions (all times in seconds, fields in uT):

* ``offset_s`` is added to the *reference* timestamps to put them on the DUT clock:
  ``t_ref_on_dut = t_ref + offset_s``. The value of the reference at DUT time ``t`` is the
  reference stream interpolated at ``t - offset_s`` (reference clock).
* ``skew_s[i]`` is the per-axis time skew of DUT axis ``i`` in the sense of the
  ``time_skew`` effect (:mod:`magstack.firmware.effects`): DUT axis ``i`` reads the field at DUT
  time ``t + skew_s[i]``. It is measured relative to the common ``offset_s`` (a common shift
  of all three axes cannot be told apart from the clock offset).
* ``axis_map`` is a signed permutation: DUT axis ``i`` = ``sign[i]`` * reference axis
  ``perm[i]`` (up to gain and offset).

Every estimate is the minimiser of the residual of a linear least-squares fit (3x3 gain
matrix + offset vector), so it is invariant to the axis map and to gains and offsets. When
the DUT rows carry a temperature whose span is material (``temp_c``; default span >= 1 degC)
the fits also get the temperature terms of the calibration model (belsten Eq. 3): the
products ``x * dT`` of every field column ``x`` and a ``dT`` column, ``dT = T - mean(T)``, and by
default the second-order ``x * dT^2``, ``dT^2``, so a thermally varying gain or offset is not
mistaken for a time shift. Which model was used is recorded (``model``); without a usable
temperature the plain model is used. The uncertainty is the larger of the curvature of that
residual, ``var = 2 s^2 / SSR''`` (residual variance ``s^2`` inflated for the residuals' lag-1
autocorrelation), and a delete-one-block jackknife. When the data cannot determine a
parameter (static field, no overlap, periodic ambiguity) :class:`magstack.drivers.errors.AlignmentError`
is raised (offset) or the per-axis result is flagged ``determined=False`` with a reason (skew,
axis map).

Only numpy is needed; reference streams are interpolated linearly, never extrapolated.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from magstack.data.dictionary import FLAG
from magstack.data.pairing import finite_rows, sort_unique, split_streams
from magstack.ground.errors import AlignmentError

AXES = "xyz"
#: Coarse offset search limits (keep a long session's search to a few seconds).
MAX_COARSE_CANDIDATES = 4000
MAX_COARSE_ROWS = 1000
#: Offsets per pass of the medium stage (all rows): long searches are refined in several passes.
MAX_MEDIUM_CANDIDATES = 81
#: Candidate offsets x rows x design columns evaluated at once: bounds the memory of every search
#: stage (~8 MB per intermediate array) independently of the session length.
MAX_CHUNK_ELEMENTS = 1_000_000
#: A reference whose RMS variation on the compared rows is below this (uT) is constant: nothing to align on.
MIN_REF_VARIATION_UT = 1e-6
#: Temperature model (``temp_model="auto"``): used when the temperature is finite on at least
#: MIN_TEMP_FRACTION of the DUT rows and its 2..98 % percentile span is at least MIN_TEMP_SPAN_C.
#: (HMC1053 sensitivity tempco ~ -2700 ppm/degC: 1 degC ~ 135 nT at 50 uT.)
MIN_TEMP_SPAN_C = 1.0
MIN_TEMP_FRACTION = 0.8
#: Temperature terms: 1 = belsten Eq. 3 (x*dT, dT); 2 = also x*dT^2, dT^2 (the inverse of a gain
#: 1 + k dT is not linear in dT: over -20..60 degC at -2700 ppm/degC the quadratic part is ~0.6 uT).
TEMP_ORDER = 2
TEMP_MODELS = ("auto", "on", "off")


# --------------------------------------------------------------------------- interpolation
def interp_no_extrapolation(t_src: np.ndarray, y_src: np.ndarray, t_query: np.ndarray,
                            max_gap_s: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """Linearly interpolate ``y_src`` (N,k) at ``t_query`` (M,); never extrapolate.

    Returns ``(y (M,k), valid (M,))``. A query outside ``[t_src[0], t_src[-1]]`` or inside a
    source interval longer than ``max_gap_s`` is invalid and gets NaN. Non-finite source rows
    are removed first (they become gaps). ``t_src`` must be strictly increasing after that.
    """
    t_src = np.asarray(t_src, dtype=float).reshape(-1)
    y = np.asarray(y_src, dtype=float)
    one_d = y.ndim == 1
    y = y.reshape(t_src.size, -1)
    tq = np.asarray(t_query, dtype=float).reshape(-1)
    ok = np.isfinite(t_src) & np.all(np.isfinite(y), axis=1)
    t_src, y = t_src[ok], y[ok]
    out = np.full((tq.size, y.shape[1]), np.nan)
    if t_src.size < 2:
        return (out[:, 0] if one_d else out), np.zeros(tq.size, bool)
    if np.any(np.diff(t_src) <= 0):
        raise AlignmentError("source timestamps must be strictly increasing")
    y_out, valid = _interp_sorted(t_src, y, tq, max_gap_s)
    return (y_out[:, 0] if one_d else y_out), valid


def _interp_sorted(t_src: np.ndarray, y: np.ndarray, tq: np.ndarray, max_gap_s: float):
    """:func:`interp_no_extrapolation` for a source already finite and strictly increasing (>= 2 rows,
    ``y`` (N,k)): the search stages call it per chunk without re-checking the whole source."""
    out = np.full((tq.size, y.shape[1]), np.nan)
    idx = np.searchsorted(t_src, tq, side="right")
    inside = np.isfinite(tq) & (tq >= t_src[0]) & (tq <= t_src[-1])
    hi = np.clip(idx, 1, t_src.size - 1)
    lo = hi - 1
    span = t_src[hi] - t_src[lo]
    valid = inside & (span <= max_gap_s)
    w = np.where(valid, (tq - t_src[lo]) / np.where(span > 0, span, 1.0), 0.0)
    vals = y[lo] * (1 - w)[:, None] + y[hi] * w[:, None]
    out[valid] = vals[valid]
    return out, valid


def _interp_batch(t_src: np.ndarray, y_src: np.ndarray, tq: np.ndarray, max_gap_s: float):
    """Interpolation of a cleaned source (N,k) (see :func:`_clean`) at a 2-D query array tq (C,M)
    -> (C,M,k), valid (C,M)."""
    shape = tq.shape
    y, valid = _interp_sorted(t_src, y_src, tq.reshape(-1), max_gap_s)
    return y.reshape(*shape, -1), valid.reshape(shape)


# --------------------------------------------------------------------------- linear fits
def _lstsq(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Least-squares solution of ``X @ B ~ Y`` (as ``np.linalg.lstsq`` for a full-rank ``X``; for a
    rank-deficient one, minimum norm in column-scaled coordinates: the residual is the same).

    Tall problems are solved through the normal equations of the column-scaled design (the same
    sums the batched offset search uses), so LAPACK only sees a p x p system: the SVD or QR of
    the full rows took 20-90 ms per call on the 2-core machine under load, this ~0.1 ms.
    """
    if X.shape[0] > 4 * X.shape[1]:
        scale = np.sqrt(np.sum(X * X, axis=0))
        scale[scale == 0] = 1.0
        xs = X / scale
        return np.linalg.lstsq(xs.T @ xs, xs.T @ Y, rcond=None)[0] / scale[:, None]
    return np.linalg.lstsq(X, Y, rcond=None)[0]


def linear_fit(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares ``y ~ x @ M.T + c`` on finite rows; returns ``(M (k,p), c (k,), residual (n,k))``."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    ok = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(y), axis=1)
    X = np.column_stack([x[ok], np.ones(ok.sum())])
    coef = _lstsq(X, y[ok])
    resid = y[ok] - X @ coef
    return coef[:-1].T, coef[-1], resid


def linear_fit_rmse_uT(ref_uT: np.ndarray, dut_uT: np.ndarray) -> dict[str, float]:
    """RMSE of the calibration-direction linear fit ``ref ~ A dut + b`` (12 parameters).

    Returns per-axis RMSE, the vector-norm RMSE ``sqrt(mean |r|^2)`` in uT and the row count.
    """
    _, _, r = linear_fit(dut_uT, ref_uT)
    if r.shape[0] < 5:
        raise AlignmentError(f"only {r.shape[0]} paired rows: too few for a linear fit")
    return _rmse_dict(r)


def _rmse_dict(r: np.ndarray) -> dict[str, float]:
    """Per-axis and vector RMSE (uT) and row count of residuals (n,3)."""
    rms = np.sqrt(np.mean(r ** 2, axis=0))
    return {"x": float(rms[0]), "y": float(rms[1]), "z": float(rms[2]),
            "vector": float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))), "n": int(r.shape[0])}


def _normal_eqs(X: np.ndarray, Y: np.ndarray, valid: np.ndarray):
    """Per candidate c, the normal equations of ``Y[c] ~ [X[c], 1]`` on rows valid[c].

    X (C,M,p) or (M,p); Y (C,M,k) or (M,k); valid (C,M). Returns the additive sums
    ``(xtx (C,p+1,p+1), xty (C,p+1,k), yty (C,k), ysum (C,k), n (C,))``: sums over row blocks
    add up, so a delete-one-block fit is ``total - block`` (no refit over the rows).
    """
    C, M = valid.shape
    X = np.broadcast_to(X, (C,) + X.shape[-2:]) if X.ndim == 2 else X
    Y = np.broadcast_to(Y, (C,) + Y.shape[-2:]) if Y.ndim == 2 else Y
    w = valid.astype(float)
    Xa = np.concatenate([np.where(valid[..., None], X, 0.0), w[..., None]], axis=2)
    Yw = np.where(valid[..., None], Y, 0.0)
    xa_t = Xa.transpose(0, 2, 1)
    return np.matmul(xa_t, Xa), np.matmul(xa_t, Yw), np.sum(Yw * Yw, axis=1), Yw.sum(axis=1), w.sum(axis=1)


def _solve_ssr(xtx, xty, yty, ysum, n) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SSR and SST per candidate and target column, (C,k) each, from :func:`_normal_eqs` sums.

    Candidates with too few rows (n <= p + 2) get NaN.
    """
    p = xtx.shape[-1]
    ridge = 1e-12 * np.trace(xtx, axis1=1, axis2=2)[:, None, None] * np.eye(p)
    ok = n > p + 2
    beta = np.zeros_like(xty)
    if ok.any():
        beta[ok] = np.linalg.solve(xtx[ok] + ridge[ok], xty[ok])
    ssr = yty - np.sum(beta * xty, axis=1)
    sst = yty - ysum ** 2 / np.maximum(n, 1)[:, None]
    ssr = np.where(ok[:, None], np.maximum(ssr, 0.0), np.nan)
    return ssr, np.where(ok[:, None], sst, np.nan), n


#: Progress callback: ``progress(stage, fraction_done)`` with fraction in [0, 1], called per row chunk.
Progress = Callable[[str, float], None]


def _block_sums(design, n_cand: int, n_rows: int, n_blocks: int, width: int,
                progress: tuple[Progress, str] | None = None) -> list[tuple]:
    """:func:`_normal_eqs` sums of each of ``n_blocks`` contiguous row blocks, accumulated over row chunks.

    ``design(rows: slice) -> (X, Y, valid)`` gives every candidate's design on those rows (as
    :func:`_normal_eqs` takes them). Chunks hold at most about :data:`MAX_CHUNK_ELEMENTS`
    candidate x row x ``width`` values, so the memory of a search does not grow with the row count
    (the sums are the same as over all rows at once, up to rounding).
    """
    edges = np.linspace(0, n_rows, n_blocks + 1).astype(int)
    step = max(1, MAX_CHUNK_ELEMENTS // max(1, n_cand * width))
    parts = []
    for b in range(n_blocks):
        acc = None
        for r0 in range(edges[b], edges[b + 1], step) if edges[b + 1] > edges[b] else [edges[b]]:
            r1 = min(r0 + step, edges[b + 1])
            sums = _normal_eqs(*design(slice(r0, r1)))
            acc = sums if acc is None else tuple(a + q for a, q in zip(acc, sums, strict=True))
            if progress is not None:
                progress[0](progress[1], r1 / max(1, n_rows))
        parts.append(acc)
    return parts


def _block_ssr(design, n_cand: int, n_rows: int, n_blocks: int, width: int,
               progress: tuple[Progress, str] | None = None):
    """SSR (C,k) on all rows and with each of ``n_blocks`` contiguous row blocks deleted.

    Returns ``(ssr_all, sst_all, [ssr_without_block_b])``; one streamed pass over the rows
    (:func:`_block_sums`; the normal equations of each block are subtracted from the total).
    """
    parts = _block_sums(design, n_cand, n_rows, n_blocks, width, progress)
    total = tuple(sum(pt[i] for pt in parts) for i in range(5))
    ssr, sst, _ = _solve_ssr(*total)
    loo = [_solve_ssr(*(t - q for t, q in zip(total, pt, strict=True)))[0] for pt in parts]
    return ssr, sst, loo


# --------------------------------------------------------------------------- results
@dataclass
class ParamEstimate:
    """A scalar estimate with a 1-sigma uncertainty; ``determined`` False gives the reason."""

    value: float
    sigma: float
    determined: bool = True
    reason: str = ""

    def as_dict(self) -> dict:
        return {"value": self.value, "sigma": self.sigma, "determined": self.determined, "reason": self.reason}


@dataclass
class OffsetEstimate:
    offset_s: float
    sigma_s: float
    r2: float
    n_pairs: int
    searched_s: tuple[float, float]
    runner_up_ratio: float
    curve_s: np.ndarray = field(repr=False, default_factory=lambda: np.empty(0))
    curve_unexplained: np.ndarray = field(repr=False, default_factory=lambda: np.empty(0))
    sigma_curvature_s: float = math.nan
    sigma_jackknife_s: float = math.nan
    model: str = "linear"
    sigma_resolution_s: float = math.nan


@dataclass
class AxisMap:
    """DUT axis i = sign[i] * reference axis perm[i] (plus gain/offset)."""

    perm: tuple[int, int, int]
    sign: tuple[int, int, int]
    dominance: tuple[float, float, float]
    t_stat: tuple[float, float, float]
    determined: tuple[bool, bool, bool]
    reasons: tuple[str, str, str]

    def describe(self) -> str:
        parts = []
        for i in range(3):
            s = "-" if self.sign[i] < 0 else "+"
            tag = "" if self.determined[i] else f" (undetermined: {self.reasons[i]})"
            parts.append(f"dut_{AXES[i]} = {s}ref_{AXES[self.perm[i]]}{tag}")
        return "; ".join(parts)


@dataclass
class AlignmentReport:
    offset: OffsetEstimate
    skew_s: list[ParamEstimate]
    axis_map: AxisMap
    rmse_uT: dict[str, float]
    notes: list[str] = field(default_factory=list)
    #: regression model used for offset, skew and axis map (``"linear"`` or ``"linear+temperature ..."``)
    model: str = "linear"
    #: RMSE of ``ref ~ A dut + K (dut dT) + k dT + b`` when the temperature model was used, else None
    rmse_model_uT: dict[str, float] | None = None

    def as_dict(self) -> dict:
        return {
            "offset_s": self.offset.offset_s, "offset_sigma_s": self.offset.sigma_s, "r2": self.offset.r2,
            "n_pairs": self.offset.n_pairs, "runner_up_ratio": self.offset.runner_up_ratio,
            "model": self.model, "rmse_model_uT": self.rmse_model_uT,
            "skew_s": {AXES[i]: e.as_dict() for i, e in enumerate(self.skew_s)},
            "axis_map": {"perm": list(self.axis_map.perm), "sign": list(self.axis_map.sign),
                         "determined": list(self.axis_map.determined), "reasons": list(self.axis_map.reasons),
                         "dominance": list(self.axis_map.dominance), "t_stat": list(self.axis_map.t_stat),
                         "text": self.axis_map.describe()},
            "rmse_uT": self.rmse_uT, "notes": list(self.notes),
        }


# --------------------------------------------------------------------------- helpers
def _clean(t: np.ndarray, v: np.ndarray, what: str, temp_c: np.ndarray | None = None):
    """Finite rows sorted by time, duplicate timestamps removed: ``(t, v)``, or ``(t, v, temp)``
    when ``temp_c`` (one value per row, may be NaN) is given."""
    t = np.asarray(t, float).reshape(-1)
    v = np.asarray(v, float)
    if v.ndim != 2 or v.shape != (t.size, 3):
        raise AlignmentError(f"{what}: expected (N,3) field array matching {t.size} timestamps, got {v.shape}")
    temp = None
    if temp_c is not None:
        temp = np.asarray(temp_c, float).reshape(-1)
        if temp.size != t.size:
            raise AlignmentError(f"{what}: temp_c has {temp.size} values for {t.size} timestamps")
    arrays = (v,) if temp is None else (v, temp)
    t, cleaned, _ = sort_unique(t, *arrays, keep=finite_rows(t, v))
    if t.size < 10:
        raise AlignmentError(f"{what}: only {t.size} finite samples; need at least 10")
    return (t, cleaned[0]) if temp is None else (t, cleaned[0], cleaned[1])


def _temperature_terms(t_s: np.ndarray, temp_c: np.ndarray | None, mode: str, min_span_c: float,
                       order: int) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """Decide the regression model; returns ``(tcols (N,order) or None, temp_c filled, description)``.

    ``tcols[:, 0] = u = (T - mean T) / std T`` and, for ``order`` 2, ``tcols[:, 1] = u^2 - 1``
    (scaled only for conditioning: the residuals do not depend on the scale). Missing
    temperatures between finite ones are interpolated in time (the temperature is slow); rows
    before the first or after the last finite value get NaN and are left out of the fits.
    """
    if mode not in TEMP_MODELS:
        raise AlignmentError(f"temp_model must be one of {TEMP_MODELS}, got {mode!r}")
    if order not in (1, 2):
        raise AlignmentError(f"temp_order must be 1 (Eq. 3) or 2 (Eq. 3 + dT^2 terms), got {order!r}")
    if mode == "off":
        return None, None, "linear (temperature model switched off)"
    if temp_c is None:
        return None, None, "linear (no temperature column)"
    fin = np.isfinite(temp_c)
    frac = float(fin.mean()) if temp_c.size else 0.0
    if frac < MIN_TEMP_FRACTION or fin.sum() < 10:
        return None, None, (f"linear (temperature finite on only {frac:.0%} of the DUT rows, "
                            f"< {MIN_TEMP_FRACTION:.0%})")
    lo_c, hi_c = np.percentile(temp_c[fin], [2.0, 98.0])
    span = float(hi_c - lo_c)
    need = min_span_c if mode == "auto" else 0.0
    if not span > need or not span > 0:
        return None, None, f"linear (temperature span {span:.2f} degC < {min_span_c:g} degC)"
    temp = temp_c.copy()
    if not fin.all():
        inside = (t_s >= t_s[fin][0]) & (t_s <= t_s[fin][-1])
        temp[~fin & inside] = np.interp(t_s[~fin & inside], t_s[fin], temp_c[fin])
    mean_c = float(np.nanmean(temp))
    u = (temp - mean_c) / float(np.nanstd(temp))
    cols = [u] if order == 1 else [u, u * u - 1.0]
    terms = "x*dT, dT" if order == 1 else "x*dT, dT and second-order x*dT^2, dT^2"
    desc = (f"linear+temperature (belsten Eq. 3 terms {terms}; dT = T - {mean_c:.2f} degC; "
            f"temperature span {span:.1f} degC on {int(np.isfinite(temp).sum())} rows)")
    return np.column_stack(cols), temp, desc


def _with_temp(x: np.ndarray, tcols: np.ndarray | None) -> np.ndarray:
    """Design columns ``[x, x * t_1, .., t_1, ..]`` for field columns ``x`` (..., M, 3) and
    temperature columns ``tcols`` (M, q)."""
    if tcols is None:
        return x
    parts = [x] + [x * tcols[:, j:j + 1] for j in range(tcols.shape[1])]
    parts.append(np.broadcast_to(tcols, x.shape[:-1] + (tcols.shape[1],)))
    return np.concatenate(parts, axis=-1)


def _prepare_dut(t_dut, dut_uT, temp_c, temp_model: str, min_temp_span_c: float, temp_order: int):
    """Clean the DUT stream; returns ``(t, dut, temp_c or None, tcols or None, model description)``.

    With the temperature model, DUT rows without a temperature are dropped.
    """
    if temp_c is None:
        t, v = _clean(t_dut, dut_uT, "DUT")
        temp = None
    else:
        t, v, temp = _clean(t_dut, dut_uT, "DUT", temp_c)
    tcols, temp, model = _temperature_terms(t, temp, temp_model, min_temp_span_c, temp_order)
    if tcols is not None:
        ok = np.isfinite(temp)
        if ok.sum() < 10:
            raise AlignmentError(f"DUT: only {int(ok.sum())} rows with a temperature; need at least 10")
        t, v, temp, tcols = t[ok], v[ok], temp[ok], tcols[ok]
    return t, v, temp, tcols, model


def _eff_factor(resid: np.ndarray) -> float:
    """sqrt(n / n_eff) from the residuals' mean lag-1 autocorrelation (>= 1)."""
    r = resid - resid.mean(axis=0)
    num = np.sum(r[1:] * r[:-1])
    den = np.sum(r * r)
    rho = float(num / den) if den > 0 else 0.0
    rho = min(max(rho, 0.0), 0.95)
    return math.sqrt((1 + rho) / (1 - rho))


def _parabola_min(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Vertex and second derivative of the least-squares parabola through (x, y)."""
    x0 = x.mean()
    a, b, _ = np.polyfit(x - x0, y, 2)
    if a <= 0:
        return float(x[np.argmin(y)]), 0.0
    return float(x0 - b / (2 * a)), float(2 * a)


def _vertex(grid: np.ndarray, ssr: np.ndarray, half_window_s: float) -> tuple[float, float, int]:
    """(vertex, SSR'' , argmin) of a cost curve: parabola through the points within the window."""
    if not np.any(np.isfinite(ssr)):
        return math.nan, 0.0, -1
    k = int(np.nanargmin(ssr))
    sel = (np.abs(grid - grid[k]) <= half_window_s) & np.isfinite(ssr)
    if sel.sum() < 5:
        return float(grid[k]), 0.0, k
    vertex, curv = _parabola_min(grid[sel], ssr[sel])
    if not (grid[sel][0] <= vertex <= grid[sel][-1]):
        vertex = float(grid[k])
    return vertex, curv, k


def _resolution_sigma(xd: np.ndarray, t_dut: np.ndarray, t_ref: np.ndarray, ref: np.ndarray, vertex: float,
                      gap: float, dt_dut: float, dt_ref: float) -> float:
    """Timing-resolution floor (s) of the clock offset: ``sqrt((dt_ref^2 + dt_dut^2) / (12 n_eff))``.

    A field transition between two samples is located by each stream only to within its sample
    interval (uniform: interval / sqrt(12)). ``n_eff`` is the effective number of DUT rows that
    carry the offset information: each row's weight is the second difference of its squared
    residual at ``vertex +- dt_ref / 2`` (fit at the vertex held fixed), ``n_eff = (sum w)^2 /
    sum w^2``. Steps faster than the sampling put the information in a few rows; the estimate
    then hinges on where those few samples fell, which neither the curvature nor the block
    jackknife sees (they under-covered such data by up to ~10x).
    """
    y0, ok0 = interp_no_extrapolation(t_ref, ref, t_dut - vertex, gap)
    if ok0.sum() < xd.shape[1] + 3:
        return math.inf
    m, c, _ = linear_fit(xd[ok0], y0[ok0])
    pred = xd @ m.T + c
    ok = np.ones(t_dut.size, bool)
    r2 = []
    for o in (vertex - dt_ref / 2, vertex, vertex + dt_ref / 2):
        y, v = interp_no_extrapolation(t_ref, ref, t_dut - o, gap)
        ok &= v & np.all(np.isfinite(pred), axis=1)
        r2.append(np.sum((y - pred) ** 2, axis=1))
    w = np.maximum(r2[0][ok] + r2[2][ok] - 2 * r2[1][ok], 0.0)
    total = float(w.sum())
    if not total > 0:
        return math.inf
    n_eff = total ** 2 / float(np.sum(w ** 2))
    return math.sqrt((dt_ref ** 2 + dt_dut ** 2) / (12.0 * n_eff))


def _jackknife_sigma(values: list[float]) -> float:
    v = np.asarray([x for x in values if math.isfinite(x)])
    g = v.size
    if g < 3:
        return math.inf
    return float(math.sqrt((g - 1) / g * np.sum((v - v.mean()) ** 2)))


# --------------------------------------------------------------------------- clock offset
def _check_search(prior_s, halfwidth_s, step_s, min_overlap, max_gap_s, min_r2, max_sigma_s) -> None:
    """AlignmentError for a search parameter that is not finite or out of its range."""
    def need(ok: bool, what: str, value) -> None:
        if not ok:
            raise AlignmentError(f"{what}, got {value!r}")
    if prior_s is not None:
        need(math.isfinite(prior_s), "prior_s must be finite (s)", prior_s)
    for name, v in (("search_halfwidth_s", halfwidth_s), ("step_s", step_s), ("max_gap_s", max_gap_s)):
        if v is not None:
            need(math.isfinite(v) and v > 0, f"{name} must be finite and > 0 (s)", v)
    need(0 < min_overlap <= 1, "min_overlap must be in (0, 1]", min_overlap)
    need(0 < min_r2 <= 1, "min_r2 must be in (0, 1]", min_r2)
    need(max_sigma_s > 0, "max_sigma_s must be > 0 (s)", max_sigma_s)


def estimate_clock_offset(t_dut: np.ndarray, dut_uT: np.ndarray, t_ref: np.ndarray, ref_uT: np.ndarray, *,
                          prior_s: float | None = None, search_halfwidth_s: float | None = None,
                          step_s: float | None = None, min_overlap: float = 0.5, max_gap_s: float | None = None,
                          min_r2: float = 0.9, max_sigma_s: float = 1.0,
                          ambiguity_ratio: float = 2.0, n_blocks: int = 20, temp_c: np.ndarray | None = None,
                          temp_model: str = "auto", min_temp_span_c: float = MIN_TEMP_SPAN_C,
                          temp_order: int = TEMP_ORDER, progress: Progress | None = None) -> OffsetEstimate:
    """Clock offset (add to reference time to get DUT time) minimising ``ref ~ A dut + b``.

    ``temp_c`` (degC, one per DUT row, NaN allowed) adds the Eq. 3 temperature columns
    (``ref ~ A dut + K (dut dT) + k dT + b``) when ``temp_model`` is ``"on"``, or ``"auto"``
    and the temperature span is at least ``min_temp_span_c``; ``model`` records the choice.

    Coarse search: every offset in ``prior_s +- search_halfwidth_s`` (default: every offset that
    overlaps at least ``min_overlap`` of the shorter stream) at ``step_s`` (default half the
    reference's median period); refine on a 5 ms grid and take the vertex of the residual
    parabola. ``sigma_s`` is the largest of the curvature estimate (``2 s^2 / SSR''``, inflated for
    residual autocorrelation), a delete-one-block jackknife over ``n_blocks`` contiguous blocks
    of DUT rows, and the timing-resolution floor of :func:`_resolution_sigma` (field steps
    faster than the sampling, located only to within the sample intervals). Raises
    AlignmentError when the streams do not overlap, when the best fit explains less than
    ``min_r2`` of the reference variance (static field: nothing to align on), when the
    uncertainty exceeds ``max_sigma_s`` or when another, distant minimum fits within
    ``ambiguity_ratio`` of the best unexplained variance (periodic signal).
    """
    _check_search(prior_s, search_halfwidth_s, step_s, min_overlap, max_gap_s, min_r2, max_sigma_s)
    t_dut, dut, _, tcols, model = _prepare_dut(t_dut, dut_uT, temp_c, temp_model, min_temp_span_c, temp_order)
    xd = _with_temp(dut, tcols)  # regressors on the DUT rows (fixed for every candidate offset)
    t_ref, ref = _clean(t_ref, ref_uT, "reference")
    dt_ref = float(np.median(np.diff(t_ref)))
    dt_dut = float(np.median(np.diff(t_dut)))
    gap = max_gap_s if max_gap_s is not None else max(4 * dt_ref, 1.0)
    h = step_s if step_s is not None else dt_ref / 2
    dur_dut, dur_ref = t_dut[-1] - t_dut[0], t_ref[-1] - t_ref[0]
    need = min_overlap * min(dur_dut, dur_ref)
    if prior_s is not None and search_halfwidth_s is not None:
        lo, hi = prior_s - search_halfwidth_s, prior_s + search_halfwidth_s
    else:
        lo = t_dut[0] - t_ref[-1] + need  # a prior without halfwidth is only reported, not imposed
        hi = t_dut[-1] - t_ref[0] - need
    if not hi > lo:
        raise AlignmentError(f"streams cannot overlap by {min_overlap:.0%}: DUT {dur_dut:.1f} s, "
                             f"reference {dur_ref:.1f} s")
    # Coarse stage: at most MAX_COARSE_CANDIDATES offsets on at most MAX_COARSE_ROWS evenly spaced
    # DUT rows (long sessions), then a medium stage at step h on all rows around the best.
    h_coarse = max(h, (hi - lo) / MAX_COARSE_CANDIDATES)
    grid = np.linspace(lo, hi, int(math.ceil((hi - lo) / h_coarse)) + 1)
    sub = np.unique(np.linspace(0, t_dut.size - 1, min(t_dut.size, MAX_COARSE_ROWS)).astype(int))

    def cost(offsets: np.ndarray, rows: np.ndarray | None = None, stage: str = ""):
        td = t_dut if rows is None else t_dut[rows]
        dd = xd if rows is None else xd[rows]
        min_rows = max(10, int(0.2 * td.size))

        def design(rs: slice):
            y, valid = _interp_batch(t_ref, ref, td[None, rs] - offsets[:, None], gap)
            return dd[rs], y, valid

        (sums,) = _block_sums(design, offsets.size, td.size, 1, dd.shape[1] + 8,
                              None if progress is None else (progress, stage))
        out_ssr, out_sst, out_n = _solve_ssr(*sums)
        out_ssr, out_sst = out_ssr.sum(axis=1), out_sst.sum(axis=1)
        out_ssr[out_n < min_rows] = np.nan
        # a constant reference (zero-field session, the first seconds of a run) explains nothing
        out_sst[~(out_sst > 3 * out_n * MIN_REF_VARIATION_UT ** 2)] = np.nan
        return out_ssr, out_sst, out_n

    ssr, sst, n = cost(grid, sub, "clock offset: coarse search")
    if not np.any(np.isfinite(ssr)):
        raise AlignmentError("no offset in the searched range gives enough overlapping samples "
                             f"(searched {lo:.1f}..{hi:.1f} s)")
    if not np.any(np.isfinite(ssr / sst)):
        raise AlignmentError("the data cannot determine a clock offset: the reference field is constant on the "
                             "overlapping samples (a zero-field session or the start of a run?); record while "
                             "the field changes")
    unexpl = ssr / sst
    k = int(np.nanargmin(unexpl))
    best_u = float(unexpl[k])
    # Runner-up: the best local minimum further than max(2 s, 4 DUT periods) away.
    far = np.abs(grid - grid[k]) > max(2.0, 4 * dt_dut, 4 * h_coarse)
    u = np.where(np.isfinite(unexpl), unexpl, np.inf)
    locmin = np.zeros_like(far)
    locmin[1:-1] = (u[1:-1] <= u[:-2]) & (u[1:-1] <= u[2:])
    cand = far & locmin & np.isfinite(unexpl)
    runner = float(np.min(unexpl[cand])) if cand.any() else math.inf
    ratio = runner / best_u if best_u > 0 else math.inf
    center = float(grid[k])
    if h_coarse > h or sub.size < t_dut.size:
        # medium stage on all rows: +-2 coarse steps around the best, refined in passes of at most
        # MAX_MEDIUM_CANDIDATES offsets down to step h (one pass at step h for all but long searches;
        # a single pass at step h over +-2 coarse steps grew with the searched range x rows)
        half = 2 * h_coarse
        while True:
            step = max(h, 2 * half / (MAX_MEDIUM_CANDIDATES - 1))
            mid = center + np.arange(-half, half + step / 2, step)
            ssr_m, sst_m, _ = cost(mid, None, "clock offset: medium search")
            if np.any(np.isfinite(ssr_m / sst_m)):
                center = float(mid[int(np.nanargmin(ssr_m / sst_m))])
            if step <= h:
                break
            half = 2 * step

    # Fine stage on a 5 ms grid; the curve is computed once, then once per deleted block.
    fine = center + np.arange(-max(2 * h, 0.25), max(2 * h, 0.25) + 0.0025, 0.005)

    def fine_design(rs: slice):
        y, valid = _interp_batch(t_ref, ref, t_dut[None, rs] - fine[:, None], gap)
        return xd[rs], y, valid

    ssr_f, _, loo = _block_ssr(fine_design, fine.size, t_dut.size, n_blocks, xd.shape[1] + 8,
                               None if progress is None else (progress, "clock offset: fine search"))
    win = max(h, 0.1)
    vertex, curv, kf = _vertex(fine, ssr_f.sum(axis=1), win)
    jack = [_vertex(fine, s_b.sum(axis=1), win)[0] for s_b in loo]
    sigma_jk = _jackknife_sigma(jack)
    # residual statistics at the vertex
    y, valid = interp_no_extrapolation(t_ref, ref, t_dut - vertex, gap)
    _, _, resid = linear_fit(xd[valid], y[valid])
    dof = max(1, resid.size - 3 * (xd.shape[1] + 1))
    s2 = float(np.sum(resid ** 2)) / dof
    # curvature: var = 2 s^2 / SSR'' (SSR summed over the 3 components), inflated for autocorrelation
    sigma_curv = math.sqrt(2 * s2 / curv) * _eff_factor(resid) if curv > 0 else math.inf
    sigma_res = _resolution_sigma(xd, t_dut, t_ref, ref, vertex, gap, dt_dut, dt_ref)
    sigma = max(sigma_curv, sigma_jk, sigma_res)
    r2 = 1.0 - best_u
    est = OffsetEstimate(vertex, sigma, r2, int(valid.sum()), (float(lo), float(hi)), ratio, grid, unexpl,
                         sigma_curv, sigma_jk, model, sigma_res)
    if r2 < min_r2:
        raise AlignmentError(f"the data do not determine the clock offset: best linear fit explains only "
                             f"{r2:.1%} of the reference variance (static or unrelated field?)")
    if not sigma <= max_sigma_s:
        raise AlignmentError(f"the data do not determine the clock offset: uncertainty {sigma:.3g} s "
                             f"> {max_sigma_s} s")
    if ratio < ambiguity_ratio:
        other = float(grid[np.nanargmin(np.where(cand, unexpl, np.nan))])
        raise AlignmentError(f"clock offset ambiguous: a minimum {abs(other - vertex):.1f} s away fits almost as "
                             f"well (ratio {ratio:.2f} < {ambiguity_ratio}); give a prior and halfwidth")
    return est


# --------------------------------------------------------------------------- per-axis skew
def estimate_axis_skew(t_dut: np.ndarray, dut_uT: np.ndarray, t_ref: np.ndarray, ref_uT: np.ndarray,
                       offset_s: float, *, max_skew_s: float | None = None, max_gap_s: float | None = None,
                       min_r2: float = 0.9, max_sigma_s: float | None = None,
                       n_blocks: int = 20, temp_c: np.ndarray | None = None, temp_model: str = "auto",
                       min_temp_span_c: float = MIN_TEMP_SPAN_C, temp_order: int = TEMP_ORDER,
                       progress: Progress | None = None) -> list[ParamEstimate]:
    """Per-axis time skew of the DUT relative to ``offset_s`` (see module doc for the sign).

    For axis ``i`` the skew minimises the residual of ``dut_i ~ a . ref(t + skew - offset) + c``.
    An axis whose fit explains less than ``min_r2`` of its variance, or whose uncertainty exceeds
    ``max_sigma_s`` (default: one DUT sample period), is returned with ``determined=False``.
    The uncertainty is the larger of the curvature and the delete-one-block jackknife estimates.
    With a usable temperature (``temp_c``, as for :func:`estimate_clock_offset`) the fit is
    ``dut_i ~ a . ref + a' . (ref dT) + k dT + c``.
    """
    t_dut, dut, _, tcols, _ = _prepare_dut(t_dut, dut_uT, temp_c, temp_model, min_temp_span_c, temp_order)
    t_ref, ref = _clean(t_ref, ref_uT, "reference")
    dt_ref = float(np.median(np.diff(t_ref)))
    dt_dut = float(np.median(np.diff(t_dut)))
    gap = max_gap_s if max_gap_s is not None else max(4 * dt_ref, 1.0)
    half = max_skew_s if max_skew_s is not None else dt_dut
    sig_max = max_sigma_s if max_sigma_s is not None else dt_dut
    grid = np.arange(-half, half + 0.0025, 0.005)
    q = 0 if tcols is None else tcols.shape[1]
    width = 3 * (1 + q) + q + 8
    step = max(1, MAX_CHUNK_ELEMENTS // (grid.size * width))

    def reference_at(rows):
        return _interp_batch(t_ref, ref, t_dut[None, rows] + grid[:, None] - offset_s, gap)

    # rows valid for every candidate so that all costs use the same samples
    common = np.concatenate([reference_at(slice(r0, r0 + step))[1].all(axis=0)
                             for r0 in range(0, t_dut.size, step)])
    idx = np.flatnonzero(common)
    out: list[ParamEstimate] = []
    if idx.size < 10:
        return [ParamEstimate(math.nan, math.nan, False, "too little overlap") for _ in range(3)]

    def design(rs: slice):
        rows = idx[rs]
        y, _ = reference_at(rows)
        yv = _with_temp(y, None if tcols is None else tcols[rows])
        return yv, dut[rows], np.ones(yv.shape[:2], bool)

    # the design (reference columns) is shared by the three DUT axes: one pass gives every axis's
    # residual curve, all rows and each block deleted
    ssr_all, sst_all, loo = _block_ssr(design, grid.size, idx.size, n_blocks, width,
                                       None if progress is None else (progress, "per-axis skew"))
    tcols_c = None if tcols is None else tcols[idx]
    win = max(dt_ref / 2, 0.1)
    for i in range(3):
        ssr, sst = ssr_all[:, i], sst_all[:, i]
        vertex, curv, k = _vertex(grid, ssr, win)
        r2 = 1 - ssr[k] / sst[k]
        y_k, _ = interp_no_extrapolation(t_ref, ref, t_dut[idx] + grid[k] - offset_s, gap)
        yv_k = _with_temp(y_k, tcols_c)
        _, _, resid = linear_fit(yv_k, dut[idx, i:i + 1])
        s2 = float(np.sum(resid ** 2)) / max(1, resid.size - yv_k.shape[1] - 1)
        sigma_curv = math.sqrt(2 * s2 / curv) * _eff_factor(resid) if curv > 0 else math.inf
        jack = [_vertex(grid, s_b[:, i], win)[0] for s_b in loo]
        sigma = max(sigma_curv, _jackknife_sigma(jack))
        if r2 < min_r2:
            out.append(ParamEstimate(vertex, sigma, False, f"axis fit explains only {r2:.1%} of its variance "
                                                           "(axis not exercised)"))
        elif not sigma <= sig_max:
            out.append(ParamEstimate(vertex, sigma, False, f"uncertainty {sigma:.3g} s > {sig_max:.3g} s"))
        elif k in (0, grid.size - 1):
            out.append(ParamEstimate(vertex, sigma, False, f"minimum at the search edge (+-{half:.3g} s)"))
        else:
            out.append(ParamEstimate(vertex, sigma, True, ""))
    return out


# --------------------------------------------------------------------------- axis map
def estimate_axis_map(dut_uT: np.ndarray, ref_on_dut_uT: np.ndarray, *, min_t: float = 10.0,
                      min_dominance: float = 3.0, temp_c: np.ndarray | None = None, temp_model: str = "auto",
                      min_temp_span_c: float = MIN_TEMP_SPAN_C, temp_order: int = TEMP_ORDER) -> AxisMap:
    """Signed permutation relating time-aligned DUT and reference samples.

    Fits ``dut ~ G ref + c`` (with a usable temperature ``temp_c`` (degC per row) also the
    temperature terms ``ref dT``, ``dT`` (and ``dT^2`` ones for ``temp_order`` 2), so ``G`` is the
    gain at the mean temperature); the permutation maximises
    ``sum_i |G[i, perm[i]]| * std(ref_perm[i])`` (the field each reference axis contributes),
    the sign is that of ``G[i, perm[i]]``. DUT axis
    ``i`` is determined when its coefficient's t statistic is at least ``min_t`` and its
    contribution dominates the other reference axes in that row by ``min_dominance``.
    """
    dut = np.asarray(dut_uT, float)
    ref = np.asarray(ref_on_dut_uT, float)
    if dut.ndim != 2 or dut.shape[1:] != (3,) or ref.shape != dut.shape:
        raise AlignmentError(f"axis map: expected two (N,3) arrays, got {dut.shape} and {ref.shape}")
    ok = np.all(np.isfinite(dut), axis=1) & np.all(np.isfinite(ref), axis=1)
    temp = None
    if temp_c is not None:
        temp = np.asarray(temp_c, float).reshape(-1)
        if temp.size != ok.size:
            raise AlignmentError(f"axis map: temp_c has {temp.size} values for {ok.size} rows")
    tcols, temp, _ = _temperature_terms(np.arange(ok.size, dtype=float), temp, temp_model, min_temp_span_c,
                                        temp_order)
    if tcols is not None:
        ok &= np.isfinite(temp)
        tcols = tcols[ok]
    dut, ref = dut[ok], ref[ok]
    if dut.shape[0] < 10:
        raise AlignmentError(f"only {dut.shape[0]} paired samples: cannot estimate the axis map")
    X = np.column_stack([_with_temp(ref, tcols), np.ones(ref.shape[0])])
    coef = _lstsq(X, dut)
    G = coef[:3].T  # (dut axis, ref axis) at the mean temperature
    resid = dut - X @ coef
    dof = max(1, ref.shape[0] - X.shape[1])
    xtx_inv = np.linalg.pinv(X.T @ X)
    se = np.sqrt(np.outer(np.sum(resid ** 2, axis=0) / dof, np.diag(xtx_inv)[:3]))  # (dut, ref)
    contrib = np.abs(G) * ref.std(axis=0)[None, :]
    best, best_score = None, -1.0
    for perm in itertools.permutations(range(3)):
        score = sum(contrib[i, perm[i]] for i in range(3))
        if score > best_score:
            best, best_score = perm, score
    perm = tuple(int(p) for p in best)
    sign, dom, tst, det, why = [], [], [], [], []
    for i in range(3):
        j = perm[i]
        sign.append(1 if G[i, j] >= 0 else -1)
        others = [contrib[i, m] for m in range(3) if m != j]
        d = contrib[i, j] / max(max(others), 1e-300)
        t = abs(G[i, j]) / se[i, j] if se[i, j] > 0 else math.inf
        dom.append(float(d))
        tst.append(float(t))
        if t < min_t:
            det.append(False)
            why.append(f"coefficient t={t:.1f} < {min_t:g} (reference axis {AXES[j]} not exercised)")
        elif d < min_dominance:
            det.append(False)
            why.append(f"dominance {d:.2f} < {min_dominance:g} over other reference axes")
        else:
            det.append(True)
            why.append("")
    return AxisMap(perm, tuple(sign), tuple(dom), tuple(tst), tuple(det), tuple(why))


# --------------------------------------------------------------------------- all together
def align_streams(t_dut: np.ndarray, dut_uT: np.ndarray, t_ref: np.ndarray, ref_uT: np.ndarray, *,
                  prior_s: float | None = None, search_halfwidth_s: float | None = None,
                  max_gap_s: float | None = None, min_r2: float = 0.9, temp_c: np.ndarray | None = None,
                  temp_model: str = "auto", min_temp_span_c: float = MIN_TEMP_SPAN_C,
                  temp_order: int = TEMP_ORDER, progress: Progress | None = None) -> AlignmentReport:
    """Clock offset, per-axis skew and axis map of a DUT/reference pair, with uncertainties.

    Raises AlignmentError when the clock offset cannot be determined; skew and axis-map entries
    that the data do not determine are flagged in the report. ``temp_c`` (degC, one value per DUT
    row, NaN allowed) switches every regression to the temperature model when its span is
    material (see :func:`estimate_clock_offset`); ``model`` records which model was used.
    ``rmse_uT`` is the residual of the 12-parameter linear fit ``ref ~ A dut + b`` with the
    reference interpolated onto the DUT timestamps at the estimated offset; ``rmse_model_uT``
    that of the temperature model (None when it was not used).
    """
    tkw = {"temp_c": temp_c, "temp_model": temp_model, "min_temp_span_c": min_temp_span_c, "temp_order": temp_order,
           "progress": progress}
    off = estimate_clock_offset(t_dut, dut_uT, t_ref, ref_uT, prior_s=prior_s,
                                search_halfwidth_s=search_halfwidth_s, max_gap_s=max_gap_s, min_r2=min_r2, **tkw)
    skew = estimate_axis_skew(t_dut, dut_uT, t_ref, ref_uT, off.offset_s, max_gap_s=max_gap_s, min_r2=min_r2,
                              **tkw)
    td, dut, temp, tcols, model = _prepare_dut(t_dut, dut_uT, temp_c, temp_model, min_temp_span_c, temp_order)
    tr, ref = _clean(t_ref, ref_uT, "reference")
    gap = max_gap_s if max_gap_s is not None else max(4 * float(np.median(np.diff(tr))), 1.0)
    y, valid = interp_no_extrapolation(tr, ref, td - off.offset_s, gap)
    amap = estimate_axis_map(dut[valid], y[valid], temp_c=None if temp is None else temp[valid],
                             temp_model="off" if tcols is None else "on", temp_order=temp_order)
    rmse = linear_fit_rmse_uT(y[valid], dut[valid])
    rmse_model = None
    if tcols is not None:
        _, _, r = linear_fit(_with_temp(dut[valid], tcols[valid]), y[valid])
        rmse_model = _rmse_dict(r)
    notes = []
    if prior_s is not None:
        notes.append(f"estimated offset differs from the prior {prior_s:.3f} s by {off.offset_s - prior_s:+.3f} s")
    return AlignmentReport(off, skew, amap, rmse, notes, model, rmse_model)


# --------------------------------------------------------------------------- applying an alignment
def aligned_session(session, report: AlignmentReport, *, correct_skew: bool = False,
                    max_gap_s: float | None = None, gaps: str = "nan"):
    """Pair a raw bench session (interleaved DUT and reference rows) using ``report``.

    Output rows are the DUT rows; the reference is interpolated at ``t - offset_s`` (never
    extrapolated, never across a gap longer than ``max_gap_s``; such rows get NaN and flag bit NO_REF,
    or are dropped with ``gaps="drop"``). With ``correct_skew`` each DUT axis whose skew is
    determined is re-sampled at ``t - skew_i`` (interpolating the DUT stream itself). Temperature,
    session id and currents come from the DUT rows. Metadata records what was applied.
    """
    from magstack.data.session import Session

    if gaps not in ("nan", "drop"):
        raise AlignmentError(f"gaps must be 'nan' or 'drop', got {gaps!r}")
    streams = split_streams(session)
    d = streams.dut_rows
    if d.sum() < 2 or streams.ref_rows.sum() < 2:
        raise AlignmentError(f"session has {int(d.sum())} DUT and {int(streams.ref_rows.sum())} reference rows: "
                             "nothing to pair")
    streams.require_increasing()   # names file and line of the first out-of-order row
    t_dut, dut = streams.t_dut_s, streams.dut_uT.copy()
    t_ref, ref = streams.t_ref_s, streams.ref_uT
    gap = max_gap_s if max_gap_s is not None else max(4 * float(np.median(np.diff(t_ref))), 1.0)
    off = report.offset.offset_s
    ref_on, ok = interp_no_extrapolation(t_ref + off, ref, t_dut, gap)
    applied = [f"clock offset {off:+.4f} +- {report.offset.sigma_s:.4f} s added to reference time",
               "reference linearly interpolated onto DUT timestamps"]
    if correct_skew:
        dut_gap = max(4 * float(np.median(np.diff(t_dut))), 1.0)
        for i, e in enumerate(report.skew_s):
            if e.determined:
                col, ok_i = interp_no_extrapolation(t_dut, dut[:, i], t_dut - e.value, dut_gap)
                dut[:, i] = col
                ok &= ok_i
                applied.append(f"dut_{AXES[i]} re-sampled for skew {e.value:+.4f} s")
    flag = np.where(ok, 0, FLAG["NO_REF"].value).astype(np.int64)
    meta = dict(session.metadata)
    meta["alignment_applied"] = "; ".join(applied)
    meta["axis_map_estimated"] = report.axis_map.describe()
    meta["gap_rows"] = str(int((flag != 0).sum()))
    meta["gap_policy"] = gaps
    out = Session(t_dut, ref_on, dut, session.temp_c[d], session.session[d],
                  {k: v[d] for k, v in session.currents_A.items()}, meta, flag,
                  extra={k: v[d] for k, v in session.extra.items()})
    return out.select(flag == 0) if gaps == "drop" else out
