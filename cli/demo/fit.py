"""Demo step 4: fit the calibration on the paired session.

Term selection (:func:`magstack.ground.term_selection.select_terms`) and the fit-vs-simulator
check (:func:`magstack.ground.preset_recovery.recovery_vs_preset`) are library functions; this
step adds what only the demo shows: the same fit on the thermally flattest slice of the session,
to show what is held (or refused) when the data cannot determine a parameter.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from magstack.cli.demo.config import Say
from magstack.data.session import read_session
from magstack.firmware.calibration import FitData, FitOptions, fit
from magstack.firmware.errors import FitError
from magstack.ground.preset_recovery import recovery_vs_preset
from magstack.ground.term_selection import CANDIDATE_TERMS, select_terms


@dataclass
class FitFigures:
    model: str
    terms: list[str]
    candidates: list[dict]
    recovery: dict[str, float]       # fitted vs the simulator's preset (see recovery_vs_preset)
    n_used: int
    n_excluded: int
    raw_rmse_uT: list[float]
    raw_rmse_norm_uT: float
    rmse_uT: list[float]
    rmse_norm_uT: float
    holdout_blocks_norm_uT: float | None
    noise_floor_norm_uT: float
    held: list[dict]
    temp_span_with_field_c: list[float]
    slice_window_s: tuple[float, float]
    slice_temp_span_c: float
    slice_held: list[dict]
    slice_refused: str
    report_path: Path
    result: Any = field(repr=False, default=None)


def flattest_window(temp_c: np.ndarray, fraction: float = 0.1, min_rows: int = 300) -> tuple[np.ndarray, float]:
    """Rows of the contiguous window (``fraction`` of the rows, at least ``min_rows``) with the
    smallest temperature span (mask), and that span (degC)."""
    n = len(temp_c)
    w = max(min_rows, int(fraction * n))
    if n <= w:
        return np.ones(n, bool), float(np.nanmax(temp_c) - np.nanmin(temp_c))
    win = sliding_window_view(np.nan_to_num(temp_c, nan=np.nanmean(temp_c)), w)
    span = win.max(axis=1) - win.min(axis=1)
    k = int(np.argmin(span))
    m = np.zeros(n, bool)
    m[k:k + w] = True
    return m, float(span[k])


def _held(result) -> list[dict]:
    return [{"param": h.name, "value": h.value, "reason": h.reason} for h in result.held]


def fit_calibration(paired_path: Path, report_path: Path, *, exclude_steps_uT: float,
                    say: Say = print) -> FitFigures:
    """Fit Eq. 3 (+ the optional terms that help held out) to the paired session."""
    paired = read_session(paired_path)
    fit_data = FitData.from_session(paired)
    chip = paired.metadata.get("dut_chip")
    opts = FitOptions(exclude_ref_steps_uT=exclude_steps_uT, chip=chip)
    sel = select_terms(fit_data, candidates=CANDIDATE_TERMS, t0_c=25.0, options=opts)
    res, best, cands = sel.result, sel.best, sel.candidates
    stats = res.stats()
    for c in cands:
        mark = "<- adopted" if c is best else ("" if c["fixed_point"] else "(float-only: not loadable on board)")
        say(f"  {c['model']:<22} in-sample {c['rmse_norm_uT'] * 1e3:7.1f} nT   held-out time blocks "
            f"{(c['holdout_blocks_norm_uT'] or math.nan) * 1e3:7.1f} nT  {mark}".rstrip())
    coverage = res.coverage
    spans = [float(coverage.temp_span_with_field(j)) for j in range(3)]
    say(f"  rows used {res.n_used}, excluded {res.n_excluded} (coil transitions > {exclude_steps_uT:g} uT "
        f"between rows, gaps); temperature span with field present per axis "
        f"{', '.join(f'{s:.1f}' for s in spans)} degC (need {opts.min_temp_span_c:g})")
    held = _held(res)
    if held:
        say(f"  identifiability: {len(held)} parameters determined by the {chip or 'generic'} prior: "
            + "; ".join(f"{h['param']} ({h['reason']})" for h in held[:4]) + (" ..." if len(held) > 4 else ""))
    else:
        say(f"  identifiability: all {int(res.model.axis_mask().sum())} parameters of {res.model.name} determined "
            "(none held)")
    rec = recovery_vs_preset(res)
    say(f"  vs the simulated sensor (preset hmc1053, first order in dT): max |S - G^-1| {rec['S_max_abs']:.2g}, "
        f"max |K_S - (-G^-1 k_s)| {rec['K_S_max_abs_per_c']:.2g} /degC, max |O - (-G^-1 o)| "
        f"{rec['O_max_abs_uT'] * 1e3:.1f} nT")
    # the same fit on the thermally flattest slice: what the report does when the data cannot
    # determine the temperature terms
    mask, span = flattest_window(fit_data.temp_c)
    flat = fit_data.select(mask)
    t0 = float(np.nanmin(paired.t_s))
    window = (float(flat.t_s.min() - t0), float(flat.t_s.max() - t0))
    flat_opts = FitOptions(exclude_ref_steps_uT=exclude_steps_uT, holdout=False, chip=chip)
    try:
        slice_held = _held(fit(flat, "eq3", list(best["terms"]), (), 25.0, flat_opts))
    except FitError as exc:  # too few rows in a short session: the report says so
        slice_held = [{"param": "(all)", "value": math.nan, "reason": str(exc)}]
    try:
        fit(flat, "eq3", list(best["terms"]), (), 25.0, FitOptions(exclude_ref_steps_uT=exclude_steps_uT,
                                                                   holdout=False, on_unidentifiable="refuse",
                                                                   chip=chip))
        refused = ""
    except FitError as exc:
        refused = str(exc)
    names = sorted({h["param"].split("[")[0] for h in slice_held})
    say(f"  same fit on the thermally flattest {len(flat)} rows (t {window[0]:.0f}..{window[1]:.0f} s, "
        f"T span {span:.2f} degC): {len(slice_held)} parameters from the prior ({', '.join(names) or 'none'})"
        + (f"; with --refuse-unidentifiable: FitError ({len(refused)} chars naming them)" if refused else
           "; nothing to refuse"))
    Path(report_path).write_text(res.report() + "\n\nCandidates (held-out by time blocks, uT):\n"
                                 + "\n".join(json.dumps(c) for c in cands) + "\n\nFlat-slice refusal:\n"
                                 + (refused or "none") + "\n", encoding="utf-8")
    return FitFigures(res.model.name, list(best["terms"]), cands, rec, res.n_used, res.n_excluded,
                      [float(x) for x in res.raw_rmse_uT], stats["raw_rmse_norm_uT"], [float(x) for x in res.rmse_uT],
                      stats["rmse_norm_uT"], stats["holdout_blocks_rmse_norm_uT"], stats["noise_floor_norm_uT"], held,
                      spans,
                      window, span, slice_held, refused, Path(report_path), res)
