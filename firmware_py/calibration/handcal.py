"""Calibration without a reference instrument: a session of hand rotations against the local field's magnitude.

Pipeline (:func:`calibrate`): usable rows -> model (``gain_offset``, or ``eq3`` when the session spans
temperature) -> the attitude-independent MAP fit (:mod:`.scalar_map`: chip priors, gauge fixed) ->
disturbance screen (windows whose magnitude residual departs from the rest, e.g. a laptop brought near,
are excluded and the fit repeated) -> residual autocorrelation inflation -> held-out time blocks ->
the calibrated field's coverage of the sphere (:mod:`.coverage_bins`) -> the frame: a level turn about the
board's z axis, when the session has one, fixes the tilt; the rotation the magnitude cannot see is named,
never guessed -> verdict (refused when the coverage or the parameters the data determined are not enough).

The field magnitude comes from the caller: a constant (IGRF/WMM at the site, or a given value), per-row
magnitudes (a reference instrument's ``|B|``), or none (estimated: the overall scale then rests on the
chip's gain prior, and the result says the scale is relative).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from magstack.drivers.cal_priors import priors_for
from magstack.firmware.calibration import scalar_map as sm
from magstack.firmware.calibration.coverage_bins import N_BINS, AttitudeCoverage
from magstack.firmware.calibration.estimator import Posterior, apply_overrides, autocorr_inflation, model_prior
from magstack.firmware.calibration.model import AXES, MODELS, CalModel
from magstack.firmware.errors import FitError

TEMPERATURE = ("auto", "on", "off")
FRAMES = ("auto", "sensor", "level")
#: Coverage below which the calibration is refused (fraction of the 192 direction cells, and the smallest
#: eigenvalue of the mean outer product of the field directions: 1/3 for a uniform sphere, 0 for a plane).
MIN_CELL_FRACTION = 0.30
MIN_DIRECTION_EIG = 0.08
#: Coverage at which the live view says "enough".
ENOUGH_CELL_FRACTION = 0.55
ENOUGH_DIRECTION_EIG = 0.18
#: A level turn: the calibrated field's angle to the board's z axis stays within this (deg) while its
#: azimuth about z sweeps at least LEVEL_SWEEP_DEG.
LEVEL_BAND_DEG = 5.0
LEVEL_SWEEP_DEG = 300.0
#: Blocks the residual-autocorrelation inflation keeps at least (the bench fit uses 16): a hand session is
#: minutes long and the 1/f noise of some parts (LIS3MDL) correlates residuals over tens of seconds.
KAPPA_MIN_BLOCKS = 8


@dataclass
class HandCalData:
    """Samples of a hand-rotation session: ``b_meas_uT`` (N, 3) the sensor's readings, ``temp_c`` (N,) degC
    (NaN allowed when not used), ``t_s`` (N,) s, ``r_uT`` (N,) the field magnitude per row or None,
    ``session`` (N,) ints; ``flag`` (N,) 0 = usable."""

    b_meas_uT: np.ndarray
    temp_c: np.ndarray
    t_s: np.ndarray
    r_uT: np.ndarray | None = None
    session: np.ndarray | None = None
    flag: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.b_meas_uT = np.asarray(self.b_meas_uT, dtype=float).reshape(-1, 3)
        n = len(self.b_meas_uT)
        self.temp_c = np.asarray(self.temp_c, dtype=float).reshape(n)
        self.t_s = np.asarray(self.t_s, dtype=float).reshape(n)
        if self.r_uT is not None:
            self.r_uT = np.asarray(self.r_uT, dtype=float).reshape(n)
        self.session = np.zeros(n, np.int64) if self.session is None else np.asarray(self.session).astype(np.int64)
        if self.flag is not None:
            self.flag = np.asarray(self.flag).astype(np.int64).reshape(n)

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass
class HandCalOptions:
    """Policy. ``field_uT``: the local field magnitude (uT) with ``field_source`` saying where it came from;
    None and no per-row magnitudes: estimated (relative scale). ``temperature``: "auto" fits the temperature
    terms (the chip's prior decides what a session without ``min_temp_span_c`` of span cannot); ``t0_c`` None:
    the session's mean temperature. ``frame``: "level" needs a level turn, "sensor" keeps the sensor's
    frame, "auto" uses a level turn when there is one. ``allow_poor_coverage``:
    return a result (flagged) instead of refusing."""

    chip: str | None = None
    soft_iron: str = "symmetric"
    field_uT: float | None = None
    field_source: str = ""
    temperature: str = "auto"
    min_temp_span_c: float = 3.0
    t0_c: float | None = None
    use_priors: bool = True
    priors: dict = field(default_factory=dict)
    holdout: bool = True
    block_s: float = 10.0
    n_folds: int = 5
    screen: bool = True
    screen_window_s: float = 1.0
    screen_k: float = 5.0
    frame: str = "auto"
    allow_poor_coverage: bool = False
    autocorr: bool = True

    def __post_init__(self) -> None:
        if self.temperature not in TEMPERATURE:
            raise FitError(f"temperature must be one of {TEMPERATURE}, got {self.temperature!r}")
        if self.frame not in FRAMES:
            raise FitError(f"frame must be one of {FRAMES}, got {self.frame!r}")
        if self.soft_iron not in sm.SOFT_IRON:
            raise FitError(f"soft_iron must be one of {sm.SOFT_IRON}, got {self.soft_iron!r}")
        if self.field_uT is not None and not (math.isfinite(self.field_uT) and self.field_uT > 0):
            raise FitError(f"field_uT must be finite and > 0, got {self.field_uT!r}")
        for name in ("block_s", "screen_window_s", "screen_k", "min_temp_span_c"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise FitError(f"{name} must be finite and > 0, got {v!r}")
        if self.n_folds < 2:
            raise FitError("n_folds must be >= 2")


@dataclass
class SphereCoverage:
    """Coverage of the field sphere by the calibrated field directions: filled cells of the 192 equal-area
    cells, the smallest eigenvalue of the directions' mean outer product, and the counts per cell."""

    cells_filled: int
    fraction: float
    min_eig: float
    counts: np.ndarray

    @classmethod
    def of(cls, b_uT: np.ndarray, temp_c: np.ndarray | None = None) -> SphereCoverage:
        b = np.asarray(b_uT, dtype=float).reshape(-1, 3)
        cov = AttitudeCoverage()
        t = np.full(len(b), 20.0) if temp_c is None else np.where(np.isfinite(temp_c), temp_c, 20.0)
        cov.update(b, t)
        n = np.linalg.norm(b, axis=1)
        ok = n > 0
        u = b[ok] / n[ok, None]
        eig = float(np.linalg.eigvalsh(u.T @ u / max(len(u), 1))[0]) if len(u) else 0.0
        counts = cov.counts.sum(axis=0)
        return cls(int(np.count_nonzero(counts)), cov.fraction, eig, counts)

    @property
    def enough(self) -> bool:
        return self.fraction >= ENOUGH_CELL_FRACTION and self.min_eig >= ENOUGH_DIRECTION_EIG

    @property
    def poor(self) -> bool:
        return self.fraction < MIN_CELL_FRACTION or self.min_eig < MIN_DIRECTION_EIG

    def to_dict(self) -> dict:
        return {"cells_filled": self.cells_filled, "cells": N_BINS, "fraction": self.fraction,
                "min_direction_eig": self.min_eig}


@dataclass
class LevelTurn:
    """Rows of a detected level turn (``start``..``stop`` indices into the used rows), its swept azimuth."""

    start: int
    stop: int
    sweep_deg: float
    t0_s: float
    t1_s: float


@dataclass
class Frame:
    """How the calibrated frame was fixed. ``kind``: "sensor" (symmetric gauge: the sensor's frame turned by
    the smallest rotation; 3 angles undetermined) or "level" (tilt from level turns; the rotation about z
    undetermined). ``rotation``: applied to the symmetric-gauge result; ``tilt_deg`` its angle."""

    kind: str
    undetermined: str
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    tilt_deg: float = 0.0
    tilt_sd_deg: float = float("nan")
    turns: list[LevelTurn] = field(default_factory=list)


def find_level_turns(b_cal_uT: np.ndarray, t_s: np.ndarray, band_deg: float = LEVEL_BAND_DEG,
                     sweep_deg: float = LEVEL_SWEEP_DEG) -> list[LevelTurn]:
    """Stretches where the calibrated field's angle to the board's z axis stays within ``band_deg`` while its
    azimuth about z sweeps at least ``sweep_deg``: the board turned about z with z vertical (on a table)."""
    b = np.asarray(b_cal_uT, dtype=float)
    n = len(b)
    if n < 10:
        return []
    mag = np.linalg.norm(b, axis=1)
    theta = np.degrees(np.arccos(np.clip(b[:, 2] / np.where(mag > 0, mag, 1.0), -1.0, 1.0)))
    psi = np.degrees(np.unwrap(np.arctan2(b[:, 1], b[:, 0])))
    out: list[LevelTurn] = []
    i = 0
    from collections import deque
    while i < n - 1:
        lo: deque = deque()
        hi: deque = deque()
        j = i
        while j < n:
            while lo and theta[lo[-1]] >= theta[j]:
                lo.pop()
            lo.append(j)
            while hi and theta[hi[-1]] <= theta[j]:
                hi.pop()
            hi.append(j)
            if theta[hi[0]] - theta[lo[0]] > band_deg or (j > i and t_s[j] - t_s[j - 1] > 1.0):
                break
            j += 1
        sweep = float(np.ptp(psi[i:j])) if j - i > 1 else 0.0
        if sweep >= sweep_deg and 10.0 < float(np.median(theta[i:j])) < 170.0:
            out.append(LevelTurn(i, j, sweep, float(t_s[i]), float(t_s[j - 1])))
            i = j
        else:
            i = max(i + 1, (i + j) // 2) if j - i > 50 else i + 1
    return out


def _level_rotation(b_cal: np.ndarray, turns: list[LevelTurn], sigma_uT: float) -> tuple[np.ndarray, float, float]:
    """(rotation taking the turns' mean plane normal onto the board's z axis, its angle deg, the angle's sd deg)."""
    normals, weights = [], []
    for tn in turns:
        pts = b_cal[tn.start:tn.stop]
        u = pts - pts.mean(axis=0)
        w, v = np.linalg.eigh(u.T @ u)
        nrm = v[:, 0] * np.sign(v[2, 0] or 1.0)
        radius = math.sqrt(max(w[1] + w[2], 0.0) / len(pts))
        normals.append(nrm)
        weights.append(len(pts) * radius ** 2)
    nbar = np.average(np.asarray(normals), axis=0, weights=np.asarray(weights))
    nbar /= np.linalg.norm(nbar)
    rot, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [nbar])
    angle = math.degrees(rot.magnitude())
    # the normal of points spread round a circle of radius R: angular sd ~ sigma / (R sqrt(n / 2))
    sd = math.degrees(sigma_uT / math.sqrt(max(sum(weights) / 2.0, 1e-300)))
    if len(normals) > 1:
        spread = [math.degrees(math.acos(min(1.0, abs(float(x @ nbar))))) for x in normals]
        sd = max(sd, float(np.std(spread, ddof=1)) / math.sqrt(len(normals)))
    return rot.as_matrix(), angle, sd


def noise_floor_uT(b_uT: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> np.ndarray:
    """(3,) white-noise level per axis (uT) from second differences of consecutive rows (robust: MAD), which
    remove smooth motion; slower noise (1/f) is not in it."""
    b = np.asarray(b_uT, dtype=float)
    ok = (session[2:] == session[:-2]) & (session[1:-1] == session[:-2])
    dt = np.diff(t_s)
    if len(dt):
        med = np.median(dt[dt > 0]) if np.any(dt > 0) else 1.0
        ok &= (np.abs(dt[1:] - med) < 0.5 * med) & (np.abs(dt[:-1] - med) < 0.5 * med)
    d2 = b[2:] - 2 * b[1:-1] + b[:-2]
    d2 = d2[ok]
    if len(d2) < 10:
        return np.full(3, np.nan)
    mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    return 1.4826 * mad / math.sqrt(6.0)


@dataclass
class HandCalResult:
    """Everything :func:`calibrate` produced (uT, degC, s). ``theta`` is in the final frame."""

    model: CalModel
    posterior: sm.ScalarPosterior
    theta: np.ndarray
    frame: Frame
    n_rows: int
    n_used: int
    n_disturbed: int
    disturbed_spans_s: list[tuple[float, float, float]]
    magnitude: dict
    coverage: SphereCoverage
    noise_floor_axes_uT: np.ndarray
    noise_floor_mag_uT: float
    temp_range_c: tuple[float, float]
    field_uT: float | None
    field_source: str
    scale: str
    chip: str | None
    prior_name: str
    kappa: float
    notes: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    used: np.ndarray | None = None
    holdout_residual_uT: np.ndarray | None = None
    #: the fit rows' readings and calibrated field (final frame) as :class:`~.fit.Coverage` (validity region)
    field_coverage: object | None = None

    # ------------------------------------------------------------------ applying
    def apply(self, b_meas_uT: np.ndarray, temp_c: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) calibrated field in the result's frame."""
        X = sm.design(self.model, b_meas_uT, temp_c)
        return X @ self.theta.T

    @property
    def params(self) -> dict:
        return self.model.unpack(self.theta)

    @property
    def ok(self) -> bool:
        return not self.refused

    # ------------------------------------------------------------------ report
    def parameter_rows(self) -> list[dict]:
        """Per free parameter (symmetric gauge): value, posterior sd, prior, data share, who determined it.
        With a level frame the table's matrices are these turned by ``frame.rotation``."""
        out = []
        for r in sm.parameter_rows(self.posterior):
            out.append({"param": r.name, "value": r.value, "sd": r.sd, "prior_mean": r.prior_mean,
                        "prior_sd": r.prior_sd, "data_share": r.data_share, "determined_by": r.determined_by,
                        "unit": r.unit})
        return out

    def stats(self) -> dict:
        """JSON-friendly statistics (the table's ``fit`` block)."""
        p = self.posterior
        return {
            "method": "attitude-independent MAP (magnitude only)", "model": self.model.name,
            "soft_iron": p.par.soft_iron, "rows": self.n_rows, "n_used": self.n_used,
            "disturbed_rows_excluded": self.n_disturbed,
            "disturbed_spans_s": [list(x) for x in self.disturbed_spans_s],
            "magnitude_nT": {k[:-3] + "_nT" if k.endswith("_uT") else k: (None if v is None else
                                                                      (np.asarray(v, dtype=float) * 1e3).tolist())
                             for k, v in self.magnitude.items()},
            "noise_floor_axes_nT": [float(x) * 1e3 for x in self.noise_floor_axes_uT],
            "noise_floor_magnitude_nT": self.noise_floor_mag_uT * 1e3,
            "coverage": self.coverage.to_dict(), "temp_range_c": list(self.temp_range_c),
            "field_uT": self.field_uT, "field_source": self.field_source, "scale": self.scale,
            "frame": {"kind": self.frame.kind, "undetermined": self.frame.undetermined,
                      "tilt_applied_deg": self.frame.tilt_deg, "tilt_sd_deg": self.frame.tilt_sd_deg,
                      "level_turns_s": [[t.t0_s, t.t1_s, t.sweep_deg] for t in self.frame.turns]},
            "priors": self.prior_name, "sigma_uT": p.sigma_uT, "autocorr_inflation": self.kappa,
            "gauss_newton_iterations": p.iterations, "parameters": self.parameter_rows(),
            "refused": list(self.refused), "notes": list(self.notes),
        }

    def report(self) -> str:
        m = self.magnitude
        L = [f"model {self.model.name} (soft iron {self.posterior.par.soft_iron}); "
             f"field magnitude {self._field_text()}",
             f"rows {self.n_rows}, used {self.n_used}" + (f", {self.n_disturbed} excluded as disturbed "
                                                           f"({len(self.disturbed_spans_s)} spans)"
                                                           if self.n_disturbed else ""),
             f"temperature {self.temp_range_c[0]:.1f}..{self.temp_range_c[1]:.1f} degC", "",
             f"field-sphere coverage: {self.coverage.cells_filled} of {N_BINS} cells "
             f"({self.coverage.fraction:.0%}), smallest direction eigenvalue {self.coverage.min_eig:.3f} "
             f"(uniform sphere 0.333)", "",
             f"{'|B| error (nT)':34s}{'RMS':>10s}",
             f"{'  raw (sensor as read)':34s}{_nt(m.get('raw_rms_uT')):>10s}",
             f"{'  calibrated, in-sample':34s}{_nt(m.get('in_sample_rms_uT')):>10s}",
             f"{'  calibrated, held-out time blocks':34s}{_nt(m.get('holdout_rms_uT')):>10s}",
             f"{'  white-noise floor (2nd diff.)':34s}{_nt(self.noise_floor_mag_uT):>10s}", ""]
        f = self.frame
        L.append(f"frame: {f.kind}" + (f" (tilt {f.tilt_deg:.2f} +- {f.tilt_sd_deg:.2f} deg from "
                                       f"{len(f.turns)} level turn(s))" if f.kind == "level" else ""))
        L.append(f"UNDETERMINED by the data: {f.undetermined}")
        L += ["", f"priors: {self.prior_name}; residual sigma {self.posterior.sigma_uT * 1e3:.0f} nT, "
                  f"autocorrelation inflation {self.kappa:.1f}", "",
              f"{'parameter':14s}{'value':>13s}{'post. sd':>11s}{'prior':>24s}{'data':>6s}  determined by  unit"]
        for r in self.parameter_rows():
            pr = f"{r['prior_mean']:.4g} +- {r['prior_sd']:.2g}"
            sh = f"{r['data_share']:5.0%}" if np.isfinite(r["data_share"]) else "    -"
            L.append(f"{r['param']:14s}{r['value']:13.6g}{r['sd']:11.3g}{pr:>24s} {sh}  "
                     f"{r['determined_by']:13s}  {r['unit']}")
        L += [f"note: {n}" for n in self.notes]
        L += [f"REFUSED: {r}" for r in self.refused]
        return "\n".join(L)

    def _field_text(self) -> str:
        if self.scale == "per-row":
            return "per row (given)"
        if self.scale == "relative":
            F = self.posterior.phi[-1]
            return (f"ESTIMATED {F:.2f} +- {self.posterior.sd[-1]:.2f} uT: the scale is RELATIVE (set by the "
                    f"chip's gain prior, not by a known field)")
        return f"{self.field_uT:.3f} uT ({self.field_source or 'given'})"

    # ------------------------------------------------------------------ the table
    def table(self, device_id: str, *, description: str = "", created_utc: str = "",
              validity_temp_c=None, validity_field_uT=None, validity_sd_uT=None):
        """A :class:`~magstack.firmware.cal_table.CalTable` in the flight format, through
        :func:`~magstack.firmware.cal_table.table_from_fit` (posterior block and validity box from it)."""
        from magstack.firmware.cal_table import table_from_fit

        return table_from_fit(_TableView(self), device_id, description=description, created_utc=created_utc,
                              validity_temp_c=validity_temp_c, validity_field_uT=validity_field_uT,
                              validity_sd_uT=validity_sd_uT)


def _nt(v) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v * 1e3:.1f}"


class _TableView:
    """What :func:`magstack.firmware.cal_table.table_from_fit` reads from a fit result, for a hand calibration:
    the model and coefficients (final frame), a per-axis posterior (the parameter covariance in the final
    frame, cross-axis terms dropped as the table stores them), the coverage, the noise floor and statistics."""

    def __init__(self, res: HandCalResult) -> None:
        from magstack.firmware.calibration.fit import Coverage

        self.model = res.model
        self.theta = res.theta
        self.chip = res.chip
        self.prior_name = res.prior_name
        self._stats = res.stats()
        p = res.model.n_columns
        Cfull = res.posterior.theta_cov()
        Rk = np.kron(res.frame.rotation, np.eye(p))          # rotating every term: theta -> Q theta (per column)
        Cfull = Rk @ Cfull @ Rk.T
        cov = np.stack([Cfull[i * p:(i + 1) * p, i * p:(i + 1) * p] for i in range(3)])
        prior = _axis_prior(res.model, res.posterior)
        self.posterior = Posterior(res.model, prior, res.theta.copy(), cov, np.full(3, res.posterior.sigma_uT),
                                   np.full(3, res.kappa), np.zeros(3), np.zeros(3), np.zeros(3), res.n_used)
        self.noise_floor_uT = np.asarray(res.noise_floor_axes_uT, dtype=float)
        self.rmse_uT = np.full(3, res.magnitude.get("in_sample_rms_uT") or np.nan)
        if res.field_coverage is not None:
            self.coverage = res.field_coverage
        else:
            cov_ = Coverage()
            cov_.temp_min_c, cov_.temp_max_c = res.temp_range_c
            cov_.field_max_uT = np.asarray(res.magnitude.get("field_max_axes_uT", np.full(3, 100.0)), dtype=float)
            self.coverage = cov_

    def stats(self) -> dict:
        return dict(self._stats)


def _axis_prior(model: CalModel, post: sm.ScalarPosterior):
    from magstack.firmware.calibration.estimator import Prior

    p = model.n_columns
    mean = np.zeros((3, p))
    var = np.full((3, p), np.inf)
    src = [["" for _ in range(p)] for _ in range(3)]
    for k, g in enumerate(post.par.groups):
        for idx in g:
            i, c = divmod(idx, p)
            mean[i, c] = post.prior_mean[k]
            var[i, c] = post.prior_cov[k, k] * len(g)
            src[i][c] = post.sources[k]
    cov = np.zeros((3, p, p))
    for i in range(3):
        np.fill_diagonal(cov[i], np.where(np.isfinite(var[i]), var[i], np.inf))
    return Prior(mean, cov, tuple(tuple(r) for r in src))


# ---------------------------------------------------------------------- the pipeline
def _windowed_median(x: np.ndarray, t: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(median of ``x`` over windows of ``window_s`` (time bins), rows in the window), per row."""
    k = np.floor((t - t[0]) / window_s).astype(np.int64)
    out = np.empty_like(x)
    cnt = np.empty(len(x))
    order = np.argsort(k, kind="stable")
    ks = k[order]
    cuts = np.r_[0, np.flatnonzero(np.diff(ks)) + 1, len(ks)]
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        idx = order[a:b]
        out[idx] = np.median(x[idx])
        cnt[idx] = b - a
    return out, cnt


def _close_spans(bad: np.ndarray, t: np.ndarray, window_s: float, gap_windows: float = 3.0) -> np.ndarray:
    """``bad`` with gaps shorter than ``gap_windows`` windows between flagged rows filled, and each flagged span
    widened by one window on both sides: a magnet brought near the board is one event, whose field at the
    sensor passes through zero change in some attitudes."""
    out = bad.copy()
    idx = np.flatnonzero(bad)
    if not idx.size:
        return out
    for a, b in zip(idx[:-1], idx[1:], strict=True):
        if b > a + 1 and t[b] - t[a] <= gap_windows * window_s:
            out[a:b] = True
    runs = np.flatnonzero(np.diff(np.r_[0, out.astype(np.int8), 0]))
    for a, b in zip(runs[::2], runs[1::2], strict=True):
        out[(t >= t[a] - window_s) & (t <= t[b - 1] + window_s)] = True
    return out


def _spans(mask: np.ndarray, t: np.ndarray, e: np.ndarray) -> list[tuple[float, float, float]]:
    """(t start, t end, largest |residual| uT) of each run of True in ``mask``."""
    out = []
    idx = np.flatnonzero(mask)
    if not idx.size:
        return out
    cuts = np.r_[0, np.flatnonzero(np.diff(idx) > 1) + 1, idx.size]
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        run = idx[a:b]
        out.append((float(t[run[0]]), float(t[run[-1]]), float(np.max(np.abs(e[run])))))
    return out


def choose_model(temp_c: np.ndarray, options: HandCalOptions) -> tuple[CalModel, str]:
    """(model, note): ``eq3`` when every row has a temperature (``temperature`` "auto" or "on"), with ``t0``
    the session's mean temperature unless given; the estimator lets the chip's prior decide the temperature
    terms the session's span cannot (so the table's validity box says how far from the session's temperature
    it holds); ``gain_offset`` otherwise."""
    fin = np.isfinite(temp_c)
    t = temp_c[fin]
    span = float(np.ptp(t)) if t.size else 0.0
    if options.temperature == "off" or (options.temperature == "auto" and (not t.size or not fin.all())):
        t0 = options.t0_c if options.t0_c is not None else (round(float(np.mean(t)), 2) if t.size else 25.0)
        why = "temperature terms off" if options.temperature == "off" else "no temperature on every row"
        return CalModel(MODELS["gain_offset"], t0_c=t0, name="gain_offset"), why
    if not fin.all():
        raise FitError("temperature terms need the temperature on every row (some rows have none)")
    t0 = options.t0_c if options.t0_c is not None else round(float(np.mean(t)), 2)
    if span >= options.min_temp_span_c:
        return (CalModel(MODELS["eq3"], t0_c=t0, name="eq3"),
                f"temperature span {span:.1f} degC: temperature terms fitted")
    return (CalModel(MODELS["eq3"], t0_c=t0, name="eq3"),
            f"temperature span {span:.1f} degC (< {options.min_temp_span_c:g}): the temperature terms are the chip's "
            f"prior about t0 = {t0:g} degC; the table's validity box says how far from it the calibration holds")


def calibrate(data: HandCalData, options: HandCalOptions | None = None) -> HandCalResult:
    """Attitude-independent calibration of a hand-rotation session (module docstring). Raises FitError when
    the data cannot be fitted at all; a fit the coverage does not support is returned with ``refused`` set
    (the caller writes no table) unless ``allow_poor_coverage``."""
    opt = options or HandCalOptions()
    b = data.b_meas_uT
    ok = np.all(np.isfinite(b), axis=1) & np.isfinite(data.t_s)
    if data.flag is not None:
        from magstack.data.dictionary import usable

        ok &= usable(data.flag)
    if data.r_uT is not None:
        ok &= np.isfinite(data.r_uT) & (data.r_uT > 0)
    model, tnote = choose_model(data.temp_c[ok], opt)
    n_rows = len(data)
    idx = np.flatnonzero(ok)
    if idx.size < 50:
        raise FitError(f"{idx.size} usable rows of {n_rows}: a hand calibration needs at least 50")
    order = idx[np.lexsort((data.t_s[idx], data.session[idx]))]
    bb, tt, ss = b[order], data.t_s[order], data.session[order]
    temp = data.temp_c[order]
    if data.r_uT is not None:
        r, scale, F_prior = data.r_uT[order], "per-row", None
    elif opt.field_uT is not None:
        r, scale, F_prior = np.full(len(order), opt.field_uT), "absolute", None
    else:
        r, scale, F_prior = None, "relative", (0.0, np.inf)
    par = sm.parametrise(model, opt.soft_iron, magnitude=r is None)
    chip = priors_for(opt.chip)
    from magstack.firmware.calibration.estimator import Prior

    theta_prior = model_prior(model, chip) if opt.use_priors else Prior.flat(model.n_columns)
    if opt.priors:
        ov = {k: ((float(v), 0.0) if np.isscalar(v) else (float(v[0]), float(v[1]))) for k, v in opt.priors.items()}
        theta_prior = apply_overrides(theta_prior, model, ov)
    mean, cov, src = sm.phi_prior(par, theta_prior, F_prior)
    X = sm.design(model, bb, temp)
    start = sm.start_phi(par, bb, r)
    if r is None:
        # the magnitude scales with the whole calibration (a gauge the data cannot see): fit with F held at the
        # start's value, then choose the overall scale the gain prior prefers (below)
        mean[-1], cov[-1, -1] = start[-1], 0.0
    notes = [tnote]
    # the sensor's white noise along the field bounds the residual scale from below
    nf0 = noise_floor_uT(bb, tt, ss)
    floor = float(np.sqrt(np.mean(nf0 ** 2))) if np.all(np.isfinite(nf0)) else 0.0
    # 1. fit, screen disturbed windows, refit
    use = np.ones(len(order), dtype=bool)
    post = sm.fit_magnitude(par, X, r, mean, cov, src, start=start, sigma_floor_uT=floor)
    n_dist = 0
    spans: list = []
    if opt.screen:
        for _ in range(3):
            e = sm.residual(par, post.phi, X, r)
            med, cnt = _windowed_median(e, tt, opt.screen_window_s)
            centre = float(np.median(med[use]))
            spread = 1.4826 * float(np.median(np.abs(med[use] - centre)))
            # a window's median of white residuals has sd ~1.25 sigma / sqrt(rows): never flag below that
            sigma = 1.4826 * float(np.median(np.abs(e[use] - np.median(e[use]))))
            bad = np.abs(med - centre) > opt.screen_k * np.maximum(spread, 1.2533 * sigma / np.sqrt(cnt))
            bad = _close_spans(bad, tt, opt.screen_window_s)
            new_use = ~bad
            if new_use.sum() < 0.5 * len(use) or np.array_equal(new_use, use):
                break
            use = new_use
            post = sm.fit_magnitude(par, X[use], None if r is None else r[use], mean, cov, src, start=post.phi,
                                    sigma_floor_uT=floor)
        n_dist = int((~use).sum())
        if n_dist:
            e_all = sm.residual(par, post.phi, X, r)
            spans = _spans(~use, tt, e_all)
            notes.append(f"{n_dist} rows in {len(spans)} span(s) excluded: the field magnitude there departs from "
                         f"the rest by up to {max(s[2] for s in spans):.2f} uT (a magnetic object moved near the "
                         f"board?)")
    Xu, ru, tu, su, bu, temp_u = X[use], (None if r is None else r[use]), tt[use], ss[use], bb[use], temp[use]
    kappa = 1.0
    if opt.autocorr:
        e = sm.residual(par, post.phi, Xu, ru)
        kappa = float(autocorr_inflation(np.repeat(e[:, None], 3, axis=1), tu, su, min_blocks=KAPPA_MIN_BLOCKS)[0])
        post = sm.fit_magnitude(par, Xu, ru, mean, cov, src, start=post.phi, kappa=kappa, sigma_floor_uT=floor)
    if r is None:
        post = _prior_scale(post, theta_prior, model, opt.use_priors)
    e_in = sm.residual(par, post.phi, Xu, ru)
    b_cal = Xu @ post.theta.T
    raw_ref = ru if ru is not None else post.phi[-1]
    magnitude = {"raw_rms_uT": float(np.sqrt(np.mean((np.linalg.norm(bu, axis=1) - raw_ref) ** 2))),
                 "in_sample_rms_uT": float(np.sqrt(np.mean(e_in ** 2))),
                 "holdout_rms_uT": None,
                 "field_max_axes_uT": np.max(np.abs(bu), axis=0)}
    # 2. held-out time blocks
    hold = None
    if opt.holdout:
        hold, hnotes = _holdout(par, Xu, ru, tu, su, mean, cov, src, post, kappa, opt, floor)
        notes += hnotes
        if hold is not None:
            ok_h = np.isfinite(hold)
            magnitude["holdout_rms_uT"] = float(np.sqrt(np.mean(hold[ok_h] ** 2))) if ok_h.any() else None
    # 3. coverage, noise floor
    coverage = SphereCoverage.of(b_cal, temp_u)
    nf = noise_floor_uT(bu, tu, su)
    S = model.unpack(post.theta)["S"]
    nf_cal = np.sqrt((S ** 2) @ (nf ** 2))
    u = b_cal / np.linalg.norm(b_cal, axis=1, keepdims=True)
    nf_mag = float(np.sqrt(np.mean((u ** 2) @ (nf_cal ** 2))))
    # 4. frame
    frame = _frame(b_cal, tu, post, opt, notes)
    theta = _rotate_theta(model, post.theta, frame.rotation)
    t_fin = temp_u[np.isfinite(temp_u)]
    trange = (float(t_fin.min()), float(t_fin.max())) if t_fin.size else (math.nan, math.nan)
    prior_name = (f"{chip.chip} ({chip.source})" + ("" if chip.chip != "generic" else
                                                     f": no prior table for chip {opt.chip!r}")
                  if opt.use_priors else "none (unregularised least squares)")
    res = HandCalResult(model, post, theta, frame, n_rows, int(use.sum()), n_dist, spans, magnitude, coverage,
                        nf_cal, nf_mag, trange, opt.field_uT if scale == "absolute" else None, opt.field_source,
                        scale, opt.chip, prior_name, kappa, notes)
    used = np.zeros(n_rows, dtype=bool)
    used[order[use]] = True
    res.used = used
    from magstack.firmware.calibration.fit import Coverage

    res.field_coverage = Coverage()
    res.field_coverage.update(bu, temp_u, {}, su, tu, 5.0, ref_uT=b_cal @ frame.rotation.T)
    if hold is not None:
        h = np.full(n_rows, np.nan)
        h[order[use]] = hold
        res.holdout_residual_uT = h
    if scale == "relative":
        notes.append("no field magnitude given: |B| is estimated from the chip's gain prior; the calibrated "
                     "field is right in shape and direction but its scale is RELATIVE (give --site/--date or "
                     "--field-uT for an absolute one)")
    res.refused = _verdict(res)
    if res.refused and opt.allow_poor_coverage:
        notes.append("poor coverage accepted on request: " + "; ".join(res.refused))
        res.refused = []
    return res


def _prior_scale(post: sm.ScalarPosterior, theta_prior, model: CalModel, use_priors: bool) -> sm.ScalarPosterior:
    """Relative scale: every parameter and ``F`` times ``alpha``, the scale the gain diagonal's prior prefers
    (``alpha = sum S_ii m_i / v_i / sum S_ii^2 / v_i``); ``F``'s sd is the prior's sd of that scale, labelled as
    the prior's. Without priors the start's scale is kept (and said)."""
    S = model.unpack(post.theta)["S"]
    cols = [c for c, col in enumerate(model.columns) if col.param == "S"]
    m = np.array([theta_prior.mean[i, cols[i]] for i in range(3)])
    v = np.array([theta_prior.cov[i, cols[i], cols[i]] for i in range(3)])
    d = np.diag(S)
    F0 = float(post.phi[-1])
    if not (use_priors and np.all(np.isfinite(v)) and np.all(v > 0)):
        post.prior_cov[-1, -1] = post.cov[-1, -1] = 0.0
        return post
    alpha = float(np.sum(d * m / v) / np.sum(d * d / v))
    sd_alpha = float(1.0 / np.sqrt(np.sum(d * d / v)))
    post.phi = post.phi * alpha
    post.cov = post.cov * alpha * alpha
    post.cov[-1, -1] = (F0 * sd_alpha) ** 2
    post.prior_mean = post.prior_mean.copy()
    post.prior_cov = post.prior_cov.copy()
    post.prior_mean[-1] = F0 * alpha
    post.prior_cov[-1, -1] = (F0 * sd_alpha) ** 2      # all of it from the gain prior: "prior"
    post.sigma_uT *= alpha
    return post


def _holdout(par, X, r, t, s, mean, cov, src, post, kappa, opt, floor=0.0) -> tuple[np.ndarray | None, list[str]]:
    """Out-of-fold magnitude residual per used row (time blocks of ``block_s``, block k -> fold k mod n)."""
    fold = np.zeros(len(t), dtype=np.int64)
    for sid in np.unique(s):
        m = s == sid
        fold[m] = np.floor((t[m] - t[m].min()) / opt.block_s).astype(np.int64) % opt.n_folds
    out = np.full(len(t), np.nan)
    notes = []
    for f in np.unique(fold):
        test = fold == f
        if test.all():
            continue
        try:
            q = sm.fit_magnitude(par, X[~test], None if r is None else r[~test], mean, cov, src, start=post.phi,
                                 kappa=kappa, sigma_floor_uT=floor)
        except FitError as exc:
            notes.append(f"held-out fold {int(f)} skipped: {exc}")
            continue
        out[test] = sm.residual(par, q.phi, X[test], None if r is None else r[test])
    if not np.isfinite(out).any():
        return None, notes + ["held-out: no fold could be fitted"]
    return out, notes


def _frame(b_cal, t, post, opt, notes) -> Frame:
    rot_temp = " and a rotation that changes with temperature (3 more)" if "temperature_gain" in post.par.model.terms \
        else ""
    sensor = Frame("sensor", "the calibrated frame's rotation relative to the board (3 angles)" + rot_temp +
                   ": the field magnitude is the same in every rotated frame. The table keeps the sensor's own "
                   "axes (the smallest rotation); mount alignment needs a direction reference")
    if opt.frame == "sensor":
        return sensor
    turns = find_level_turns(b_cal, t)
    if not turns:
        if opt.frame == "level":
            raise FitError("--frame level: no level turn found (a full turn about the board's z axis with the "
                           "board flat on a table)")
        return sensor
    rot, angle, sd = _level_rotation(b_cal, turns, post.sigma_uT)
    notes.append(f"{len(turns)} level turn(s) about the board's z axis found: the tilt of the calibrated frame "
                 f"({angle:.2f} deg) is taken from them, assuming the table was level")
    return Frame("level", "the rotation about the board's z axis (heading offset, 1 angle)" + rot_temp +
                 ": a level turn fixes the tilt, not the heading; set the heading offset from a known direction",
                 rot, angle, sd, turns)


def _rotate_theta(model: CalModel, theta: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Every term of a calibration rotated: B_cal -> Q B_cal (each coefficient column turned by Q)."""
    return Q @ theta


def _verdict(res: HandCalResult) -> list[str]:
    """Reasons to refuse the table: poor coverage, or gains/offsets the data did not determine."""
    out = []
    c = res.coverage
    if c.poor:
        out.append(f"the field directions cover {c.cells_filled} of {N_BINS} cells ({c.fraction:.0%}; need "
                   f"{MIN_CELL_FRACTION:.0%}) with smallest direction eigenvalue {c.min_eig:.3f} (need "
                   f"{MIN_DIRECTION_EIG:g}): turn the board through more orientations (upside down, on its sides "
                   "and ends), not only flat")
    weak = [r["param"] for r in res.parameter_rows()
            if r["param"].split("[")[0] in ("S", "O") and r["determined_by"] in ("prior", "undetermined")]
    if weak:
        out.append(f"the data did not determine {', '.join(weak)} (left to the prior)")
    return out


def heading_error_deg(b_cal_uT: np.ndarray, b_true_uT: np.ndarray) -> np.ndarray:
    """(N,) signed angle (deg) from the true to the calibrated field's projection on the board's x-y plane:
    the heading error of a level compass."""
    a, b = np.asarray(b_cal_uT, dtype=float), np.asarray(b_true_uT, dtype=float)
    cross = b[:, 0] * a[:, 1] - b[:, 1] * a[:, 0]
    dot = a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]
    return np.degrees(np.arctan2(cross, dot))


__all__ = ["HandCalData", "HandCalOptions", "HandCalResult", "SphereCoverage", "Frame", "LevelTurn", "calibrate",
           "choose_model", "find_level_turns", "noise_floor_uT", "heading_error_deg", "AXES", "TEMPERATURE",
           "FRAMES", "MIN_CELL_FRACTION", "MIN_DIRECTION_EIG", "ENOUGH_CELL_FRACTION", "ENOUGH_DIRECTION_EIG"]
