"""Effects that are not linear in their parameters, estimated as such.

* ``time_skew`` (catalogue: DUT axis j reads the field at ``t + dt_j``): a per-axis delay search.
  The DUT axis j is re-sampled at ``t - dt_j`` (linear interpolation inside contiguous runs of a
  session) and the base model is refitted; ``dt_j`` minimises the training residual, coordinate by
  coordinate over a grid (two passes, parabolic refinement). Used in mode (a) with a fitted gain:
  there the re-sampled reading replaces the reading in the design, so the DUT's own sample noise
  never enters both sides of the fit. Elsewhere the catalogue's first-order calibration term
  (``dB/dt`` columns by central differences, which exclude the row's own sample) is used.
* ``hysteresis`` (catalogue: the offset shifts by a remanent amount signed by the last excursion
  beyond a threshold, not cleared by power cycles): per axis a state column in {-1, +1} that
  follows the sign of the last DUT reading with ``|B_j| >= threshold``; the threshold is chosen
  on the training rows among high quantiles of ``|B_j|``. The excursion history is built from
  every row with a DUT reading (also rows whose reference is missing or saturated: the excursion
  that sets the state is often exactly where the reference saturates) and then restricted to the
  rows tested. The state before an axis' first excursion is unknown (+ or -, never 0): both signs
  are tried per axis and the one with the lower training SSE is kept (one discrete parameter).
  A per-session offset is constant within a session, the hysteresis state changes inside a session
  at an excursion and persists across sessions: the two are told apart by those rows (and declared
  confounded when they coincide).
"""
from __future__ import annotations

import numpy as np
import scipy.signal

#: Delay grid half-width, in units of the median row spacing, and number of grid points.
DELAY_HALF_WIDTH_ROWS = 1.25
DELAY_GRID_POINTS = 15
#: Quantiles of |B_j| tried as the hysteresis threshold.
HYSTERESIS_QUANTILES = (0.90, 0.95, 0.98, 0.99, 0.995)
#: Fractions of the top quantile's level also tried (below an excursion plateau).
HYSTERESIS_TOP_FRACTIONS = (0.7, 0.9)
#: A threshold must exceed this multiple of the median |B_j| (an "excursion", not ordinary field).
HYSTERESIS_MIN_RATIO = 1.5
#: Rows needed in each of at least two states for a hysteresis column to be testable.
HYSTERESIS_MIN_ROWS = 20


def runs(t_s: np.ndarray, session: np.ndarray, gap_factor: float = 3.0) -> np.ndarray:
    """Contiguous-run id per row: breaks at a session change, a non-increasing time or a gap above
    ``gap_factor`` times the median spacing."""
    dt = np.diff(t_s)
    pos = dt[dt > 0]
    med = float(np.median(pos)) if pos.size else 1.0
    brk = (dt <= 0) | (dt > gap_factor * med) | (session[1:] != session[:-1])
    return np.concatenate([[0], np.cumsum(brk)])


def shift_axes(p_uT: np.ndarray, t_s: np.ndarray, run: np.ndarray, delay_s) -> np.ndarray:
    """Copy of ``p_uT`` with axis j re-sampled at ``t - delay_s[j]`` inside each run (ends held).

    One interpolation per axis over a composite time axis on which runs are far apart."""
    out = p_uT.copy()
    d = np.asarray(delay_s, dtype=float)
    if not np.any(d):
        return out
    t = t_s - t_s.min()
    big = 2.0 * (float(np.ptp(t)) + 1.0 + float(np.max(np.abs(d))))
    T = t + run * big
    first = np.r_[0, np.flatnonzero(np.diff(run)) + 1]
    lo = T[first]
    hi = np.r_[T[first[1:] - 1], T[-1]]
    k = np.repeat(np.arange(first.size), np.diff(np.r_[first, run.size]))
    for j in range(3):
        if d[j] != 0:
            q = np.clip(T - d[j], lo[k], hi[k])
            out[:, j] = np.interp(q, T, p_uT[:, j])
    return out


def delay_grid(t_s: np.ndarray) -> np.ndarray:
    dt = np.diff(t_s)
    med = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    half = DELAY_HALF_WIDTH_ROWS * med
    return np.linspace(-half, half, DELAY_GRID_POINTS)


def search_delays(sse_of, grid: np.ndarray, passes: int = 2) -> np.ndarray:
    """Coordinate search of three delays minimising ``sse_of(delays (3,)) -> float``."""
    d = np.zeros(3)
    for _ in range(passes):
        for j in range(3):
            vals = []
            for g in grid:
                trial = d.copy()
                trial[j] = g
                vals.append(sse_of(trial))
            d[j] = parabola_minimum(grid, np.array(vals))
    return d


def parabola_minimum(grid: np.ndarray, vals: np.ndarray) -> float:
    """The evenly spaced ``grid``'s point with the lowest value, refined by the parabola through it and its
    neighbours (not refined at an end of the grid or where the parabola does not open upwards)."""
    k = int(np.argmin(vals))
    best = float(grid[k])
    if 0 < k < grid.size - 1:
        y0, y1, y2 = vals[k - 1], vals[k], vals[k + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            best = float(grid[k] + 0.5 * (y0 - y2) / den * (grid[1] - grid[0]))
    return best


#: Thermal-lag time constants tried: geometric grid from LAG_MIN_ROWS row spacings (at least LAG_MIN_S)
#: to LAG_MAX_FRACTION of the longest session (at most LAG_MAX_S).
LAG_GRID_POINTS = 12
LAG_MIN_S = 5.0
LAG_MIN_ROWS = 4
LAG_MAX_FRACTION = 0.5
LAG_MAX_S = 3600.0
#: Points of the fine grid between the neighbours of the best coarse time constant.
LAG_FINE_POINTS = 15


def lag_grid(t_s: np.ndarray, session: np.ndarray) -> np.ndarray:
    """Time constants (s) the thermal-lag search tries (geometric)."""
    dt = np.diff(t_s)
    pos = dt[dt > 0]
    lo = max(LAG_MIN_S, LAG_MIN_ROWS * (float(np.median(pos)) if pos.size else 1.0))
    span = max(float(np.ptp(t_s[session == k])) for k in np.unique(session))
    hi = min(LAG_MAX_S, LAG_MAX_FRACTION * span)
    if hi <= lo:
        return np.array([lo])
    return np.geomspace(lo, hi, LAG_GRID_POINTS)


def refine_log_minimum(grid: np.ndarray, vals: np.ndarray) -> float:
    """The grid point with the lowest value, refined by a parabola in log(grid) through it and its
    neighbours (kept inside them)."""
    k = int(np.argmin(vals))
    if not 0 < k < grid.size - 1:
        return float(grid[k])
    x = np.log(grid[k - 1:k + 2])
    y0, y1, y2 = vals[k - 1:k + 2]
    den = (y0 - 2 * y1 + y2)
    if not den > 0:
        return float(grid[k])
    h = x[1] - x[0]
    return float(np.exp(np.clip(x[1] + 0.5 * (y0 - y2) / den * h, x[0], x[2])))


def lagged_temperature(t_s: np.ndarray, temp_c: np.ndarray, session: np.ndarray, tau_s: float,
                       groups: list[np.ndarray] | None = None) -> np.ndarray:
    """First-order lag (time constant ``tau_s``) of the temperature: ``dT_die/dt = (T - T_die)/tau``. The die
    does not cool at a power cycle: the rows are taken in time order across sessions, in stretches split
    where the record stops for more than LAG_EQUILIBRIUM x tau (the die has then caught up; each stretch
    starts in equilibrium). Computed exactly for a temperature linear between grid points on a uniform grid
    of the median spacing (scipy.signal.lfilter), read back at the rows; gaps (left-out rows, dropouts,
    short pauses) are bridged by linear interpolation of the temperature. Sessions that overlap in time
    (separate recordings) are filtered one by one. ``groups``: :func:`lag_groups` of these rows, if known."""
    t_all = np.asarray(t_s, dtype=float)
    out = np.array(temp_c, dtype=float, copy=True)
    if tau_s <= 0:
        return out
    for g in lag_groups(t_all, session) if groups is None else groups:
        cut = np.flatnonzero(np.diff(t_all[g]) > LAG_EQUILIBRIUM * tau_s) + 1
        for m in np.split(g, cut):
            _lag_stretch(t_all, out, m, tau_s)
    return out


def lag_groups(t_s: np.ndarray, session: np.ndarray) -> list[np.ndarray]:
    """The row groups :func:`lagged_temperature` filters, each in time order: all rows, or each session's when
    sessions overlap in time. Independent of the time constant (a search over many passes them in)."""
    t_all = np.asarray(t_s, dtype=float)
    order = np.argsort(t_all, kind="stable")
    ids = np.unique(session)
    spans = [(t_all[session == k].min(), t_all[session == k].max()) for k in ids]
    overlap = any(a[1] > b[0] and b[1] > a[0] for i, a in enumerate(spans) for b in spans[i + 1:])
    groups = [np.flatnonzero(session == k) for k in ids] if overlap else [order]
    return [g[np.argsort(t_all[g], kind="stable")] for g in groups]


#: A pause longer than this many time constants restarts the lag in equilibrium.
LAG_EQUILIBRIUM = 10.0


def _lag_stretch(t_all: np.ndarray, out: np.ndarray, m: np.ndarray, tau_s: float) -> None:
    t, x = t_all[m], out[m]
    ok = np.isfinite(x)
    if ok.sum() < 2:
        return
    dt = np.diff(t)
    h = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    grid = t[0] + h * np.arange(int(np.ceil((t[-1] - t[0]) / h)) + 1)
    u = np.interp(grid, t[ok], x[ok])
    a = np.exp(-h / tau_s)
    # exact response to a ramp between grid points: y_k = a y_(k-1) + b0 u_k + b1 u_(k-1), from equilibrium
    c = tau_s / h * (1 - a)
    b0, b1 = 1 - c, c - a
    y, _ = scipy.signal.lfilter([b0, b1], [1.0, -a], u, zi=[u[0] * (1 - b0)])
    out[m] = np.interp(t, grid, y)


def hysteresis_state(b_uT: np.ndarray, threshold_uT: np.ndarray, initial=None) -> np.ndarray:
    """(N,3) sign (-1/+1) of the last reading with ``|B_j| >= threshold_j``; before an axis' first such
    reading the state is ``initial[j]`` (the remanence the part had when the file starts: a magnetised
    part is + or -, never 0, but which one is unknown; the search tries both, see ``search``).
    ``initial`` None: 0 there."""
    n = b_uT.shape[0]
    out = np.zeros((n, 3))
    init = np.zeros(3) if initial is None else np.asarray(initial, dtype=float)
    ar = np.arange(n)
    for j in range(3):
        thr = threshold_uT[j]
        if not np.isfinite(thr):
            continue
        e = np.where(np.abs(b_uT[:, j]) >= thr, np.sign(b_uT[:, j]), 0.0)
        last = np.maximum.accumulate(np.where(e != 0, ar, -1))
        out[:, j] = np.where(last >= 0, e[np.maximum(last, 0)], init[j])
    return out


def before_first_excursion(hist_uT: np.ndarray, idx: np.ndarray, threshold_uT: np.ndarray,
                           session: np.ndarray) -> np.ndarray:
    """(N,) bool for the tested rows ``idx`` (into the excursion history ``hist_uT``, sorted by session then
    time): the row comes before the first excursion (|B_j| >= threshold_j on any axis) of its session."""
    exc = np.any(np.abs(hist_uT) >= np.where(np.isfinite(threshold_uT), threshold_uT, np.inf), axis=1)
    # excursions counted in the history, mapped to the tested rows by position: a tested row is "before"
    # when no history row of its session up to its own position was an excursion
    cum = np.cumsum(exc)
    out = np.zeros(idx.size, bool)
    for k in np.unique(session):
        m = np.flatnonzero(session == k)
        first = idx[m[0]]
        # history rows of this session start at or before the session's first tested row
        base = cum[first - 1] if first > 0 else 0
        out[m] = (cum[idx[m]] - base) == 0
    return out


def hysteresis_thresholds(b_uT: np.ndarray, rows: np.ndarray | None = None) -> list[list[float]]:
    """Candidate thresholds per axis (uT) whose state column has >= 2 states with enough rows.

    ``b_uT`` is the excursion history (every row with a DUT reading, also where the reference is
    missing or saturated); ``rows`` (indices into it) are the rows the diagnosis tests on, where the
    states must have enough rows (None: all)."""
    rows = np.arange(b_uT.shape[0]) if rows is None else rows
    out = []
    for j in range(3):
        a = np.abs(b_uT[:, j])
        med = float(np.median(a))
        cands = []
        top = float(np.quantile(a, HYSTERESIS_QUANTILES[-1]))
        # quantiles, plus levels below the top plateau: a quantile inside an excursion's plateau can miss the
        # excursion of the other sign (cross-axis terms make +- plateaus differ by a few uT)
        levels = sorted({float(np.quantile(a, q)) for q in HYSTERESIS_QUANTILES} |
                        {f * top for f in HYSTERESIS_TOP_FRACTIONS})
        for thr in levels:
            if thr <= HYSTERESIS_MIN_RATIO * med or thr <= 0 or any(abs(thr - c) < 1e-9 for c in cands):
                continue
            st = hysteresis_state(b_uT[:, [j, j, j]], np.array([thr, np.inf, np.inf]))[rows, 0]
            counts = [int(np.sum(st == v)) for v in (-1.0, 0.0, 1.0)]
            if sum(c >= HYSTERESIS_MIN_ROWS for c in counts) >= 2:
                cands.append(thr)
        out.append(cands)
    return out


def higher_order_temperature_gain(p_uT: np.ndarray, temp_c: np.ndarray, t0_c: float):
    """On-axis columns ``B_i dT^2``, ``B_i dT^3`` (N,6): the catalogue's forward ``temperature_gain``
    (B <- (I + K_S dT) B) seen from the calibration side is ``(I + K_S dT)^-1 = I - K_S dT + K_S^2 dT^2
    - ...``; over a +-25 degC cycle at -2700 ppm/degC the second-order part is ~0.5 % of the field
    (0.7 uT at 150 uT), the third ~0.05 %, both above bench noise."""
    dT = np.asarray(temp_c, dtype=float) - t0_c
    return np.hstack([p_uT * (dT ** 2)[:, None], p_uT * (dT ** 3)[:, None]])


def _d2(x: np.ndarray, run: np.ndarray) -> np.ndarray:
    d2 = np.zeros_like(x)
    same = (run[2:] == run[:-2]) & (run[1:-1] == run[2:])
    d2[1:-1] = np.where(same[:, None], x[2:] - 2 * x[1:-1] + x[:-2], 0.0)
    return d2


def _mad(x: np.ndarray) -> np.ndarray:
    return 1.4826 * np.median(np.abs(x - np.median(x, axis=0)), axis=0)


def bend_rows(ref_uT: np.ndarray, t_s: np.ndarray, session: np.ndarray, factor: float,
              dut_uT: np.ndarray | None = None) -> np.ndarray:
    """Rows where the reference field bends sharply (step corners), and their neighbours.

    A row is flagged when the reference's second difference on some axis exceeds both ``factor``
    times its robust (1.4826 MAD) level and 8 times the DUT's white-noise level on that axis
    (``1.4826 MAD`` of the DUT's second differences / sqrt 6): linear interpolation across a bend
    errs by up to |second difference| / 8, so below that the pairing error hides under the DUT noise.
    There no interpolation pairs two sample streams to a fraction of a sample, so time skew and
    pairing error cannot be told apart."""
    run = runs(t_s, session)
    d2 = _d2(ref_uT, run)
    scale = np.maximum(_mad(d2[1:-1]), 1e-6)
    thr = factor * scale
    if dut_uT is not None:
        ok = np.all(np.isfinite(dut_uT), axis=1)
        sig = _mad(_d2(np.where(ok[:, None], dut_uT, 0.0), run)[1:-1]) / np.sqrt(6.0)
        thr = np.maximum(thr, 8.0 * sig)
    big = np.any(np.abs(d2) > thr, axis=1)
    out = big.copy()
    out[1:] |= big[:-1]
    out[:-1] |= big[1:]
    return out


def second_order_cross_axis(p_uT: np.ndarray) -> np.ndarray:
    """Columns ``B_i B_c^2`` for every output axis i and cross axis c != i (N,6; order: x<-y, x<-z, y<-x,
    y<-z, z<-x, z<-y): the catalogue's cross-axis effect with set/reset averaging leaves
    ``B_i H0^2/(H0^2 - B_c^2) ~ B_i (1 + B_c^2/H0^2)``, which the first-order products B_j B_k miss."""
    cols = []
    for i in range(3):
        for c in range(3):
            if c != i:
                cols.append(p_uT[:, i] * p_uT[:, c] ** 2)
    return np.column_stack(cols)
