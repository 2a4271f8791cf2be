"""Paper study (ground/studies/riwanto.py) and the paper-model CLI helper (cli/refit_pso.py)."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from magstack.cli.refit_pso import add_paper_model_arguments, run_paper_model_cli
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.calibration.pso import PsoOptions
from magstack.ground.errors import GroundError
from magstack.ground.studies import riwanto


def test_truth_matches_table_ii_reference():
    # Table II "Reference" column (rows 11, 22, 33, 12, 13, 23, 21, 31, 32)
    S = riwanto.TRUTH_S_MC
    assert [S[0, 0], S[1, 1], S[2, 2], S[0, 1], S[0, 2], S[1, 2], S[1, 0], S[2, 0], S[2, 1]] == \
        [0.749, 1.122, 2.433, 0.354, 0.677, -0.209, -0.242, -0.395, -1.043]
    assert riwanto.TRUTH_OFF_NT.tolist() == [12600.0, -200.0, 1800.0]
    assert {m: riwanto.PAPER_TABLE_II[m]["fitness"] for m in range(1, 6)} == \
        {1: 199.05, 2: 470.09, 3: 185.0, 4: 179.39, 5: 200.36}
    assert riwanto.PAPER_TABLE_II[5]["offset_nT"] == [11565.0, -263.0, 157.0]


@pytest.mark.parametrize("model", [1, 2, 3, 4, 5])
def test_simulated_models_follow_section_iv(model):
    spec = riwanto.PAPER_MODELS[model]
    d = riwanto.simulate(spec, np.random.default_rng(0))
    assert d.b_meas_nT.shape == (100, 3) and len(np.unique(d.locus)) == spec.n_loci
    np.testing.assert_allclose(np.linalg.norm(d.b_true_nT, axis=1), d.b_ref_norm_nT)
    assert d.b_ref_norm_nT[0] == spec.b_nT[0] and d.b_ref_norm_nT[-1] == spec.b_nT[1]
    # forward model eq. (2a): noise inside S_mc
    np.testing.assert_allclose(d.b_meas_nT, (d.b_true_nT + riwanto.TRUTH_OFF_NT + d.noise_nT) @ riwanto.TRUTH_S_MC.T)
    assert np.std(d.noise_nT) == pytest.approx(spec.delta_nT, rel=0.15)
    for l, om in enumerate(d.omega):                 # each locus lies in a plane normal to its axis
        assert np.abs(d.b_true_nT[d.locus == l] @ om).max() < 1e-9


def test_run_paper_model_is_deterministic_and_complete():
    o = PsoOptions(k_max=100)
    a = riwanto.run_paper_model(3, 4, o).to_dict()
    b = riwanto.run_paper_model(3, 4, o).to_dict()
    for key in ("fitness", "S_mc", "offset_nT", "fitness_at_truth"):
        assert a[key] == b[key]
    assert a["least_squares"]["S_mc"] == b["least_squares"]["S_mc"]
    assert a["runtime_s"] > 0 and a["paper"]["fitness"] == 185.0
    json.dumps(a, allow_nan=False)


def test_bad_model_and_seed():
    with pytest.raises(GroundError, match="paper model"):
        riwanto.run_paper_model(6, 0)
    with pytest.raises(GroundError, match="seed"):
        riwanto.run_paper_model(1, -1)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="magstack refit")
    p.add_argument("--method", default="attitude", choices=("attitude", "scalar", "pso"))
    add_paper_model_arguments(p)
    return p


def test_cli_helper_writes_json(tmp_path, capsys):
    out = tmp_path / "m1.json"
    args = _parser().parse_args(["--method", "pso", "--paper-model", "1", "--seed", "2", "--json", str(out),
                                 "--iterations", "80"])
    assert run_paper_model_cli(args) == 0
    doc = json.loads(out.read_text())
    assert {"fitness", "S_mc", "offset_nT", "runtime_s"} <= set(doc)
    assert np.array(doc["S_mc"]).shape == (3, 3) and len(doc["offset_nT"]) == 3
    assert doc["model"] == 1 and doc["seed"] == 2
    assert "paper model 1 seed 2: PSO fitness" in capsys.readouterr().out
    assert [p.name for p in tmp_path.iterdir()] == ["m1.json"]      # no temp file left


def test_cli_helper_usage_errors(tmp_path):
    p = _parser()
    with pytest.raises(SystemExit) as exc:
        p.parse_args(["--paper-model", "9"])
    assert exc.value.code == 2
    with pytest.raises(ConfigurationError, match="--method pso"):
        run_paper_model_cli(p.parse_args(["--paper-model", "1"]))
    with pytest.raises(ConfigurationError, match="does not exist"):
        run_paper_model_cli(p.parse_args(["--method", "pso", "--paper-model", "1", "--json",
                                          str(tmp_path / "no" / "x.json")]))
    with pytest.raises(ConfigurationError, match="seed"):
        run_paper_model_cli(p.parse_args(["--method", "pso", "--paper-model", "1", "--seed", "-3"]))


def test_general_geometry_loci_are_cones_about_their_axes():
    d = riwanto.simulate_general(np.random.default_rng(4))
    assert d.b_meas_nT.shape == (100, 3) and len(d.omega) in (2, 3)
    for l, om in enumerate(d.omega):
        along = d.b_true_nT[d.locus == l] @ om           # constant along the axis: a circle on a cone
        assert np.ptp(along) < 1e-6 * 35000
        assert 0.0 <= along[0] <= np.cos(np.deg2rad(40.0)) * 35000 + 1e-6
    np.testing.assert_allclose(d.b_meas_nT, (d.b_true_nT + riwanto.TRUTH_OFF_NT + d.noise_nT) @ riwanto.TRUTH_S_MC.T)
