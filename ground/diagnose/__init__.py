"""Sim-to-real gap diagnosis: where the gap lies, which unmodelled catalogue effect causes
it, how far it shrinks (docs/diagnosis.md).

The core (every module here except ``validate`` and ``sim_adapter``) never imports the simulator's
error model (import-linter contract in pyproject.toml).
"""
from magstack.ground.diagnose.core import Diagnosis, diagnose
from magstack.ground.diagnose.gap import Gap, check_rows, fixed_gap, kept_rows, model_gap
from magstack.ground.diagnose.search import Options
from magstack.ground.diagnose.spec import parse_model

__all__ = ["Diagnosis", "diagnose", "Gap", "check_rows", "fixed_gap", "model_gap", "Options", "parse_model",
           "diagnose_model", "diagnose_orbit", "shift_source", "attach_rows", "kept_rows"]


def shift_source(full, keep):
    """Gap.shift_source: the reference field of every usable row (and the DUT excursion history that
    :func:`check_rows` recorded, for hysteresis)."""
    from magstack.ground.diagnose.nonlinear import runs
    return (full.t_s, full.ref_uT, keep, runs(full.t_s, full.session), getattr(full, "dut_history", None))


def attach_rows(gap, full, keep, notes=()):
    """Give ``gap`` what :func:`check_rows` recorded: the shift source, its notes and the reference guard."""
    gap.shift_source = shift_source(full, keep)
    gap.notes += list(notes)
    gap.reference = getattr(full, "reference_guard", None)
    return gap


def diagnose_model(session, model: str = "gain_offset", options: Options | None = None,
                   t0_c: float = 25.0, notes=()) -> Diagnosis:
    """Mode (a) in one call: ``model`` as ``--model``; parameters fitted to ``session``."""
    from magstack.ground.diagnose.spec import hysteresis_base
    options = options or Options()
    terms, modelled, hyst = parse_model(model)
    full, keep, more = check_rows(session, exclude_bends=options.exclude_bends,
                                  include_saturated=options.include_saturated)
    notes = list(notes) + more
    s = kept_rows(full, keep)
    extra = hysteresis_base(s.dut_uT) if hyst else None
    g = model_gap(s, terms, modelled, f"--model {model}", t0_c, extra)
    return diagnose(attach_rows(g, full, keep, notes), options)


def diagnose_orbit(paths, model: str = "gain_offset", options: Options | None = None, t0_c: float = 25.0,
                   reference: str = "igrf", dut1_s: float = 0.0) -> Diagnosis:
    """Mode (a) on orbit telemetry (refit's input, docs/refit.md): the reference is IGRF at the GPS position
    rotated by the attitude (``reference`` "session": the files' ref columns; "auto": those when they hold
    values; orbit.session_from_blocks), currents interpolated as ``refit``
    does; the reference's error budget joins the noise floor (orbit.py)."""
    from magstack.ground.diagnose.orbit import orbit_session, without_missing_currents

    s, notes = without_missing_currents(orbit_session(paths, dut1_s, reference))
    return diagnose_model(s, model, options, t0_c, notes)
