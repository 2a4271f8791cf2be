"""Parse ``--model`` (which effects the simulator models, parameters fitted to the session).

``eq3`` / ``gain_offset`` (the calibration's named models) or effect names joined by ``+`` (e.g.
``gain+offset+time_skew``, ``eq3+session_offset``). An effect stands for its catalogue ``cal_term``;
effects sharing a term are modelled together (gain and misalignment), except hysteresis, which has
its own estimator and is modelled only when named, and mount_rotation, whose per-session angles couple
the axes: when named, every fit of the search solves them jointly with the base (rotation.py).
"""
from __future__ import annotations

import numpy as np

from magstack.drivers.errors import ConfigurationError
from magstack.firmware.calibration.model import JOINT_TERMS, MODELS
from magstack.firmware.effects import EFFECT_NAMES, EFFECTS
from magstack.ground.diagnose import nonlinear as nl
from magstack.ground.diagnose.gap import Block

#: Effects estimated by their own (non-linear) estimator: modelled only when named.
OWN_ESTIMATOR = ("hysteresis",)
#: Effects whose parameters couple the output axes, modelled (when named) by solving the base columns
#: and the effect's parameters as one stacked problem (search.oof_residual, rotation.py).
JOINT_ESTIMATOR = ("mount_rotation",)


def parse_model(spec: str) -> tuple[tuple[str, ...], tuple[str, ...], bool]:
    """(calibration terms, modelled effect names, hysteresis modelled) of a ``--model`` string."""
    tokens = [t.strip() for t in str(spec).split("+") if t.strip()]
    if not tokens:
        raise ConfigurationError("--model is empty")
    terms: list[str] = []
    named: list[str] = []
    for tok in tokens:
        if tok in MODELS:
            terms += list(MODELS[tok])
        elif tok in EFFECT_NAMES:
            e = EFFECTS[tok]
            if tok in JOINT_ESTIMATOR:
                named.append(tok)   # fitted jointly with the base by the search (rotation.py), no base term
                continue
            if e.cal_term is None:
                raise ConfigurationError(f"--model: effect {tok!r} has no calibration term (cannot be modelled)")
            if e.cal_term in JOINT_TERMS:
                raise ConfigurationError(f"--model: effect {tok!r} is fitted by its own joint solver; diagnose "
                                         "cannot model it yet")
            named.append(tok)
            if tok not in OWN_ESTIMATOR:
                terms.append(e.cal_term)
        else:
            raise ConfigurationError(f"--model: unknown model or effect {tok!r}; valid: {', '.join(MODELS)} or "
                                     f"effects {', '.join(n for n in EFFECT_NAMES if EFFECTS[n].cal_term)} "
                                     "joined by '+'")
    terms = list(dict.fromkeys(terms))
    modelled = [n for n in EFFECT_NAMES if n in named or (EFFECTS[n].cal_term in terms and n not in OWN_ESTIMATOR)]
    return tuple(terms), tuple(modelled), "hysteresis" in named


def hysteresis_base(dut_uT: np.ndarray):
    """Base columns for a model that names hysteresis: state columns at the highest candidate level."""
    cands = nl.hysteresis_thresholds(dut_uT)
    thr = np.array([c[-1] if c else np.inf for c in cands])

    def build(_predictor_uT):
        st = nl.hysteresis_state(dut_uT, thr)
        keep = np.isfinite(thr)
        mask = np.eye(3, dtype=bool)[:, keep]
        names = [[f"H[{a}]" for a in "xyz" if True] for _ in range(3)]
        names = [[n for n, k in zip(r, keep, strict=True) if k] for r in names]
        return Block(st[:, keep], mask, names, ["uT"] * int(keep.sum()))
    return build


def modelled_by_terms(terms) -> tuple[str, ...]:
    """Effects whose calibration term is among ``terms`` (hysteresis only through its own estimator)."""
    return tuple(n for n in EFFECT_NAMES if EFFECTS[n].cal_term in set(terms) and n not in OWN_ESTIMATOR)


def table_gap(s, table, description: str):
    """Mode (b) gap from a calibration table: ``ref - table(dut)`` (ground/apply_session.py)."""
    from magstack.ground.apply_session import calibrate_session
    from magstack.ground.diagnose.gap import fixed_gap

    cal = calibrate_session(table, s, extrapolate=True)   # the table's prediction on every row
    # candidate columns from the reference (the calibrated reading carries the DUT noise that is in the gap)
    g = fixed_gap(s, s.ref_uT - cal.dut_uT, s.ref_uT, modelled_by_terms(table.terms), description, (),
                  float(table.t0_c))
    g.deskew_J = np.asarray(table.S, dtype=float)
    return g
