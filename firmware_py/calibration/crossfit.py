"""The batch fit and its held-out folds from per-piece R factors, in blocks of rows.

Rows are cut into *pieces*: (session, time-block fold) pairs. One pass over the rows in blocks of
:data:`CHUNK_ROWS` accumulates each piece's R factor of the weighted ``[X | Y]`` (QR, never normal
equations) and its coverage. The full fit's R is the QR of all pieces' factors stacked; a held-out fit's
training R is the QR of the other pieces' factors ("total minus fold"): no fold refits its rows. A fold's
model can differ from the full one (``session_offset`` columns of the sessions it saw, ``drift`` about its
own mean time); its design is a fixed linear map of the full design on its training rows
(:func:`basis_change`), applied to the stacked factor. Two more passes rebuild the design block by block
(it is never kept whole): the residual autocorrelation of every fit's training rows in time order
(:class:`.blocking.BlockingInflation`), then the full fit's residuals and each fold's held-out residuals.
Rows in (session, time) order hand the full fit's residuals block by block to
:class:`.residual_figures.ResidualFigures` (noise floor, step split, sums of squares), replaying the last
pass until its exact medians are found; no per-row array is kept (a row's piece is computed per block).
Other rows keep the (N, 3) residuals. The results equal refitting each fold's rows to rounding
(tests/test_calibration_crossfit.py). Robust
IRLS, ``time_skew`` and ``mount_rotation`` need all rows at once: :func:`applies` sends them to the refit path.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magstack.firmware.blas import single_thread
from magstack.firmware.calibration.blocking import BlockingInflation
from magstack.firmware.calibration.estimator import Posterior
from magstack.firmware.calibration.fit import (
    BLOCK_ROWS,
    CoreFit,
    Coverage,
    FirstSolve,
    FitData,
    FitOptions,
    first_solve,
    gate_solve,
    held_or_refuse,
    qr_r,
    raw_cond,
    time_block_fold,
)
from magstack.firmware.calibration.heldout_test import BlockSSE
from magstack.firmware.calibration.model import CalModel
from magstack.firmware.calibration.predictive import (
    Accumulated,
    HeldOutBins,
    LeftOutMoments,
    SlowNoiseGrams,
    left_out_features,
    left_out_terms,
)
from magstack.firmware.calibration.residual_figures import ResidualFigures
from magstack.firmware.errors import FitError

#: Rows per block of every pass (the design of one block is the largest array built: 64k x p floats).
CHUNK_ROWS = BLOCK_ROWS


def applies(model: CalModel, options: FitOptions) -> bool:
    """Whether :func:`cross_fit` can fit ``model`` (else every fold refits its rows)."""
    terms = set(model.terms)
    if options.robust or {"time_skew", "mount_rotation"} & terms:
        return False
    return "offset" in terms or not {"session_offset", "drift"} & terms


def basis_change(full: CalModel, sub: CalModel) -> np.ndarray:
    """``T`` (p_full, p_sub) with ``sub.design(rows) == full.design(rows) @ T`` on rows of ``sub``'s sessions
    (same terms; ``sub`` sees a subset of the sessions and its own ``t_ref_s``)."""
    col = {(c.term, c.feature): k for k, c in enumerate(full.columns)}
    off = col.get(("offset", "1"))
    T = np.zeros((full.n_columns, sub.n_columns))

    def indicator(j: int) -> np.ndarray:   # full-basis coefficients of 1[session == j] (effect coding)
        e = np.zeros(full.n_columns)
        e[off] = 1.0 / len(full.sessions)
        for k in full.sessions[1:]:
            e[col[("session_offset", f"session_{k}")]] -= 1.0 / len(full.sessions)
        if j != full.sessions[0]:
            e[col[("session_offset", f"session_{j}")]] += 1.0
        return e

    for k, c in enumerate(sub.columns):
        if c.term == "session_offset":
            T[:, k] = indicator(int(c.param[4:])) - indicator(sub.sessions[0])
        else:
            T[col[(c.term, c.feature)], k] = 1.0
            if c.term == "drift":
                T[off, k] += full.t_ref_s - sub.t_ref_s
    return T


@dataclass
class _Pieces:
    """Pass 1's state per piece (session x time-block fold): R factor of the weighted [X | Y], coverage,
    row count, sum of t_s, unweighted column sums of [X | Y]; the piece's session and fold."""

    R: list[np.ndarray]
    cov: list[Coverage]
    count: np.ndarray
    t_sum: np.ndarray
    xy_sum: np.ndarray
    session: np.ndarray
    fold: np.ndarray


@dataclass
class _Fit:
    """One estimator run: the full fit (``kind`` "full"), a time-block fold or a left-out session."""

    kind: str
    key: int
    train: np.ndarray            # (n_pieces,) bool
    test: np.ndarray             # (n_pieces,) bool
    model: CalModel
    T: np.ndarray
    R: np.ndarray
    n: int
    coverage: Coverage
    first: FirstSolve | None = None
    post: Posterior | None = None
    held: list = field(default_factory=list)
    error: str | None = None
    unseen: bool = False         # held-out rows of a session the fit did not see (it has no offset column)
    sq: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cnt: int = 0

    def theta_full_basis(self) -> np.ndarray:
        """(p_full, 3) coefficients on the full model's design (valid on the training rows)."""
        return self.T @ np.where(self.model.axis_mask(), self.post.theta, 0.0).T


@dataclass
class CrossFit:
    """The full fit (``core``), the figures of its residuals (``figures``, rows in (session, time) order) or
    else the residuals themselves (``resid_uT`` (N, 3)), and the held-out figures (uT) with the notes the
    refit path would have written."""

    core: CoreFit
    resid_uT: np.ndarray | None
    figures: ResidualFigures | None = None
    holdout_blocks_uT: np.ndarray | None = None
    holdout_sessions_uT: np.ndarray | None = None
    holdout_per_session_uT: dict[int, np.ndarray] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    acc: Accumulated | None = None       # what the passes collected for the predictive parts
    block_sse: BlockSSE | None = None    # the time-block folds' squared held-out residuals per time block
    piece_coverage: list | None = None   # pass 1's coverage per piece (the same for any model of these rows)


class _Rows:
    """Blocks of the fit rows: views in row order, or gathered in another order."""

    def __init__(self, d: FitData, model: CalModel) -> None:
        self.d, self.model = d, model

    def block(self, idx):
        d = self.d
        cur = {k: v[idx] for k, v in d.currents_A.items()}
        X = self.model.design(d.b_meas_uT[idx], d.temp_c[idx], cur, d.session[idx], d.t_s[idx])
        return X, d.b_ref_uT[idx]

    def chunks(self, order: np.ndarray | None):
        n = len(self.d)
        for a in range(0, n, CHUNK_ROWS):
            yield slice(a, min(a + CHUNK_ROWS, n)) if order is None else order[a:a + CHUNK_ROWS]


def cross_fit(d: FitData, model: CalModel, options: FitOptions, piece_coverage: list | None = None) -> CrossFit:
    """The fit of ``d`` under ``model`` and, when ``options.holdout``, its held-out figures; see the module
    docstring. FitError as the refit path (a failing fold is skipped with a note). ``piece_coverage``: pass 1's
    coverage per piece from another model's cross-fit of the same rows and options (not recomputed)."""
    with single_thread():          # block QRs and products of ~64k x 30: threads only wait (bench_blas.py)
        return _cross_fit(d, model, options, piece_coverage)


def _cross_fit(d: FitData, model: CalModel, options: FitOptions, piece_coverage: list | None) -> CrossFit:
    rows = _Rows(d, model)
    piece = _PieceOf(d, rows, options)
    sessions, n_folds = piece.sessions, piece.n_folds
    pcs = _pieces(d, rows, piece, sessions, n_folds, model, options, piece_coverage)
    every = pcs.count > 0
    fits = [_make("full", 0, every, ~every, pcs, model)]
    if options.holdout:
        for f in np.unique(pcs.fold[every]):
            test = every & (pcs.fold == f)
            if test.any() and (every & ~test).any():
                fits.append(_make("blocks", int(f), every & ~test, test, pcs, model))
        for s in sessions if sessions.size > 1 else ():
            test = every & (pcs.session == s)
            fits.append(_make("session", int(s), every & ~test, test, pcs, model))
    for f in fits:
        f.first = _run(f, lambda f=f: first_solve(f.R, f.n, f.model, f.coverage, options))
        f.post = f.first.post if f.first is not None else None
    in_order = ordered(d)
    rw = SlowNoiseGrams(model.n_columns, _time_span(fits[0].coverage))
    levels: list = []
    if options.autocorr:
        levels = _autocorr(d, rows, piece, fits, pcs.xy_sum, options, in_order, rw)
    for f in fits:
        if f.error is None:
            f.held = _run(f, lambda f=f: held_or_refuse(f.post, f.first.explain, options)) or []
    full = fits[0]
    if full.error is not None:
        raise FitError(full.error)
    figures = ResidualFigures(d.b_meas_uT, d.b_ref_uT, d.t_s, d.session, options.noise_lag_s,
                              steps=options.exclude_ref_steps_uT is None) if in_order else None
    from magstack.drivers.cal_priors import priors_for

    terms = left_out_terms(model, priors_for(options.chip), np.diag(model.unpack(full.post.theta)["S"]))
    p = model.n_columns
    bins = HeldOutBins.for_coverage(full.coverage, p) if options.holdout else None
    moments = LeftOutMoments(p, len(terms))
    block_sse = BlockSSE() if options.holdout else None
    resid = _final_pass(d, rows, piece, fits, figures, terms, moments, bins, block_sse)
    out = CrossFit(CoreFit(None, full.post.theta.copy(), np.where(model.axis_mask(), full.post.sd, np.nan),
                           full.held, np.vstack([full.post.cond, raw_cond(full.R, model)]), full.coverage, None,
                           full.post), resid, figures)
    Rx = full.R[:, :p]
    taus, ou, rwg, dt = rw.result()
    out.acc = Accumulated(Rx.T @ Rx, taus, ou + [rwg], levels, dt, terms, moments, bins)
    out.block_sse = block_sse
    out.piece_coverage = pcs.cov
    if options.holdout:
        _figures(out, fits)
    return out


class _PieceOf:
    """Piece of rows (session index x n_folds + time-block fold, as :func:`.fit.block_folds`), computed per
    block of rows from each session's first time (no per-row array is kept)."""

    def __init__(self, d: FitData, rows: _Rows, options: FitOptions) -> None:
        self.d, self.options = d, options
        self.n_folds = options.n_folds if options.holdout else 1
        self.sessions = d.sessions()
        self.t0_s = np.full(self.sessions.size, np.inf)
        for sl in rows.chunks(None):
            np.minimum.at(self.t0_s, np.searchsorted(self.sessions, d.session[sl]), d.t_s[sl])

    def __getitem__(self, idx) -> np.ndarray:
        k = np.searchsorted(self.sessions, self.d.session[idx])
        if self.n_folds == 1:
            return k
        return k * self.n_folds + time_block_fold(self.d.t_s[idx], self.t0_s[k], self.options)

    def time_block(self, idx) -> tuple[np.ndarray, np.ndarray]:
        """(session index, time-block number from the session's start) of rows ``idx``."""
        k = np.searchsorted(self.sessions, self.d.session[idx])
        return k, np.floor((self.d.t_s[idx] - self.t0_s[k]) / self.options.block_s).astype(np.int64)


def ordered(d: FitData) -> bool:
    """Whether the rows of ``d`` are in (session, time) order, which the streamed figures need (checked block by
    block, one row of overlap)."""
    s, t, n = d.session, d.t_s, len(d)
    for lo in range(0, n, CHUNK_ROWS):
        a, b = max(lo - 1, 0), min(lo + CHUNK_ROWS, n)
        s0, s1 = s[a:b - 1], s[a + 1:b]
        if np.any(s1 < s0) or np.any((s1 == s0) & (t[a + 1:b] < t[a:b - 1])):
            return False
    return True


def _pieces(d: FitData, rows: _Rows, piece: _PieceOf, sessions: np.ndarray, n_folds: int, model: CalModel,
            options: FitOptions, coverage: list | None = None) -> _Pieces:
    """Pass 1: every piece's state (:class:`_Pieces`); piece = session index x n_folds + fold. ``coverage``:
    the pieces' coverage already known (taken as is)."""
    m = model.n_columns + 3
    n_pieces = sessions.size * n_folds
    R = [np.zeros((m, m)) for _ in range(n_pieces)]
    known = coverage is not None and len(coverage) == n_pieces
    cov = list(coverage) if known else [Coverage() for _ in range(n_pieces)]
    count = np.zeros(n_pieces, dtype=np.int64)
    t_sum = np.zeros(n_pieces)
    xy_sum = np.zeros((n_pieces, m))
    for sl in rows.chunks(None):
        pc = piece[sl]
        idx = sl
        if not np.all(pc[1:] >= pc[:-1]):                                    # piece order
            o = np.argsort(pc, kind="stable")
            idx, pc = sl.start + o, pc[o]
        X, Y = rows.block(idx)
        Z = np.hstack([X, Y])
        w = None if d.weights is None else d.weights[idx]
        b, temp, sess, t = d.b_meas_uT[idx], d.temp_c[idx], d.session[idx], d.t_s[idx]
        cur = {c: d.currents_A[c][idx] for c in model.currents}
        cuts = np.r_[0, np.flatnonzero(pc[1:] != pc[:-1]) + 1, pc.size]
        for a, e in zip(cuts[:-1], cuts[1:], strict=True):
            k = int(pc[a])
            xy_sum[k] += np.ones(e - a) @ Z[a:e]
            R[k] = qr_r(np.vstack([R[k], Z[a:e] if w is None else Z[a:e] * np.sqrt(w[a:e])[:, None]]))
            if not known:
                cov[k].update(b[a:e], temp[a:e], {c: v[a:e] for c, v in cur.items()}, sess[a:e], t[a:e],
                              options.field_present_uT, np.ones(e - a) if w is None else w[a:e], ref_uT=Y[a:e])
            count[k] += e - a
            t_sum[k] += float(np.sum(t[a:e]))
    return _Pieces(R, cov, count, t_sum, xy_sum, np.repeat(sessions, n_folds), np.tile(np.arange(n_folds),
                                                                                        sessions.size))


def _make(kind: str, key: int, train: np.ndarray, test: np.ndarray, pcs: _Pieces, model: CalModel) -> _Fit:
    """The fit of the pieces ``train``: its model (sessions it saw, its mean time), stacked R, coverage."""
    if kind == "full":
        sub = model
    else:
        seen = tuple(int(s) for s in np.unique(pcs.session[train])) if "session_offset" in model.terms else ()
        sub = CalModel(model.terms, model.currents, seen, model.t0_c,
                       float(pcs.t_sum[train].sum() / pcs.count[train].sum()), model.name)
    p = model.n_columns
    T = np.eye(p) if sub == model else basis_change(model, sub)
    Rt = qr_r(np.vstack([pcs.R[k] for k in np.flatnonzero(train)]))
    if not np.array_equal(T, np.eye(p)):
        Rt = qr_r(np.hstack([Rt[:, :p] @ T, Rt[:, p:]]))
    c = Coverage()
    for k in np.flatnonzero(train):
        c.merge(pcs.cov[k])
    unseen = "session_offset" in model.terms and bool(set(pcs.session[test].tolist()) - set(sub.sessions))
    return _Fit(kind, key, train, test, sub, T, Rt, int(pcs.count[train].sum()), c, unseen=unseen)


def _run(f: _Fit, step):
    """``step()``; a FitError becomes the fit's error (a fold is then skipped with a note) and gives None."""
    try:
        return step()
    except FitError as exc:
        f.error = str(exc)
        return None


def _time_span(cov: Coverage) -> float:
    """The data's time span (s), for the slow-noise model's correlation times."""
    return float(cov.t_max_s - cov.t_min_s) if np.isfinite(cov.t_max_s - cov.t_min_s) else 0.0


def _autocorr(d, rows, piece, fits, xy_sum, options, ordered: bool, rw: SlowNoiseGrams) -> list:
    """Pass 2: residuals of every fit's training rows in (session, time) order -> kappa -> the final solve.
    The full fit's rows also feed ``rw`` (its random-walk Gram matrix); returns the adjacent block-mean
    differences of the full fit's residuals (:meth:`.blocking.BlockingInflation.adjacent_levels`)."""
    live = [f for f in fits if f.error is None]
    if not live:
        return []
    p = fits[0].T.shape[0]
    theta = np.hstack([f.theta_full_basis() for f in live])              # (p, 3 F)
    center = []                              # each fit's mean training residual, from the column sums
    for f in live:
        s = xy_sum[f.train].sum(axis=0)
        center.append((s[p:] - s[:p] @ f.theta_full_basis()) / f.n)
    center = np.array(center)[:, :, None]
    accs = [BlockingInflation() for _ in live]
    s, t = d.session, d.t_s
    order = None if ordered else np.lexsort((t, s))
    for idx in rows.chunks(order):
        X, Y = rows.block(idx)
        r = (theta.T @ X.T).reshape(len(live), 3, -1)                    # fit, axis, row: rows contiguous
        np.subtract(Y.T[None], r, out=r)
        r -= center
        pc, sess = piece[idx], s[idx]
        if live[0] is fits[0]:
            rw.add(X if d.weights is None else X * d.weights[idx][:, None], t[idx], sess)
        for j, f in enumerate(live):
            use = f.train[pc]
            if use.all():
                accs[j].add(r[j], sess)
            else:
                keep = np.flatnonzero(use)
                accs[j].add(np.take(r[j], keep, axis=1), sess[keep])
    for f, acc in zip(live, accs, strict=True):
        post = _run(f, lambda f=f, acc=acc: gate_solve(f.R, f.n, f.model, f.first.prior, f.first.gated,
                                                       acc.kappa(), options))
        f.post = post if post is not None else f.post
    return accs[0].adjacent_levels() if live[0] is fits[0] else []


def _final_pass(d, rows, piece, fits, figures: ResidualFigures | None, terms=(),
                moments: LeftOutMoments | None = None, bins: HeldOutBins | None = None,
                block_sse: BlockSSE | None = None) -> np.ndarray | None:
    """Pass 3: the full fit's residuals, into ``figures`` (then replayed while it needs them again) or else
    returned whole (N, 3); each fold's squared held-out residuals. Also the moments of the design and the
    left-out features ``terms`` (into ``moments``), the time-block folds' held-out residuals binned (into
    ``bins``) and summed per time block (into ``block_sse``)."""
    full = fits[0]
    folds = [f for f in fits[1:] if f.error is None]
    scale = {id(f): full.n / f.n for f in folds}
    theta = full.theta_full_basis()
    theta_f = np.hstack([f.theta_full_basis() for f in folds]) if folds else None   # (p, 3 F)
    resid = None if figures is not None else np.empty((len(d), 3))
    t0 = full.model.t0_c
    for sl in rows.chunks(None):
        X, Y = rows.block(sl)
        r = _resid(X, Y, theta)
        if figures is not None:
            figures.add(sl.start, r)
        else:
            resid[sl] = r.T
        if moments is not None and len(terms):
            moments.add(X, left_out_features(terms, d.b_meas_uT[sl], d.temp_c[sl] - t0),
                        None if d.weights is None else d.weights[sl])
        if not folds:
            continue
        P = (theta_f.T @ X.T).reshape(-1, 3, X.shape[0])                      # fold, axis, row
        pc = piece[sl]
        for j, f in enumerate(folds):
            keep = np.flatnonzero(f.test[pc])
            if not keep.size:
                continue
            if f.unseen:
                Xf, Yf = _Rows(d, f.model).block(sl.start + keep)
                rf = (Yf - f.model.predict(f.post.theta, Xf)).T
            else:
                rf = np.take(Y.T, keep, axis=1) - np.take(P[j], keep, axis=1)
            f.sq += np.einsum("ij,ij->i", rf, rf)
            f.cnt += keep.size
            if f.kind == "blocks" and (bins is not None or block_sse is not None):
                rows_k = sl.start + keep
                if bins is not None:
                    bins.add(np.take(X, keep, axis=0), rf, d.b_meas_uT[rows_k], d.temp_c[rows_k], scale[id(f)])
                if block_sse is not None:
                    block_sse.add(*piece.time_block(rows_k), np.einsum("ij,ij->j", rf, rf))
    while figures is not None:
        figures.end_pass()
        if not figures.pending:
            break
        for sl in rows.chunks(None):                 # the same residuals again, bit for bit
            X, Y = rows.block(sl)
            figures.add(sl.start, _resid(X, Y, theta))
    return resid


def _resid(X: np.ndarray, Y: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(3, m) residuals ``Y - X theta``, axis first (every pass computes them alike, to the bit)."""
    r = theta.T @ X.T
    return np.subtract(Y.T, r, out=r)


def _figures(out: CrossFit, fits: list[_Fit]) -> None:
    """Pool the folds' held-out residuals into the figures and notes of the refit path."""
    notes = out.notes
    full_held = {h.name for h in fits[0].held}
    sq, cnt = np.zeros(3), 0
    for f in (f for f in fits if f.kind == "blocks"):
        if f.error is not None:
            notes.append(f"time-block fold {f.key} skipped: {f.error}")
            continue
        sq += f.sq
        cnt += f.cnt
    if cnt == 0:
        notes.append("held-out by time blocks: no fold could be fitted")
    else:
        out.holdout_blocks_uT = np.sqrt(sq / cnt)
    sq, cnt = np.zeros(3), 0
    sess = [f for f in fits if f.kind == "session"]
    if not sess:
        notes.append("held-out by sessions: needs at least two sessions")
        return
    for f in sess:
        if f.error is not None:
            notes.append(f"session {f.key} left out: skipped: {f.error}")
            continue
        lost = sorted({h.name for h in f.held} - full_held)
        if lost:
            notes.append(f"session {f.key} left out: the other sessions cannot determine {', '.join(lost)} "
                         "(prior-determined), so its held-out error measures extrapolation, not calibration quality")
        out.holdout_per_session_uT[f.key] = np.sqrt(f.sq / f.cnt)
        sq += f.sq
        cnt += f.cnt
    out.holdout_sessions_uT = np.sqrt(sq / cnt) if cnt else None
