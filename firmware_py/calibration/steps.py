"""Reference steps: rows next to a field transition, and the residual split the fit reports.

Two independently clocked streams cannot be paired sample-exactly across a coil step, so rows next to a
reference change carry pairing error; ``fit`` can exclude them (``--exclude-steps``) or, by default,
reports the residual split (:func:`diagnose_steps`); ``apply`` scores with and without them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class StepDiagnosis:
    """In-sample residual split between rows at reference steps and the rest (plain RMS, uT).

    ``threshold_uT``: a row is "at a step" when the reference changes by more than this between it
    and a neighbouring row of its session (:func:`reference_steps`)."""

    threshold_uT: float
    n_step: int
    n_steady: int
    step_rms_uT: np.ndarray     # (3,)
    steady_rms_uT: np.ndarray   # (3,)
    step_share: float           # fraction of the total squared residual on step rows

    @property
    def dominant(self) -> bool:
        """Step rows carry a disproportionate share of the misfit (worth excluding or modelling)."""
        ratio = np.linalg.norm(self.step_rms_uT) / max(float(np.linalg.norm(self.steady_rms_uT)), 1e-300)
        return ratio >= STEP_RATIO and self.step_share >= STEP_SHARE


#: The step diagnosis reports step rows as dominant when their residual RMS is at least STEP_RATIO
#: times that of the other rows and they carry at least STEP_SHARE of the squared residual.
STEP_RATIO = 2.0
STEP_SHARE = 0.5
#: Automatic step threshold: this many times the median non-zero row-to-row reference change
#: (the reference's own sample-to-sample noise while the field is steady).
STEP_NOISE_FACTOR = 10.0


def step_threshold_uT(b_ref_uT: np.ndarray, session: np.ndarray) -> float:
    """Reference change between consecutive rows (uT, max over axes) that counts as a step:
    STEP_NOISE_FACTOR x the median non-zero change within sessions; NaN if there is none."""
    d = np.abs(np.diff(b_ref_uT, axis=0)).max(axis=1)
    d = d[(session[1:] == session[:-1]) & np.isfinite(d) & (d > 0)]
    return float(STEP_NOISE_FACTOR * np.median(d)) if d.size else math.nan


def diagnose_steps(resid_uT: np.ndarray, b_ref_uT: np.ndarray, session: np.ndarray,
                   threshold_uT: float | None = None) -> StepDiagnosis | None:
    """Split the residual between rows at reference steps and the rest; None when the data has
    no steps (fewer than 10 step or 10 other rows, or no usable threshold)."""
    thr = step_threshold_uT(b_ref_uT, session) if threshold_uT is None else float(threshold_uT)
    if not (math.isfinite(thr) and thr > 0):
        return None
    at = reference_steps(b_ref_uT, session, thr)
    if at.sum() < 10 or (~at).sum() < 10:
        return None
    sq = resid_uT ** 2
    total = float(sq.sum())
    return StepDiagnosis(thr, int(at.sum()), int((~at).sum()), np.sqrt(sq[at].mean(axis=0)),
                         np.sqrt(sq[~at].mean(axis=0)), float(sq[at].sum()) / total if total > 0 else 0.0)


def reference_steps(b_ref_uT: np.ndarray, session: np.ndarray, step_uT: float) -> np.ndarray:
    """Rows on either side of a reference change above ``step_uT`` (any axis) between
    consecutive rows of one session: field transitions, where interpolating two
    asynchronous streams is least trustworthy (the authors' step 4)."""
    d = np.abs(np.diff(b_ref_uT, axis=0))
    big = np.any(d > step_uT, axis=1) & (session[1:] == session[:-1])   # NaN compares False
    out = np.zeros(len(session), dtype=bool)
    out[1:] |= big
    out[:-1] |= big
    return out
