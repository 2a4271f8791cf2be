"""Identifiability: which parameters the data can determine (held at their prior otherwise).

Rules in order (docs/calibration.md): coverage (temperature span with field present, independent field
per input axis, sessions), numerical rank, then degenerate groups by variance inflation
(:mod:`magstack.firmware.calibration.degeneracy`). ``identify`` works on the R factor of the weighted
design, so the batch and the streaming fit share it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magstack.firmware.calibration.degeneracy import degenerate_groups
from magstack.firmware.calibration.linalg import RANK_RTOL
from magstack.firmware.calibration.model import AXES, CalModel
from magstack.firmware.errors import FitError


@dataclass
class HeldParam:
    """A parameter left to the prior: ``value`` (its estimate), ``reason`` (why), ``rule``: which analysis
    named it ("temperature", "field", "sessions", "rank", "degenerate", or "" for the posterior's own
    sd ratio / a user-held value)."""

    axis: int
    column: int
    name: str
    value: float
    reason: str
    rule: str = ""


def independent_field_rms(model: CalModel, R: np.ndarray, cov, min_rms_uT: float = 0.0) -> np.ndarray:
    """(3,) uT: how much the data excites each input axis on its own.

    Axes are taken in order of decreasing field RMS (about the offset); each gets the RMS of its
    component not explained (least squares) by a constant and the axes accepted before it, and is
    accepted when that is at least ``min_rms_uT``. A single-axis sweep thus determines its own axis
    even though the DUT's cross-axis coupling makes the other channels scaled copies of it: only
    those copies are reported as not excited on their own.

    The same is taken of the reference field (``R`` of ``[X | Y]``: its last three columns) and each axis gets
    the smaller of the two: a gain needs the true field to vary along its axis, not only the DUT's reading (a
    one-field thermal run moves the DUT's reading by its tempco while the reference stays put; the gain is
    then the offset's partner, not something the data can tell)."""
    cols = {c.index: k for k, c in enumerate(model.columns) if c.term == "gain_matrix"}
    off = [k for k, c in enumerate(model.columns) if c.term == "offset"]
    n = max(cov.sum_w, 1e-300)
    p = model.n_columns

    def excitation(col_of) -> np.ndarray:
        def orth_rms(j: int, others: list[int]) -> float:
            A = R[:, [col_of[k] for k in others] + off]
            v = R[:, col_of[j]]
            if A.shape[1] == 0:
                return float(np.linalg.norm(v) / np.sqrt(n))
            coef, *_ = np.linalg.lstsq(A, v, rcond=None)
            return float(np.linalg.norm(v - A @ coef) / np.sqrt(n))

        own = [orth_rms(j, []) for j in range(3)]
        out = np.zeros(3)
        accepted: list[int] = []
        for j in sorted(range(3), key=lambda k: -own[k]):
            out[j] = orth_rms(j, accepted)
            if out[j] >= min_rms_uT:
                accepted.append(j)
        return out

    dut = excitation(cols)
    if R.shape[1] < p + 3:
        return dut
    return np.minimum(dut, excitation({j: p + j for j in range(3)}))


def identify(model: CalModel, R: np.ndarray, cov, options) -> list[HeldParam]:
    """Parameters the data cannot determine. ``R``: R factor of the weighted [X | Y].

    Coverage rules (temperature terms, sessions) first, then numerical rank: columns
    are accepted in order (gain and offset first, nuisance terms last) and a column
    whose component orthogonal to the accepted ones is below RANK_RTOL of its norm is held.
    """
    p = model.n_columns
    mask = model.axis_mask()
    prior = model.prior()
    names = {model.param_name(i, c): (i, c) for i in range(3) for c in range(p) if mask[i, c]}
    for k, v in options.priors.items():
        if k not in names:
            raise FitError(f"prior for unknown parameter {k!r}")
        prior[names[k]] = float(v)
    held: dict[tuple[int, int], str] = {}
    rules: dict[tuple[int, int], str] = {}
    orth = independent_field_rms(model, R, cov, options.min_field_rms_uT)
    for c, col in enumerate(model.columns):
        reason = None
        rule = "temperature"
        if col.term in ("temperature_gain", "temperature_gain2"):
            span = cov.temp_span_with_field(col.index)
            if span < options.min_temp_span_c:
                reason = (f"temperature spans only {span:.2f} degC while |B_{AXES[col.index]}| >= "
                          f"{options.field_present_uT:g} uT (need {options.min_temp_span_c:g} degC)")
                if span < GATE_TEMP_SPAN_C:
                    rule = "temperature-no-field"
        elif col.term == "temperature_offset":
            if cov.temp_span_c < options.min_temp_span_c:
                reason = (f"temperature spans only {cov.temp_span_c:.2f} degC "
                          f"(need {options.min_temp_span_c:g} degC)")
        elif col.term in ("gain_matrix", "cubic") and orth[col.index] < options.min_field_rms_uT:
            rule = "field"
            reason = (f"field on {AXES[col.index]} not explained by the more excited axes has RMS "
                      f"{orth[col.index]:.3g} uT (need {options.min_field_rms_uT:g} uT)")
        elif col.term == "cross_products":
            jj, kk = ((0, 1), (0, 2), (1, 2))[col.index]
            if min(orth[jj], orth[kk]) < options.min_field_rms_uT:
                rule = "field"
                reason = (f"{col.feature}: both axes need independent field RMS >= "
                          f"{options.min_field_rms_uT:g} uT")
        elif col.term == "session_offset" and len(cov.sessions) < options.min_sessions:
            rule = "sessions"
            reason = f"only {len(cov.sessions)} session(s)"
        if reason:
            for i in range(3):
                if mask[i, c]:
                    held[(i, c)] = reason
                    rules[(i, c)] = rule
    norms = np.linalg.norm(R[:, :p], axis=0)
    priority = {"gain_matrix": 0, "offset": 1}
    order = sorted(range(p), key=lambda c: (priority.get(model.columns[c].term, 2), c))
    for i in range(3):
        accepted: list[int] = []
        for c in order:
            if not mask[i, c] or (i, c) in held:
                continue
            if norms[c] == 0:
                held[(i, c)] = "column is zero in the data (never excited)"
                continue
            if accepted:
                A = R[:, accepted] / norms[accepted]
                v = R[:, c] / norms[c]
                coef, *_ = np.linalg.lstsq(A, v, rcond=None)
                resid = np.linalg.norm(v - A @ coef)
            else:
                resid = 1.0
            if resid < RANK_RTOL * 1e3 * np.sqrt(p):
                others = ", ".join(model.columns[a].feature for a in accepted)
                held[(i, c)] = f"column {model.columns[c].feature} is a combination of [{others}]"
            else:
                accepted.append(c)
    _hold_degenerate(model, R, held, options)
    out = [HeldParam(i, c, model.param_name(i, c), float(prior[i, c]), r,
                     rules.get((i, c), "degenerate" if r.startswith("degenerate") else "rank"))
           for (i, c), r in sorted(held.items())]
    if out and options.on_unidentifiable == "refuse":
        raise FitError("data cannot determine: " + "; ".join(f"{h.name} ({h.reason})" for h in out))
    return out


#: A sensitivity tempco column whose input axis saw less temperature span than this (degC) with field
#: present is informed only by near-zero fields, i.e. the DUT's noise times temperature (errors in
#: variables): the estimator takes it from the prior alone (fit.gate_solve).
GATE_TEMP_SPAN_C = 0.5
#: Rules whose parameters the estimator takes from the prior alone.
GATE_RULES = ("field", "temperature-no-field")

#: Terms never held by the degeneracy rule (the core of every model; rank rules cover them).
CORE_TERMS = ("gain_matrix", "offset")


def degenerate_sets(model: CalModel, R: np.ndarray, options, exclude=()) -> list[tuple[int, object, list[int]]]:
    """``(axis, Degeneracy, active columns)`` of every degenerate group (module degeneracy), per output axis,
    among the columns not in ``exclude`` ((axis, column) pairs) and not the offset."""
    p = model.n_columns
    mask = model.axis_mask()
    off = [c for c, col in enumerate(model.columns) if col.term == "offset"]
    out = []
    for i in range(3):
        act = [c for c in range(p) if mask[i, c] and (i, c) not in exclude and c not in off]
        if not act:
            continue
        o = R[:, off[0]] if off and (i, off[0]) not in exclude else None
        for g in degenerate_groups(R[:, act], [model.columns[c].term not in CORE_TERMS for c in act], o,
                                   options.max_vif, options.group_corr):
            out.append((i, g, act))
    return out


def _hold_degenerate(model: CalModel, R: np.ndarray, held: dict, options) -> None:
    """Add the degenerate groups of each output axis to ``held`` (module degeneracy)."""
    for i, g, act in degenerate_sets(model, R, options, exclude=set(held)):
        names = [model.param_name(i, act[a]) for a in g.members]
        partner = "" if g.partner is None else (
            f" its estimate correlates at {g.corr:+.4f} with {model.param_name(i, act[g.partner])};")
        for a in g.members:
            others = [n for n in names if n != model.param_name(i, act[a])]
            held[(i, act[a])] = (
                f"degenerate: variance inflation {g.vif:.3g} >= {options.max_vif:g} for "
                f"{model.param_name(i, act[g.worst])};{partner} the data determine only a combination"
                + (f" (with {', '.join(others)})" if others else "")
                + " -- e.g. temperature varied at one field level only; needs two or more")
