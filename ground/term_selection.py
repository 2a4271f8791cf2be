"""Choose the optional calibration terms by held-out error, among sets the board can apply.

Each candidate term set is fitted on top of the base model; the one with the lowest held-out
(time-block) error among those the fixed-point applier carries (or that are ground-only and
skipped on board) is adopted. Used by the demo; any command that wants "the best loadable model"
calls :func:`select_terms`.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from magstack.firmware.cal_table import GROUND_ONLY_TERMS
from magstack.firmware.calibration import FitOptions, fit
from magstack.firmware.errors import FitError
from magstack.firmware.fixed_point import FIXED_POINT_TERMS

__all__ = ["CANDIDATE_TERMS", "TermSelection", "fixed_point_ok", "select_terms"]

#: Optional terms tried on top of Eq. 3 by default.
CANDIDATE_TERMS: tuple[tuple[str, ...], ...] = ((), ("time_skew",), ("time_skew", "cubic"))


def fixed_point_ok(terms: Sequence[str]) -> bool:
    """True when a table with these terms loads on board (each term applied or ground-only)."""
    return all(t in FIXED_POINT_TERMS or t in GROUND_ONLY_TERMS for t in terms)


@dataclass
class TermSelection:
    """``candidates``: one dict per term set (terms, model, fixed_point, rmse_norm_uT,
    holdout_blocks_norm_uT, held); ``best`` the adopted one; ``result`` its FitResult."""

    candidates: list[dict]
    best: dict
    result: object


def select_terms(fd, *, model: str = "eq3", candidates: Sequence[Sequence[str]] = CANDIDATE_TERMS,
                 t0_c: float = 25.0, options: FitOptions | None = None) -> TermSelection:
    """Fit every candidate term set (with held-out folds) and adopt the best loadable one.

    FitError when no fixed-point-compatible candidate could be evaluated held out.
    """
    opts = options or FitOptions()
    cands, results = [], []
    for terms in candidates:
        r = fit(fd, model, list(terms), (), t0_c, opts)
        st = r.stats()
        results.append(r)
        cands.append({"terms": list(terms), "model": r.model.name, "fixed_point": fixed_point_ok(terms),
                      "rmse_norm_uT": st["rmse_norm_uT"], "holdout_blocks_norm_uT": st["holdout_blocks_rmse_norm_uT"],
                      "held": len(st["held"])})
    usable = [i for i, c in enumerate(cands) if c["fixed_point"] and c["holdout_blocks_norm_uT"] is not None]
    if not usable:
        raise FitError("no fixed-point-compatible model could be evaluated held out")
    i = min(usable, key=lambda k: cands[k]["holdout_blocks_norm_uT"])
    return TermSelection(cands, cands[i], results[i])
