"""The thermal-lag candidate: temperature terms on the die temperature, with the die's starting temperature fitted
where the record restarts.

The die follows the board thermistor through a first-order lag, ``dT_die/dt = (T_board - T_die)/tau``
(:func:`nonlinear.lagged_temperature`: continuous across short pauses, bridged by interpolation). Where a session
starts, or the record pauses for more than RESTART_GAP_TAU time constants, the die's temperature is not known: a
powered-down bench cools (or the generator restarts the lag from equilibrium), a bench left on keeps its heat.
Carried across such a pause, the die's temperature is wrong for minutes after each start (90 s pauses, a 260 s
lag: after/floor 4.6-6.2 and a time constant of 46 s); so each such stretch ``r`` gets its own starting offset
``delta_r`` (degC):

    T_die(t) = T_lag(t) + delta_r exp(-(t - t_r) / tau)       (t in stretch r, starting at t_r)

exact for a linear first-order lag (two solutions with different starting values differ by that decaying term).
The candidate's columns ``L(T_die)`` (the temperature terms, LAG_TERMS) are linear in ``T_die`` forward, so the
model is bilinear: ``Y = X_b th_b + (F_0 + sum_r delta_r D_r) th_L`` with ``F_0 = L(T_lag)`` and ``D_r`` the
change of ``L`` per degC of starting offset on stretch r. It is fitted in normal-equation space (:func:`bilinear_fit`):
per training set the products of ``[X_b F_0 D Y]`` over each stretch's rows are formed once; ``th`` given ``delta``
is one small solve, and ``delta`` moves by Gauss-Newton steps of the profiled SSE (variable projection: ``th``
eliminated exactly), Levenberg-Marquardt damped, with a weak ridge (prior sd :data:`DELTA_SD_MIN_C` or the
temperature span) and bounds (:func:`design`: between carrying the die across the pause and restarting it at the
board's temperature) held by projection. ``delta = 0`` is the continuous lag, so the model nests it.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from magstack.ground.diagnose import nonlinear as nl
from magstack.ground.diagnose.gap import Block, Gap, fold_products, solve_normal_batch

#: Calibration terms evaluated on the lagged temperature by the thermal-lag candidate.
LAG_TERMS = ("temperature_gain", "temperature_offset")
#: Floats of lagged temperature series a gap keeps (:func:`lagged_temperature`).
LAG_CACHE_FLOATS = 500_000
#: A pause inside a session longer than this many time constants restarts the die's temperature (fitted).
RESTART_GAP_TAU = 3.0
#: Prior sd of a starting offset: the temperature span, at least this (degC).
DELTA_SD_MIN_C = 5.0
#: A starting offset lies between 0 (the die carried across the pause) and the board's temperature at the restart
#: less the carried value, widened by this fraction of that difference and RESTART_MARGIN_C (degC).
RESTART_MARGIN = 0.1
RESTART_MARGIN_C = 0.2
#: Gauss-Newton rounds in the starting offsets at most, stopping when no offset moves by more than GN_TOL_C degC
#: or the objective falls by less than GN_REL_TOL of itself (far below the differences between time constants).
GN_ROUNDS = 10
GN_TOL_C = 1e-3
GN_REL_TOL = 1e-7


def lagged_temperature(gap: Gap, tau_s: float) -> np.ndarray:
    """``nonlinear.lagged_temperature`` of the gap's session (read-only), kept on the gap per time constant
    while the kept series hold at most LAG_CACHE_FLOATS floats: the search, the per-fold fits and the
    surrogate test ask for the same grid of time constants (a short session also keeps the rows' time order,
    :func:`nonlinear.lag_groups`)."""
    cache = gap.__dict__.setdefault("_lag_temp", {})
    key = float(tau_s)
    if key not in cache:
        s = gap.session
        groups = gap.__dict__.get("_lag_groups")      # the rows' time order: kept for a short session too
        if groups is None:
            groups = nl.lag_groups(s.t_s, s.session)
            if gap.n <= LAG_CACHE_FLOATS:
                gap.__dict__["_lag_groups"] = groups
        temp = nl.lagged_temperature(s.t_s, s.temp_c, s.session, key, groups)
        temp.setflags(write=False)
        if (len(cache) + 1) * gap.n > LAG_CACHE_FLOATS:
            return temp
        cache[key] = temp
    return cache[key]


def lag_block(gap: Gap, tau_s: float, rows: np.ndarray | None = None, temp: np.ndarray | None = None,
              temp_on_rows: bool = False) -> Block:
    """The thermal-lag candidate's columns: the temperature terms (LAG_TERMS, plus a constant when the base
    has none) evaluated on the temperature lagged by ``tau_s`` (or on ``temp``, a die temperature of the gap's
    rows, or with ``temp_on_rows`` of ``rows`` only, in their order). ``rows``: the columns on those rows only
    (the lag is filtered on the whole series; the terms are row by row). Forward, the columns (``1``,
    ``B_j dT``, ``dT``) are formed directly (:func:`_forward_columns`: the calibration model's columns without
    its full design, memory of the block alone)."""
    from magstack.ground.diagnose.search import temperature_gain_higher_order
    temp = lagged_temperature(gap, tau_s) if temp is None else np.asarray(temp, dtype=float)
    if rows is not None:
        gap, temp = gap.rows_view(rows), (temp if temp_on_rows else temp[rows])
    terms = LAG_TERMS if "offset" in gap.base_terms else ("offset",) + LAG_TERMS
    if gap.forward:
        X, cm, keep = _forward_columns(gap, terms, np.asarray(temp, dtype=float) - gap.t0_c)
        blk = Block(X, cm.axis_mask()[:, keep], [[cm.param_name(i, c) for c in keep] for i in range(3)],
                    [cm.columns[c].unit for c in keep])
    else:
        lagged = dataclasses.replace(gap.session)
        lagged.temp_c = temp
        blk = dataclasses.replace(gap, session=lagged).term_design(terms)
        blk = Block.join([blk, temperature_gain_higher_order(gap, lagged.temp_c)], gap.n)
    names = [[n + "@lag" for n in row] for row in blk.names]
    return Block(blk.X, blk.mask, names, blk.units)


def _forward_columns(gap: Gap, terms, factor: np.ndarray):
    """(X (N,k), the calibration model, its column indices): the columns of ``terms`` (offset, temperature_gain,
    temperature_offset) with ``dT`` replaced by ``factor`` (N,): ``1``, ``B_j x factor``, ``factor``; in the
    calibration model's column order (equal to ``CalModel.design``'s, test)."""
    cm, keep = gap.term_model(terms)
    b = gap.predictor_uT
    X = np.empty((gap.n, len(keep)))
    for k, c in enumerate(keep):
        col = cm.columns[c]
        if col.term == "offset":
            X[:, k] = 1.0
        elif col.term == "temperature_gain":
            np.multiply(b[:, col.index], factor, out=X[:, k])
        elif col.term == "temperature_offset":
            X[:, k] = factor
        else:                                   # a term this fast path does not know: the model's own design
            raise ValueError(f"no forward lag column for term {col.term!r}")
    return X, cm, keep


def restarts(gap: Gap, tau_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stretch id per row (N,) int, the starting transient ``exp(-(t - t_r)/tau)`` per row (N,), the first row of
    each stretch (R,)): a stretch starts at each session's first row (time order) and after a pause longer than
    RESTART_GAP_TAU x ``tau_s`` inside a session."""
    s = gap.session
    t = np.asarray(s.t_s, dtype=float)
    order = np.lexsort((t, s.session))
    ts, ss = t[order], np.asarray(s.session)[order]
    new = np.r_[True, (ss[1:] != ss[:-1]) | (np.diff(ts) > RESTART_GAP_TAU * tau_s)]
    sid_sorted = np.cumsum(new) - 1
    first_sorted = np.flatnonzero(new)
    sid = np.empty(t.size, dtype=np.int64)
    sid[order] = sid_sorted
    e = np.exp(-(t - ts[first_sorted][sid]) / tau_s)
    return sid, e, order[first_sorted]


def transient_columns(gap: Gap, tau_s: float, lag: Block, rows: np.ndarray | None = None) -> np.ndarray:
    """(N,q) ``D``: the change of the lag block's columns per degC of starting offset, on each row of its own
    stretch: forward the columns are linear in the temperature, so ``D`` is the block with ``dT`` replaced by the
    transient ``exp(-(t - t_r)/tau)`` (the constant's column 0); the calibration direction's higher orders are
    linearised by a 1 degC difference."""
    _, e, _ = restarts(gap, tau_s)
    if gap.forward:
        g = gap if rows is None else gap.rows_view(rows)
        terms = LAG_TERMS if "offset" in gap.base_terms else ("offset",) + LAG_TERMS
        X, cm, keep = _forward_columns(g, terms, e if rows is None else e[rows])
        for k, c in enumerate(keep):
            if cm.columns[c].term == "offset":
                X[:, k] = 0.0
        return X
    temp = lagged_temperature(gap, tau_s)
    moved = lag_block(gap, tau_s, rows, temp=temp + e)
    return moved.X - lag.X


def delta_sd(gap: Gap) -> float:
    """Prior sd and bound of a starting offset, degC (DELTA_SD_MIN_C or the temperature span)."""
    t = np.asarray(gap.session.temp_c, dtype=float)
    t = t[np.isfinite(t)]
    return max(DELTA_SD_MIN_C, float(np.ptp(t)) if t.size else 0.0)


@dataclasses.dataclass
class LagFit:
    """Alternating least squares of one or more training sets (K of them) at one time constant."""

    theta: np.ndarray          # (K, 3, p + q): base then lag coefficients per output axis
    delta: np.ndarray          # (K, R) starting offsets, degC
    sse: np.ndarray            # (K,) training SSE


def stretch_products(base: Block, lag: Block, D: np.ndarray, Y: np.ndarray, code: np.ndarray, n_sets: int,
                     sid: np.ndarray, R: int) -> np.ndarray:
    """(n_sets, R, m, m) products of ``Z = [X_b F_0 D Y]`` over the rows of each (row set ``code``, stretch)
    pair (m = p + 2q + 3), in row chunks (gap.fold_products)."""
    cols = [base.X, lag.X, D, Y]
    S = fold_products(cols, cols, code * R + sid, n_sets * R)
    return S.reshape(n_sets, R, S.shape[1], S.shape[2])


def bilinear_fit(S: np.ndarray, mask: np.ndarray, p: int, q: int, n_rows: np.ndarray, sd_c: float,
                 delta0: np.ndarray | None = None, lo: np.ndarray | None = None,
                 hi: np.ndarray | None = None) -> LagFit:
    """Bilinear least squares (module docs) of K training sets from their stretch products ``S`` (K, R, m, m);
    ``mask`` (3, p + q) the columns each output axis uses (base then lag block), ``n_rows`` (K,) rows per set,
    ``sd_c`` the starting offsets' prior sd; ``lo``, ``hi`` (R,) their bounds (default +-sd_c); ``delta0`` (K, R)
    where they start (0, clipped into the bounds)."""
    K, R = S.shape[0], S.shape[1]
    b, f, d, y = slice(0, p), slice(p, p + q), slice(p + q, p + 2 * q), slice(p + 2 * q, p + 2 * q + 3)
    T = S.sum(axis=1)                                                  # (K, m, m): every stretch
    n = p + q
    G0 = np.zeros((K, n, n))
    G0[:, :p, :p], G0[:, :p, p:], G0[:, p:, p:] = T[:, b, b], T[:, b, f], T[:, f, f]
    G0[:, p:, :p] = np.swapaxes(G0[:, :p, p:], 1, 2)
    C0 = np.concatenate([T[:, b, y], T[:, f, y]], axis=1)             # (K, n, 3)
    G1 = np.zeros((K, R, n, n))                                        # the part linear in delta_r
    G1[:, :, :p, p:] = S[:, :, b, d]
    G1[:, :, p:, p:] = S[:, :, f, d] + np.swapaxes(S[:, :, f, d], 2, 3)
    G1[:, :, p:, :p] = np.swapaxes(G1[:, :, :p, p:], 2, 3)
    G2 = np.zeros((K, R, n, n))                                        # ... and quadratic
    G2[:, :, p:, p:] = S[:, :, d, d]
    C1 = np.zeros((K, R, n, 3))
    C1[:, :, p:] = S[:, :, d, y]
    yy = np.einsum("kii->k", T[:, y, y])
    Sdb, Sdf, Sdd, Sdy = S[:, :, d, b], S[:, :, d, f], S[:, :, d, d], S[:, :, d, y]
    lo = np.full(R, -sd_c) if lo is None else np.asarray(lo, dtype=float)
    hi = np.full(R, sd_c) if hi is None else np.asarray(hi, dtype=float)
    delta = np.clip(np.zeros((K, R)) if delta0 is None else np.asarray(delta0, dtype=float), lo, hi)
    groups: dict[bytes, list[int]] = {}
    for i in range(3):
        groups.setdefault(mask[i].tobytes(), []).append(i)
    theta, sse, G = _solve_theta(delta, G0, G1, G2, C0, C1, yy, mask, groups)
    mu = np.zeros(K)                                          # Levenberg-Marquardt damping, raised after a failed step
    for _ in range(GN_ROUNDS):
        tb, tl = theta[:, :, :p], theta[:, :, p:]                       # (K, 3, p), (K, 3, q)
        # the profiled SSE's gradient and Gauss-Newton matrix in delta (variable projection, Kaufman): with
        # u_ri = D_r th_L,i on stretch r, g_r = sum_i u_ri . residual_i and H = U^T (I - P) U, P the projection
        # on the design's columns (theta eliminated exactly at every step)
        den = np.einsum("kia,krab,kib->kr", tl, Sdd, tl)
        g = _delta_numerator(tl, tb, Sdy, Sdb, Sdf) - delta * den
        cb = np.einsum("krba,kia->kirb", S[:, :, b, d], tl)                # (K, 3, R, p): X_b^T u_ri
        cf = (np.einsum("krfa,kia->kirf", S[:, :, f, d], tl)
              + delta[:, None, :, None] * np.einsum("krab,kib->kira", Sdd, tl))   # (K, 3, R, q): F(delta)^T u_ri
        c = np.concatenate([cb, cf], axis=3)                               # (K, 3, R, n)
        H = np.zeros((K, R, R))
        H[:, np.arange(R), np.arange(R)] = den
        for axes in groups.values():
            cols = np.flatnonzero(mask[axes[0]])
            if cols.size:
                ci = np.concatenate([c[:, i][:, :, cols] for i in axes], axis=1)      # (K, R x axes, c)
                W = solve_normal_batch(G[:, cols][:, :, cols], np.swapaxes(ci, 1, 2))
                P = np.einsum("kac,kcb->kab", ci, W)
                for m in range(len(axes)):
                    H -= P[:, m * R:(m + 1) * R, m * R:(m + 1) * R]
        lam = np.maximum(sse, 0.0) / np.maximum(3.0 * n_rows, 1.0) / sd_c ** 2   # the ridge: residual variance / sd^2
        obj = sse + lam * np.sum(delta ** 2, axis=1)
        A = H + (lam + mu)[:, None, None] * np.eye(R)
        rhs = g - lam[:, None] * delta                      # half the objective's descent direction
        # offsets at a bound that the descent direction pushes outwards are held there (projected Newton)
        held = ((delta <= lo + 1e-12) & (rhs < 0)) | ((delta >= hi - 1e-12) & (rhs > 0))
        A = np.where(held[:, :, None] | held[:, None, :], 0.0, A)
        A[:, np.arange(R), np.arange(R)] = np.where(held, 1.0, A[:, np.arange(R), np.arange(R)])
        step = solve_normal_batch(A, np.where(held, 0.0, rhs)[:, :, None])[:, :, 0]
        trial = np.clip(delta + step, lo, hi)
        th_t, sse_t, G_t = _solve_theta(trial, G0, G1, G2, C0, C1, yy, mask, groups)
        obj_t = sse_t + lam * np.sum(trial ** 2, axis=1)
        ok = obj_t <= obj
        moved = np.max(np.abs(trial - delta), axis=1) if R else np.zeros(K)
        delta = np.where(ok[:, None], trial, delta)
        theta = np.where(ok[:, None, None], th_t, theta)
        sse = np.where(ok, sse_t, sse)
        G = np.where(ok[:, None, None], G_t, G)
        mu = np.where(ok, 0.1 * mu, np.maximum(10.0 * mu, 1e-3 * np.maximum(np.einsum("krr->k", H) / max(R, 1), 1e-12)))
        if np.all((ok & (moved < GN_TOL_C)) | (obj - np.minimum(obj_t, obj) <= GN_REL_TOL * np.abs(obj))):
            break
    return LagFit(theta, delta, sse)


def _solve_theta(delta, G0, G1, G2, C0, C1, yy, mask, groups):
    """(theta (K, 3, n), training SSE (K,), the design's Gram matrix (K, n, n)) of the linear step at starting
    offsets ``delta`` (K, R)."""
    G = G0 + np.einsum("kr,krij->kij", delta, G1) + np.einsum("kr,krij->kij", delta ** 2, G2)
    C = C0 + np.einsum("kr,krij->kij", delta, C1)
    theta = np.zeros((G.shape[0], 3, G.shape[1]))
    for axes in groups.values():
        cols = np.flatnonzero(mask[axes[0]])
        if cols.size:
            sol = solve_normal_batch(G[:, cols][:, :, cols], C[:, cols][:, :, axes])     # (K, c, axes)
            for a, i in enumerate(axes):
                theta[:, i, cols] = sol[:, :, a]
    sse = yy - 2 * np.einsum("kin,kni->k", theta, C) + np.einsum("kin,knm,kim->k", theta, G, theta)
    return theta, sse, G


def _delta_numerator(tl, tb, Sdy, Sdb, Sdf) -> np.ndarray:
    """(K, R): ``sum_i tl_i . (D_r^T y_i - D_r^T X_b tb_i - D_r^T F_0 tl_i)``."""
    a = np.einsum("kia,krai->kr", tl, Sdy)
    bb = np.einsum("kia,krab,kib->kr", tl, Sdb, tb)
    ff = np.einsum("kia,krab,kib->kr", tl, Sdf, tl)
    return a - bb - ff


@dataclasses.dataclass
class LagDesign:
    """The thermal-lag columns at one time constant: the lag block ``F_0``, its transients ``D``, the stretch of
    each row and the first row of each stretch."""

    tau_s: float
    lag: Block
    D: np.ndarray
    sid: np.ndarray
    first: np.ndarray
    #: (R,) bounds of each stretch's starting offset (degC): between carrying the die across the pause (0) and
    #: restarting it at the board's temperature (``restart_c``), widened by RESTART_MARGIN
    lo: np.ndarray
    hi: np.ndarray
    restart_c: np.ndarray

    @property
    def R(self) -> int:
        return int(self.first.size)


def design(gap: Gap, tau_s: float) -> LagDesign:
    """The thermal-lag columns at ``tau_s`` with each stretch's bounds: the die at a restart lies between its
    carried value (offset 0) and the board's temperature there (offset ``T_board - T_lag``: a die that cooled or
    warmed with the unpowered board), widened by RESTART_MARGIN of that difference and RESTART_MARGIN_C."""
    lag = lag_block(gap, tau_s)
    sid, _, first = restarts(gap, tau_s)
    u = np.asarray(gap.session.temp_c, dtype=float)[first] - lagged_temperature(gap, tau_s)[first]
    u = np.where(np.isfinite(u), u, 0.0)
    pad = RESTART_MARGIN * np.abs(u) + RESTART_MARGIN_C
    return LagDesign(float(tau_s), lag, transient_columns(gap, tau_s, lag), sid, first,
                     np.minimum(u, 0.0) - pad, np.maximum(u, 0.0) + pad, u)


def fits(gap: Gap, base: Block, Y: np.ndarray, fold: np.ndarray, dz: LagDesign,
         delta0: np.ndarray | None = None) -> LagFit:
    """:func:`bilinear_fit` of every fold's training set (``np.unique(fold)`` order) and, last, of all rows (starting
    offsets from ``delta0``, e.g. a neighbouring time constant's fit)."""
    folds = np.unique(fold)
    code = np.searchsorted(folds, fold)
    S = stretch_products(base, dz.lag, dz.D, Y, code, folds.size, dz.sid, dz.R)
    tot = S.sum(axis=0)
    sets = np.concatenate([tot[None] - S, tot[None]], axis=0)
    counts = np.bincount(code, minlength=folds.size).astype(float)
    n_rows = np.r_[counts.sum() - counts, counts.sum()]
    mask = np.hstack([base.mask, dz.lag.mask])
    return bilinear_fit(sets, mask, base.p, dz.lag.p, n_rows, delta_sd(gap), delta0, dz.lo, dz.hi)


def train_sse(gap: Gap, base: Block, Y: np.ndarray, fold: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """(folds, taus) training SSE of base + the thermal-lag columns with fitted starting offsets, each fold left
    out in turn (``np.unique(fold)`` order)."""
    folds = np.unique(fold)
    out = np.full((folds.size, grid.size), np.inf)
    prev = None
    for k in np.argsort(grid):                 # increasing time constants, each starting where its neighbour ended
        dz = design(gap, float(grid[k]))
        fit = fits(gap, base, Y, fold, dz, prev if prev is not None and prev.shape[1] == dz.R else None)
        out[:, k] = fit.sse[:-1]
        prev = fit.delta
    return out


def predict(base: Block, dz: LagDesign, theta: np.ndarray, delta: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(len(rows), 3) the base + thermal-lag prediction on ``rows`` (indices or a mask) with coefficients ``theta``
    (3, p + q) and starting offsets ``delta`` (R,)."""
    p = base.p
    mask = np.hstack([base.mask, dz.lag.mask])
    th = np.where(mask, theta, 0.0)
    F = dz.lag.X[rows] + delta[dz.sid[rows]][:, None] * dz.D[rows]
    return base.X[rows] @ th[:, :p].T + F @ th[:, p:].T


def die_temperature(gap: Gap, dz: LagDesign, delta: np.ndarray) -> np.ndarray:
    """(N,) the die temperature of the fit: the lagged board temperature plus each stretch's starting offset."""
    _, e, _ = restarts(gap, dz.tau_s)
    return lagged_temperature(gap, dz.tau_s) + delta[dz.sid] * e


def fit_all(gap: Gap, base: Block, Y: np.ndarray, dz: LagDesign) -> LagFit:
    """:func:`bilinear_fit` of all rows (K = 1)."""
    S = stretch_products(base, dz.lag, dz.D, Y, np.zeros(gap.n, dtype=np.int64), 1, dz.sid, dz.R)
    mask = np.hstack([base.mask, dz.lag.mask])
    return bilinear_fit(S, mask, base.p, dz.lag.p, np.array([float(gap.n)]), delta_sd(gap), None, dz.lo, dz.hi)


def die_temperature_on(gap: Gap, base: Block, tau_s: float, rows: np.ndarray) -> np.ndarray:
    """(len(rows),) the die temperature of the fit on ``rows`` only (indices; the surrogate test's thinned rows):
    the lag filtered and the stretches found on the whole series, the columns, the fit and the path on ``rows``
    (memory of those rows, not of the whole series' design)."""
    sid, e, first = restarts(gap, tau_s)
    lagged = lagged_temperature(gap, tau_s)
    u = np.asarray(gap.session.temp_c, dtype=float)[first] - lagged[first]
    u = np.where(np.isfinite(u), u, 0.0)
    pad = RESTART_MARGIN * np.abs(u) + RESTART_MARGIN_C
    sid, e, lagged = sid[rows], e[rows], lagged[rows]
    lag = lag_block(gap, tau_s, rows)
    if gap.forward:
        terms = LAG_TERMS if "offset" in gap.base_terms else ("offset",) + LAG_TERMS
        D, cm, keep = _forward_columns(gap.rows_view(rows), terms, e)
        for k, c in enumerate(keep):
            if cm.columns[c].term == "offset":
                D[:, k] = 0.0
    else:
        D = transient_columns(gap, tau_s, lag_block(gap, tau_s), None)[rows]
    b = Block(base.X[rows], base.mask, base.names, base.units)
    S = stretch_products(b, lag, D, gap.target[rows], np.zeros(rows.size, dtype=np.int64), 1, sid, first.size)
    fit = bilinear_fit(S, np.hstack([base.mask, lag.mask]), base.p, lag.p, np.array([float(rows.size)]),
                       delta_sd(gap), None, np.minimum(u, 0.0) - pad, np.maximum(u, 0.0) + pad)
    return lagged + fit.delta[0][sid] * e


def transient_block(gap: Gap, base: Block, dz: LagDesign, rows: np.ndarray | None = None) -> Block:
    """The starting transients as free linear columns: per output axis and stretch the shape of the starting
    offset's effect at the lag coefficients fitted on all rows (``D_r th_L,i`` on stretch r's rows), with a free
    coefficient per axis and stretch: the surrogate test's linear stand-in for the fitted starting offsets
    (per-axis offsets are more freedom than one shared offset per stretch, so the test stays conservative)."""
    fit = fit_all(gap, base, gap.target, dz)
    tl = np.where(dz.lag.mask, fit.theta[0][:, base.p:], 0.0)          # (3, q)
    sid = dz.sid if rows is None else dz.sid[rows]
    D = dz.D if rows is None else dz.D[rows]
    shape = D @ tl.T                                                     # (n, 3)
    R = dz.R
    X = np.zeros((sid.size, 3 * R))
    mask = np.zeros((3, 3 * R), bool)
    for i in range(3):
        for r in range(R):
            X[:, i * R + r] = np.where(sid == r, shape[:, i], 0.0)
            mask[i, i * R + r] = True
    names = [[f"start{r}[{a}]" if i == k else "" for k in range(3) for r in range(R)] for i, a in enumerate("xyz")]
    return Block(X, mask, names, ["degC"] * (3 * R))
