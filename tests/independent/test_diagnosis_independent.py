"""``magstack diagnose`` on sessions from an independent generator (generator.py: pure numpy, its own
physics, stimulus and CSV writer; nothing from magstack.sim). The diagnosis is judged on
sessions from generators that are not ours; here the truth is known.

For every catalogue effect the generator can switch on: a session with that effect at a realistic
strength on top of gain matrix + offset + noise; the effect is withheld from ``--model``
(``gain_offset``; ``offset`` for gain and misalignment). Pass: the verdict is the effect (or, when the
diagnosis says it cannot tell the verdict from its runner-up, the runner-up is the effect), and the
held-out gap after adding it is within 1.3x the diagnosis' own noise floor. Clean sessions must give
``none``. Results: docs/diagnosis-independent.md.
"""
from __future__ import annotations

import importlib

import pytest

try:
    importlib.import_module("magstack.cli.commands.diagnose")
except ModuleNotFoundError as exc:   # only "the command does not exist" skips; any other import error fails
    if exc.name != "magstack.cli.commands.diagnose":
        raise
    pytest.skip("magstack diagnose does not exist in this checkout: magstack.cli.commands.diagnose "
                "is not importable (docs/diagnosis-independent.md)",
                allow_module_level=True)

from generator import EFFECTS as GENERATOR_EFFECTS  # noqa: E402
from harness import AFTER_OVER_NOISE_MAX, case, fit_table  # noqa: E402

from magstack.firmware.effects import EFFECT_NAMES  # noqa: E402

#: The effects the catalogue of the code under test names and this generator can produce (an effect
#: added to the catalogue, e.g. mount_rotation, is tested as soon as the catalogue has it).
EFFECTS = tuple(e for e in GENERATOR_EFFECTS if e in EFFECT_NAMES)

#: Below this fraction of the noise floor (norm of per-axis RMS, 3 x 400 s at ~48 nT) an effect is
#: at the detection limit of the session: ``none`` is accepted (measured hits go down to ~0.25).
IDENTIFIABLE_EXCESS = 0.5
#: One seed per effect. The default run covers the two non-linear estimators (delay search, hysteresis
#: state), a temperature, a current and a per-power-cycle effect; the rest are slow (each diagnosis of a
#: 3 x 400 s session takes 3-10 s on the shared 2-core machine).
FAST_SEED = 1
FAST_EFFECTS = ("time_skew", "hysteresis", "temperature_gain", "interference", "session_offset")
SLOW_EFFECTS = tuple(e for e in EFFECTS if e not in FAST_EFFECTS)
#: Clean seeds in the default run; the false-alarm rate over more seeds is the slow test.
FAST_CLEAN_SEEDS = (100,)


def _explain(o) -> str:
    d = o.doc
    rank = ", ".join(f"{r['effect']} {r['rmse_nT']:.1f}{'*' if r['significant'] else ''}" for r in d["ranking"])
    how = o.model if o.model.startswith("--") else f"--model {o.model}"
    return (f"true {o.effect} (seed {o.seed}, x{o.strength:g}, {how}, oracle excess {o.excess_nT:.1f} nT): "
            f"verdict {o.verdict}, "
            f"runner-up {d.get('runner_up')}, distinguishable {d.get('distinguishable')}; baseline "
            f"{d['baseline_rmse_nT']:.1f} nT, after {d['after_rmse_nT']:.1f} nT, "
            f"noise floor {d['noise_floor_nT']:.1f} nT; "
            f"ranking (held-out nT, * significant): {rank}")


#: Cases of this harness that the diagnosis does not yet meet (none at present; docs/diagnosis-independent.md).
#: Each is a known limit under work, run and reported as xfail (not strict: a fix shows as XPASS); remove the
#: entry when it is fixed. Keyed by (test name, effect); effect None = any parameter.
KNOWN_LIMITS: dict = {
}


@pytest.fixture(autouse=True)
def _known_limit(request):
    name = request.node.originalname
    effect = request.node.callspec.params.get("effect") if hasattr(request.node, "callspec") else None
    reason = KNOWN_LIMITS.get((name, effect)) or KNOWN_LIMITS.get((name, None))
    if reason:
        request.node.add_marker(pytest.mark.xfail(reason=f"known limit: {reason}", strict=False))


def _check_effect(o):
    """Found (or the indistinguishable runner-up) and closed to 1.3x the noise floor. An effect whose
    oracle size (harness.excess_nT) is below IDENTIFIABLE_EXCESS x the noise floor need not be found,
    but then the verdict must be ``none``: a wrong effect is never acceptable."""
    if o.excess_nT < IDENTIFIABLE_EXCESS * o.doc["noise_floor_nT"] and o.verdict == "none":
        return
    assert o.outcome in ("hit", "runner_up"), _explain(o)
    assert o.after_over_noise <= AFTER_OVER_NOISE_MAX, _explain(o)


@pytest.mark.parametrize("effect", [*FAST_EFFECTS, *(pytest.param(e, marks=pytest.mark.slow) for e in SLOW_EFFECTS)])
def test_withheld_effect_is_named(tmp_path, effect):
    o = case(tmp_path, effect, FAST_SEED)
    tested = {r["effect"] for r in o.doc["ranking"]}
    assert effect in tested, (f"{effect} was not tried although the session has temperature, currents and "
                              f"3 power cycles: not_testable = {o.doc['not_testable']}")
    _check_effect(o)


@pytest.mark.parametrize("seed", FAST_CLEAN_SEEDS)
def test_clean_session_gives_none(tmp_path, seed):
    o = case(tmp_path, None, seed)
    assert o.verdict == "none", _explain(o)
    assert {"noise", "quantization", "saturation"} <= {n["effect"] for n in o.doc["not_testable"]}


@pytest.mark.slow
@pytest.mark.parametrize("effect", EFFECTS)
def test_withheld_effect_is_named_on_other_seeds(tmp_path, effect):
    for seed in (2, 3):
        _check_effect(case(tmp_path, effect, seed))


@pytest.mark.slow
@pytest.mark.parametrize("effect", ["time_skew", "interference", "temperature_offset", "session_offset"])
def test_withheld_effect_is_named_at_half_strength(tmp_path, effect):
    """Half the realistic size: effects that stay well above the noise at half strength."""
    _check_effect(case(tmp_path, effect, FAST_SEED, 0.5))


@pytest.mark.slow
def test_false_alarm_rate_on_clean_sessions(tmp_path):
    outs = [case(tmp_path, None, 100 + k) for k in range(10)]
    alarms = [o for o in outs if o.verdict != "none"]
    assert len(alarms) <= 1, "false alarms > 10 %:\n" + "\n".join(_explain(o) for o in alarms)


@pytest.mark.slow
def test_nonlinearity_with_excursions_at_random_times(tmp_path):
    """Control for the even bench program: the same unit and effect with excursions at random times,
    so an axis' two excursions rarely share a held-out fold (the folds are stratified by field magnitude:
    docs/diagnosis.md, "Which effect")."""
    _check_effect(case(tmp_path, "nonlinearity", 3, excursion_times="random"))


@pytest.mark.slow
def test_hysteresis_when_the_reference_saturates_in_the_excursions(tmp_path):
    """Belsten 2.3.4: the +-150 uT run saturated the reference. Rows beyond a 100 uT reference range are
    logged with empty reference cells and flag 1, but the DUT reading that sets the remanence state is
    in the file; the rows with a reference still carry the state change (oracle excess > 60 nT)."""
    _check_effect(case(tmp_path, "hysteresis", 3, ref_range_uT=100.0))


# ---- mode (b): "last month's model against today's unit" (--table fitted on an earlier clean session)
DEVICE = 7


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    return fit_table(tmp_path_factory.mktemp("table"), seed=201, device_seed=DEVICE)


def test_table_mode_names_the_changed_effect(tmp_path, table):
    o = case(tmp_path, "temperature_offset", 202, table=table, device_seed=DEVICE)
    _check_effect(o)


@pytest.mark.slow
@pytest.mark.parametrize("effect", [None, "interference", "hysteresis", "session_offset", "time_skew"])
def test_table_mode_other_effects(tmp_path, table, effect):
    o = case(tmp_path, effect, 202, table=table, device_seed=DEVICE)
    if effect is None:
        assert o.verdict == "none", _explain(o)
    else:
        _check_effect(o)
