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
:class:`.residual_figures.ResidualFigures` (noise floor, step split, sums of squares; exact medians in that pass as
a rule, else in replays of it); no per-row array is kept (a row's piece is computed per block).
Other rows keep the (N, 3) residuals. The results equal refitting each fold's rows to rounding
(tests/test_calibration_crossfit.py). A model and a wider one
(:func:`.fit.fit`'s second-order tempco candidate) share one set of passes (:func:`cross_fit_with`); a choice
between them, made on their held-out figures after pass 3, leaves the rest to the chosen one, and a wider model
that provably cannot reach the gain the choice requires is not fitted at all (:func:`wider_gain_bound`). Robust
IRLS, ``time_skew`` and ``mount_rotation`` need all rows at once: :func:`applies` sends them to the refit path.
"""
from __future__ import annotations

from collections.abc import Callable
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
    left_out_terms,
    weighed_components,
    weighed_grams,
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
    wider_gain_bound: float | None = None   # a wider model ruled out: the most it could gain (:func:`cross_fit_with`)


class _Rows:
    """Blocks of the fit rows: views in row order, or gathered in another order."""

    def __init__(self, d: FitData, model: CalModel) -> None:
        self.d, self.model = d, model

    def inputs(self, idx) -> dict:
        """The design's inputs of rows ``idx``: ``b``, ``temp``, ``currents``, ``session``, ``t``."""
        d = self.d
        return {"b": d.b_meas_uT[idx], "temp": d.temp_c[idx], "currents": {k: v[idx] for k, v in d.currents_A.items()},
                "session": d.session[idx], "t": d.t_s[idx]}

    def joint(self, idx) -> tuple[np.ndarray, dict]:
        """``[X | Y]`` (m, p + 3) of rows ``idx``: design and reference field, in column order (each column
        contiguous: the design is filled without strides, and QR reads columns); and the rows' :meth:`inputs`."""
        got = self.inputs(idx)
        p = self.model.n_columns
        Z = np.empty((got["b"].shape[0], p + 3), order="F")
        self.model.design(got["b"], got["temp"], got["currents"], got["session"], got["t"], out=Z[:, :p])
        Z[:, p:] = self.d.b_ref_uT[idx]
        return Z, got

    def block(self, idx) -> tuple[np.ndarray, np.ndarray]:
        """The design (m, p) and reference field (m, 3) of rows ``idx`` in row order (what the passes' row
        gathers, bin sums and products read fastest)."""
        got = self.inputs(idx)
        X = self.model.design(got["b"], got["temp"], got["currents"], got["session"], got["t"])
        return X, self.d.b_ref_uT[idx]

    def chunks(self, order: np.ndarray | None):
        n = len(self.d)
        for a in range(0, n, CHUNK_ROWS):
            yield slice(a, min(a + CHUNK_ROWS, n)) if order is None else order[a:a + CHUNK_ROWS]


def column_map(model: CalModel, wider: CalModel) -> np.ndarray:
    """(p,) the index of each column of ``model`` among ``wider``'s (matched by term and feature), so that
    ``model.design(rows) == wider.design(rows)[:, column_map(model, wider)]``. ValueError when ``wider`` lacks a
    column of ``model`` or builds one otherwise (other currents, sessions, ``t0_c`` or ``t_ref_s``)."""
    if (model.currents, model.sessions, model.t0_c, model.t_ref_s) != (wider.currents, wider.sessions, wider.t0_c,
                                                                       wider.t_ref_s):
        raise ValueError(f"models {model.name} and {wider.name} build their columns from different references")
    col = {(c.term, c.feature): k for k, c in enumerate(wider.columns)}
    cols = [col.get((c.term, c.feature)) for c in model.columns]
    if any(k is None or wider.columns[k].axes != c.axes for k, c in zip(cols, model.columns, strict=True)):
        raise ValueError(f"model {wider.name} does not have every column of {model.name}")
    return np.array(cols, dtype=np.intp)


def cross_fit(d: FitData, model: CalModel, options: FitOptions) -> CrossFit:
    """The fit of ``d`` under ``model`` and, when ``options.holdout``, its held-out figures; see the module
    docstring. FitError as the refit path (a failing fold is skipped with a note)."""
    with single_thread():          # block QRs and products of ~64k x 30: threads only wait (bench_blas.py)
        rows = _Rows(d, model)
        piece = _PieceOf(d, rows, options)
        pcs = _pieces(d, rows, piece, model, options)
        return _cross_fit(d, rows, piece, [_Run(model, np.arange(model.n_columns), pcs)], options)[0]


def cross_fit_with(d: FitData, model: CalModel, wider: CalModel, options: FitOptions,
                   try_wider: Callable[[Coverage], bool],
                   adopt: Callable[[CrossFit, CrossFit], bool] | None = None, min_gain: float | None = None
                   ) -> tuple[CrossFit, CrossFit | None]:
    """``cross_fit(d, model)`` and, when ``try_wider`` says yes to the full fit's coverage, ``cross_fit(d, wider)``
    (else None), from one set of passes over the rows; ``wider`` has every column of ``model``
    (:func:`column_map`). Pass 1 factors the rows of ``wider``'s design; ``model``'s R factor of a piece is the R of
    its columns of that piece's R (``R^T R = Z^T Z`` holds for any subset of the columns). Passes 2 and 3 take both
    models' residuals from one product per block (``model``'s coefficients zero on the columns it lacks); the
    slow-noise Grams and the left-out moments are accumulated once over ``wider``'s design, ``model``'s are their
    rows and columns of its own. The results equal two :func:`cross_fit` calls to rounding. ``adopt(base, wider)``,
    given both CrossFits after pass 3 (held-out figures and block SSE), says whether ``wider`` is the one to
    finish: only that one's figures, discrepancy bins and predictive parts are then returned (the other's CrossFit
    keeps its fit, held-out figures and block SSE).

    ``min_gain`` (with ``adopt``): the share of ``model``'s held-out sum of squares by which ``adopt`` requires
    ``wider`` to lower it at least. ``model``'s passes come first; when no time-block fold's held-out rows, fitted
    by ``wider``'s columns themselves, would come that far below ``model``'s held-out sum of squares there
    (:func:`wider_gain_bound`: no fit of ``wider`` on the other rows can do better), ``wider`` cannot be adopted
    and is not fitted: the result is ``(cross_fit(d, model), None)`` with the bound in ``wider_gain_bound``. Else
    ``wider``'s second pass follows and everything is as without ``min_gain``."""
    cols = column_map(model, wider)
    with single_thread():
        rows = _Rows(d, wider)
        piece = _PieceOf(d, rows, options)
        pcs = _pieces(d, rows, piece, wider, options)
        base = _Run(model, cols, _column_pieces(pcs, cols, wider.n_columns))
        if not try_wider(_coverage(base.pcs, base.pcs.count > 0)):
            base.cols = np.arange(model.n_columns)         # passes 2 and 3 on the model's own design
            return _cross_fit(d, _Rows(d, model), piece, [base], options)[0], None
        choose = None if adopt is None else (lambda outs: 1 if adopt(outs[0], outs[1]) else 0)
        out = _cross_fit(d, rows, piece, [base, _Run(wider, np.arange(wider.n_columns), pcs)], options, choose,
                         None if adopt is None else min_gain)
        return out[0], (out[1] if len(out) > 1 else None)


@dataclass
class _Run:
    """One model in passes over the rows that may serve several: its columns in the passes' design (``cols``), its
    pieces and fits, and what the passes collect for it."""

    model: CalModel
    cols: np.ndarray
    pcs: _Pieces
    fits: list[_Fit] = field(default_factory=list)
    levels: list = field(default_factory=list)
    figures: ResidualFigures | None = None
    resid: np.ndarray | None = None
    terms: list = field(default_factory=list)
    bins: HeldOutBins | None = None
    block_sse: BlockSSE | None = None

    def own_design(self, p: int) -> bool:
        """Whether the passes' design (``p`` columns) is this model's."""
        return self.cols.size == p and bool(np.all(self.cols == np.arange(p)))

    def embed(self, theta: np.ndarray, p: int) -> np.ndarray:
        """``theta`` (p_model, k) as coefficients of the passes' design (p, k): 0 on the columns the model lacks."""
        if self.own_design(p):
            return theta
        out = np.zeros((p, theta.shape[1]))
        out[self.cols] = theta
        return out


def _cross_fit(d: FitData, rows: _Rows, piece: _PieceOf, runs: list[_Run], options: FitOptions,
               choose: Callable[[list[CrossFit]], int] | None = None, min_gain: float | None = None
               ) -> list[CrossFit]:
    """Every model of ``runs`` fitted and cross-fitted in one set of passes over the rows (design ``rows.model``).
    ``choose``: given every model's held-out figures and block SSE (after pass 3), the index of the one to finish;
    the others' figures, discrepancy bins and predictive parts are then dropped (their CrossFit holds the fit, the
    held-out figures and the block SSE only). ``min_gain`` (two runs): the second is ruled out
    after the first's pass 2 when :func:`wider_gain_bound` stays below it (then one CrossFit is returned, its
    ``wider_gain_bound`` set), else its own pass 2 follows; where the bound of the first solves is already twice
    ``min_gain``, both share pass 2 as without it."""
    P = rows.model.n_columns
    lead = runs
    if min_gain is not None and len(runs) == 2:       # the bound from the first solves foretells the final one's:
        _first_solves(runs[:1], piece, options)          # where it is far above, both models share pass 2
        guess = wider_gain_bound(d, runs[0], runs[1], P)
        lead = runs[:1] if guess is not None and guess < 2.0 * min_gain else runs
        _first_solves(lead[1:], piece, options)
    else:
        _first_solves(runs, piece, options)
    in_order = ordered(d)
    rw = SlowNoiseGrams(P, _time_span(runs[0].fits[0].coverage))
    grams = None                 # rows in order: pass 3 feeds the Grams the slow-noise fits need (else pass 2 all)
    if options.autocorr:
        _autocorr(d, rows, piece, lead, options, in_order, rw)
    bound = None
    if len(lead) < len(runs):
        bound = wider_gain_bound(d, runs[0], runs[1], P)
        if bound is not None and bound < min_gain * (1.0 - 1e-9):
            runs = lead
        else:
            bound = None
            _first_solves(runs[1:], piece, options)
            if options.autocorr:
                _autocorr(d, rows, piece, runs[1:], options, in_order, rw, feed_rw=False)
    if options.autocorr and in_order:
        grams = _needed_grams(rw, runs)
    for run in runs:
        for f in run.fits:
            if f.error is None:
                f.held = _run(f, lambda f=f: held_or_refuse(f.post, f.first.explain, options)) or []
    for run in runs:
        if run.fits[0].error is not None:
            raise FitError(run.fits[0].error)
    from magstack.drivers.cal_priors import priors_for

    chip = priors_for(options.chip)
    for run in runs:
        full = run.fits[0]
        run.figures = ResidualFigures(d.b_meas_uT, d.b_ref_uT, d.t_s, d.session, options.noise_lag_s,
                                      steps=options.exclude_ref_steps_uT is None) if in_order else None
        run.terms = left_out_terms(run.model, chip, np.diag(run.model.unpack(full.post.theta)["S"]))
        run.bins = HeldOutBins.for_coverage(full.coverage, run.model.n_columns) if options.holdout else None
        run.block_sse = BlockSSE() if options.holdout else None
    union = list({t.name: t for run in runs for t in run.terms}.values())   # by name: the features
    moments = LeftOutMoments(P, len(union))
    outs = [CrossFit(CoreFit(None, run.fits[0].post.theta.copy(),
                             np.where(run.model.axis_mask(), run.fits[0].post.sd, np.nan), run.fits[0].held,
                             np.vstack([run.fits[0].post.cond, raw_cond(run.fits[0].R, run.model)]),
                             run.fits[0].coverage, None, run.fits[0].post), None) for run in runs]
    if bound is not None:
        outs[0].wider_gain_bound = bound

    def decide() -> list[int]:
        for out, run in zip(outs, runs, strict=True):
            out.block_sse = run.block_sse
            if options.holdout:
                _figures(out, run.fits)
        return list(range(len(runs))) if choose is None or len(runs) == 1 else [choose(outs)]

    keep = _final_pass(d, rows, piece, runs, union, moments, decide, grams)
    taus, ou, rwg, dt = rw.result()
    for k in keep:
        run, out = runs[k], outs[k]
        full, p, cols = run.fits[0], run.model.n_columns, run.cols
        out.resid_uT, out.figures = run.resid, run.figures
        Rx = full.R[:, :p]
        sub = np.ix_(cols, cols)
        out.acc = Accumulated(Rx.T @ Rx, taus, weighed_grams(run.levels, dt, taus, [g[sub] for g in ou + [rwg]]),
                              run.levels, dt, run.terms,
                              _moments_of(moments, union, run.terms, cols), run.bins)
    return outs


def _first_solves(runs: list[_Run], piece: _PieceOf, options: FitOptions) -> None:
    """Each run's fits (:func:`_fits`) and their first solves."""
    for run in runs:
        run.fits = _fits(run.pcs, run.model, piece, options)
        for f in run.fits:
            f.first = _run(f, lambda f=f: first_solve(f.R, f.n, f.model, f.coverage, options))
            f.post = f.first.post if f.first is not None else None


def wider_gain_bound(d: FitData, base: _Run, wider: _Run, P: int) -> float | None:
    """The most by which ``wider`` could lower ``base``'s held-out sum of squares on any time-block fold:
    ``max_f (1 - L_f / B_f)``, ``B_f`` the sum of squares of ``base``'s final fit of fold ``f`` on the fold's
    held-out rows and ``L_f`` the least ``wider``'s columns reach on those rows when fitted to them (each axis on
    its own columns; from the held-out pieces' R factors, no pass over the rows). No fit of ``wider`` on the other
    rows does better than ``L_f``, and a share of several folds' sums is at most the largest fold's, so the paired
    test's gain over any of the blocks is below the bound. None where it does not apply: weighted rows (the pieces'
    R factors are of the weighted rows, the held-out sums of the raw ones), a time-block fold of ``base`` not fitted
    or predicting a session it did not see, or no held-out error."""
    folds = [f for f in base.fits if f.kind == "blocks"]
    if d.weights is not None or not folds or any(f.error is not None or f.unseen for f in folds):
        return None
    mask = wider.model.axis_mask()
    worst = -np.inf
    for f in folds:
        Rt = qr_r(*[wider.pcs.R[k] for k in np.flatnonzero(f.test)])
        B = float(np.sum((Rt[:, :P] @ base.embed(f.theta_full_basis(), P) - Rt[:, P:]) ** 2))
        L = 0.0
        for i in range(3):
            A, y = Rt[:, :P][:, mask[i]], Rt[:, P + i]
            L += float(np.sum((A @ np.linalg.lstsq(A, y, rcond=None)[0] - y) ** 2))
        if not B > 0:
            return None
        worst = max(worst, 1.0 - L / B)
    return float(worst)


def _needed_grams(rw: SlowNoiseGrams, runs: list[_Run]) -> SlowNoiseGrams | None:
    """``rw`` set to keep only the components some model's slow-noise fit weighs (its levels from pass 2, as
    :func:`.predictive.assemble` will fit them: the same fit, so the others' Grams would be weighed by 0), or None
    when none is."""
    use = np.zeros(len(rw.taus_s) + 1, dtype=bool)
    for run in runs:
        if run.levels:
            use |= weighed_components(run.levels, rw.mean_dt_s, rw.taus_s)
    rw.keep(use[:-1], bool(use[-1]))
    return rw if use.any() else None


def _moments_of(moments: LeftOutMoments, union: list, terms: list, cols: np.ndarray) -> LeftOutMoments:
    """The moments of design columns ``cols`` and left-out ``terms`` (a subset of ``union``, by name) out of
    ``moments`` (of the passes' design and ``union``)."""
    at = {t.name: k for k, t in enumerate(union)}
    idx = np.array([at[t.name] for t in terms], dtype=np.intp)
    out = LeftOutMoments(cols.size, idx.size)
    if idx.size:
        out.XtWG = moments.XtWG[np.ix_(cols, idx)]
        out.g2 = moments.g2[idx]
        out.sum_w = moments.sum_w
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

    def with_blocks(self, idx) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(piece, session index, time-block number)`` of rows ``idx`` (``self[idx]`` and :meth:`time_block`)."""
        k, blk = self.time_block(idx)
        return (k if self.n_folds == 1 else k * self.n_folds + blk % self.options.n_folds), k, blk


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


def _pieces(d: FitData, rows: _Rows, piece: _PieceOf, model: CalModel, options: FitOptions) -> _Pieces:
    """Pass 1: every piece's state (:class:`_Pieces`); piece = session index x n_folds + fold."""
    sessions, n_folds = piece.sessions, piece.n_folds
    m = model.n_columns + 3
    n_pieces = sessions.size * n_folds
    R = [np.zeros((m, m)) for _ in range(n_pieces)]
    cov = [Coverage() for _ in range(n_pieces)]
    count = np.zeros(n_pieces, dtype=np.int64)
    t_sum = np.zeros(n_pieces)
    xy_sum = np.zeros((n_pieces, m))
    for sl in rows.chunks(None):
        pc = piece[sl]
        idx = sl
        if not np.all(pc[1:] >= pc[:-1]):                                    # piece order
            o = np.argsort(pc, kind="stable")
            idx, pc = sl.start + o, pc[o]
        Z, got = rows.joint(idx)
        Y = Z[:, model.n_columns:]
        w = None if d.weights is None else d.weights[idx]
        b, temp, sess, t = got["b"], got["temp"], got["session"], got["t"]
        cur = {c: got["currents"][c] for c in model.currents}
        cuts = np.r_[0, np.flatnonzero(pc[1:] != pc[:-1]) + 1, pc.size]
        for a, e in zip(cuts[:-1], cuts[1:], strict=True):
            k = int(pc[a])
            xy_sum[k] += np.ones(e - a) @ Z[a:e]
            R[k] = qr_r(R[k], Z[a:e] if w is None else Z[a:e] * np.sqrt(w[a:e])[:, None])
            cov[k].update(b[a:e], temp[a:e], {c: v[a:e] for c, v in cur.items()}, sess[a:e], t[a:e],
                          options.field_present_uT, np.ones(e - a) if w is None else w[a:e], ref_uT=Y[a:e])
            count[k] += e - a
            t_sum[k] += float(np.sum(t[a:e]))
    return _Pieces(R, cov, count, t_sum, xy_sum, np.repeat(sessions, n_folds), np.tile(np.arange(n_folds),
                                                                                        sessions.size))


def _column_pieces(pcs: _Pieces, cols: np.ndarray, p: int) -> _Pieces:
    """The pieces of the design's columns ``cols`` (of ``p``) from ``pcs``: each R factor the R of those columns
    of the piece's R (and the targets)."""
    sel = np.r_[cols, p + np.arange(3)]
    return _Pieces([qr_r(R[:, sel]) for R in pcs.R], pcs.cov, pcs.count, pcs.t_sum, pcs.xy_sum[:, sel], pcs.session,
                   pcs.fold)


def _fits(pcs: _Pieces, model: CalModel, piece: _PieceOf, options: FitOptions) -> list[_Fit]:
    """The full fit, then (``options.holdout``) one per time-block fold and one per left-out session."""
    every = pcs.count > 0
    fits = [_make("full", 0, every, ~every, pcs, model)]
    if options.holdout:
        for f in np.unique(pcs.fold[every]):
            test = every & (pcs.fold == f)
            if test.any() and (every & ~test).any():
                fits.append(_make("blocks", int(f), every & ~test, test, pcs, model))
        for s in piece.sessions if piece.sessions.size > 1 else ():
            test = every & (pcs.session == s)
            fits.append(_make("session", int(s), every & ~test, test, pcs, model))
    return fits


def _coverage(pcs: _Pieces, train: np.ndarray) -> Coverage:
    """The coverage of the pieces ``train``."""
    c = Coverage()
    for k in np.flatnonzero(train):
        c.merge(pcs.cov[k])
    return c


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
    Rt = qr_r(*[pcs.R[k] for k in np.flatnonzero(train)])
    if not np.array_equal(T, np.eye(p)):
        Rt = qr_r(np.hstack([Rt[:, :p] @ T, Rt[:, p:]]))
    c = _coverage(pcs, train)
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


def _autocorr(d, rows, piece, runs: list[_Run], options, ordered: bool, rw: SlowNoiseGrams,
              feed_rw: bool = True) -> None:
    """Pass 2: residuals of every fit's training rows in (session, time) order -> kappa -> the final solve (one
    product per block for the fits of every model). The rows' times (``ordered``: pass 3 feeds the design), else the
    rows, also feed ``rw`` (the random-walk and correlated
    noise Grams of the passes' design); each model's ``levels`` are the adjacent block-mean differences of its full
    fit's residuals (:meth:`.blocking.BlockingInflation.adjacent_levels`)."""
    live = [(run, f) for run in runs for f in run.fits if f.error is None]
    if not live:
        return
    by_rows: dict[bytes, list] = {}          # fits of the same training rows (a fold of each model) side by side:
    for run, f in live:                      # one accumulator, their residuals a contiguous stack (each series
        by_rows.setdefault(f.train.tobytes(), []).append((run, f))     # accumulated on its own)
    live = [x for group in by_rows.values() for x in group]
    P = rows.model.n_columns
    theta = np.hstack([run.embed(f.theta_full_basis(), P) for run, f in live])         # (P, 3 F)
    center = []                              # each fit's mean training residual, from the column sums
    for run, f in live:
        p = run.model.n_columns
        s = run.pcs.xy_sum[f.train].sum(axis=0)
        center.append((s[p:] - s[:p] @ f.theta_full_basis()) / f.n)
    center = np.array(center)[:, :, None]
    groups: dict[bytes, list[int]] = {}
    for j, (_, f) in enumerate(live):
        groups.setdefault(f.train.tobytes(), []).append(j)
    accs = {key: BlockingInflation(3 * len(js), adjacent=any(live[j][1] is live[j][0].fits[0] for j in js))
            for key, js in groups.items()}                  # the adjacent levels: of the full fits only
    feed = feed_rw and any(run.fits[0].error is None for run in runs)
    s, t = d.session, d.t_s
    order = None if ordered else np.lexsort((t, s))
    for idx in rows.chunks(order):
        X, Y = rows.block(idx)
        r = (theta.T @ X.T).reshape(len(live), 3, -1)                    # fit, axis, row: rows contiguous
        np.subtract(Y.T[None], r, out=r)
        r -= center
        pc, sess = piece[idx], s[idx]
        if feed and ordered:
            rw.add_times(t[idx], sess)                     # the rows themselves in pass 3 (_needed_grams)
        elif feed:
            rw.add(X if d.weights is None else X * d.weights[idx][:, None], t[idx], sess)
        for key, js in groups.items():
            rj = r[js[0]:js[-1] + 1].reshape(3 * len(js), -1)                  # a view
            use = live[js[0]][1].train[pc]
            if use.all():
                accs[key].add(rj, sess)
            else:
                keep = np.flatnonzero(use)
                accs[key].add(np.take(rj, keep, axis=1), sess[keep])
    kappa, levels = {}, {}
    for key, js in groups.items():
        kap, lev = accs[key].kappa(), accs[key].adjacent_levels()
        for q, j in enumerate(js):
            kappa[j] = kap[3 * q:3 * q + 3]
            levels[j] = [(L, k, d2[3 * q:3 * q + 3]) for L, k, d2 in lev]
    for j, (_, f) in enumerate(live):
        post = _run(f, lambda f=f, j=j: gate_solve(f.R, f.n, f.model, f.first.prior, f.first.gated, kappa[j],
                                                   options))
        f.post = post if post is not None else f.post
    for j, (run, f) in enumerate(live):
        if f is run.fits[0]:
            run.levels = levels[j]


def _final_pass(d, rows, piece, runs: list[_Run], union: list, moments: LeftOutMoments,
                decide: Callable[[], list[int]], grams: SlowNoiseGrams | None = None) -> list[int]:
    """Pass 3, for every model of ``runs``: each fold's squared held-out residuals, the time-block folds' summed per
    time block (``block_sse``) and binned (``bins``); the full fit's residuals into its streamed ``figures`` (or kept
    whole, ``resid`` (N, 3), where rows are not in order); the moments of the design and the left-out features
    ``union`` (into ``moments``); the rows of the slow-noise Grams ``grams`` needs (rows in order). Then
    ``decide()`` names the models to finish (returned); those whose figures need the residuals again (a median
    outside its guessed bracket, :mod:`.rank_select`) get them in replays of the pass. A model not finished has
    its figures and bins dropped (each model's figures hold at most :data:`.rank_select.COLLECT_CAP` values per
    axis while they wait)."""
    P = rows.model.n_columns
    theta = np.hstack([run.embed(run.fits[0].theta_full_basis(), P) for run in runs])     # (P, 3 models)
    folds = [[f for f in run.fits[1:] if f.error is None] for run in runs]
    theta_f = [[run.embed(f.theta_full_basis(), P) for f in fs] for run, fs in zip(runs, folds, strict=True)]
    own = [run.own_design(P) for run in runs]
    for run in runs:
        run.resid = None if run.figures is not None else np.empty((len(d), 3))
    t0 = runs[0].model.t0_c

    order = list({(f.kind, f.key): None for fs in folds for f in fs})      # every fold, any model's
    by_fold = [{(f.kind, f.key): (f, th) for f, th in zip(fs, ths, strict=True)}
               for fs, ths in zip(folds, theta_f, strict=True)]

    def held_out(j: int, f: _Fit, th: np.ndarray, sl, X, Y, held: dict) -> None:
        """Model ``j``'s fold ``f`` (coefficients ``th`` of the passes' design) on the block ``sl``: squared held-out
        residuals, block SSE and the discrepancy bins (``held``: what the models' same fold shares on the block:
        its held-out rows, their design and targets, time blocks, bins and design moments)."""
        run, own_x = runs[j], own[j]
        if "rows" not in held:
            keep = np.flatnonzero(f.test[held["piece"]])
            held["rows"] = (keep, np.take(X, keep, axis=0), np.take(Y, keep, axis=0).T)
        keep, Xk, Yt = held["rows"]
        if not keep.size:
            return
        if f.unseen:
            Xf, Yf = _Rows(d, f.model).block(sl.start + keep)
            rf = (Yf - f.model.predict(f.post.theta, Xf)).T
        else:
            rf = Yt - (Xk @ th).T
        f.sq += np.einsum("ij,ij->i", rf, rf)
        f.cnt += keep.size
        if f.kind == "blocks" and run.block_sse is not None:
            if "sse" not in held:
                held["sse"] = BlockSSE.group(held["session"][keep], held["block"][keep])
            run.block_sse.add_grouped(held["sse"], np.einsum("ij,ij->j", rf, rf))
        if f.kind == "blocks" and run.bins is not None:
            scale = run.fits[0].n / f.n
            bn = run.bins
            edges = (bn.field_edges_uT.tobytes(), bn.temp_edges_c.tobytes(), bn.temp_centre_c)
            if ("where", edges) not in held:                  # the rows' bins: any model's
                rows_k = sl.start + keep
                held["where", edges] = bn.locate(d.b_meas_uT[rows_k], d.temp_c[rows_k])
            k = bn.add_residuals(rf, None, None, scale, held["where", edges])
            if ("M", edges) not in held:
                held["M", edges] = bn.design_moments(k, Xk)
            G = held["M", edges]
            bn.M += scale * (G if own_x else G[:, run.cols][:, :, run.cols])

    for sl in rows.chunks(None):
        X, Y = rows.block(sl)
        r = _resid(X, Y, theta)
        for k, run in enumerate(runs):
            if run.figures is not None:
                run.figures.add(sl.start, r[k])
            if run.resid is not None:
                run.resid[sl] = r[k].T
        del r
        if union:
            moments.add_rows(X, union, d.b_meas_uT[sl], d.temp_c[sl] - t0, None if d.weights is None else d.weights[sl])
        if grams is not None:
            grams.add_rows(X if d.weights is None else X * d.weights[sl][:, None], d.t_s[sl], d.session[sl])
        if order:
            at = dict(zip(("piece", "session", "block"), piece.with_blocks(sl), strict=True))
            for key in order:                  # one fold at a time: its held-out rows' copies live while it is done
                held = dict(at)
                for j in range(len(runs)):
                    if key in by_fold[j]:
                        held_out(j, *by_fold[j][key], sl, X, Y, held)
                del held
        del X, Y                               # before the next block's are built
    keep = decide()
    active = [k for k in keep if runs[k].figures is not None]
    while True:
        for k in active:
            runs[k].figures.end_pass()
        active = [k for k in active if runs[k].figures.pending]
        if not active:
            break
        for sl in rows.chunks(None):                 # the same residuals again, bit for bit
            X, Y = rows.block(sl)
            r = _resid(X, Y, theta)
            for k in active:
                runs[k].figures.add(sl.start, r[k])
    return keep


def _resid(X: np.ndarray, Y: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(k, 3, m) residuals ``Y - X theta_k`` of coefficient sets ``theta`` (p, 3 k), axis then row (every pass
    computes them alike, to the bit)."""
    r = (theta.T @ X.T).reshape(-1, 3, X.shape[0])
    return np.subtract(Y.T[None], r, out=r)


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
