"""The gap between a session and "the simulator", and the linear machinery to explain it.

Two ways to say what the simulator is:

* ``model`` (a): a set of calibration terms whose parameters are fitted to the session. The gap is
  measured the way a simulator works, truth to sensor: what remains of
  ``dut - model(ref, temp, currents)``; the target is the DUT reading and the base design holds the
  model's columns built by :class:`magstack.firmware.calibration.model.CalModel` from the *reference*
  (the forward form of the same terms). Without ``gain_matrix`` the gain is held at identity (target
  ``dut - ref``). In the calibration direction (``ref - model(dut)``) a session with one field level
  let the fitted gain go to zero and a constant absorb a real temperature drift.
* ``fixed`` (b): parameters held fixed (a calibration table, or error-model parameters through the
  ``--sim`` adapter). The gap is the session minus the fixed prediction; the base design holds only
  nuisance terms the fixed simulator treats as random (per-session offsets).

Every candidate effect is then a block of extra columns added to the base design. Folds are sets of
time blocks stratified by field magnitude (:func:`folds_from_blocks`: robust to bench programs that
repeat per power cycle); all figures are uT inside, nT at the JSON boundary.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from magstack.data.dictionary import usable
from magstack.data.session import Session
from magstack.firmware.calibration.model import CalModel
from magstack.firmware.errors import FitError
from magstack.ground.diagnose.reference_clip import reference_guard
from magstack.ground.errors import DiagnosisError

#: Memoised skew columns kept (floats); one column per (axis, delay) tried by the delay search.
SKEW_CACHE_FLOATS = 4_000_000
#: Relative singular-value cut-off of the column-equilibrated least-squares solves.
RCOND = 1e-10


@dataclass
class Block:
    """Design columns ``X`` (N,p), output-axis mask (3,p), parameter names [axis][col], units (p,)."""

    X: np.ndarray
    mask: np.ndarray
    names: list[list[str]]
    units: list[str]

    @property
    def p(self) -> int:
        return self.X.shape[1]

    @staticmethod
    def join(blocks: Sequence[Block], n: int) -> Block:
        if not blocks:
            return Block(np.zeros((n, 0)), np.zeros((3, 0), bool), [[], [], []], [])
        return Block(np.hstack([b.X for b in blocks]), np.hstack([b.mask for b in blocks]),
                     [sum((b.names[i] for b in blocks), []) for i in range(3)], sum((b.units for b in blocks), []))


@dataclass
class Gap:
    """What the search explains.

    ``target`` (N,3) uT; ``predictor_uT`` (N,3) the field candidate columns are built from (the
    reference in mode (a) and ``--sim``, the prediction's input in mode (b)); ``forward``: the gap is
    sensor minus a forward model of the reference (mode (a), ``--sim``), not the calibration direction
    (``--table``: ``ref - table(dut)``); ``base_terms`` the calibration terms
    fitted as the base (mode (a)) or as nuisance (mode (b)); ``identity_gain``: the base has no
    gain_matrix and the target already has the predictor subtracted; ``modelled`` effect names the
    simulator covers; ``raw_gap_uT`` the fixed gap in mode (b) (None in (a)).
    """

    mode: str
    session: Session
    target: np.ndarray
    predictor_uT: np.ndarray
    base_terms: tuple[str, ...]
    identity_gain: bool
    modelled: tuple[str, ...]
    description: str
    t0_c: float = 25.0
    extra_base: Callable[[np.ndarray], Block] | None = None
    forward: bool = False
    notes: list[str] = field(default_factory=list)
    #: (t_s, ref_uT, keep, run) of all usable rows, to re-sample the reference in time across rows
    #: the diagnosis leaves out (None: the gap's own rows)
    shift_source: tuple | None = None

    #: mode (b): d(prediction)/d(DUT reading) (3,3) used to de-skew the fixed gap (None in mode (a),
    #: where the base is refitted on the de-skewed reading)
    deskew_J: np.ndarray | None = None

    #: mode (a) with ``mount_rotation`` modelled: (MountColumns, per-axis weights sigma (3,) uT), set by
    #: the search; every fit then solves the base columns and the per-session angles jointly (rotation.py)
    rotation: tuple | None = None

    #: the reference-range guard of :func:`check_rows` (reference, range, saturated rows, excluded)
    reference: dict | None = None

    def history(self) -> tuple[np.ndarray, np.ndarray]:
        """(dut (M,3), idx (N,)): the excursion history for hysteresis, i.e. the DUT reading of every
        row with one, sorted by session then time (also rows left out for a missing or saturated
        reference), and the position of each of the gap's rows in it. Without a recorded history
        (``shift_source`` without it, or rows dropped after it was made): the gap's own rows."""
        src = self.shift_source
        if src is not None and len(src) > 4 and src[4] is not None:
            dut, idx_full = src[4]
            keep = src[2]
            idx = idx_full[keep] if not isinstance(keep, slice) else idx_full
            if idx.size == self.n:
                return dut, idx
        return self.session.dut_uT, np.arange(self.n)

    def _dut_image(self) -> np.ndarray:
        """A (3,3): the DUT-space image of the reference, ``dut ~ A ref + b`` (least squares)."""
        if getattr(self, "_A", None) is None:
            s = self.session
            X = np.column_stack([s.ref_uT, np.ones(len(s))])
            coef, *_ = np.linalg.lstsq(X, s.dut_uT, rcond=None)
            self._A = coef[:3].T
        return self._A

    def skew_columns(self, delay_s, shift_fn, cache: bool = True) -> np.ndarray:
        """(N,3) what DUT axis j gains by reading ``delay_j`` late, from the reference's (nearly
        noiseless) field mapped into DUT units: ``F_j = A_j . (ref(t + delay_j) - ref(t))``.
        ``shift_fn`` = nonlinear.shift_axes; shifting the clean reference (not the DUT reading) keeps
        the DUT's sample noise out of the correction. ``cache``: keep each axis' column for a repeat of its
        delay (the coordinate search; at most SKEW_CACHE_FLOATS floats)."""
        if self.shift_source is None:
            from magstack.ground.diagnose.nonlinear import runs
            t, ref, keep = self.session.t_s, self.session.ref_uT, slice(None)
            run = runs(t, self.session.session)
        else:
            t, ref, keep, run = self.shift_source[:4]
        A = self._dut_image()
        d = np.asarray(delay_s, dtype=float)
        out = np.zeros((self.n, 3))
        cache = self.__dict__.setdefault("_skew_cache", {}) if cache else None
        todo = []
        for j in range(3):
            if d[j] != 0:
                col = None if cache is None else cache.get((j, float(d[j])))
                if col is None:
                    todo.append(j)
                else:
                    out[:, j] = col
        for dv in sorted({float(d[j]) for j in todo}):   # one shift of the reference per distinct delay
            moved = (shift_fn(ref, t, run, np.full(3, -dv)) - ref)[keep]
            for j in todo:
                if float(d[j]) == dv:
                    out[:, j] = moved @ A[j]
                    if cache is not None:
                        if len(cache) * self.n > SKEW_CACHE_FLOATS:
                            cache.clear()
                        cache[(j, dv)] = out[:, j].copy()
            del moved
        return out

    def rows_view(self, rows: np.ndarray) -> Gap:
        """This gap on ``rows`` (indices), to build row-wise candidate columns for those rows only: session,
        target and predictor taken down; the reference's DUT-space image (:meth:`_dut_image`) stays the whole
        gap's. Terms that are not row-wise (time derivatives, shifts, histories) must not be built here; the
        drift pivot (the rows' mean time) and the session list may differ from the whole gap's, which leaves
        the span of columns with a constant unchanged."""
        g = dataclasses.replace(self, session=self.session.select(rows), target=self.target[rows],
                                predictor_uT=self.predictor_uT[rows], notes=list(self.notes))
        g._A = self._dut_image()
        return g

    def deskewed(self, F: np.ndarray, base: Block | None = None) -> tuple[Block, np.ndarray]:
        """(base design, target) with the DUT reading corrected by ``F`` (N,3); ``base``: the base design when
        the caller has it (it does not depend on ``F`` where ``deskew_J`` moves only the target)."""
        if self.deskew_J is not None:
            return (self.base_design() if base is None else base), self.target + F @ self.deskew_J.T
        p = self.predictor_uT - F
        return self.base_design(p), self.target_for(p)

    @property
    def n(self) -> int:
        return self.target.shape[0]

    @property
    def sessions(self) -> tuple[int, ...]:
        return tuple(int(s) for s in np.unique(self.session.session))

    def term_design(self, terms: Sequence[str], predictor_uT: np.ndarray | None = None) -> Block:
        """Columns of calibration ``terms`` (catalogue ``cal_term`` names) built from the predictor.

        FitError from the calibration model (e.g. no temperature) propagates; the caller turns it
        into "not testable".
        """
        s = self.session
        p = self.predictor_uT if predictor_uT is None else predictor_uT
        cm, keep = self.term_model(terms)
        X = cm.design(p, s.temp_c, s.currents_A, s.session, s.t_s)
        names = [[cm.param_name(i, c) for c in keep] for i in range(3)]
        return Block(X[:, keep], cm.axis_mask()[:, keep], names, [cm.columns[c].unit for c in keep])

    def term_model(self, terms: Sequence[str]) -> tuple[CalModel, list[int]]:
        """(the calibration model that builds ``terms``' columns, indices of those columns in it)."""
        terms = tuple(terms)
        s = self.session
        cm = CalModel(("gain_matrix",) + tuple(t for t in terms if t != "gain_matrix"),
                      tuple(s.currents_A) if "currents" in terms else (),
                      self.sessions if "session_offset" in terms else (), self.t0_c, float(np.mean(s.t_s)))
        return cm, [c for c, col in enumerate(cm.columns) if col.term in terms]

    def base_design(self, predictor_uT: np.ndarray | None = None) -> Block:
        """The base model's (mode a) or nuisance (mode b) columns."""
        blocks = []
        if self.base_terms:
            blocks.append(self.term_design(self.base_terms, predictor_uT))
        if self.extra_base is not None:
            blocks.append(self.extra_base(self.predictor_uT if predictor_uT is None else predictor_uT))
        return Block.join(blocks, self.n)

    def target_for(self, predictor_uT: np.ndarray) -> np.ndarray:
        """Target with a (shifted) predictor: only the identity-gain base subtracts the predictor."""
        if self.identity_gain:
            return self.target + self.predictor_uT - predictor_uT
        return self.target


# ----------------------------------------------------------------------------- folds
def time_blocks(t_s: np.ndarray, session: np.ndarray, block_s: float) -> np.ndarray:
    """Block id per row: consecutive ``block_s`` windows of each session, numbered globally."""
    out = np.zeros(t_s.size, dtype=np.int64)
    nxt = 0
    for s in np.unique(session):
        m = session == s
        k = np.floor((t_s[m] - np.nanmin(t_s[m])) / block_s).astype(np.int64)
        _, inv = np.unique(k, return_inverse=True)
        out[m] = inv + nxt
        nxt += int(inv.max()) + 1 if inv.size else 0
    return out


def folds_from_blocks(blocks: np.ndarray, session: np.ndarray, n_folds: int,
                      field_uT: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    """Fold id per row.

    With ``field_uT`` (N,3), stratified by field magnitude: blocks are ranked by their largest
    ``|B_j|`` (per axis as a rank percentile among the blocks, then the largest over axes), taken in
    consecutive groups of ``n_folds`` down that ranking, and each group is dealt to the folds by a
    seeded random permutation. Every fold then sees a spread of field magnitudes on every axis,
    whatever the timing of the program: "block k of a session -> fold k mod n" puts all of an axis'
    excursions into one fold when the program repeats per power cycle (its training then never sees
    that axis at high field). Without ``field_uT``: block k of each session -> fold k mod n_folds."""
    fold = np.zeros(blocks.size, dtype=np.int64)
    if field_uT is None:
        for s in np.unique(session):
            m = session == s
            _, inv = np.unique(blocks[m], return_inverse=True)
            fold[m] = inv % n_folds
        return fold
    ids, inv = np.unique(blocks, return_inverse=True)
    a = np.where(np.isfinite(field_uT), np.abs(field_uT), 0.0)
    peak = np.zeros((ids.size, 3))
    for j in range(3):
        np.maximum.at(peak[:, j], inv, a[:, j])
    pct = np.argsort(np.argsort(peak, axis=0, kind="stable"), axis=0, kind="stable") / max(ids.size - 1, 1)
    key = pct.max(axis=1) + 1e-3 * peak.max(axis=1) / max(float(peak.max()), 1e-12)
    order = np.argsort(-key, kind="stable")
    rng = np.random.default_rng(seed)
    bfold = np.empty(ids.size, dtype=np.int64)
    group = np.empty(ids.size, dtype=np.int64)
    for k in range(0, ids.size, n_folds):
        grp = order[k:k + n_folds]
        bfold[grp] = rng.permutation(n_folds)[:grp.size]
        group[grp] = k
    bsess = np.zeros(ids.size, dtype=session.dtype)
    bsess[inv] = session
    _separate_neighbours(bfold, group, bsess, order, n_folds)
    return bfold[inv]


def _separate_neighbours(bfold: np.ndarray, group: np.ndarray, bsess: np.ndarray, order: np.ndarray,
                         n_folds: int) -> None:
    """Swap folds within a stratification group (in place) so that no two consecutive blocks of a session
    share a fold where a swap allows it: a state or regime spanning two blocks (the remanence between a
    + and a - excursion) is then never held out whole, which no out-of-fold prediction could recover."""
    def clash(b: int) -> int:
        return sum(1 for c in (b - 1, b + 1) if 0 <= c < bfold.size and bsess[c] == bsess[b] and bfold[c] == bfold[b])

    for _ in range(3):
        changed = False
        for b in range(1, bfold.size):
            if bsess[b] != bsess[b - 1] or bfold[b] != bfold[b - 1]:
                continue
            k = group[b]
            for m in order[k:k + n_folds]:
                if m == b:
                    continue
                before = clash(b) + clash(m)
                bfold[b], bfold[m] = bfold[m], bfold[b]
                if clash(b) + clash(m) < before:
                    changed = True
                    break
                bfold[b], bfold[m] = bfold[m], bfold[b]
        if not changed:
            return


# ----------------------------------------------------------------------------- least squares
def gram(X: np.ndarray, Y: np.ndarray, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Normal-equation blocks ``X^T X`` (p,p) and ``X^T Y`` (p,3) over ``rows``."""
    A = X if rows is None else X[rows]
    B = Y if rows is None else Y[rows]
    return A.T @ A, A.T @ B


def solve_gram(G: np.ndarray, XtY: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Least-squares coefficients (3,p) from normal equations, per output axis over ``mask[i]``
    (:func:`solve_normal` once per group of axes sharing their columns)."""
    p = G.shape[0]
    theta = np.zeros((3, p))
    groups: dict[bytes, list[int]] = {}
    for i in range(3):
        groups.setdefault(mask[i].tobytes(), []).append(i)
    for _, axes in groups.items():
        cols = np.flatnonzero(mask[axes[0]])
        if cols.size == 0:
            continue
        if cols.size == p:                                  # every column: no sub-matrix to gather
            theta[axes] = solve_normal(G, XtY[:, axes]).T
        else:
            theta[np.ix_(axes, cols)] = solve_normal(G[np.ix_(cols, cols)], XtY[np.ix_(cols, axes)]).T
    return theta


def solve_normal(G: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Least-squares coefficients (p,k) from normal equations ``G`` (p,p), ``C`` (p,k): columns
    equilibrated (unit diagonal) and solved by Cholesky; a (near) rank-deficient ``G`` falls back to
    the pseudo-inverse with relative cut-off RCOND (minimum-norm solution)."""
    if G.shape[0] == 0:
        return np.zeros((0, C.shape[1]))
    d = np.sqrt(G.diagonal())
    d[d == 0] = 1.0
    Gn = G / np.outer(d, d)
    Cn = C / d[:, None]
    if np.isfinite(Gn).all() and np.isfinite(Cn).all():     # (what cho_factor's own check would refuse)
        # the LAPACK calls without scipy's per-call input checks: this runs hundreds of times per diagnosis
        c, info = scipy.linalg.lapack.dpotrf(Gn, lower=False, clean=False)
        dc = c.diagonal()
        if info == 0 and dc.min() ** 2 >= RCOND * dc.max() ** 2:
            sol, info = scipy.linalg.lapack.dpotrs(c, Cn, lower=False)
            if info == 0:
                return sol / d[:, None]
    sol = np.linalg.pinv(Gn, rcond=RCOND, hermitian=True) @ Cn
    return sol / d[:, None]


def solve_normal_batch(G: np.ndarray, C: np.ndarray) -> np.ndarray:
    """:func:`solve_normal` of a stack of systems ``G`` (k,p,p), ``C`` (k,p,r) -> (k,p,r): the same
    equilibration and rank test, the well-conditioned systems solved together (one numpy call instead of k),
    the others one by one through :func:`solve_normal` (its pseudo-inverse path). Equal to solving each
    system alone to rounding (~1e-15 relative)."""
    k, p = G.shape[0], G.shape[1]
    out = np.zeros((k, p, C.shape[2]))
    if k == 0 or p == 0:
        return out
    d = np.sqrt(np.einsum("kii->ki", G))
    d[d == 0] = 1.0
    Gn = G / (d[:, :, None] * d[:, None, :])
    Cn = C / d[:, :, None]
    ok = np.isfinite(Gn).all(axis=(1, 2)) & np.isfinite(Cn).all(axis=(1, 2))
    if ok.any():
        try:
            L = np.linalg.cholesky(Gn[ok])
            dl = np.einsum("kii->ki", L)
            good = dl.min(axis=1) ** 2 >= RCOND * dl.max(axis=1) ** 2
        except np.linalg.LinAlgError:             # some system not positive definite: each on its own
            good = np.zeros(int(ok.sum()), bool)
        idx = np.flatnonzero(ok)[good]
        if idx.size:
            out[idx] = np.linalg.solve(Gn[idx], Cn[idx]) / d[idx][:, :, None]
        ok[np.flatnonzero(ok)[~good]] = False
    for i in np.flatnonzero(~ok):
        out[i] = solve_normal(G[i], C[i])
    return out


def solve(X: np.ndarray, Y: np.ndarray, mask: np.ndarray, rows: np.ndarray | None = None,
          with_se: bool = False):
    """Least squares per output axis over the columns ``mask[i]`` uses.

    Returns ``theta`` (3,p) (unused entries 0) and, with ``with_se``, OLS standard errors (3,p)
    (NaN where unused): ``s^2 (X^T X)^-1`` with ``s^2 = SSE / (n - p_i)``.
    """
    G, XtY = gram(X, Y, rows)
    theta = solve_gram(G, XtY, mask)
    if not with_se:
        return theta
    A = X if rows is None else X[rows]
    Yr = Y if rows is None else Y[rows]
    se = np.full(theta.shape, np.nan)
    r = Yr - predict(A, theta, mask)
    for i in range(3):
        cols = np.flatnonzero(mask[i])
        if cols.size == 0:
            continue
        Gs = G[np.ix_(cols, cols)]
        d = np.sqrt(np.diag(Gs))
        d[d == 0] = 1.0
        cov = np.linalg.pinv(Gs / np.outer(d, d), rcond=RCOND, hermitian=True) / np.outer(d, d)
        s2 = float(r[:, i] @ r[:, i]) / max(A.shape[0] - cols.size, 1)
        se[i, cols] = np.sqrt(np.clip(np.diag(cov), 0, None) * s2)
    return theta, se


def predict(X: np.ndarray, theta: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return X @ np.where(mask, theta, 0.0).T


def out_of_fold(X: np.ndarray, Y: np.ndarray, mask: np.ndarray, fold: np.ndarray):
    """Out-of-fold residual (N,3) and the per-fold coefficient arrays (for a delete-one-fold jackknife).

    The training normal equations are the total minus the fold's own (one pass over the data)."""
    resid = np.full(Y.shape, np.nan)
    thetas = []
    G, XtY = gram(X, Y)
    for f in np.unique(fold):
        test = fold == f
        if (~test).sum() <= X.shape[1] or test.sum() == 0:
            continue
        Gf, Bf = gram(X, Y, test)
        th = solve_gram(G - Gf, XtY - Bf, mask)
        resid[test] = Y[test] - predict(X[test], th, mask)
        thetas.append(th)
    return resid, thetas


#: Rows per chunk of :func:`fold_products` and :func:`out_of_fold_blocks`.
FOLD_CHUNK = 65536


def fold_products(A, B, code: np.ndarray, n_folds: int) -> np.ndarray:
    """(folds, a, b): ``A_f^T B_f`` over the rows of each fold (``code`` 0..n_folds-1), in row chunks of
    FOLD_CHUNK. ``A`` and ``B`` are arrays (N,a), (N,b) or lists of arrays taken side by side per chunk (the
    joined N-row matrix is never formed)."""
    A, B = (A if isinstance(A, list) else [A]), (B if isinstance(B, list) else [B])
    out = np.zeros((n_folds, sum(x.shape[1] for x in A), sum(x.shape[1] for x in B)))
    for a in range(0, A[0].shape[0], FOLD_CHUNK):
        sl = slice(a, a + FOLD_CHUNK)
        c, Ac, Bc = code[sl], np.hstack([x[sl] for x in A]), np.hstack([x[sl] for x in B])
        for f in np.unique(c):
            m = c == f
            out[f] += Ac[m].T @ Bc[m]
    return out


def out_of_fold_blocks(blocks: Sequence[Block], Y: np.ndarray, fold: np.ndarray) -> np.ndarray:
    """:func:`out_of_fold`'s residual (N,3) for the design ``Block.join(blocks)``, never formed: its fold
    normal equations (:func:`fold_products`) and each fold's predictions are built in row chunks (memory of
    one chunk of the joined design instead of N rows of it)."""
    folds = np.unique(fold)
    code = np.searchsorted(folds, fold)
    mask = np.hstack([b.mask for b in blocks])
    p = mask.shape[1]
    Xs = [b.X for b in blocks]
    GC = fold_products(Xs, Xs + [Y], code, folds.size)             # (folds, p, p + 3): [X^T X | X^T Y]
    G, C = GC[:, :, :p], GC[:, :, p:]
    counts = np.bincount(code, minlength=folds.size)
    theta = [None if (Y.shape[0] - counts[f]) <= p or counts[f] == 0 else
             solve_gram(G.sum(axis=0) - G[f], C.sum(axis=0) - C[f], mask) for f in range(folds.size)]
    resid = np.full(Y.shape, np.nan)
    for a in range(0, Y.shape[0], FOLD_CHUNK):
        sl = slice(a, a + FOLD_CHUNK)
        X, c = np.hstack([x[sl] for x in Xs]), code[sl]
        for f in np.unique(c):
            if theta[f] is not None:
                m = c == f
                rows = np.flatnonzero(m) + a
                resid[rows] = Y[rows] - predict(X[m], theta[f], mask)
    return resid


def jackknife_se(thetas: list[np.ndarray]) -> np.ndarray:
    """Delete-one-fold jackknife standard error of fold estimates (each fit leaves one fold out)."""
    if len(thetas) < 2:
        return np.full_like(thetas[0], np.nan) if thetas else np.array([])
    a = np.stack(thetas)
    k = a.shape[0]
    return np.sqrt((k - 1) / k * np.sum((a - a.mean(axis=0)) ** 2, axis=0))


def usable_rows(s: Session) -> np.ndarray:
    """Rows with finite reference and DUT fields, finite time and flag 0."""
    ok = np.all(np.isfinite(s.ref_uT), axis=1) & np.all(np.isfinite(s.dut_uT), axis=1) & np.isfinite(s.t_s)
    if s.flag is not None:
        ok &= usable(s.flag)            # the dictionary's one rule: informational bits keep a row
    return ok


def check_rows(s: Session, min_rows: int = 50, exclude_bends: float | None = None,
               include_saturated: bool = False) -> tuple[Session, np.ndarray, list[str]]:
    """The usable rows sorted by session then time (attributes ``dut_history``: see
    :meth:`Gap.history`; ``reference_guard``: see :func:`.reference_clip.reference_guard`), the mask of those kept for
    the diagnosis (with ``exclude_bends``: not at sharp bends of the reference, see
    :func:`nonlinear.bend_rows`, nor at the edges of a contiguous run, see :func:`run_edge_rows`), and
    notes; DiagnosisError when too few remain. Rows with the reference at or beyond its range are
    left out (counted) unless ``include_saturated``: the calibration fit's guard."""
    from magstack.ground.diagnose.nonlinear import bend_rows
    notes = []
    ok = usable_rows(s)
    if ok.sum() < min_rows:
        raise DiagnosisError(f"only {int(ok.sum())} usable rows (finite ref and DUT, flag 0) of {len(s)}: "
                             f"need at least {min_rows}")
    if (~ok).any():
        notes.append(f"{int((~ok).sum())} rows without finite ref/DUT or with a disqualifying flag left out")
    guard, sat = reference_guard(s, ok, include_saturated)
    if guard["note"]:
        notes.append(guard["note"])
    if guard["saturated_rows"]:
        notes.append(f"{guard['saturated_rows']} rows with the reference at or beyond its range "
                     f"(+-{guard['range_uT']:g} uT, {guard['reference']}) "
                     + ("INCLUDED as requested (--include-saturated)" if include_saturated else
                        "left out (a clipped reference against the DUT's real reading looks like a nonlinearity; "
                        "--include-saturated keeps them)") + f": {guard['why']}")
        if not include_saturated:
            ok &= ~sat
            if ok.sum() < min_rows:
                raise DiagnosisError(f"only {int(ok.sum())} usable rows of {len(s)} with the reference inside its "
                                     f"range: need at least {min_rows}")
    # rows already usable and in order (the common case) share the caller's arrays (kept_rows)
    s2 = kept_rows(s, ok)
    order = np.lexsort((s2.t_s, s2.session))
    if not np.all(order == np.arange(order.size)):
        s2 = s2.select(order)
    # excursion history (hysteresis): every row with a DUT reading, sorted the same way
    has = np.all(np.isfinite(s.dut_uT), axis=1) & np.isfinite(s.t_s)
    h_rows = np.flatnonzero(has)
    h_rows = h_rows[np.lexsort((s.t_s[h_rows], s.session[h_rows]))]
    pos = np.full(len(s), -1, dtype=np.int64)
    pos[h_rows] = np.arange(h_rows.size)
    same = has.all() and bool(np.all(h_rows == np.arange(h_rows.size)))
    s2.dut_history = (s.dut_uT if same else s.dut_uT[h_rows], pos[np.flatnonzero(ok)[order]])
    s2.reference_guard = dict(guard)
    keep = np.ones(len(s2), bool)
    if exclude_bends is not None:
        bend = bend_rows(s2.ref_uT, s2.t_s, s2.session, exclude_bends, s2.dut_uT)
        if (~bend).sum() >= min_rows and bend.any():
            notes.append(f"{int(bend.sum())} rows at sharp bends of the reference field (step corners: "
                         f"|second difference| > {exclude_bends:g}x its robust level and > 8x the DUT noise) left "
                         "out: there two sample "
                         "streams cannot be paired to a fraction of a sample")
            keep = ~bend
        edge = run_edge_rows(s2.t_s, s2.session)
        if edge.any() and (keep & ~edge).sum() >= min_rows:
            notes.append(f"{int((edge & keep).sum())} rows within the delay search's half-width of a run's start or "
                         "end (session ends, gaps, reference dropouts) left out: a delayed axis there would need "
                         "the field beyond the recorded run")
            keep &= ~edge
    return s2, keep, notes


def kept_rows(full: Session, keep: np.ndarray) -> Session:
    """The rows of :func:`check_rows`' session that ``keep`` marks; when it marks them all, the same arrays
    (a copy of a 10^6-row session is 76 MiB; nothing in the diagnosis writes to a session's arrays)."""
    return dataclasses.replace(full) if keep.all() else full.select(keep)


def run_edge_rows(t_s: np.ndarray, session: np.ndarray) -> np.ndarray:
    """Rows closer than the delay search's half-width (``DELAY_HALF_WIDTH_ROWS`` median spacings) to
    the first or last row of their contiguous run (:func:`nonlinear.runs`)."""
    from magstack.ground.diagnose.nonlinear import DELAY_HALF_WIDTH_ROWS, runs
    run = runs(t_s, session)
    dt = np.diff(t_s)
    pos = dt[dt > 0]
    half = DELAY_HALF_WIDTH_ROWS * (float(np.median(pos)) if pos.size else 1.0)
    first = np.r_[0, np.flatnonzero(np.diff(run)) + 1]
    last = np.r_[first[1:] - 1, run.size - 1]
    k = np.repeat(np.arange(first.size), np.diff(np.r_[first, run.size]))
    return ((t_s - t_s[first][k]) < half) | ((t_s[last][k] - t_s) < half)


def model_gap(s: Session, base_terms: Sequence[str], modelled: Sequence[str], description: str,
              t0_c: float = 25.0, extra_base=None) -> Gap:
    """Mode (a): parameters of ``base_terms`` are fitted to the session itself, in the forward
    direction: ``dut = model(ref, temp, currents) + gap`` (the DUT reading de-skews by ``-F``)."""
    terms = tuple(base_terms)
    identity = "gain_matrix" not in terms
    # the session's own arrays where no difference is needed (nothing in the diagnosis writes to a gap's arrays)
    target = s.dut_uT - s.ref_uT if identity else s.dut_uT
    g = Gap("model", s, target, s.ref_uT, terms, identity, tuple(modelled), description, t0_c, extra_base,
            forward=True)
    g.deskew_J = -np.eye(3)
    try:
        g.base_design()
    except FitError as exc:
        raise DiagnosisError(f"the model cannot be built on this session: {exc}") from None
    return g


def fixed_gap(s: Session, gap_uT: np.ndarray, predictor_uT: np.ndarray, modelled: Sequence[str],
              description: str, nuisance_terms: Sequence[str] = (), t0_c: float = 25.0) -> Gap:
    """Mode (b): the gap (N,3) uT is the session minus a fixed prediction."""
    gap = np.asarray(gap_uT, dtype=float)
    ok = np.all(np.isfinite(gap), axis=1)
    if ok.sum() < 50:
        raise DiagnosisError(f"the fixed prediction is finite on only {int(ok.sum())} rows of {len(s)}")
    g = Gap("fixed", s.select(ok), gap[ok], np.asarray(predictor_uT, dtype=float)[ok], tuple(nuisance_terms),
            False, tuple(modelled), description, t0_c)
    if (~ok).any():
        g.notes.append(f"{int((~ok).sum())} rows without a fixed prediction (NaN) left out")
    return g
