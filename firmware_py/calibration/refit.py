"""On-orbit batch refit: telemetry + IGRF-14 reference in the body frame -> a candidate table.

Per block of telemetry rows (memory flat in the number of rows; :mod:`.streaming` accumulates):

1. housekeeping currents interpolated from their own rates (:mod:`.housekeeping`);
2. reference field: IGRF-14 at ``pos_ecef`` and ``t_s``, rotated ITRS -> GCRS -> body by
   ``q_body_eci`` (:mod:`magstack.firmware.reference`); sensor frame = body frame;
3. selection: no disqualifying flag bit (the dictionary's one rule, ``data.dictionary.usable``), finite inputs, geodetic
   latitude band, temperature band, eclipse state;
4. split: rows in every ``holdout_every``-th time block of ``holdout_block_s`` (absolute time, so
   independent of files and blocks) are held out; the rest are fitted;
5. accumulate: the fit rows' weighted ``[X | Y]`` (Eq. 3 plus currents, :class:`CalModel`), the
   held-out rows' unweighted ``[X | Y]``, fit coverage and 192-bin attitude coverage.

Passes: pass 1 is ordinary least squares. Each robust pass (``robust_passes``) re-reads the data
and weights fit rows by Huber (k = ``huber_k``) on their residual under the previous pass's
solution. The scale is 1.4826 x the median |residual| per axis, taken from a histogram of
|residual| (log bins, 0.9 % wide) accumulated in the previous robust pass, so it is global and
independent of how rows fall into blocks or files; the first robust pass, which has no histogram
yet, uses the OLS RMSE (inflated by outliers, so it down-weights only gross ones). A row's weight
is the smallest of its three axes' Huber weights. The held-out RMS of any parameter
set follows from the held-out R factor (``||R_h [theta; -1]||``), so the candidate and the active
table are compared on exactly the same rows without another pass.

Estimation: the MAP estimator of the bench fit (:mod:`.estimator`) with the active table as the prior
(:func:`prior_from_table`: its posterior covariance when the table carries one, else the chip's datasheet
sds around its values): a sequential (Kalman-style) update of the table. What the orbit's coverage cannot
determine stays at the active values with their uncertainty; no separate hold rule decides. The 192-bin
attitude coverage is reported (it explains which directions the orbit data could inform).

A candidate is proposed only if it passes :func:`cal_table.validate`, its held-out RMS (vector norm of the
per-axis values) is below the active table's by more than ``min_improvement``, and the improvement is
significant: a paired test over the held-out time blocks (over their parts when there are few:
:func:`.heldout_test.paired_test_over_parts`; on the
differences and the log ratios of the blocks' sums of squares, one-sided at ``ALPHA`` with Bonferroni, and at least
``MIN_GAIN`` of the active table's held-out sum of squares), from per-block Grams of
the held-out rows (:class:`.heldout_test.BlockGrams`), so both tables are scored on the same blocks without
another pass. A refit of the data a proposed table came from proposes nothing: within the noise, the active
table stays.

The work is a map (file -> :class:`PassStats`) and a reduce (:meth:`PassStats.merge`); ``mapper``
lets another engine (Dask, in the CLI) run the map and reduce; the in-process default reads the
files one after the other.
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magstack.data import telemetry
from magstack.data.dictionary import usable
from magstack.firmware import cal_table
from magstack.firmware.blas import single_thread
from magstack.firmware.calibration.coverage_bins import N_BINS, AttitudeCoverage
from magstack.firmware.calibration.estimator import Prior, model_prior
from magstack.firmware.calibration.fit import FitOptions, FitResult
from magstack.firmware.calibration.heldout_test import (
    PARTS_PER_BLOCK,
    BlockGrams,
    BlockSSE,
    PairedTest,
    paired_test_over_parts,
)
from magstack.firmware.calibration.housekeeping import MAX_GAP_S, interpolate_currents
from magstack.firmware.calibration.model import FLIGHT_TERMS, FLOAT_ONLY_TERMS, CalModel, resolve_terms
from magstack.firmware.calibration.predictive import (
    LeftOutMoments,
    from_holdout,
    left_out_terms,
)
from magstack.firmware.calibration.streaming import StreamingFit
from magstack.firmware.errors import FitError
from magstack.firmware.reference import frames, geomag

#: Histogram of |residual| per axis (robust scale without keeping residuals): log bins, uT.
HIST_EDGES_uT = np.geomspace(1e-5, 1e4, 2401)
ECLIPSE_MODES = ("any", "sunlit", "eclipse")


@dataclass(frozen=True)
class Selection:
    """Which rows may be used. ``lat_band_deg``: geodetic latitude (lo, hi) deg; ``temp_band_c``:
    (lo, hi) degC; ``eclipse``: any | sunlit | eclipse (cylindrical Earth shadow)."""

    lat_band_deg: tuple[float, float] | None = None
    temp_band_c: tuple[float, float] | None = None
    eclipse: str = "any"

    def __post_init__(self) -> None:
        if self.eclipse not in ECLIPSE_MODES:
            raise FitError(f"eclipse must be one of {ECLIPSE_MODES}, got {self.eclipse!r}")
        for name in ("lat_band_deg", "temp_band_c"):
            v = getattr(self, name)
            if v is not None and not (len(v) == 2 and all(math.isfinite(x) for x in v) and v[0] < v[1]):
                raise FitError(f"{name} must be (lo, hi) with lo < hi, got {v!r}")


@dataclass(frozen=True)
class RefitOptions:
    model: str = "eq3"
    currents: tuple[str, ...] | None = None      # None: every current column of the files
    selection: Selection = field(default_factory=Selection)
    robust: bool = True
    huber_k: float = 1.345
    robust_passes: int = 4
    cache_mb: float = 256.0                      # fit rows kept in memory for the robust passes
    holdout_block_s: float = 600.0
    holdout_every: int = 5
    max_current_gap_s: float = MAX_GAP_S
    block_rows: int = telemetry.BLOCK_ROWS
    dut1_s: float = 0.0
    min_holdout_rows: int = 100
    min_improvement: float = 0.0                 # fraction of the active held-out RMS
    min_temp_span_c: float = 5.0
    min_field_rms_uT: float = 2.0
    device_id: str | None = None

    def __post_init__(self) -> None:
        if self.holdout_every < 2 or not self.holdout_block_s > 0:
            raise FitError("holdout_every must be >= 2 and holdout_block_s > 0")
        if self.robust_passes < 0 or not self.huber_k > 0:
            raise FitError("robust_passes must be >= 0 and huber_k > 0")


def identity_table(device_id: str = "identity") -> cal_table.CalTable:
    """The table meaning "raw output taken as calibrated" (used when no active table is given)."""
    return cal_table.CalTable(device_id=device_id, terms=("gain_matrix", "offset"), S=np.eye(3),
                              model_name="identity", description="identity (raw output)")


def theta_from_table(model: CalModel, table: cal_table.CalTable) -> np.ndarray:
    """(3, p) coefficients of ``table`` in ``model``'s columns (terms the table lacks read 0)."""
    th = np.zeros((3, model.n_columns))
    d = dict(table.D)
    for c, col in enumerate(model.columns):
        if col.term not in table.terms:
            continue
        if col.term == "gain_matrix":
            th[:, c] = table.S[:, col.index]
        elif col.term == "temperature_gain":
            th[:, c] = table.K_S[:, col.index]
        elif col.term == "temperature_gain2":
            th[col.index, c] = table.K_S2[col.index]
        elif col.term == "offset":
            th[:, c] = table.O
        elif col.term == "temperature_offset":
            th[:, c] = table.K_O
        elif col.term == "currents":
            th[:, c] = d.get(col.param[2:], np.zeros(3))
        elif col.term == "cubic":
            th[col.index, c] = table.c3[col.index]
        elif col.term == "cross_products":
            th[:, c] = table.P[:, col.index]
    return th


@dataclass(frozen=True)
class Plan:
    """What every pass needs (picklable: shipped to workers)."""

    model: CalModel
    options: RefitOptions
    theta_active: np.ndarray
    prior: Prior | None = None
    left_out: tuple = ()                         # the catalogue terms the model leaves out (predictive.LeftOut)


@dataclass
class PassStats:
    """Mergeable result of one pass over some rows."""

    fit: StreamingFit
    hold: StreamingFit | None
    bins: AttitudeCoverage
    counts: dict[str, int]
    eclipse_rows: int = 0
    rows: int = 0
    hold_blocks: BlockGrams | None = None        # per held-out time block Grams (first pass)
    left_moments: LeftOutMoments | None = None   # fit rows' design x left-out features (first pass)
    abs_resid_hist: np.ndarray = field(default_factory=lambda: np.zeros((3, HIST_EDGES_uT.size + 1), np.int64))

    def robust_scale_uT(self) -> np.ndarray | None:
        """1.4826 x the median |residual| per axis from the histogram (None if empty)."""
        c = self.abs_resid_hist
        if c.sum() == 0:
            return None
        out = np.zeros(3)
        mids = np.r_[HIST_EDGES_uT[0], np.sqrt(HIST_EDGES_uT[1:] * HIST_EDGES_uT[:-1]), HIST_EDGES_uT[-1]]
        for i in range(3):
            cum = np.cumsum(c[i])
            out[i] = 1.4826 * mids[int(np.searchsorted(cum, 0.5 * cum[-1]))]
        return out

    def merge(self, other: PassStats) -> PassStats:
        self.fit.merge(other.fit)
        if self.hold is not None and other.hold is not None:
            self.hold.merge(other.hold)
        if self.hold_blocks is not None and other.hold_blocks is not None:
            self.hold_blocks.merge(other.hold_blocks)
        if self.left_moments is not None and other.left_moments is not None:
            self.left_moments.merge(other.left_moments)
        self.bins = self.bins.merge(other.bins)
        for k, v in other.counts.items():
            self.counts[k] = self.counts.get(k, 0) + v
        self.eclipse_rows += other.eclipse_rows
        self.rows += other.rows
        self.abs_resid_hist = self.abs_resid_hist + other.abs_resid_hist
        return self


def merge_stats(parts: Sequence[PassStats]) -> PassStats:
    out = parts[0]
    for p in parts[1:]:
        out = out.merge(p)
    return out


def _new_stats(plan: Plan, first_pass: bool) -> PassStats:
    fo = FitOptions(holdout=False)
    return PassStats(StreamingFit(plan.model, fo), StreamingFit(plan.model, fo) if first_pass else None,
                     AttitudeCoverage(), {}, hold_blocks=BlockGrams() if first_pass else None,
                     left_moments=LeftOutMoments(plan.model.n_columns, len(plan.left_out))
                     if first_pass and plan.left_out else None)


def reference_block(blk: telemetry.TelemetryBlock, dut1_s: float = 0.0):
    """(b_ref_body_uT (N,3), geodetic latitude deg (N,), eclipse (N,) bool) for rows with finite time,
    |position| 6300..100000 km and a unit quaternion (+-1e-3); other rows NaN / False."""
    n = len(blk)
    with np.errstate(invalid="ignore"):
        r = np.linalg.norm(blk.pos_ecef_km, axis=1)
        qn = np.linalg.norm(blk.q_body_eci, axis=1)
        # a GPS without fix (zeros) or a corrupted quaternion loses its row, not the whole refit
        ok = np.isfinite(blk.t_s) & (r >= 6300.0) & (r <= 100_000.0) & (np.abs(qn - 1.0) <= 1e-3)
    b = np.full((n, 3), np.nan)
    lat = np.full(n, np.nan)
    ecl = np.zeros(n, dtype=bool)
    if ok.any():
        t, p = blk.t_s[ok], blk.pos_ecef_km[ok]
        m = frames.gcrs_to_itrs_matrix(t, dut1_s)
        b_gcrs = np.einsum("nji,nj->ni", m, geomag.igrf_ecef_nT(t, p))
        b[ok] = geomag.attitude(blk.q_body_eci[ok]).apply(b_gcrs).reshape(-1, 3) / 1e3
        lat[ok] = frames.ecef_to_geodetic(p)[0]
        ecl[ok] = frames.in_eclipse(t, np.einsum("nji,nj->ni", m, p))
    return b, lat, ecl


def _nbytes(arrays: tuple) -> int:
    bm, y, tc, cc, ss, tt = arrays
    return bm.nbytes + y.nbytes + tc.nbytes + ss.nbytes + tt.nbytes + sum(v.nbytes for v in cc.values())


class FitRowCache:
    """In-process store of each file's fit rows (design inputs and reference) from pass 1, so the
    robust passes need not re-read files and re-evaluate IGRF; a file whose rows would exceed the
    budget is not kept (its passes re-read it), so memory stays below ``budget_mb``."""

    def __init__(self, budget_mb: float) -> None:
        self._lock = threading.Lock()        # tasks of a threaded scheduler add concurrently
        self.left = int(budget_mb * 1e6)
        self.files: dict[str, list[tuple]] = {}
        self.complete: set[str] = set()
        self._open: set[str] = set()

    def start(self, path: str) -> None:
        with self._lock:
            self.files[path] = []
            self._open.add(path)

    def add(self, path: str, arrays: tuple) -> None:
        with self._lock:
            if path not in self._open:
                return
            size = _nbytes(arrays)
            if size > self.left:   # does not fit: give this file's rows back, re-read it later
                self.left += sum(_nbytes(x) for x in self.files.pop(path))
                self._open.discard(path)
                return
            self.left -= size
            self.files[path].append(arrays)

    def finish(self, path: str) -> None:
        with self._lock:
            if path in self._open:
                self._open.discard(path)
                self.complete.add(path)


def file_pass(path: str, plan: Plan, theta: np.ndarray | None = None, sigma_uT: np.ndarray | None = None,
              progress: Callable[[int], None] | None = None, cache: FitRowCache | None = None) -> PassStats:
    """One pass over one file: the map step. ``theta`` None = OLS pass (also accumulates the
    held-out rows and coverage); otherwise Huber weights on residuals under ``theta``."""
    opt, model = plan.options, plan.model
    st = _new_stats(plan, theta is None)
    if theta is not None and cache is not None and path in cache.complete:
        for arrays in cache.files[path]:
            _robust_add(st, arrays, plan, theta, sigma_uT)
            if progress is not None:
                progress(arrays[0].shape[0])
        return st
    if theta is None and cache is not None:
        cache.start(path)
    blocks = interpolate_currents(telemetry.iter_telemetry(path, opt.block_rows), model.currents,
                                  opt.max_current_gap_s)
    for blk in blocks:
        _block_pass(st, blk, plan, theta, sigma_uT, cache)
        if progress is not None:
            progress(len(blk))
    if theta is None and cache is not None:
        cache.finish(path)
    return st


def _robust_add(st: PassStats, arrays: tuple, plan: Plan, theta, sigma_uT) -> None:
    """Huber-weighted accumulation of fit rows (b_meas, b_ref, temp, currents, session, t)."""
    bm, y, tc, cc, ss, tt = arrays
    if bm.shape[0] == 0:
        return
    model = plan.model
    X = model.design(bm, tc, cc, ss, tt)
    r = y - model.predict(theta, X)
    for i in range(3):
        st.abs_resid_hist[i] += np.bincount(np.searchsorted(HIST_EDGES_uT, np.abs(r[:, i])),
                                            minlength=HIST_EDGES_uT.size + 1)
    u = np.abs(r) / (plan.options.huber_k * np.maximum(sigma_uT, 1e-12))
    w = np.min(np.where(u <= 1, 1.0, 1.0 / np.maximum(u, 1e-300)), axis=1)
    st.fit.add(bm, y, tc, cc, ss, tt, weights=w, design=X, hist=False)    # pass 1's rows: its histograms


def _prepare_block(st: PassStats, blk: telemetry.TelemetryBlock, plan: Plan):
    """Reference field and row selection of one block: (b_ref (N,3), usable (N,), held out (N,), currents);
    counts the excluded rows by reason in ``st``."""
    opt, model = plan.options, plan.model
    sel = opt.selection
    cnt = st.counts
    n = len(blk)
    st.rows += n
    b_ref, lat, ecl = reference_block(blk, opt.dut1_s)
    st.eclipse_rows += int(ecl.sum())
    use = np.ones(n, dtype=bool)
    checks = []
    if blk.flag is not None:
        checks.append((~usable(blk.flag), "flag: not a good sample"))
    checks += [(~np.all(np.isfinite(blk.dut_uT), 1), "no sensor sample"),
               (~np.all(np.isfinite(b_ref), 1), "no or implausible position/attitude"),
               (~np.isfinite(blk.temp_c), "no temperature")]
    checks += [(~np.isfinite(blk.currents_A[k]), f"current {k} not interpolable") for k in model.currents]
    if sel.lat_band_deg is not None:
        checks.append((~((lat >= sel.lat_band_deg[0]) & (lat <= sel.lat_band_deg[1])), "outside latitude band"))
    if sel.temp_band_c is not None:
        checks.append((~((blk.temp_c >= sel.temp_band_c[0]) & (blk.temp_c <= sel.temp_band_c[1])),
                       "outside temperature band"))
    if sel.eclipse == "sunlit":
        checks.append((ecl, "in eclipse"))
    elif sel.eclipse == "eclipse":
        checks.append((~ecl, "sunlit"))
    for bad, reason in checks:
        k = int((use & bad).sum())
        if k:
            cnt[reason] = cnt.get(reason, 0) + k
        use &= ~bad
    held_out = holdout_block(blk.t_s, opt) % opt.holdout_every == 0
    cur = {k: blk.currents_A[k] for k in model.currents}
    return b_ref, use, held_out, cur


def _rows(blk: telemetry.TelemetryBlock, b_ref, cur, mask) -> tuple:
    """(b_meas, b_ref, temp, currents, session, t) of the rows in ``mask``."""
    return (blk.dut_uT[mask], b_ref[mask], blk.temp_c[mask], {k: v[mask] for k, v in cur.items()},
            blk.session[mask], blk.t_s[mask])


def _block_pass(st: PassStats, blk: telemetry.TelemetryBlock, plan: Plan, theta, sigma_uT,
                cache: FitRowCache | None = None) -> None:
    b_ref, use, held_out, cur = _prepare_block(st, blk, plan)
    fit_rows = use & ~held_out
    if theta is None:
        arrays = _rows(blk, b_ref, cur, fit_rows)
        st.fit.add(*arrays)
        if st.left_moments is not None and arrays[0].shape[0]:
            X = plan.model.design(arrays[0], arrays[2], arrays[3], arrays[4], arrays[5])
            st.left_moments.add_rows(X, plan.left_out, arrays[0], arrays[2] - plan.model.t0_c)
        st.bins.update(b_ref[fit_rows], blk.temp_c[fit_rows])
        held = _rows(blk, b_ref, cur, use & held_out)
        st.hold.add(*held)
        if held[0].shape[0]:
            X = plan.model.design(held[0], held[2], held[3], held[4], held[5])
            st.hold_blocks.add(np.zeros(X.shape[0], np.int64), holdout_part(held[5], plan.options), X, held[1])
        if cache is not None:
            cache.add(blk.path, arrays)
    else:
        _robust_add(st, _rows(blk, b_ref, cur, fit_rows), plan, theta, sigma_uT)


def holdout_block(t_s: np.ndarray, options: RefitOptions) -> np.ndarray:
    """The held-out time block of each row (absolute time: independent of files and blocks)."""
    return np.floor(np.asarray(t_s) / options.holdout_block_s).astype(np.int64)


def holdout_part(t_s: np.ndarray, options: RefitOptions) -> np.ndarray:
    """The part of its held-out block each row falls in (``PARTS_PER_BLOCK`` per block; ``part //
    PARTS_PER_BLOCK`` is :func:`holdout_block`), the unit of the paired held-out test."""
    return np.floor(np.asarray(t_s) / (options.holdout_block_s / PARTS_PER_BLOCK)).astype(np.int64)


def holdout_rms(R: np.ndarray, theta: np.ndarray, model: CalModel, n: int) -> np.ndarray:
    """(3,) RMS residual of ``theta`` on the rows whose R factor is ``R`` (unweighted), uT."""
    p = model.n_columns
    th = np.where(model.axis_mask(), theta, 0.0)
    out = np.zeros(3)
    for i in range(3):
        z = np.zeros(p + 3)
        z[:p] = th[i]
        z[p + i] = -1.0
        out[i] = np.linalg.norm(R @ z)
    return out / np.sqrt(max(n, 1))


def prior_from_table(model: CalModel, table: cal_table.CalTable, chip: str | None = None) -> Prior:
    """The prior of a refit: the active table's values, with its posterior covariance where the table
    carries one (parameters it lacks: the chip's datasheet sd around the table's value, or 0 for terms the
    table does not have), else the chip's datasheet sds around the table's values."""
    from magstack.drivers.cal_priors import priors_for

    chip_prior = model_prior(model, priors_for(chip or table.device_id), table.S)
    mean = theta_from_table(model, table)
    cov = chip_prior.cov.copy()
    src = [list(r) for r in chip_prior.source]
    block = table.posterior
    if block is not None:
        for i, a in enumerate(("x", "y", "z")):
            names = list(block[a]["names"])
            C = np.asarray(block[a]["cov"], dtype=float)
            idx = {model.param_name(i, c): c for c in range(model.n_columns) if model.axis_mask()[i, c]}
            have = [k for k, nm in enumerate(names) if nm in idx]
            cols = [idx[names[k]] for k in have]
            for c in cols:   # replace the chip prior by the table's posterior for these parameters
                cov[i, c, :] = 0.0
                cov[i, :, c] = 0.0
            cov[i][np.ix_(cols, cols)] = C[np.ix_(have, have)]
            for c in cols:
                src[i][c] = f"active table posterior ({table.description or table.table_name})"
    return Prior(mean, cov, tuple(tuple(r) for r in src))


def solve(stats: PassStats, plan: Plan) -> FitResult:
    """The MAP candidate of the accumulated pass: prior = the active table (:func:`prior_from_table`), so
    what the orbit's coverage cannot determine stays at the active values with their uncertainty."""
    model = plan.model
    sf = stats.fit
    p = model.n_columns
    if sf.n_used <= p:
        raise FitError(f"{sf.n_used} usable fit rows for {p} columns: not enough data "
                       f"(excluded: {dict(stats.counts) or 'none'})")
    sf.options = dataclasses.replace(sf.options, prior=plan.prior, min_temp_span_c=plan.options.min_temp_span_c,
                                     min_field_rms_uT=plan.options.min_field_rms_uT)
    res = sf.solve()
    res.notes.clear()
    return res


@dataclass
class RefitResult:
    """Outcome of a refit. ``candidate`` is None when no fit was possible; ``proposed`` says whether
    it may be offered to the flight table commands (validated and better on held-out data)."""

    method: str
    candidate: cal_table.CalTable | None
    proposed: bool
    reasons: list[str]
    fit: FitResult | None
    holdout_candidate_uT: np.ndarray | None
    holdout_active_uT: np.ndarray | None
    n_holdout: int
    bins: AttitudeCoverage | None
    counts: dict[str, int]
    rows: int
    eclipse_rows: int
    passes: int
    runtime_s: float
    active_name: str
    notes: list[str] = field(default_factory=list)
    paired_test: PairedTest | None = None

    def to_dict(self) -> dict[str, Any]:
        def lst(v):
            return None if v is None else [float(x) for x in v]
        f = self.fit
        cov = None if f is None else f.coverage
        return {
            "method": self.method, "proposed": self.proposed, "reasons": self.reasons,
            "rows": self.rows, "rows_fitted": None if f is None else f.n_used, "rows_holdout": self.n_holdout,
            "rows_in_eclipse": self.eclipse_rows, "excluded": dict(self.counts), "passes": self.passes,
            "runtime_s": self.runtime_s, "active": self.active_name,
            "holdout_rms_candidate_uT": lst(self.holdout_candidate_uT),
            "holdout_rms_active_uT": lst(self.holdout_active_uT),
            "holdout_rms_candidate_norm_uT": None if self.holdout_candidate_uT is None
            else float(np.linalg.norm(self.holdout_candidate_uT)),
            "holdout_rms_active_norm_uT": None if self.holdout_active_uT is None
            else float(np.linalg.norm(self.holdout_active_uT)),
            "paired_test": _test_dict(self.paired_test),
            "attitude_bins_filled": None if self.bins is None else self.bins.bins_filled,
            "attitude_bins_total": N_BINS,
            "attitude_coverage": None if self.bins is None else self.bins.fraction,
            "attitude_bins_per_temp_band": None if self.bins is None else
            [{"temp_c": [lo, hi], "bins": k} for lo, hi, k in self.bins.per_temp_band()],
            "temp_range_c": None if cov is None else [cov.temp_min_c, cov.temp_max_c],
            "temp_span_c": None if cov is None else cov.temp_span_c,
            "held": [] if f is None else [{"param": h.name, "value": h.value, "reason": h.reason} for h in f.held],
            "fitted": [] if f is None else fitted_names(f),
            "parameters": None if f is None else {f.model.param_name(i, c): float(f.theta[i, c])
                                                  for i in range(3) for c in range(f.model.n_columns)
                                                  if f.model.axis_mask()[i, c]},
            "notes": self.notes,
        }

    def report(self) -> str:
        d = self.to_dict()
        L = [f"refit ({self.method}): {self.rows} rows read, {d['rows_fitted']} fitted, {self.n_holdout} held out, "
             f"{self.passes} pass(es), {self.runtime_s:.1f} s; active table: {self.active_name}"]
        if self.counts:
            L.append("excluded rows: " + ", ".join(f"{k} {v}" for k, v in sorted(self.counts.items())))
        if self.bins is not None:
            L.append(f"attitude coverage: {self.bins.bins_filled} of {N_BINS} equal-area bins "
                     f"({100 * self.bins.fraction:.1f} %); temperature {d['temp_range_c'][0]:.1f}.."
                     f"{d['temp_range_c'][1]:.1f} degC (span {d['temp_span_c']:.1f} degC); "
                     f"{self.eclipse_rows} rows in eclipse")
            L.append("  bins per 5 degC band: " + ", ".join(f"{lo:g}..{hi:g}: {k}" for lo, hi, k in
                                                           self.bins.per_temp_band()))
        if self.fit is not None:
            L.append(f"fitted ({len(d['fitted'])}): " + ", ".join(d["fitted"]))
            if self.fit.held:
                L.append(f"determined by the prior (the active table), not the orbit data ({len(self.fit.held)}):")
                L += [f"  {h.name} = {h.value:g}: {h.reason}" for h in self.fit.held]
        if self.holdout_candidate_uT is not None:
            def row(label, v):
                v = np.asarray(v) * 1e3
                return f"  {label:22s}" + "".join(f"{x:10.1f}" for x in v) + f"{np.linalg.norm(v):10.1f}"
            L += [f"held-out RMS on {self.n_holdout} rows (nT):{'x':>9s}{'y':>10s}{'z':>10s}{'norm':>10s}",
                  row("candidate", self.holdout_candidate_uT), row(f"active ({self.active_name})",
                                                                    self.holdout_active_uT)]
        if self.paired_test is not None:
            L.append("candidate vs active, paired over held-out blocks: " + self.paired_test.describe())
        L.append(("PROPOSED: " if self.proposed else "NOT proposed: ") + "; ".join(self.reasons))
        L += [f"note: {n}" for n in self.notes]
        return "\n".join(L)


def fitted_names(f: FitResult) -> list[str]:
    held = {(h.axis, h.column) for h in f.held}
    m = f.model.axis_mask()
    return [f.model.param_name(i, c) for i in range(3) for c in range(f.model.n_columns)
            if m[i, c] and (i, c) not in held]


def make_plan(paths: Sequence[str], active: cal_table.CalTable, options: RefitOptions) -> Plan:
    """Model (terms of ``options.model`` plus the active table's flight terms, currents) for these files."""
    if not paths:
        raise FitError("no telemetry files")
    headers = [telemetry.read_header(p) for p in paths]
    in_data = set(headers[0].currents)
    for h in headers[1:]:
        in_data &= set(h.currents)
    if options.currents is None:
        currents = tuple(sorted(in_data))
    else:
        currents = tuple(options.currents)
    missing = [k for k in set(currents) | set(active.currents) if k not in in_data]
    if missing:
        raise FitError(f"current(s) {sorted(missing)} not in every telemetry file (have {sorted(in_data)})")
    currents = tuple(dict.fromkeys(currents + active.currents))
    extra = [t for t in active.terms if t in FLIGHT_TERMS + FLOAT_ONLY_TERMS and t != "currents"]
    terms = resolve_terms(options.model, extra, currents)
    model = CalModel(terms, currents, (), active.t0_c, 0.0, options.model)
    from magstack.drivers.cal_priors import priors_for

    left_out = tuple(left_out_terms(model, priors_for(active.device_id), np.diag(np.asarray(active.S, dtype=float))))
    return Plan(model, options, theta_from_table(model, active), prior_from_table(model, active), left_out)


def local_mapper(paths: Sequence[str], fn: Callable[[str], PassStats]) -> PassStats:
    """In-process map (file order) and reduce."""
    return merge_stats([fn(p) for p in paths])


def refit(paths: Sequence[str], active: cal_table.CalTable | None = None, options: RefitOptions | None = None,
          *, progress: Callable[[int, str], None] | None = None,
          mapper: Callable[[Sequence[str], Callable[[str], PassStats]], PassStats] | None = None,
          metadata: Mapping[str, str] | None = None) -> RefitResult:
    """Refit the calibration against the attitude-rotated IGRF reference (see the module docstring).

    ``progress(rows, label)`` is called per block; ``mapper(paths, fn)`` runs ``fn`` per file and
    reduces (default :func:`local_mapper`). BLAS runs on one thread meanwhile (blocks of ~1k rows x 30
    columns and the validity search's small products: more threads only wait, ``firmware/blas.py``)."""
    with single_thread():
        return _refit(paths, active, options, progress, mapper, metadata)


def _refit(paths, active, options, progress, mapper, metadata) -> RefitResult:
    t_start = time.perf_counter()
    options = options or RefitOptions()
    paths = [str(p) for p in paths]
    if len(set(paths)) != len(paths):
        raise FitError("a telemetry file is given more than once")
    active_name = "identity" if active is None else (active.description or active.table_name or "active")
    if not paths:
        raise FitError("no telemetry files")
    meta = dict(metadata) if metadata is not None else telemetry.read_header(paths[0]).metadata
    device = options.device_id or (active.device_id if active is not None else None) \
        or meta.get("device_id") or meta.get("dut_serial") or meta.get("dut_chip")
    if not device:
        raise FitError("no device id: pass one (--device-id) or an active table")
    active = active if active is not None else identity_table(device)
    plan = make_plan(paths, active, options)
    mapper = mapper or local_mapper
    n_pass = 1 + (options.robust_passes if options.robust else 0)

    # a mapper whose tasks run in this process (the in-process default, Dask's threaded scheduler) shares the
    # fit-row cache, so the robust passes do not re-read the files and re-evaluate the reference field
    same_process = mapper is local_mapper or getattr(mapper, "in_process", False)
    cache = FitRowCache(options.cache_mb) if same_process and options.cache_mb > 0 else None

    def run(theta, sigma, k):
        cb = None if progress is None else (lambda n: progress(n, f"pass {k}/{n_pass}"))
        return mapper(paths, lambda p: file_pass(p, plan, theta, sigma, cb, cache))

    first = run(None, None, 1)
    res = solve(first, plan)
    scale = res.rmse_uT
    for k in range(2, n_pass + 1):
        stats = run(res.theta, scale, k)   # same rows as pass 1 (Huber weights are never 0)
        stats.fit.coverage.field_hist = first.fit.coverage.field_hist.copy()       # so its field histograms
        stats.fit.coverage.ref_hist = first.fit.coverage.ref_hist.copy()
        scale = stats.robust_scale_uT()
        if scale is None:
            break
        res = solve(stats, plan)
        res.robust = True
    hold = first.hold
    h_cand = holdout_rms(hold.R, res.theta, plan.model, hold.n_used)
    h_act = holdout_rms(hold.R, plan.theta_active, plan.model, hold.n_used)
    if res.posterior is not None:
        res.uncertainty = from_holdout(res.posterior, hold.R, hold.n_used, res.coverage, plan.left_out,
                                       first.left_moments, first.fit.R)
    table = cal_table.table_from_fit(res, device, description=f"on-orbit refit (attitude, IGRF-14) vs {active_name}")
    stats_doc = dict(table.fit_stats)
    stats_doc.update({"refit_method": "attitude", "holdout_rms_candidate_uT": h_cand.tolist(),
                      "holdout_rms_active_uT": h_act.tolist(), "holdout_rows": hold.n_used,
                      "attitude_bins_filled": first.bins.bins_filled})
    table = dataclasses.replace(table, fit_stats=stats_doc)
    reasons = []
    val = cal_table.validate(table)
    if not val.ok:
        reasons.append("candidate fails validation: " + "; ".join(val.problems))
    if hold.n_used < options.min_holdout_rows:
        reasons.append(f"only {hold.n_used} held-out rows (need {options.min_holdout_rows})")
    nc, na = float(np.linalg.norm(h_cand)), float(np.linalg.norm(h_act))
    mask = plan.model.axis_mask()
    test = paired_test_over_parts(first.hold_blocks.sse(np.where(mask, plan.theta_active, 0.0)),
                                  first.hold_blocks.sse(np.where(mask, res.theta, 0.0)), scale_free=True)
    stats_doc["paired_test"] = _test_dict(test)
    table = dataclasses.replace(table, fit_stats=stats_doc)
    if not nc < na * (1.0 - options.min_improvement):
        reasons.append(f"held-out RMS {nc * 1e3:.1f} nT is not better than the active table's {na * 1e3:.1f} nT")
    elif not test.significant:
        reasons.append(f"held-out RMS {nc * 1e3:.1f} nT vs active {na * 1e3:.1f} nT is within the noise: "
                       + test.describe())
    proposed = not reasons
    if proposed:
        reasons.append(f"held-out RMS {nc * 1e3:.1f} nT vs active {na * 1e3:.1f} nT, significant ({test.describe()}); "
                       "validation passed")
    out = RefitResult("attitude", table, proposed, reasons, res, h_cand, h_act, hold.n_used, first.bins,
                      first.counts, first.rows, first.eclipse_rows, n_pass, time.perf_counter() - t_start,
                      active_name, paired_test=test)
    return out


def _test_dict(test: PairedTest | None) -> dict | None:
    """JSON form of a paired held-out test, with its thresholds."""
    if test is None:
        return None
    from magstack.firmware.calibration.heldout_test import ALPHA, MIN_GAIN

    return {"gain": test.gain, "t": test.t, "p": test.p, "blocks": test.blocks, "batches": test.batches,
            "significant": test.significant, "scale_free": test.scale_free, "parts_of_blocks": test.parts_of,
            "alpha": ALPHA, "min_gain": MIN_GAIN}


__all__ = ["RefitOptions", "RefitResult", "Selection", "Plan", "PassStats", "refit", "file_pass", "make_plan",
           "merge_stats", "local_mapper", "identity_table", "theta_from_table", "holdout_rms"]


# ---------------------------------------------------------------------- attitude-independent (scalar)
@dataclass
class ScalarRefitResult:
    """Outcome of ``--method scalar``: magnitude-only fit (:func:`scalar.refit_scalar`) on the fit rows,
    candidate vs active compared by the RMS of ``|B_cal| - |B_ref|`` on the held-out rows."""

    candidate: cal_table.CalTable | None
    proposed: bool
    reasons: list[str]
    fit: Any
    holdout_candidate_uT: float
    holdout_active_uT: float
    n_fit: int
    n_holdout: int
    counts: dict[str, int]
    rows: int
    runtime_s: float
    active_name: str
    paired_test: PairedTest | None = None

    def to_dict(self) -> dict[str, Any]:
        f = self.fit
        return {"method": "scalar", "proposed": self.proposed, "reasons": self.reasons, "rows": self.rows,
                "paired_test": _test_dict(self.paired_test),
                "rows_fitted": self.n_fit, "rows_holdout": self.n_holdout, "excluded": dict(self.counts),
                "runtime_s": self.runtime_s, "active": self.active_name,
                "holdout_scalar_rms_candidate_uT": self.holdout_candidate_uT,
                "holdout_scalar_rms_active_uT": self.holdout_active_uT,
                "gauge": None if f is None else f.gauge,
                "S": None if f is None else np.asarray(f.S).tolist(),
                "O_uT": None if f is None else np.asarray(f.O_uT).tolist(),
                "fit_scalar_rms_uT": None if f is None else f.rms_residual_uT}

    def report(self) -> str:
        L = [f"refit ({self.fit.method}, attitude-independent): {self.rows} rows read, {self.n_fit} fitted, "
             f"{self.n_holdout} "
             f"held out, {self.runtime_s:.1f} s; active table: {self.active_name}"]
        if self.counts:
            L.append("excluded rows: " + ", ".join(f"{k} {v}" for k, v in sorted(self.counts.items())))
        if self.fit is not None:
            L.append(f"fitted: S (3x3), O (3) [gauge {self.fit.gauge}]; every other term of the active table "
                     "is dropped (magnitude-only fit)")
        L.append(f"held-out RMS of |B_cal| - |B_ref| (nT): candidate {self.holdout_candidate_uT * 1e3:.1f}, "
                 f"active ({self.active_name}) {self.holdout_active_uT * 1e3:.1f}")
        if self.paired_test is not None:
            L.append("candidate vs active, paired over held-out blocks: " + self.paired_test.describe())
        L.append(("PROPOSED: " if self.proposed else "NOT proposed: ") + "; ".join(self.reasons))
        return "\n".join(L)


#: PSO on telemetry: samples kept per locus and loci kept (the swarm's cost is linear in the samples).
PSO_SAMPLES_PER_LOCUS = 48
PSO_MAX_LOCI = 24
#: Smallest angle between two loci axes for the rotation-axis gauge to fix the sensor rotation.
PSO_MIN_AXIS_SPREAD_DEG = 20.0


def _axis_spread_deg(axes: np.ndarray) -> float:
    """Largest angle (deg) between any two loci axes, sign-free (0 for fewer than two)."""
    if len(axes) < 2:
        return 0.0
    c = np.clip(np.abs(axes @ axes.T), 0.0, 1.0)
    return float(np.degrees(np.arccos(c.min())))


def _pso_loci(t_s: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row indices, locus labels of those rows, unit axes) for the PSO: rotation-axis loci from the
    attitude (:mod:`.spin_loci`), each thinned to ``PSO_SAMPLES_PER_LOCUS`` evenly spaced rows, at most
    ``PSO_MAX_LOCI`` loci spread over the run."""
    from magstack.firmware.calibration.spin_loci import loci_from_attitude

    labels, axes = loci_from_attitude(t_s, q)
    keep = np.unique(labels[labels >= 0])
    if keep.size > PSO_MAX_LOCI:
        keep = keep[np.linspace(0, keep.size - 1, PSO_MAX_LOCI).round().astype(int)]
    rows, labs = [], []
    for new, old in enumerate(keep):
        idx = np.flatnonzero(labels == old)
        idx = idx[np.linspace(0, idx.size - 1, min(PSO_SAMPLES_PER_LOCUS, idx.size)).round().astype(int)]
        rows.append(idx)
        labs.append(np.full(idx.size, new))
    if not rows:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3))
    return np.concatenate(rows), np.concatenate(labs), axes[keep]


def refit_scalar_telemetry(paths: Sequence[str], active: cal_table.CalTable | None = None,
                           options: RefitOptions | None = None, *,
                           progress: Callable[[int, str], None] | None = None, method: str = "scalar",
                           seed: int = 0) -> ScalarRefitResult:
    """``--method scalar|pso`` on telemetry: the same reading, reference, selection and held-out split as
    :func:`refit`, then :func:`magstack.firmware.calibration.scalar.refit_scalar` on the fit rows.
    ``scalar``: closed form + least squares on ``|B_ref|`` (gauge ``prior`` = the active table's S when
    given). ``pso``: the riwanto PSO on rotation-axis loci found in the attitude (:func:`_pso_loci`; a
    spinning spacecraft; refused when fewer than two loci with non-parallel axes exist). The fit rows are
    collected in memory (a batch fit: O(N))."""
    from magstack.firmware.calibration.scalar import refit_scalar

    t_start = time.perf_counter()
    options = options or RefitOptions()
    paths = [str(p) for p in paths]
    if not paths:
        raise FitError("no telemetry files")
    meta = telemetry.read_header(paths[0]).metadata
    device = options.device_id or (active.device_id if active is not None else None) \
        or meta.get("device_id") or meta.get("dut_serial") or meta.get("dut_chip")
    if not device:
        raise FitError("no device id: pass one (--device-id) or an active table")
    active_name = "identity" if active is None else (active.description or active.table_name or "active")
    act = active if active is not None else identity_table(device)
    plan = make_plan(paths, act, options)
    fit_parts, hold_parts, att_parts, counts, rows = [], [], [], {}, 0
    for path in paths:
        st = _new_stats(plan, True)
        blocks = interpolate_currents(telemetry.iter_telemetry(path, options.block_rows), plan.model.currents,
                                      options.max_current_gap_s)
        for blk in blocks:
            b_ref, use, held_out, cur = _prepare_block(st, blk, plan)
            fit_parts.append(_rows(blk, b_ref, cur, use & ~held_out))
            att_parts.append(blk.q_body_eci[use & ~held_out])
            h = _rows(blk, b_ref, cur, use & held_out)
            hold_parts.append((h[0], h[1], plan.model.design(*h[:1], h[2], h[3], h[4], h[5]), h[5]))
            if progress is not None:
                progress(len(blk), "pass 1/1")
        for k, v in st.counts.items():
            counts[k] = counts.get(k, 0) + v
        rows += st.rows
    bm = np.vstack([a[0] for a in fit_parts]) if fit_parts else np.zeros((0, 3))
    y = np.vstack([a[1] for a in fit_parts]) if fit_parts else np.zeros((0, 3))
    if bm.shape[0] < 20:
        raise FitError(f"{bm.shape[0]} usable fit rows: not enough for a scalar fit")
    K_prior = None if active is None else act.S
    if method not in ("scalar", "pso"):
        raise FitError(f"unknown telemetry refit method {method!r}; valid: scalar, pso")
    t_fit = np.concatenate([a[5] for a in fit_parts])
    idx, lab, axes = _pso_loci(t_fit, np.vstack(att_parts))
    spread = _axis_spread_deg(axes)
    axes_ok = np.unique(lab).size >= 2 and spread >= PSO_MIN_AXIS_SPREAD_DEG
    if method == "pso":
        if not axes_ok:
            raise FitError("the PSO fixes the rotation by the rotation axes and needs loci about at least two body "
                           f"axes >= {PSO_MIN_AXIS_SPREAD_DEG:g} deg apart (each turning >= 90 deg at >= 0.5 deg/s); "
                           f"the attitude shows {np.unique(lab).size} loci whose axes span {spread:.1f} deg (a spin "
                           "about one body axis leaves the rotation about it free): use --method attitude or scalar")
        fit = refit_scalar(bm[idx], y[idx], method="pso", locus=lab, omega_body=axes, K_prior=K_prior, seed=seed)
    elif axes_ok:
        # the loci fix the rotation too: least squares on |B_ref| plus the rotation-axis residuals (gauge "axes")
        loc = np.full(bm.shape[0], -1)
        loc[idx] = lab
        keep = loc >= 0
        fit = refit_scalar(bm[keep], y[keep], method="scalar", locus=loc[keep], omega_body=axes, K_prior=K_prior)
    else:
        fit = refit_scalar(bm, y, method="scalar", K_prior=K_prior)
    hb = [h for h in hold_parts if h[0].shape[0]]
    n_hold = int(sum(h[0].shape[0] for h in hb))
    cand_sq = act_sq = 0.0
    cand_blocks, act_blocks = BlockSSE(), BlockSSE()
    for bmh, yh, xh, th in hb:
        r = np.linalg.norm(yh, axis=1)
        ec = (np.linalg.norm(bmh @ np.asarray(fit.S).T + fit.O_uT, axis=1) - r) ** 2
        ea = (np.linalg.norm(plan.model.predict(plan.theta_active, xh), axis=1) - r) ** 2
        cand_sq += float(np.sum(ec))
        act_sq += float(np.sum(ea))
        blk = holdout_part(th, options)
        cand_blocks.add(np.zeros(blk.size, np.int64), blk, ec)
        act_blocks.add(np.zeros(blk.size, np.int64), blk, ea)
    hc = math.sqrt(cand_sq / max(n_hold, 1))
    ha = math.sqrt(act_sq / max(n_hold, 1))
    test = paired_test_over_parts(act_blocks.sse, cand_blocks.sse, scale_free=True)
    table = fit.to_table(device, description=f"on-orbit refit ({method}, IGRF-14 magnitude) vs {active_name}")
    reasons = []
    val = cal_table.validate(table)
    if not val.ok:
        reasons.append("candidate fails validation: " + "; ".join(val.problems))
    if n_hold < options.min_holdout_rows:
        reasons.append(f"only {n_hold} held-out rows (need {options.min_holdout_rows})")
    if not hc < ha * (1.0 - options.min_improvement):
        reasons.append(f"held-out scalar RMS {hc * 1e3:.1f} nT is not better than the active table's {ha * 1e3:.1f} nT")
    elif not test.significant:
        reasons.append(f"held-out scalar RMS {hc * 1e3:.1f} nT vs active {ha * 1e3:.1f} nT is within the noise: "
                       + test.describe())
    proposed = not reasons
    if proposed:
        reasons.append(f"held-out scalar RMS {hc * 1e3:.1f} nT vs active {ha * 1e3:.1f} nT, significant "
                       f"({test.describe()}); validation passed")
    return ScalarRefitResult(table, proposed, reasons, fit, hc, ha, int(bm.shape[0]), n_hold, counts, rows,
                             time.perf_counter() - t_start, active_name, paired_test=test)

