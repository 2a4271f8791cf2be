"""Linear least-squares fit of the calibration model, with an honest error report.

Pipeline: rows usable for the model -> design matrix -> identifiability (terms the
data cannot determine are held at their prior, or the fit is refused) -> weighted
least squares per output axis (optionally Huber IRLS) solved by QR -> parameter
standard errors, condition numbers, in-sample RMSE -> held-out RMSE by interleaved time
blocks and by leaving whole sessions out -> noise floor from the residuals. The fit and its
folds run in 64k-row blocks from per-piece R factors (:mod:`.crossfit`) unless the model needs
all rows at once (robust IRLS, time skew, mount rotations: ``_fit_core`` per fold).

RMSE conventions (uT): in-sample per axis is ``sqrt(SSE / (N - p_i))`` (fitnlm's, as in
belsten Table 7); held-out per axis is the plain RMS of out-of-fold residuals; the
scalar figure is the vector norm of the three per-axis values.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from magstack.data.dictionary import usable
from magstack.data.io import json_safe
from magstack.drivers.cal_priors import priors_for
from magstack.firmware.cal_terms import TEMPERATURE_TERMS
from magstack.firmware.calibration.degeneracy import GROUP_CORR, VIF_LIMIT
from magstack.firmware.calibration.estimator import (
    Posterior,
    Prior,
    apply_overrides,
    autocorr_inflation,
    map_solve,
    model_prior,
    names_of,
)
from magstack.firmware.calibration.heldout_test import MIN_GAIN, BlockSSE, paired_block_test
from magstack.firmware.calibration.identify import (
    CORE_TERMS,
    GATE_RULES,
    HeldParam,
    identify,
    independent_field_rms,
)
from magstack.firmware.calibration.linalg import RANK_RTOL, qr_r
from magstack.firmware.calibration.model import AXES, MODELS, CalModel, resolve_terms
from magstack.firmware.calibration.mount import MountSolution, solve_mount
from magstack.firmware.calibration.predictive import (
    Accumulated,
    HeldOutBins,
    LeftOutMoments,
    SlowNoiseGrams,
    Uncertainty,
    assemble,
    left_out_terms,
    weighed_grams,
)
from magstack.firmware.calibration.reference import SATURATION_MARGIN, saturated_rows
from magstack.firmware.calibration.session_map import compare, comparison_lines
from magstack.firmware.calibration.steps import (
    STEP_NOISE_FACTOR,
    STEP_RATIO,
    STEP_SHARE,
    StepDiagnosis,
    diagnose_steps,
    reference_steps,
    step_threshold_uT,
)
from magstack.firmware.errors import FitError

#: Names other modules import from here (the pieces now live in steps, identify, linalg).
__all__ = ["FitData", "FitOptions", "FitResult", "Coverage", "HeldParam", "StepDiagnosis",
           "fit", "identify", "independent_field_rms", "noise_floor", "qr_r", "reference_steps",
           "diagnose_steps", "step_threshold_uT", "build_model", "block_folds", "frame_reference", "comparison_lines",
           "RANK_RTOL", "CORE_TERMS", "STEP_RATIO", "STEP_SHARE", "STEP_NOISE_FACTOR"]


#: Bins (1 uT each) of the coverage's field histograms.
FIELD_HIST_BINS = 2048


def _field_hist(b: np.ndarray, mag: np.ndarray | None = None) -> np.ndarray:
    """(4, FIELD_HIST_BINS) counts of |b_x|, |b_y|, |b_z| and |b| in 1 uT bins (rows with a non-finite component
    left out); ``mag``: ``|b|`` transposed, (3, N) contiguous, when the caller has it. One bincount over the four."""
    nb = FIELD_HIST_BINS
    b = np.asarray(b, dtype=float).reshape(-1, 3)
    v = np.empty((4, b.shape[0]))
    if mag is None:
        np.abs(b.T, out=v[:3])
    else:
        v[:3] = mag
    np.sqrt(np.einsum("ij,ij->j", v[:3], v[:3]), out=v[3])
    bad = ~np.isfinite(v[3])                       # any non-finite component makes |b| so
    np.minimum(v, nb - 1, out=v)
    if bad.any():
        v[:, bad] = 0.0
    idx = v.astype(np.int64)
    idx += (np.arange(4, dtype=np.int64) * nb)[:, None]
    if bad.any():
        idx[:, bad] = 4 * nb                       # a bin past the four, dropped
    return np.bincount(idx.reshape(-1), minlength=4 * nb + 1)[:4 * nb].reshape(4, nb)


#: Rows per block where a pass over the rows works block by block (the cross-fit's passes, the row checks).
BLOCK_ROWS = 65536


@dataclass
class FitData:
    """Paired samples for a fit. b_meas_uT: DUT (N,3) uT; b_ref_uT: reference (N,3) uT;
    temp_c (N,) degC; t_s (N,) s; session (N,) int; currents_A {name: (N,) A};
    weights (N,) >= 0 or None; flag (N,) int, rows with a disqualifying flag bit are not used."""

    b_meas_uT: np.ndarray
    b_ref_uT: np.ndarray
    temp_c: np.ndarray
    t_s: np.ndarray
    session: np.ndarray
    currents_A: dict[str, np.ndarray] = field(default_factory=dict)
    weights: np.ndarray | None = None
    flag: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.b_meas_uT = np.asarray(self.b_meas_uT, dtype=float).reshape(-1, 3)
        n = self.b_meas_uT.shape[0]
        self.b_ref_uT = np.asarray(self.b_ref_uT, dtype=float).reshape(n, 3)
        self.temp_c = np.asarray(self.temp_c, dtype=float).reshape(n)
        self.t_s = np.asarray(self.t_s, dtype=float).reshape(n)
        self.session = np.asarray(self.session).astype(np.int64).reshape(n)
        self.currents_A = {k: np.asarray(v, dtype=float).reshape(n) for k, v in self.currents_A.items()}
        if self.weights is not None:
            self.weights = np.asarray(self.weights, dtype=float).reshape(n)
            if np.any(~np.isfinite(self.weights)) or np.any(self.weights < 0):
                raise FitError("weights must be finite and >= 0")
        if self.flag is not None:
            self.flag = np.asarray(self.flag).astype(np.int64).reshape(n)

    def __len__(self) -> int:
        return self.t_s.size

    @classmethod
    def from_session(cls, s, weights=None) -> FitData:
        """From any object with Session's attributes (magstack.data.session.Session)."""
        return cls(s.dut_uT, s.ref_uT, s.temp_c, s.t_s, s.session, dict(s.currents_A), weights,
                   getattr(s, "flag", None))

    def kept(self, mask: np.ndarray) -> FitData:
        """The rows where ``mask`` is True, not copied: every column a :class:`.kept_rows.KeptColumn` (indexing by
        row slices and integer arrays gathers those rows). For code that reads its rows block by block (the
        cross-fit); :meth:`select` copies them."""
        from magstack.firmware.calibration.kept_rows import KeptColumn, KeptRows
        rows = KeptRows(mask)
        out = object.__new__(FitData)                  # the columns are checked already: no __post_init__

        def col(a):
            return None if a is None else KeptColumn(rows, a)
        out.b_meas_uT, out.b_ref_uT, out.temp_c = col(self.b_meas_uT), col(self.b_ref_uT), col(self.temp_c)
        out.t_s, out.session = col(self.t_s), col(self.session)
        out.currents_A = {k: col(v) for k, v in self.currents_A.items()}
        out.weights, out.flag = col(self.weights), col(self.flag)
        return out

    def select(self, mask: np.ndarray) -> FitData:
        return FitData(self.b_meas_uT[mask], self.b_ref_uT[mask], self.temp_c[mask], self.t_s[mask],
                       self.session[mask], {k: v[mask] for k, v in self.currents_A.items()},
                       None if self.weights is None else self.weights[mask],
                       None if self.flag is None else self.flag[mask])

    def usable(self, terms: Sequence[str], currents: Sequence[str]) -> np.ndarray:
        """Rows whose every quantity the model needs is finite and whose flag has no disqualifying bit
        (checked in blocks of rows: the mask is the only per-row array)."""
        for name in currents:
            if name not in self.currents_A:
                raise FitError(f"data has no current {name!r} (have {sorted(self.currents_A)})")
        temp = bool(set(TEMPERATURE_TERMS) & set(terms))
        ok = np.empty(len(self), dtype=bool)
        for a in range(0, len(self), BLOCK_ROWS):
            sl = slice(a, a + BLOCK_ROWS)
            k = np.all(np.isfinite(self.b_meas_uT[sl]), axis=1) & np.all(np.isfinite(self.b_ref_uT[sl]), axis=1)
            k &= np.isfinite(self.t_s[sl])
            if temp:
                k &= np.isfinite(self.temp_c[sl])
            for name in currents:
                k &= np.isfinite(self.currents_A[name][sl])
            if self.flag is not None:
                k &= usable(self.flag[sl])        # the dictionary's one rule: informational bits keep a row
            if self.weights is not None:
                k &= self.weights[sl] > 0
            ok[sl] = k
        return ok

    def sessions(self) -> np.ndarray:
        """The sorted distinct sessions (found block by block)."""
        return np.unique(np.concatenate([np.unique(self.session[a:a + BLOCK_ROWS])
                                         for a in range(0, len(self), BLOCK_ROWS)] or [self.session]))


@dataclass
class FitOptions:
    """Fit policy.

    Priors (the MAP estimator, :mod:`.estimator`): ``chip`` names the part whose datasheet priors
    (:mod:`magstack.drivers.cal_priors`) apply (None or unknown: generic wide priors); ``prior`` replaces
    them entirely (e.g. an active table's posterior); ``priors``: parameter name (``"K_S[y,y]"``) ->
    value (fixed, sd 0) or ``(mean, sd)`` (sd ``inf`` = flat); ``use_priors`` False = no priors at all (the
    unregularised least squares; undetermined directions get the minimum-norm value and are named).
    ``autocorr``: inflate the data variance by the residual autocorrelation (:func:`.estimator.autocorr_inflation`).
    ``validity_sd_uT``: the largest predictive vector sd of the calibrated field inside a table's validity region
    (None: :data:`magstack.firmware.cal_table.VALIDITY_SD_FACTOR` x its RMS over the data, see there).
    ``second_order_tempco``: "auto" tries ``temperature_gain2`` on wide temperature spans and adopts it on
    held-out evidence (:func:`fit`); "off" never adds it (``terms`` can still name it).

    ``on_unidentifiable``: "hold" (the prior decides what the data cannot) or "refuse" (FitError naming the
    parameters the prior determined). The coverage rules below set no values: they explain *why* a
    direction is left to the prior. Temperature terms need ``min_temp_span_c`` degC:
    ``temperature_gain`` on input axis j counts only samples with ``|B_j| >=
    field_present_uT`` (field and temperature must vary together), ``temperature_offset``
    counts every sample.

    ``max_vif`` / ``group_corr``: the degeneracy rule (module degeneracy). ``ref_range_uT``: the
    reference's range (uT, :func:`reference.reference_range` from the session metadata; None = no
    saturation guard): rows with a reference component at or beyond it are counted and excluded
    unless ``include_saturated``.
    """

    robust: bool = False
    huber_k: float = 1.345
    max_iter: int = 50
    on_unidentifiable: str = "hold"
    min_temp_span_c: float = 5.0
    field_present_uT: float = 5.0
    min_field_rms_uT: float = 2.0
    min_sessions: int = 2
    priors: dict[str, float | tuple[float, float]] = field(default_factory=dict)
    chip: str | None = None
    prior: Prior | None = None
    use_priors: bool = True
    autocorr: bool = True
    validity_sd_uT: float | None = None
    second_order_tempco: str = "auto"
    holdout: bool = True
    block_s: float = 60.0
    n_folds: int = 5
    noise_lag_s: float = 1.0
    exclude_ref_steps_uT: float | None = None
    max_vif: float = VIF_LIMIT
    group_corr: float = GROUP_CORR
    ref_range_uT: float | None = None
    include_saturated: bool = False
    mount_frame: int | None = None

    def __post_init__(self) -> None:
        if self.on_unidentifiable not in ("hold", "refuse"):
            raise FitError(f"on_unidentifiable must be 'hold' or 'refuse', got {self.on_unidentifiable!r}")
        for name in ("huber_k", "min_temp_span_c", "field_present_uT", "min_field_rms_uT", "block_s", "noise_lag_s"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise FitError(f"{name} must be finite and > 0, got {v!r}")
        if self.exclude_ref_steps_uT is not None and not self.exclude_ref_steps_uT > 0:
            raise FitError("exclude_ref_steps_uT must be > 0 or None")
        if self.second_order_tempco not in ("auto", "off"):
            raise FitError(f"second_order_tempco must be 'auto' or 'off', got {self.second_order_tempco!r}")
        if self.n_folds < 2:
            raise FitError("n_folds must be >= 2")
        if not self.max_vif > 1:
            raise FitError(f"max_vif must be > 1, got {self.max_vif!r}")
        if not 0 < self.group_corr <= 1:
            raise FitError(f"group_corr must be in (0, 1], got {self.group_corr!r}")
        if self.ref_range_uT is not None and not (np.isfinite(self.ref_range_uT) and self.ref_range_uT > 0):
            raise FitError(f"ref_range_uT must be finite and > 0 or None, got {self.ref_range_uT!r}")
        if self.validity_sd_uT is not None and not (np.isfinite(self.validity_sd_uT) and self.validity_sd_uT > 0):
            raise FitError(f"validity_sd_uT must be finite and > 0 or None, got {self.validity_sd_uT!r}")
        for k, v in self.priors.items():
            mean, sd = (v, 0.0) if np.isscalar(v) else tuple(v)
            if not np.isfinite(mean) or not (sd >= 0):
                raise FitError(f"prior {k}: mean must be finite and sd >= 0, got {v!r}")


@dataclass
class Coverage:
    """What the data excites: temperature span (degC) overall and with field on each input
    axis, field range (uT), current ranges (A), number of sessions, time span (s)."""

    n: int = 0
    sum_w: float = 0.0
    temp_min_c: float = np.inf
    temp_max_c: float = -np.inf
    temp_with_field_c: np.ndarray = field(default_factory=lambda: np.array([[np.inf, -np.inf]] * 3))
    field_max_uT: np.ndarray = field(default_factory=lambda: np.zeros(3))
    norm_max_uT: float = 0.0                   # largest |B| of a row
    #: rows per 1 uT bin of |B_x|, |B_y|, |B_z| and |B| (last bin: at or beyond FIELD_HIST_BINS - 1 uT) of the
    #: readings (``field_hist``) and of the reference field (``ref_hist``: the calibrated field's extents)
    field_hist: np.ndarray = field(default_factory=lambda: np.zeros((4, FIELD_HIST_BINS), dtype=np.int64))
    ref_hist: np.ndarray = field(default_factory=lambda: np.zeros((4, FIELD_HIST_BINS), dtype=np.int64))
    currents_A: dict[str, list[float]] = field(default_factory=dict)
    sessions: set = field(default_factory=set)
    t_min_s: float = np.inf
    t_max_s: float = -np.inf

    def update(self, b_uT, temp_c, currents_A, session, t_s, field_present_uT: float, weights=None,
               ref_uT=None, hist: bool = True) -> None:
        """Rows (units as :class:`FitData`); ``hist``: False leaves the field histograms out (the caller takes them
        from another pass over the same rows)."""
        b = np.asarray(b_uT).reshape(-1, 3)
        if b.shape[0] == 0:
            return
        if ref_uT is not None and hist:
            self.ref_hist += _field_hist(np.asarray(ref_uT, dtype=float).reshape(-1, 3))
        self.n += b.shape[0]
        self.sum_w += float(b.shape[0] if weights is None else np.sum(weights))
        t = np.asarray(temp_c)
        fin = np.isfinite(t)
        if fin.any():
            tf = t if fin.all() else t[fin]
            self.temp_min_c = min(self.temp_min_c, float(tf.min()))
            self.temp_max_c = max(self.temp_max_c, float(tf.max()))
        mag = np.abs(b.T, order="C")                         # (3, N): one contiguous row per axis
        for j in range(3):
            sel = (mag[j] >= field_present_uT) & fin
            if np.any(sel):
                self.temp_with_field_c[j, 0] = min(self.temp_with_field_c[j, 0], float(t[sel].min()))
                self.temp_with_field_c[j, 1] = max(self.temp_with_field_c[j, 1], float(t[sel].max()))
        self.field_max_uT = np.maximum(self.field_max_uT, mag.max(axis=1))
        nrm = np.einsum("ij,ij->j", mag, mag)
        if np.isfinite(nrm).any():
            self.norm_max_uT = max(self.norm_max_uT, float(np.sqrt(np.nanmax(nrm))))
        if hist:
            self.field_hist += _field_hist(b, mag)
        for k, v in (currents_A or {}).items():
            lo, hi = self.currents_A.get(k, [np.inf, -np.inf])
            self.currents_A[k] = [min(lo, float(np.min(v))), max(hi, float(np.max(v)))]
        s = np.asarray(session).reshape(-1)
        self.sessions.update((int(s[0]),) if np.all(s == s[0]) else (int(k) for k in np.unique(s)))
        self.t_min_s = min(self.t_min_s, float(np.min(t_s)))
        self.t_max_s = max(self.t_max_s, float(np.max(t_s)))

    def merge(self, other: Coverage) -> Coverage:
        """Fold ``other`` (rows counted elsewhere) into this coverage: extremes combine, counts add."""
        self.n += other.n
        self.sum_w += other.sum_w
        self.temp_min_c, self.temp_max_c = min(self.temp_min_c, other.temp_min_c), max(self.temp_max_c,
                                                                                       other.temp_max_c)
        self.temp_with_field_c = np.column_stack([np.minimum(self.temp_with_field_c[:, 0],
                                                             other.temp_with_field_c[:, 0]),
                                                  np.maximum(self.temp_with_field_c[:, 1],
                                                             other.temp_with_field_c[:, 1])])
        self.field_max_uT = np.maximum(self.field_max_uT, other.field_max_uT)
        self.norm_max_uT = max(self.norm_max_uT, other.norm_max_uT)
        self.field_hist = self.field_hist + other.field_hist
        self.ref_hist = self.ref_hist + other.ref_hist
        for k, (lo, hi) in other.currents_A.items():
            lo0, hi0 = self.currents_A.get(k, [np.inf, -np.inf])
            self.currents_A[k] = [min(lo0, lo), max(hi0, hi)]
        self.sessions |= other.sessions
        self.t_min_s, self.t_max_s = min(self.t_min_s, other.t_min_s), max(self.t_max_s, other.t_max_s)
        return self

    def field_quantile_uT(self, q: float, reference: bool = False) -> tuple[np.ndarray, float]:
        """``(per-axis |B_j| (3,), |B|)`` below which a fraction ``q`` of the rows lie, of the readings or (with
        ``reference``) of the reference field (upper edge of the 1 uT bin; readings: never above the largest
        value seen)."""
        hist = self.ref_hist if reference else self.field_hist
        out = []
        for k in range(4):
            c = np.cumsum(hist[k])
            if c[-1] == 0:
                out.append(0.0)
                continue
            out.append(float(np.searchsorted(c, q * c[-1]) + 1))
        if reference:
            return np.array(out[:3]), out[3]
        lim = np.minimum(np.array(out[:3]), self.field_max_uT)
        return lim, min(out[3], self.norm_max_uT)

    @property
    def has_reference(self) -> bool:
        return bool(self.ref_hist[3].sum())

    def temp_span_with_field(self, j: int) -> float:
        lo, hi = self.temp_with_field_c[j]
        return float(hi - lo) if hi >= lo else 0.0

    @property
    def temp_span_c(self) -> float:
        return float(self.temp_max_c - self.temp_min_c) if self.temp_max_c >= self.temp_min_c else 0.0


@dataclass
class FitResult:
    """Everything a fit produced; ``report()`` renders it as text."""

    model: CalModel
    theta: np.ndarray                 # (3, p)
    se: np.ndarray                    # (3, p)
    held: list[HeldParam]
    n_used: int
    n_excluded: int
    rmse_uT: np.ndarray               # (3,) in-sample, sqrt(SSE/(N-p_i))
    raw_rmse_uT: np.ndarray           # (3,) RMS of ref - dut before calibration
    cond_scaled: np.ndarray           # (3,)
    cond_raw: np.ndarray              # (3,)
    noise_floor_uT: np.ndarray        # (3,)
    coverage: Coverage
    robust: bool = False
    holdout_blocks_uT: np.ndarray | None = None          # (3,)
    holdout_sessions_uT: np.ndarray | None = None        # (3,) pooled over left-out sessions
    holdout_per_session_uT: dict[int, np.ndarray] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    n_excluded_steps: int = 0                          # rows excluded by exclude_ref_steps_uT
    steps: StepDiagnosis | None = None                 # residual at reference steps vs elsewhere
    n_saturated: int = 0                               # usable rows at/beyond the reference range
    saturated_excluded: bool = True                    # ... and whether they were left out
    ref_range_uT: float | None = None
    selection: dict = field(default_factory=dict)      # how rows were chosen (windows), for the table
    mount: MountSolution | None = None                 # per-session mount rotations (nuisance)
    comparison: dict = field(default_factory=dict)     # mount rotation vs a general per-session map
    posterior: Posterior | None = None                 # the MAP estimate (covariance, prior, data share)
    uncertainty: Uncertainty | None = None             # predictive parts: inflation, left-out terms, discrepancy
    term_choice: dict = field(default_factory=dict)    # an optional term tried by held-out evidence
    prior_name: str = ""                               # which priors were used
    chip: str | None = None                            # the part (its operating range bounds the validity)

    @property
    def rmse_norm_uT(self) -> float:
        return float(np.linalg.norm(self.rmse_uT))

    @property
    def _n_sat_out(self) -> int:
        return self.n_saturated if self.saturated_excluded else 0

    @property
    def params(self) -> dict:
        return self.model.unpack(self.theta)

    def stats(self) -> dict:
        """JSON-friendly fit statistics (uT)."""
        def nrm(v):
            return None if v is None else float(np.linalg.norm(v))

        def lst(v):
            return None if v is None else [float(x) for x in v]
        return {
            "n_used": self.n_used, "n_excluded": self.n_excluded, "robust": self.robust,
            "rmse_uT": lst(self.rmse_uT), "rmse_norm_uT": self.rmse_norm_uT,
            "raw_rmse_uT": lst(self.raw_rmse_uT), "raw_rmse_norm_uT": nrm(self.raw_rmse_uT),
            "holdout_blocks_rmse_uT": lst(self.holdout_blocks_uT),
            "holdout_blocks_rmse_norm_uT": nrm(self.holdout_blocks_uT),
            "holdout_sessions_rmse_uT": lst(self.holdout_sessions_uT),
            "holdout_sessions_rmse_norm_uT": nrm(self.holdout_sessions_uT),
            "noise_floor_uT": lst(self.noise_floor_uT), "noise_floor_norm_uT": nrm(self.noise_floor_uT),
            "cond_scaled": lst(self.cond_scaled), "cond_raw": lst(self.cond_raw),
            "held": [{"param": h.name, "value": h.value, "reason": h.reason} for h in self.held],
            "priors": self.prior_name,
            **({"parameters": self.parameter_rows(),
                "sigma_uT": lst(self.posterior.sigma_uT), "autocorr_inflation": lst(self.posterior.kappa)}
               if self.posterior is not None else {}),
            **({"predictive": self.uncertainty.stats()} if self.uncertainty is not None else {}),
            **({"term_choice": json_safe(self.term_choice)} if self.term_choice else {}),
            "n_excluded_steps": self.n_excluded_steps,
            "ref_range_uT": self.ref_range_uT, "saturated_rows": self.n_saturated,
            "saturated_rows_excluded": bool(self.saturated_excluded and self.n_saturated),
            **({"selection": dict(self.selection)} if self.selection else {}),
            **({"mount_rotation": self.mount.stats()} if self.mount is not None else {}),
            **({"mount_vs_session_map": dict(self.comparison)} if self.comparison else {}),
            **({} if self.steps is None else {
                "step_threshold_uT": self.steps.threshold_uT, "step_rows": self.steps.n_step,
                "step_rms_uT": lst(self.steps.step_rms_uT), "steady_rms_uT": lst(self.steps.steady_rms_uT),
                "step_share_of_sse": self.steps.step_share}),
        }

    def parameter_rows(self) -> list[dict]:
        """Per parameter: name, value, posterior sd, prior mean and sd, data share, who determined it."""
        m, post = self.model, self.posterior
        out = []
        mask = m.axis_mask()
        for i in range(3):
            for c, col in enumerate(m.columns):
                if not mask[i, c]:
                    continue
                row = {"param": m.param_name(i, c), "value": float(self.theta[i, c]), "sd": float(self.se[i, c]),
                       "unit": col.unit}
                if post is not None:
                    row.update({"prior_mean": float(post.prior.mean[i, c]), "prior_sd": float(post.prior.sd[i, c]),
                                "data_share": float(post.data_share[i, c]),
                                "determined_by": post.determined_by(i, c)})
                out.append(row)
        return out

    def parameter_lines(self) -> list[str]:
        """The parameter table of the report."""
        L = [f"{'parameter':14s}{'value':>13s}{'post. sd':>11s}{'prior':>24s}{'data':>6s}  determined by  unit"]
        for r in self.parameter_rows():
            pr = f"{r['prior_mean']:.4g} +- {r['prior_sd']:.2g}" if "prior_mean" in r else ""
            share = r.get("data_share", float("nan"))
            sh = f"{share:5.0%}" if np.isfinite(share) else "    -"
            L.append(f"{r['param']:14s}{r['value']:13.6g}{r['sd']:11.3g}{pr:>24s} {sh}  "
                     f"{r.get('determined_by', ''):13s}  {r['unit']}")
        return L

    def report(self) -> str:
        m = self.model
        L = [f"model {m.name}: terms {', '.join(m.terms)}" + (f"; currents {', '.join(m.currents)}"
                                                             if m.currents else "") + f"; t0 = {m.t0_c:g} degC",
             f"rows used {self.n_used}, excluded {self.n_excluded - self.n_excluded_steps - self._n_sat_out} "
             "(NaN / flagged / zero weight)"
             + (f" + {self.n_excluded_steps} at reference steps" if self.n_excluded_steps else "")
             + (f" + {self._n_sat_out} with the reference saturated" if self._n_sat_out else "")
             + ("; robust Huber IRLS" if self.robust else ""),
             f"coverage: T {self.coverage.temp_min_c:.2f}..{self.coverage.temp_max_c:.2f} degC, "
             f"|B| max per axis {np.array2string(self.coverage.field_max_uT, precision=1)} uT, "
             f"sessions {sorted(self.coverage.sessions)}", "",
             f"{'':24s}{'x':>10s}{'y':>10s}{'z':>10s}{'norm':>10s}   (nT)"]

        def row(label, v):
            if v is None:
                return f"{label:24s}{'n/a':>10s}{'n/a':>10s}{'n/a':>10s}{'n/a':>10s}"
            v = np.asarray(v) * 1e3
            return f"{label:24s}" + "".join(f"{x:10.1f}" for x in v) + f"{np.linalg.norm(v):10.1f}"
        L += [row("raw ref-dut RMS", self.raw_rmse_uT), row("in-sample RMSE", self.rmse_uT)]
        st = self.steps
        if st is not None:
            L += [row(f"  {st.n_step} rows at steps", st.step_rms_uT),
                  row(f"  {st.n_steady} other rows", st.steady_rms_uT)]
        L += [
              row("held-out time blocks", self.holdout_blocks_uT),
              row("held-out sessions", self.holdout_sessions_uT)]
        for s, v in sorted(self.holdout_per_session_uT.items()):
            L.append(row(f"  session {s} left out", v))
        L += [row("noise floor (residual)", self.noise_floor_uT), "",
              "condition number (equilibrated / raw): " + ", ".join(
                  f"{a} {c:.3g} / {r:.3g}" for a, c, r in zip(AXES, self.cond_scaled, self.cond_raw, strict=True)), "",
              f"priors: {self.prior_name or 'n/a'}"]
        L += [""] + self.parameter_lines()
        if self.mount is not None:
            L += [""] + self.mount.report_lines()
        if self.comparison:
            L += [""] + comparison_lines(self.comparison)
        if self.held:
            L += ["", "determined by the prior, not the data (why):"]
            L += [f"  {h.name} = {h.value:g}: {h.reason}" for h in self.held]
        if self.posterior is not None:
            srcs = sorted({self.posterior.prior.source[h.axis][h.column] for h in self.held})
            if srcs:
                L += ["prior sources of those:"] + [f"  {x}" for x in srcs]
        L += [f"note: {n}" for n in self.notes]
        if st is not None and st.dominant:
            L += [f"note: rows at reference steps (change > {st.threshold_uT:.2g} uT to a neighbouring row) are "
                  f"{st.n_step / (st.n_step + st.n_steady):.0%} of the rows but carry {st.step_share:.0%} of the "
                  f"squared residual: two independently clocked streams cannot be paired sample-exactly across "
                  f"a step. Consider --exclude-steps {st.threshold_uT:.2g} (FitOptions.exclude_ref_steps_uT); "
                  f"if the DUT samples its axes one after another, also try --terms time_skew."]
        return "\n".join(L)


# ---------------------------------------------------------------------- numerics
def noise_floor(resid_uT: np.ndarray, t_s: np.ndarray, session: np.ndarray, lag_s: float) -> np.ndarray:
    """Per-axis white-noise level (uT) of residuals: robust (MAD) spread of differences of
    samples ``lag_s`` apart within a session, divided by sqrt(2). Differencing removes
    slow misfit; the MAD ignores field-step transitions. One axis at a time (memory: a few
    columns per row)."""
    later, earlier = [], []
    for s in np.unique(session):
        idx = np.flatnonzero(session == s)
        idx = idx[np.argsort(t_s[idx], kind="stable")]
        t = t_s[idx]
        if t.size < 2:
            continue
        j = np.clip(np.searchsorted(t, t + lag_s), 1, t.size - 1)
        j = np.where(np.abs(t[j - 1] - t - lag_s) < np.abs(t[j] - t - lag_s), j - 1, j)  # nearest to t + lag
        ii = np.arange(t.size)
        good = (np.abs((t[j] - t) - lag_s) <= 0.5 * lag_s) & (j > ii)
        later.append(idx[j[good]])
        earlier.append(idx[good])
    out = np.full(3, np.nan)
    if sum(a.size for a in later) < 10:
        return out
    later, earlier = np.concatenate(later), np.concatenate(earlier)
    for a in range(3):
        d = resid_uT[later, a] - resid_uT[earlier, a]
        d -= np.median(d)
        np.abs(d, out=d)
        out[a] = 1.4826 * np.median(d) / np.sqrt(2.0)
    return out


# ---------------------------------------------------------------------- the fit
def build_model(data: FitData, terms: Sequence[str], currents: Sequence[str], t0_c: float,
                name: str) -> CalModel:
    sessions = tuple(int(s) for s in data.sessions()) if "session_offset" in terms else ()
    if isinstance(data.t_s, np.ndarray):
        t_ref = float(np.mean(data.t_s)) if len(data) else 0.0
    else:       # rows not copied (FitData.kept): the mean block by block (equal to np.mean to rounding)
        t_ref = math.fsum(float(np.sum(data.t_s[a:a + BLOCK_ROWS])) for a in range(0, len(data), BLOCK_ROWS))
        t_ref = t_ref / len(data) if len(data) else 0.0
    return CalModel(tuple(terms), tuple(currents), sessions, t0_c, t_ref, name)


def build_prior(model: CalModel, options: FitOptions, s_hint: np.ndarray | None = None) -> Prior:
    """The prior of ``model`` under ``options``: flat (``use_priors`` False), ``options.prior``, or the chip's
    datasheet priors (sensitivity tempco relative to ``s_hint``), then the named overrides."""
    if not options.use_priors:
        prior = Prior.flat(model.n_columns)
    elif options.prior is not None:
        prior = options.prior
        if prior.mean.shape != (3, model.n_columns):
            raise FitError(f"prior has {prior.mean.shape[1]} columns, model {model.n_columns}")
    else:
        prior = model_prior(model, priors_for(options.chip), s_hint)
    ov = {k: ((float(v), 0.0) if np.isscalar(v) else (float(v[0]), float(v[1]))) for k, v in options.priors.items()}
    return apply_overrides(prior, model, ov) if ov else prior


@dataclass
class CoreFit:
    """What one estimator run on some rows produced (the batch fit, each held-out fold)."""

    X: np.ndarray | None              # the design (None from the cross-fit, which never keeps it whole)
    theta: np.ndarray
    se: np.ndarray
    held: list[HeldParam]
    conds: np.ndarray
    coverage: Coverage
    mount: MountSolution | None
    posterior: Posterior


def prior_determined(post: Posterior, explain: Sequence[HeldParam]) -> list[HeldParam]:
    """Parameters the prior determined: posterior sd >= 0.9 prior sd, undetermined (flat prior), fixed by
    the user, or named by the identifiability analysis while the data reduced the prior sd by less than
    half. ``value`` is the posterior mean; ``reason`` says why (the analysis) and by how much."""
    model = post.model
    why = {(h.axis, h.column): h.reason for h in explain}
    rule = {(h.axis, h.column): h.rule for h in explain}
    prior_sd = post.prior.sd
    out = []
    for i, c, name in names_of(model):
        by = post.determined_by(i, c)
        flagged = (i, c) in why
        if by in ("prior", "undetermined", "fixed") or (flagged and by == "data+prior"):
            if by == "fixed":
                reason = "held by the user (prior sd 0)"
            elif by == "undetermined":
                reason = why.get((i, c), "no prior and the data do not determine it") + \
                    " (no prior: minimum-norm value)"
            else:
                ratio = post.sd[i, c] / prior_sd[i, c]
                reason = (why[(i, c)] + "; " if flagged else "") + f"posterior sd {ratio:.0%} of the prior's"
                if (i, c) in post.gated:
                    reason += (" (no temperature change while this axis saw field" if rule.get((i, c)) ==
                               "temperature-no-field" else " (field on this axis within the DUT's noise") + \
                        ": data not used, errors in variables)"
            out.append(HeldParam(i, c, name, float(post.theta[i, c]), reason, rule.get((i, c), "")))
    return out


def _pick_axes(posts: Sequence[Posterior]) -> Posterior:
    """One Posterior whose axis i comes from ``posts[i]`` (per-axis robust weights)."""
    base = posts[0]
    out = Posterior(base.model, base.prior, base.theta.copy(), base.cov.copy(), base.sigma_uT.copy(),
                    base.kappa.copy(), base.sse.copy(), base.dof.copy(), base.cond.copy(), base.n, [])
    for i, q in enumerate(posts):
        out.theta[i], out.cov[i] = q.theta[i], q.cov[i]
        out.sigma_uT[i], out.kappa[i], out.sse[i], out.dof[i], out.cond[i] = \
            q.sigma_uT[i], q.kappa[i], q.sse[i], q.dof[i], q.cond[i]
        out.undetermined += [u for u in q.undetermined if u[0] == i]
    return out


@dataclass
class FirstSolve:
    """The estimator's solve from an R factor before the residual autocorrelation is known: why directions
    are left to the prior (``explain``), the ``gated`` parameters, the ``prior`` and the posterior."""

    explain: list[HeldParam]
    gated: list[tuple[int, int]]
    prior: Prior
    post: Posterior


def first_solve(R: np.ndarray, n: int, model: CalModel, cov: Coverage, options: FitOptions) -> FirstSolve:
    """Identifiability, gating and the MAP solve of ``n`` weighted rows whose ``[X | Y]`` has R factor ``R``."""
    # the identifiability analysis explains why a direction is left to the prior; it decides nothing,
    # except for gain columns whose own field is within the DUT's noise (errors in variables, see gate_weak_fields)
    explain = identify(model, R, cov, dataclasses.replace(options, on_unidentifiable="hold", priors={}))
    gated = [(h.axis, h.column) for h in explain if h.rule in GATE_RULES]
    prior = build_prior(model, options)
    post = gate_solve(R, n, model, prior, gated, options=options)
    if options.use_priors and options.prior is None and {"temperature_gain", "temperature_gain2"} & set(model.terms):
        # the sensitivity tempco is relative: centre K_S on the fitted gain
        prior = build_prior(model, options, s_hint=model.unpack(post.theta)["S"])
        post = gate_solve(R, n, model, prior, gated, options=options)
    return FirstSolve(explain, gated, prior, post)


def held_or_refuse(post: Posterior, explain: Sequence[HeldParam], options: FitOptions) -> list[HeldParam]:
    """:func:`prior_determined`; FitError naming them when ``on_unidentifiable`` is "refuse"."""
    held = prior_determined(post, explain)
    if held and options.on_unidentifiable == "refuse":
        raise FitError("data cannot determine (the prior would): " + "; ".join(f"{h.name} ({h.reason})" for h in held))
    return held


def _fit_core(data: FitData, model: CalModel, options: FitOptions) -> CoreFit:
    X = model.design(data.b_meas_uT, data.temp_c, data.currents_A, data.session, data.t_s)
    Y = data.b_ref_uT
    n = len(data)
    w = np.ones(n) if data.weights is None else data.weights
    sw = np.sqrt(w)[:, None]
    cov = Coverage()
    cov.update(data.b_meas_uT, data.temp_c, {k: data.currents_A[k] for k in model.currents}, data.session,
               data.t_s, options.field_present_uT, w, ref_uT=data.b_ref_uT)
    R = qr_r(np.hstack([X, Y]) * sw)
    first = first_solve(R, n, model, cov, options)
    prior, gated, post = first.prior, first.gated, first.post
    if options.autocorr:
        kappa = autocorr_inflation(Y - model.predict(post.theta, X), data.t_s, data.session)
        post = gate_solve(R, n, model, prior, gated, kappa, options)
    if options.robust:
        posts = []
        for i in range(3):
            q = post
            for _ in range(options.max_iter):
                r = Y[:, i] - X @ np.where(model.axis_mask()[i], q.theta[i], 0.0)
                scale = 1.4826 * np.median(np.abs(r - np.median(r)))
                if not scale > 0:
                    break
                u = np.abs(r) / (options.huber_k * scale)
                wr = np.where(u <= 1, 1.0, 1.0 / np.maximum(u, 1e-300))
                Ri = qr_r(np.hstack([X, Y]) * np.sqrt(w * wr)[:, None])
                new = gate_solve(Ri, n, model, prior, gated, post.kappa, options)
                change = np.max(np.abs(new.theta[i] - q.theta[i]) / (np.abs(q.theta[i]) + 1e-12))
                q = new
                if change < 1e-10:
                    break
            posts.append(q)
        post = _pick_axes(posts)
    held = held_or_refuse(post, first.explain, options)
    theta = post.theta.copy()
    se = np.where(model.axis_mask(), post.sd, np.nan)
    conds = np.vstack([post.cond, raw_cond(R, model)])
    mount = None
    if "mount_rotation" in model.terms:
        if options.robust:
            raise FitError("robust IRLS is not available with mount_rotation")
        theta, se2, mount = solve_mount(X, Y, data.session, data.weights, model,
                                        {(h.axis, h.column): h.value for h in held}, theta, options)
        for h in held:          # the prior-determined parameters keep their posterior sd
            se2[h.axis, h.column] = se[h.axis, h.column]
        se = se2
    return CoreFit(X, theta, se, held, conds, cov, mount, post)


def gate_solve(R: np.ndarray, n: int, model: CalModel, prior: Prior, gated: Sequence[tuple[int, int]],
               kappa=None, options: FitOptions | None = None) -> Posterior:
    """:func:`.estimator.map_solve` where the data cannot be trusted to inform some directions.

    1. *Gated* parameters come from the prior alone. A gain (or cubic, cross-product) column whose input
       axis carries less field of its own than ``min_field_rms_uT``, or a sensitivity-tempco column whose
       axis saw (almost) no temperature span with field present (identify.GATE_TEMP_SPAN_C), is dominated by
       the DUT's own noise in that column: errors in variables bias its least-squares information
       (attenuation towards 0; a single-axis sweep's cross-axis copies gave S[y,y] = 0.60 +- 0.04 on real
       data where the truth is 1.12; belsten's anomalous K_S[y,y] came from such a non-excursion). They sit
       at the prior mean with the prior's sd (share of the data 0).
    2. *Degenerate* directions (identify.degenerate_sets: variance inflation >= ``max_vif``) are left to the
       prior: the data's information along the weak singular directions of each group (and its strongest
       partner) is removed, so the data fix only the combination they determine. A thermal run at one field
       otherwise "determines" the K_S / K_O split from second-order effects (a -2700 ppm/degC sensitivity
       makes the DUT's own reading drift, and the linear model's curvature error picks K_O: 4 uT off at zero
       field on the HMC1053 preset)."""

    options = options or FitOptions(holdout=False)
    fixed = prior
    for i, c in gated:
        fixed = fixed.with_values(i, c, float(prior.mean[i, c]), 0.0, prior.source[i][c])
    maps = weak_direction_maps(R, model, gated, options)
    if maps is None:
        post = map_solve(R, n, model, fixed, kappa)
    else:
        p = model.n_columns
        posts = []
        for i in range(3):
            Ri = R.copy()
            Ri[:, :p] = R[:, :p] @ maps[i]
            posts.append(map_solve(Ri, n, model, fixed, kappa))
        post = _pick_axes(posts)
    post.prior = prior
    post.gated = list(gated)
    post.design_maps = maps
    for i, c in gated:
        post.cov[i, c, :] = 0.0
        post.cov[i, :, c] = 0.0
        post.cov[i, c, c] = prior.cov[i, c, c]
    return post


def weak_direction_maps(R: np.ndarray, model: CalModel, gated: Sequence[tuple[int, int]],
                        options: FitOptions) -> list[np.ndarray] | None:
    """Per output axis the (p, p) map ``M_i`` of the design columns whose information the estimator uses
    (``X M_i``): identity, except within each degenerate group where the group's weak directions are removed
    (:func:`_weak_map`). None when no axis has a degenerate group (every map the identity)."""
    from magstack.firmware.calibration.identify import degenerate_sets

    sets = degenerate_sets(model, R, options, exclude=set(gated)) if options.use_priors else []
    if not sets:
        return None
    p = model.n_columns
    off = [c for c, col in enumerate(model.columns) if col.term == "offset"]
    maps = [np.eye(p) for _ in range(3)]
    for ax, g, act in sets:
        cols = list(dict.fromkeys([act[a] for a in g.members] + ([act[g.partner]] if g.partner is not None else [])))
        Mg, on_offset = _weak_map(R, model, cols, options.max_vif)
        M = maps[ax]
        M[:, cols] = 0.0
        M[np.ix_(cols, cols)] = Mg
        if off:
            M[off[0], cols] = on_offset
    return maps


def _weak_map(R: np.ndarray, model: CalModel, cols: list[int], max_vif: float) -> tuple[np.ndarray, np.ndarray]:
    """``(M (k, k), a (k,))`` with ``R[:, cols] @ M + outer(R[:, offset], a)`` = the group's columns with their
    information along its weak directions removed: SVD of the columns with the offset projected out and unit
    norm, directions with ``s^2 < s_max^2 / max_vif`` dropped from that fluctuating part only (each column's
    projection on the offset, its level, is kept: removing it would leave the offset to make up for it)."""
    off = [c for c, col in enumerate(model.columns) if col.term == "offset"]
    A = R[:, cols]
    k = len(cols)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    level = np.zeros(k)
    B = A.copy()
    if off:
        o = R[:, off[0]]
        oo = float(o @ o)
        if oo > 0:
            level = (o @ A) / oo
            B = B - np.outer(o, level)
    _, sv, Vt = np.linalg.svd(B / scale, full_matrices=False)
    weak = Vt[sv ** 2 < sv[0] ** 2 / max_vif]
    if weak.size == 0:
        return np.eye(k), np.zeros(k)
    P = (weak.T @ weak) * scale[None, :] / scale[:, None]
    return np.eye(k) - P, level @ P


def raw_cond(R: np.ndarray, model: CalModel) -> np.ndarray:
    """(3,) condition number of each axis's raw (not equilibrated) weighted design."""
    p = model.n_columns
    mask = model.axis_mask()
    out = np.full(3, np.nan)
    for i in range(3):
        A = R[:, :p][:, mask[i]]
        if A.shape[1]:
            sv = np.linalg.svd(A, compute_uv=False)
            out[i] = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    return out


def _prior_name(options: FitOptions) -> str:
    if not options.use_priors:
        return "none (--no-priors: unregularised least squares)"
    if options.prior is not None:
        return "given prior (e.g. the active table's posterior)"
    pr = priors_for(options.chip)
    return f"{pr.chip} ({pr.source})" + ("" if pr.chip != "generic" else
                                         f": no prior table for chip {options.chip!r}")


def frame_reference(data: FitData, mount: MountSolution | None) -> np.ndarray:
    """The reference field in the frame session's mount (unchanged without mount rotations)."""
    return data.b_ref_uT if mount is None else mount.rotate_to_frame(data.b_ref_uT, data.session)


#: Temperature span (degC, with field present on some axis) from which ``fit`` tries the second-order
#: sensitivity tempco (``temperature_gain2``) beside the model it was given.
TEMPCO2_SPAN_C = 10.0


def fit(data: FitData, model: str = "eq3", terms: Sequence[str] | None = None, currents: Sequence[str] = (),
        t0_c: float = 25.0, options: FitOptions | None = None) -> FitResult:
    """Fit the calibration model to paired data; see the module docstring.

    With ``options.second_order_tempco == "auto"``, a model with ``temperature_gain`` but not
    ``temperature_gain2``, held-out folds and a temperature span of at least ``TEMPCO2_SPAN_C`` degC with field
    present, the model with the second-order tempco is fitted too and adopted when its held-out improvement is
    significant (:func:`.heldout_test.paired_block_test`); ``result.term_choice`` says what was compared. Where
    the cross-fit serves both models, they share its passes over the rows (:func:`.crossfit.cross_fit_with`)."""
    from magstack.firmware.calibration import crossfit

    options = options or FitOptions()
    sel = _select(data, model, terms, currents, t0_c, options)
    terms_now = set(sel.cm.terms)
    if (options.second_order_tempco != "auto" or "temperature_gain" not in terms_now
            or "temperature_gain2" in terms_now or not options.holdout):
        return _fit_model(data, sel, currents, t0_c, options)[0]
    cand_terms = list(terms or []) + ["temperature_gain2"]
    if crossfit.applies(sel.cm, options):
        all_terms, name = _terms_and_name(model, cand_terms, currents)
        cm = build_model(sel.d, all_terms, currents, t0_c, name)
        if len(sel.d) > cm.n_columns and crossfit.applies(cm, options):      # the same rows (same usable mask)
            cand_sel = dataclasses.replace(sel, all_terms=all_terms, name=name, cm=cm)
            tests = []

            def adopt(base, cand) -> bool:       # only the adopted model's figures are finished
                tests.append(paired_block_test(base.block_sse.sse, cand.block_sse.sse))
                return tests[-1].significant

            cross, cross2 = crossfit.cross_fit_with(sel.d, sel.cm, cm, options,
                                                    lambda cov: _field_temp_span(cov) >= TEMPCO2_SPAN_C, adopt,
                                                    min_gain=MIN_GAIN)
            if cross2 is None:
                res = _finish(data, sel, cross, currents, t0_c, options)[0]
                if cross.wider_gain_bound is None:
                    return res
                return _note_tempco2(res, False, None, cross.holdout_blocks_uT, None, cross.wider_gain_bound)
            adopted = tests[0].significant
            res = _finish(data, cand_sel if adopted else sel, cross2 if adopted else cross, currents, t0_c,
                          options)[0]
            return _note_tempco2(res, adopted, tests[0], cross.holdout_blocks_uT, cross2.holdout_blocks_uT)
    res, sse = _fit_model(data, sel, currents, t0_c, options)
    if sse is None or _field_temp_span(res.coverage) < TEMPCO2_SPAN_C:
        return res
    cand, sse2 = _fit_model(data, _select(data, model, cand_terms, currents, t0_c, options), currents, t0_c,
                            options)
    return _choose_tempco2(res, sse, cand, sse2)


def _field_temp_span(cov: Coverage) -> float:
    """The largest temperature span (degC) with field present on an axis."""
    return max(cov.temp_span_with_field(j) for j in range(3))


def _choose_tempco2(res: FitResult, sse: BlockSSE, cand: FitResult, sse2: BlockSSE | None) -> FitResult:
    """``cand`` (the model with ``temperature_gain2``) when the paired test finds its held-out improvement over
    ``res`` significant, else ``res``; the chosen one says what was compared (:func:`_note_tempco2`)."""
    test = paired_block_test(sse.sse, sse2.sse) if sse2 is not None else None
    adopted = test is not None and test.significant
    return _note_tempco2(cand if adopted else res, adopted, test, res.holdout_blocks_uT, cand.holdout_blocks_uT)


def _note_tempco2(chosen: FitResult, adopted: bool, test, base_holdout_uT, cand_holdout_uT,
                  gain_bound: float | None = None) -> FitResult:
    """``chosen`` with what the choice of ``temperature_gain2`` compared (``term_choice``, a note); ``gain_bound``:
    the candidate was ruled out unfitted, since it could not lower any fold's held-out sum of squares by
    ``MIN_GAIN`` (:func:`.crossfit.wider_gain_bound`)."""
    span = _field_temp_span(chosen.coverage)
    chosen.term_choice = {"candidate": "temperature_gain2", "adopted": adopted,
                          "holdout_blocks_base_uT": base_holdout_uT, "holdout_blocks_candidate_uT": cand_holdout_uT,
                          **({} if test is None else dataclasses.asdict(test)),
                          **({} if gain_bound is None else {"gain_bound": gain_bound})}
    why = f": {test.describe()}" if test is not None else ""
    if gain_bound is not None:
        why = (f": fitted to each fold's held-out rows themselves it would lower their sum of squares by at most "
               f"{gain_bound:.2%} (adopted from {MIN_GAIN:.0%}), so it was not fitted")
    chosen.notes.append(f"second-order sensitivity tempco (temperature_gain2, {span:.1f} degC with field): "
                        + ("adopted" if adopted else "not adopted") + why)
    return chosen


@dataclass
class _Selection:
    """A model's terms and name, the counts of rows excluded with the reference saturated and at reference
    steps, the rows it is fitted to (``d``) and the model built on them."""

    all_terms: tuple[str, ...]
    name: str
    n_sat: int
    n_steps: int
    d: FitData
    cm: CalModel


def _terms_and_name(model: str, terms: Sequence[str] | None, currents: Sequence[str]) -> tuple[tuple[str, ...], str]:
    all_terms = resolve_terms(model, terms, currents)
    name = model if all_terms == MODELS.get(model) else f"{model}+" + "+".join(
        t for t in all_terms if t not in MODELS[model])
    return all_terms, name


def _select(data: FitData, model: str, terms: Sequence[str] | None, currents: Sequence[str], t0_c: float,
            options: FitOptions) -> _Selection:
    """The rows a model is fitted to and the model (FitError when they are too few for its columns)."""
    from magstack.firmware.calibration import crossfit

    all_terms, name = _terms_and_name(model, terms, currents)
    ok = data.usable(all_terms, currents)
    n_sat = 0
    if options.ref_range_uT is not None:
        sat = ok & saturated_rows(data.b_ref_uT, options.ref_range_uT)
        n_sat = int(sat.sum())
        if not options.include_saturated:
            ok &= ~sat
    n_steps = 0
    if options.exclude_ref_steps_uT is not None:
        at_step = ok & reference_steps(data.b_ref_uT, data.session, options.exclude_ref_steps_uT)
        n_steps = int(at_step.sum())
        ok &= ~at_step
    d = data if ok.all() else data.kept(ok)
    cm = build_model(d, all_terms, currents, t0_c, name)
    if d is not data and not (crossfit.applies(cm, options) and crossfit.ordered(d)):
        d = data.select(ok)     # the whole-array paths below need the rows copied
        cm = build_model(d, all_terms, currents, t0_c, name)
    if len(d) <= cm.n_columns:
        why = []
        for label, bad in (("DUT field", ~np.all(np.isfinite(data.b_meas_uT), axis=1)),
                           ("reference field", ~np.all(np.isfinite(data.b_ref_uT), axis=1)),
                           ("temperature", ~np.isfinite(data.temp_c)),
                           ("disqualifying flag", ~usable(data.flag) if data.flag is not None
                            else np.zeros(len(data), bool))):
            if bad.any():
                why.append(f"{label} missing/flagged on {int(bad.sum())} rows")
        raise FitError(f"{len(d)} usable rows of {len(data)} for {cm.n_columns} columns: not enough data"
                       + (f" ({'; '.join(why)})" if why else ""))
    return _Selection(all_terms, name, n_sat, n_steps, d, cm)


def _fit_model(data: FitData, sel: _Selection, currents: Sequence[str], t0_c: float, options: FitOptions
               ) -> tuple[FitResult, BlockSSE | None]:
    """One model's fit on its rows ``sel``, with the time-block folds' held-out squared residuals per block (None
    without folds)."""
    from magstack.firmware.calibration import crossfit

    cross = crossfit.cross_fit(sel.d, sel.cm, options) if crossfit.applies(sel.cm, options) else None
    return _finish(data, sel, cross, currents, t0_c, options)


def _finish(data: FitData, sel: _Selection, cross, currents: Sequence[str], t0_c: float,
            options: FitOptions) -> tuple[FitResult, BlockSSE | None]:
    """:func:`_fit_model` from the cross-fit ``cross`` (None: the refit path fits here)."""
    all_terms, name, n_sat, n_steps, d, cm = sel.all_terms, sel.name, sel.n_sat, sel.n_steps, sel.d, sel.cm
    core = cross.core if cross is not None else _fit_core(d, cm, options)
    X, theta, se, held, conds, cov, mount = (core.X, core.theta, core.se, core.held, core.conds, core.coverage,
                                             core.mount)
    figures = cross.figures if cross is not None else None     # streamed from the cross-fit's blocks
    if figures is None:
        resid = cross.resid_uT if cross is not None else frame_reference(d, mount) - cm.predict(theta, X)
        raw = d.b_ref_uT - d.b_meas_uT
        sse, raw_sse = np.einsum("ij,ij->j", resid, resid), np.einsum("ij,ij->j", raw, raw)
        floor = noise_floor(resid, d.t_s, d.session, options.noise_lag_s)
    else:
        sse, raw_sse, floor = figures.sse_uT2, figures.raw_sse_uT2, figures.noise_floor_uT()
    p_i = len(d) - core.posterior.dof          # tr H: the parameters the data determined
    if mount is not None:   # the angles are shared by the three axes: a third of them to each
        p_i = p_i + sum(1 for k in mount.se_rad for a in range(3)
                        if k != mount.frame and np.isfinite(mount.se_rad[k][a])) / 3
    rmse = np.sqrt(sse / np.maximum(len(d) - p_i, 1))
    raw = np.sqrt(raw_sse / len(d))
    res = FitResult(cm, theta, se, held, len(d), int(len(data) - len(d)), rmse, raw, conds[0], conds[1], floor,
                    cov, options.robust)
    res.posterior = core.posterior
    res.prior_name = _prior_name(options)
    res.chip = options.chip
    res.n_excluded_steps = n_steps
    res.mount = mount
    res.n_saturated, res.saturated_excluded, res.ref_range_uT = n_sat, not options.include_saturated, \
        options.ref_range_uT
    if n_sat:
        lim = (1 - SATURATION_MARGIN) * options.ref_range_uT
        res.notes.insert(0, (f"WARNING: {n_sat} rows have a reference component at or beyond {lim:.4g} uT "
                             f"(range +-{options.ref_range_uT:g} uT): reference possibly saturated; " + (
                                 "excluded (include them with --include-saturated)" if not options.include_saturated
                                 else "INCLUDED as requested (--include-saturated)")))
    if options.exclude_ref_steps_uT is None:
        res.steps = diagnose_steps(resid, d.b_ref_uT, d.session) if figures is None else figures.steps
    acc = cross.acc if cross is not None else None
    block_sse = cross.block_sse if cross is not None else None
    if options.holdout and cross is not None:
        res.holdout_blocks_uT, res.holdout_sessions_uT = cross.holdout_blocks_uT, cross.holdout_sessions_uT
        res.holdout_per_session_uT = cross.holdout_per_session_uT
        res.notes += cross.notes
    elif options.holdout or cross is None:
        acc = _accumulate_whole(d, cm, core, resid, options)
        if options.holdout:
            block_sse = BlockSSE()
            res.holdout_blocks_uT = _holdout_blocks(d, all_terms, currents, t0_c, name, options, res.notes,
                                                    acc.bins, core.X, len(d), block_sse)
            res.holdout_sessions_uT, res.holdout_per_session_uT = _holdout_sessions(
                d, all_terms, currents, t0_c, name, options, res.notes, [h.name for h in held])
    if acc is not None and core.posterior is not None and mount is None:
        res.uncertainty = assemble(core.posterior, acc, np.asarray(floor, dtype=float), cov, options.autocorr)
    if mount is not None and len(np.unique(d.session)) > 1:
        res.comparison = compare(X, d.b_ref_uT, d.b_meas_uT, d.session, d.weights, cm, held, mount,
                                 d.b_ref_uT - _rotate_from_frame(cm.predict(theta, X), d.session, mount),
                                 options, block_folds(d, options) if options.holdout else None,
                                 res.holdout_blocks_uT)
    return res, block_sse


def _accumulate_whole(d: FitData, model: CalModel, core: CoreFit, resid: np.ndarray,
                      options: FitOptions) -> Accumulated:
    """The predictive accumulators from whole arrays (the refit path; :mod:`.crossfit` streams them); the
    held-out bins are filled by :func:`_holdout_blocks`."""
    from magstack.firmware.calibration.blocking import BlockingInflation

    X = core.X
    w = np.ones(len(d)) if d.weights is None else d.weights
    order = np.lexsort((d.t_s, d.session))
    rw = SlowNoiseGrams(model.n_columns, float(np.nanmax(d.t_s) - np.nanmin(d.t_s)) if len(d) else 0.0)
    rw.add((X * w[:, None])[order], d.t_s[order], d.session[order])
    bl = BlockingInflation()
    r = np.asarray(resid, dtype=float)
    bl.add((r[order] - r.mean(axis=0)).T, d.session[order])
    terms = left_out_terms(model, priors_for(options.chip), np.diag(model.unpack(core.theta)["S"]))
    moments = LeftOutMoments(model.n_columns, len(terms))
    moments.add_rows(X, terms, d.b_meas_uT, d.temp_c - model.t0_c, d.weights)
    bins = HeldOutBins.for_coverage(core.coverage, model.n_columns) if options.holdout else None
    taus, ou, rwg, dt = rw.result()
    levels = bl.adjacent_levels()
    return Accumulated((X * w[:, None]).T @ X, taus, weighed_grams(levels, dt, taus, ou + [rwg]), levels, dt, terms,
                       moments, bins)


def _rotate_from_frame(b_uT: np.ndarray, session: np.ndarray, mount: MountSolution) -> np.ndarray:
    """``R_s b`` per row: the frame-mount model field as the session's reference would see it."""
    from scipy.spatial.transform import Rotation
    out = np.array(b_uT, dtype=float, copy=True)
    for k, rv in mount.rotvec_rad.items():
        m = session == k
        if m.any():
            out[m] = Rotation.from_rotvec(rv).apply(out[m])
    return out


def _predict_out(train: FitData, test: FitData, terms, currents, t0_c, name, options,
                 held_names: list[str] | None = None) -> np.ndarray:
    """Residual of ``test`` under a fit on ``train``; the names of the parameters that fit held
    are appended to ``held_names`` when given."""
    cm = build_model(train, terms, currents, t0_c, name)
    core = _fit_core(train, cm, options)
    theta, mount = core.theta, core.mount
    if held_names is not None:
        held_names += [h.name for h in core.held]
    Xt = cm.design(test.b_meas_uT, test.temp_c, test.currents_A, test.session, test.t_s)
    # a session the training rows saw keeps its mount; an unseen one gets the frame's (identity)
    return frame_reference(test, mount) - cm.predict(theta, Xt)


def block_folds(d: FitData, options: FitOptions) -> np.ndarray:
    """(N,) fold of each row: ``block_s`` blocks from each session's start, block k -> fold k mod n_folds."""
    fold = np.zeros(len(d), dtype=np.int64)
    for s in np.unique(d.session):
        m = d.session == s
        fold[m] = time_block_fold(d.t_s[m], d.t_s[m].min(), options)
    return fold


def time_block_fold(t_s: np.ndarray, t_first_s, options: FitOptions) -> np.ndarray:
    """Fold of rows at ``t_s`` (s) of a session whose first row is at ``t_first_s`` (see :func:`block_folds`)."""
    return np.floor((t_s - t_first_s) / options.block_s).astype(np.int64) % options.n_folds


def _holdout_blocks(d: FitData, terms, currents, t0_c, name, options, notes, bins: HeldOutBins | None = None,
                    X_full: np.ndarray | None = None, n_full: int = 0,
                    block_sse: BlockSSE | None = None) -> np.ndarray | None:
    fold = block_folds(d, options)
    sessions = np.unique(d.session)
    k_sess = np.searchsorted(sessions, d.session)
    t_first = np.array([d.t_s[d.session == s].min() for s in sessions])
    blk = np.floor((d.t_s - t_first[k_sess]) / options.block_s).astype(np.int64)
    sq, cnt = np.zeros(3), 0
    for f in np.unique(fold):
        test = fold == f
        if (~test).sum() == 0 or test.sum() == 0:
            continue
        try:
            r = _predict_out(d.select(~test), d.select(test), terms, currents, t0_c, name, options)
        except FitError as exc:
            notes.append(f"time-block fold {f} skipped: {exc}")
            continue
        sq += np.sum(r ** 2, axis=0)
        cnt += r.shape[0]
        if bins is not None and X_full is not None:
            bins.add(X_full[test], r.T, d.b_meas_uT[test], d.temp_c[test], n_full / max(int((~test).sum()), 1))
        if block_sse is not None:
            block_sse.add(k_sess[test], blk[test], np.sum(r ** 2, axis=1))
    if cnt == 0:
        notes.append("held-out by time blocks: no fold could be fitted")
        return None
    return np.sqrt(sq / cnt)


def _holdout_sessions(d: FitData, terms, currents, t0_c, name, options, notes, full_held=()):
    sessions = np.unique(d.session)
    if sessions.size < 2:
        notes.append("held-out by sessions: needs at least two sessions")
        return None, {}
    per: dict[int, np.ndarray] = {}
    sq, cnt = np.zeros(3), 0
    for s in sessions:
        test = d.session == s
        held: list[str] = []
        try:
            r = _predict_out(d.select(~test), d.select(test), terms, currents, t0_c, name, options, held)
        except FitError as exc:
            notes.append(f"session {int(s)} left out: skipped: {exc}")
            continue
        lost = sorted(set(held) - set(full_held))
        if lost:
            notes.append(f"session {int(s)} left out: the other sessions cannot determine {', '.join(lost)} "
                         "(prior-determined), so its held-out error measures extrapolation, not calibration quality")
        per[int(s)] = np.sqrt(np.mean(r ** 2, axis=0))
        sq += np.sum(r ** 2, axis=0)
        cnt += r.shape[0]
    return (np.sqrt(sq / cnt) if cnt else None), per
