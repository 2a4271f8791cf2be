"""``magstack simulate``: deterministic v1 session files with full metadata; measurement_sim arrays."""
from __future__ import annotations

import json

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.firmware.effects import EFFECT_NAMES
from magstack.sim.coil_programs import PROGRAMS, program
from magstack.sim.error_model import ErrorParams
from magstack.sim.measurement_sim import FVM400_NOISE_uT, simulate_measurement
from magstack.sim.presets import preset


def _run(tmp_path, name, *args):
    out = tmp_path / name
    rc = main(["simulate", *args, "--out", str(out)])
    assert rc == 0
    return out


def test_same_seed_identical_bytes_different_seed_differs(tmp_path):
    a = _run(tmp_path, "a.csv", "--chip", "lis3mdl", "--program", "full", "--seconds", "30", "--seed", "7")
    b = _run(tmp_path, "b.csv", "--chip", "lis3mdl", "--program", "full", "--seconds", "30", "--seed", "7")
    c = _run(tmp_path, "c.csv", "--chip", "lis3mdl", "--program", "full", "--seconds", "30", "--seed", "8")
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()
    assert not list(tmp_path.glob("*.part"))


def test_metadata_names_chip_preset_program_effects_seed_version(tmp_path):
    out = _run(tmp_path, "s.csv", "--chip", "hmc5983", "--program", "currents", "--seconds", "20", "--seed", "3",
               "--without", "noise,drift", "--interference", "solar=0.5,-0.2,0.1")
    s = read_session(out)
    md = s.metadata
    assert md["dut_chip"] == "hmc5983" and md["preset"] == "hmc5983"
    assert md["program"] == "currents" and md["seed"] == "3"
    assert md["effects"].split(",") == [e for e in EFFECT_NAMES if e not in ("noise", "drift")]
    assert md["software_version"]
    params = ErrorParams.from_dict(json.loads(md["error_params"]))
    np.testing.assert_allclose(params.interference_uT_per_A["solar"], [0.5, -0.2, 0.1])
    np.testing.assert_allclose(params.offset_uT, preset("hmc5983").offset_uT)
    assert set(s.currents_A) == {"solar", "torquer"}
    header = next(line for line in out.read_text().splitlines() if line.startswith("t_s,"))
    assert ",current_solar_A,current_torquer_A" in header and "_A_A" not in header
    assert len(s) == int(20 * 75) + 1
    np.testing.assert_allclose(np.diff(s.t_s), 1 / 75, atol=2e-6)


def test_sessions_column_and_reference_close_to_truth(tmp_path):
    out = _run(tmp_path, "s.csv", "--program", "steps_x", "--seconds", "120", "--sessions", "4")
    s = read_session(out)
    assert list(np.unique(s.session)) == [0, 1, 2, 3]
    truth = program("steps_x", 120.0, sessions=4).field_series_uT(s.t_s - s.t_s[0])
    resid = s.ref_uT - truth
    assert np.abs(resid).max() < 0.04  # FVM400-like noise (<= 6 nT rms) + 1 nT rounding
    codes = s.ref_uT / 0.001
    np.testing.assert_allclose(codes, np.round(codes), atol=1e-6)


def test_effects_option_only_selected_effects(tmp_path):
    out = _run(tmp_path, "s.csv", "--chip", "hmc1053", "--program", "zero_field", "--seconds", "10",
               "--effects", "offset")
    s = read_session(out)
    assert s.metadata["effects"] == "offset"
    np.testing.assert_allclose(s.dut_uT, np.broadcast_to(preset("hmc1053").offset_uT, s.dut_uT.shape), atol=1e-9)


@pytest.mark.parametrize("args,msg", [
    (["--effects", "offset,bogus"], "unknown effect 'bogus'"),
    (["--without", "nope"], "unknown effect 'nope'"),
    (["--program", "nope"], "invalid choice: 'nope'"),
    (["--seed", "-1"], "--seed"),
    (["--seconds", "-5"], "argument --seconds: must be within (0, 7776000] s, got '-5'"),
    # every option validated at parse time, the option named
    (["--t0", "inf"], "argument --t0: expected a finite number"),
    (["--t0", "nan"], "argument --t0: expected a finite number"),
    (["--t0", "-1"], "argument --t0: must be within [0, 4102444800] s"),
    (["--rate-hz", "1e-300"], "argument --rate-hz: must be within [0.001, 10000] Hz"),
    (["--sessions", "100000"], "argument --sessions: must be within [1, 1000]"),
    (["--sessions", "200", "--seconds", "60"], "fewer than 5 per session for --sessions 200"),
    (["--interference", "x=1,2,3"], "--interference: program 'steps_xyz' has no current x (its currents: none)"),
    (["--program", "currents", "--interference", "x=1,2,3"], "no current x (its currents: solar, torquer)"),
    (["--interference", "solar_A=1,2,inf"], "argument --interference: expected finite numbers"),
    (["--seed", "1.5"], "argument --seed: expected an integer"),
    (["--rate-hz", "0"], "--rate-hz"),
    (["--interference", "solar_A=1,2"], "--interference"),
])
def test_bad_options_give_clean_errors(tmp_path, capsys, args, msg):
    rc = main(["simulate", *args, "--out", str(tmp_path / "x.csv")])
    assert rc == 2
    assert msg in capsys.readouterr().err
    assert not (tmp_path / "x.csv").exists()


def test_empty_out_is_a_usage_error(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--out", ""]) == 2
    assert "argument --out: expected a file name, got an empty string" in capsys.readouterr().err
    assert main(["simulate", "--out", str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_help_lists_programs(capsys):
    assert main(["simulate", "--help"]) == 0
    text = capsys.readouterr().out
    for name in PROGRAMS:
        assert name in text


def test_measurement_sim_reference_noise_and_dut_from_model():
    p = preset("lsm303dlhc")
    truth = program("rotation", 60.0, sessions=1)
    run = simulate_measurement(p, truth, duration_s=60.0, rate_hz=10.0, seed=1, effects=["gain"])
    np.testing.assert_allclose(run.dut_uT, run.truth_uT @ p.gain_matrix.T, atol=1e-12)
    resid = run.ref_uT - run.truth_uT
    assert np.all(resid.std(axis=0) < np.array(FVM400_NOISE_uT) + 0.001)
    assert run.effects == ("gain",)
    again = simulate_measurement(p, truth, duration_s=60.0, rate_hz=10.0, seed=1, effects=["gain"])
    np.testing.assert_array_equal(again.ref_uT, run.ref_uT)


@pytest.mark.parametrize("kw, word", [
    ({"rate_hz": float("nan")}, "rate_hz"), ({"duration_s": 0.0}, "duration_s"),
    ({"ref_lsb_uT": float("nan")}, "ref_lsb_uT"), ({"ref_lsb_uT": -0.001}, "ref_lsb_uT"),
    ({"ref_noise_uT": (0.001, float("nan"), 0.001)}, "ref_noise_uT"), ({"t_start_s": float("inf")}, "t_start_s"),
])
def test_measurement_sim_refuses_bad_parameters(kw, word):
    from magstack.drivers.errors import ConfigurationError

    args = {"duration_s": 5.0, "rate_hz": 2.0, **kw}
    with pytest.raises(ConfigurationError, match=word):
        simulate_measurement(preset("hmc5983"), program("zero_field", 10.0, sessions=1), **args)
