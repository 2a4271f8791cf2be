"""On-orbit refit: simulated orbit telemetry (known truth) -> candidate table; CLI; Dask engine."""
from __future__ import annotations

import json

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.data.telemetry import iter_telemetry
from magstack.firmware.cal_table import load_table, validate
from magstack.firmware.calibration.refit import (
    RefitOptions,
    Selection,
    file_pass,
    make_plan,
    reference_block,
    refit,
    theta_from_table,
)
from magstack.sim.error_model import ErrorParams, misalignment_matrix

#: Effects the Eq. 3 + currents model represents (up to the second order of the temperature gain).
LINEAR_EFFECTS = "interference,misalignment,gain,temperature_gain,offset,temperature_offset,noise"
T0_2026 = "1780272000"


def _simulate(path, program="orbit_tumbling", seconds=14400, effects=LINEAR_EFFECTS, seed=3, extra=()):
    args = ["simulate", "--program", program, "--seconds", str(seconds), "--rate-hz", "1", "--sessions", "1",
            "--seed", str(seed), "--t0", T0_2026, "--out", str(path), *extra]
    if effects:
        args += ["--effects", effects]
    assert main(args) == 0
    return path


@pytest.fixture(scope="module")
def tumbling(tmp_path_factory):
    return _simulate(tmp_path_factory.mktemp("orbit") / "tumbling.csv")


@pytest.fixture(scope="module")
def tumbling_result(tumbling):
    return refit([tumbling])


def _truth(path) -> ErrorParams:
    return ErrorParams.from_dict(json.loads(read_session(path).metadata["error_params"]))


def test_recomputed_reference_is_the_simulators_true_field(tumbling):
    blk = next(iter_telemetry(tumbling, 5000))
    b, lat, ecl = reference_block(blk)
    # telemetry carries position to 1 mm and quaternions to 1e-6: the reference agrees to ~0.1 nT
    assert np.max(np.abs(b - blk.ref_uT)) < 5e-4
    assert np.all(np.abs(lat) <= 98.0) and 0 < ecl.mean() < 0.5


def test_recovers_the_true_parameters(tumbling, tumbling_result):
    r = tumbling_result
    assert r.proposed, r.report()
    p = _truth(tumbling)
    gm = p.gain_matrix @ misalignment_matrix(p.misalignment_rad, p.rotation_rad)
    s0 = np.linalg.inv(gm)
    cand = r.candidate
    assert np.allclose(cand.S, s0, atol=2e-3)
    assert np.allclose(cand.O, -s0 @ p.offset_uT, atol=0.03)
    for name, d in cand.D:   # b_act = S b_meas + O - D_true I: the fit finds -D_true (uT/A)
        assert np.allclose(d, -np.asarray(p.interference_uT_per_A[name]), rtol=0.05, atol=0.02), name
    # the sensitivity tempco (-2700 ppm/degC on the diagonal) comes back with the inverse's sign
    assert np.allclose(np.diag(cand.K_S), -np.diag(s0 @ p.k_s_per_c), atol=3e-4)
    noise = np.linalg.norm(p.noise_white_uT)
    assert np.linalg.norm(r.holdout_candidate_uT) < 2.0 * noise
    assert r.bins.bins_filled >= 180 and r.fit.held == []
    assert validate(cand).ok


def test_holdout_and_fit_rows_partition_the_used_rows(tumbling_result):
    r = tumbling_result
    assert r.fit.n_used + r.n_holdout + sum(r.counts.values()) == r.rows
    assert 0.15 < r.n_holdout / r.rows < 0.25          # every 5th 600 s block


def test_block_size_and_file_split_do_not_change_the_candidate(tumbling, tumbling_result, tmp_path):
    big = refit([tumbling], options=RefitOptions(robust_passes=1))                          # cached pass 2
    small = refit([tumbling], options=RefitOptions(robust_passes=1, block_rows=777, cache_mb=0))   # re-read
    assert np.allclose(small.fit.theta, big.fit.theta, rtol=1e-7, atol=1e-10)
    assert small.n_holdout == big.n_holdout == tumbling_result.n_holdout
    # a cache budget smaller than the file's fit rows (about 1 MB here): the file is dropped and re-read
    evicted = refit([tumbling], options=RefitOptions(robust_passes=1, cache_mb=0.3))
    assert np.allclose(evicted.fit.theta, big.fit.theta, rtol=1e-7, atol=1e-10)


def test_robust_passes_resist_outliers(tmp_path, tumbling):
    s = read_session(tumbling)
    rng = np.random.default_rng(5)
    bad = rng.random(len(s)) < 0.02
    s.dut_uT[bad] += rng.choice([-1, 1], size=(bad.sum(), 3)) * 40.0   # 2 % spikes of 40 uT (SEUs, arcing)
    from magstack.data.session import write_session
    path = write_session(tmp_path / "spiky.csv", s)
    clean = refit([tumbling], options=RefitOptions(robust=False))
    robust = refit([path])
    plain = refit([path], options=RefitOptions(robust=False))
    err_robust = np.abs(robust.candidate.S - clean.candidate.S).max()
    err_plain = np.abs(plain.candidate.S - clean.candidate.S).max()
    assert err_robust < 2e-3 < err_plain
    assert err_robust < err_plain / 5


def test_selection_latitude_temperature_eclipse(tumbling):
    opts = RefitOptions(selection=Selection(lat_band_deg=(-40.0, 40.0), temp_band_c=(0.0, 30.0), eclipse="sunlit"),
                        robust=False)
    r = refit([tumbling], options=opts)
    assert r.counts["outside latitude band"] > 0 and r.counts["in eclipse"] > 0
    assert r.counts.get("outside temperature band", 0) > 0
    cov = r.fit.coverage
    assert 0.0 <= cov.temp_min_c and cov.temp_max_c <= 30.0


def test_poor_attitude_coverage_keeps_the_active_values_within_their_uncertainty(tmp_path, tumbling_result):
    """Inertial pointing fills few attitude bins: the refit is a sequential update of the active table
    (its posterior is the prior), so what the orbit cannot determine stays at the active values, within
    the active table's sd, and is named; the report keeps the attitude coverage as the explanation."""
    path = _simulate(tmp_path / "inertial.csv", program="orbit_inertial", seconds=600)
    active = tumbling_result.candidate
    assert active.posterior is not None                       # the tumbling refit's table carries it
    r = refit([path], active, RefitOptions(robust=False, holdout_block_s=60.0))
    assert r.bins.bins_filled < 12
    post = r.fit.posterior
    th = theta_from_table(r.fit.model, active)
    gains = [(i, c) for i in range(3) for c, col in enumerate(r.fit.model.columns) if col.param == "S"]
    for i, c in gains:
        assert abs(r.fit.theta[i, c] - th[i, c]) <= 3 * post.prior.sd[i, c]
        assert post.prior.sd[i, c] < 0.01                      # the bench (tumbling) uncertainty, not a datasheet's
    by = {post.determined_by(i, c) for i, c in gains}
    assert by & {"prior", "data+prior"}
    held = {h.name for h in r.fit.held}
    assert held and held <= {r.fit.model.param_name(i, c) for i in range(3) for c in range(r.fit.model.n_columns)}
    assert "determined by the prior (the active table)" in r.report()


def test_candidate_not_better_than_active_is_not_proposed(tumbling, tumbling_result):
    r = refit([tumbling], tumbling_result.candidate, RefitOptions(min_improvement=0.05))
    assert not r.proposed
    assert any("not better" in x for x in r.reasons)


def test_a_second_refit_of_the_same_data_proposes_nothing(tumbling, tumbling_result, tmp_path, capsys):
    """The first refit (identity active) is a large, significant improvement; refitting the same data with its
    candidate active finds an improvement within the noise and proposes nothing (default options)."""
    t = tumbling_result.paired_test
    assert tumbling_result.proposed and t.significant and t.p <= 1e-3 and t.gain > 0.5 and t.blocks >= 3
    again = refit([tumbling], tumbling_result.candidate)
    assert not again.proposed and not again.paired_test.significant
    assert any("within the noise" in x or "not better" in x for x in again.reasons), again.reasons
    assert "paired over held-out blocks" in again.report()
    doc = again.to_dict()["paired_test"]
    assert doc["significant"] is False and doc["alpha"] == 0.01 and doc["min_gain"] == 0.01
    # the CLI: exit 1, nothing written, the test's figures said
    first, second = tmp_path / "c1.json", tmp_path / "c2.json"
    assert main(["refit", str(tumbling), "--out", str(first), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["refit", str(tumbling), "--active", str(first), "--out", str(second), "--no-progress"]) == 1
    assert "paired over held-out blocks" in capsys.readouterr().out and not second.exists()


def test_block_grams_give_the_held_out_rms_of_any_table(tumbling, tumbling_result):
    """The per-block Grams reproduce the held-out R factor's RMS for the candidate and the active table."""
    plan = make_plan([str(tumbling)], load_identity(), RefitOptions())
    st = file_pass(str(tumbling), plan)
    mask = plan.model.axis_mask()
    from magstack.firmware.calibration.refit import holdout_rms
    for theta in (plan.theta_active, tumbling_result.fit.theta):
        sse = sum(st.hold_blocks.sse(np.where(mask, theta, 0.0)).values())
        rms = holdout_rms(st.hold.R, theta, plan.model, st.hold.n_used)
        assert np.sqrt(sse / st.hold.n_used) == pytest.approx(float(np.linalg.norm(rms)), rel=1e-9)


def test_map_reduce_merge_equals_single_pass(tumbling):
    plan = make_plan([str(tumbling)], load_identity(), RefitOptions())
    whole = file_pass(str(tumbling), plan)
    assert whole.rows == len(read_session(tumbling))
    assert whole.fit.state_bytes < 10_000    # memory of the accumulated state is independent of N


def load_identity():
    from magstack.firmware.calibration.refit import identity_table
    return identity_table("hmc1053")


# ---------------------------------------------------------------------- CLI
def test_cli_refit_writes_a_table_that_validates_and_applies(tumbling, tmp_path, capsys):
    out, rep = tmp_path / "cand.json", tmp_path / "rep.json"
    assert main(["refit", str(tumbling), "--out", str(out), "--json", str(rep), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "attitude coverage: " in text and "held-out RMS" in text and "PROPOSED" in text
    doc = json.loads(rep.read_text())
    assert doc["proposed"] and doc["attitude_bins_filled"] >= 180 and len(doc["fitted"]) == 33
    assert main(["table", "validate", str(out)]) == 0
    assert main(["apply", str(out), str(tumbling), "--out", str(tmp_path / "cal.csv")]) == 0
    # the candidate, now active, cannot be beaten by 5 % on the same data: exit 1, nothing written
    again = tmp_path / "again.json"
    assert main(["refit", str(tumbling), "--active", str(out), "--out", str(again), "--min-improvement", "0.05",
                 "--no-progress"]) == 1
    assert not again.exists()
    assert load_table(out).fit_stats["refit_method"] == "attitude"


def test_cli_usage_errors(tumbling, tmp_path, capsys):
    assert main(["refit", "--out", str(tmp_path / "x.json")]) == 2
    assert main(["refit", str(tumbling)]) == 2
    assert main(["refit", str(tumbling), "--out", str(tmp_path / "x.json"), "--lat-band", "40,-40"]) == 2
    assert main(["refit", str(tumbling), "--out", str(tumbling)]) == 2
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,dut_x_uT\n1,2\n")
    assert main(["refit", str(bad), "--out", str(tmp_path / "x.json")]) == 3
    assert "lacks telemetry columns" in capsys.readouterr().err


def test_cli_dask_engine_equals_in_process(tmp_path, tumbling):
    pytest.importorskip("dask")
    second = _simulate(tmp_path / "b.csv", seconds=3600, seed=4, extra=["--t0", "1780300000"])
    third = _simulate(tmp_path / "c.csv", seconds=3600, seed=5, extra=["--t0", "1780310000"])
    files = [str(tumbling), str(second), str(third)]
    docs = []
    for engine in ("local", "dask"):
        rep = tmp_path / f"{engine}.json"
        assert main(["refit", *files, "--engine", engine, "--out", str(tmp_path / f"{engine}_c.json"),
                     "--json", str(rep), "--no-progress"]) == 0
        docs.append(json.loads(rep.read_text()))
    a, b = (d["parameters"] for d in docs)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-9, abs=1e-12), k
    assert docs[0]["rows"] == docs[1]["rows"] and docs[0]["rows_holdout"] == docs[1]["rows_holdout"]


def test_candidate_failing_validation_is_never_proposed(tumbling, monkeypatch):
    from magstack.firmware import cal_table
    from magstack.firmware.calibration import refit as refit_mod
    monkeypatch.setattr(refit_mod.cal_table, "validate",
                        lambda table: cal_table.ValidationResult(False, ("S diagonal outside [0.1, 10]",)))
    r = refit([tumbling], options=RefitOptions(robust=False))
    assert not r.proposed and any("fails validation" in x for x in r.reasons)


def test_cli_scalar_method_fits_the_magnitude_and_proposes(tumbling, tmp_path, capsys):
    out, rep = tmp_path / "s.json", tmp_path / "s_rep.json"
    assert main(["refit", str(tumbling), "--method", "scalar", "--out", str(out), "--json", str(rep),
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "refit (scalar, attitude-independent)" in text and "PROPOSED" in text
    doc = json.loads(rep.read_text())
    assert doc["method"] == "scalar" and doc["proposed"]
    # gain + offset only: the temperature and current terms (about 1 uT here) stay in the residual
    assert doc["holdout_scalar_rms_candidate_uT"] < 0.5 * doc["holdout_scalar_rms_active_uT"]
    table = load_table(out)
    assert table.terms == ("gain_matrix", "offset") and validate(table).ok
    # a magnitude fit determines S up to a rotation: its singular values are the truth's
    p = _truth(tumbling)
    s0 = np.linalg.inv(p.gain_matrix @ misalignment_matrix(p.misalignment_rad, p.rotation_rad))
    assert np.allclose(np.linalg.svd(table.S, compute_uv=False), np.linalg.svd(s0, compute_uv=False), atol=0.01)


def test_cli_pso_paper_model_and_telemetry(tumbling, tmp_path, capsys):
    rep = tmp_path / "pso.json"
    assert main(["refit", "--method", "pso", "--paper-model", "1", "--seed", "0", "--iterations", "20",
                 "--json", str(rep)]) == 0
    doc = json.loads(rep.read_text())
    assert {"fitness", "S_mc", "offset_nT", "runtime_s"} <= set(doc)
    # a tumbling body turns about no fixed axis long enough: no rotation-axis loci, the PSO is refused (bad data)
    capsys.readouterr()
    assert main(["refit", str(tumbling), "--method", "pso", "--out", str(tmp_path / "x.json")]) == 3
    assert "needs loci about at least two body axes" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()
    assert main(["refit", "--method", "scalar", "--paper-model", "1"]) == 2


def test_streaming_fit_merge_equals_one_accumulation():
    from magstack.firmware.calibration.model import CalModel
    from magstack.firmware.calibration.streaming import StreamingFit
    rng = np.random.default_rng(2)
    n = 2000
    b = rng.normal(size=(n, 3)) * 30
    y = b @ np.array([[1.01, 0.02, 0], [0, 0.99, 0.01], [0.03, 0, 1.02]]).T + 0.5 + rng.normal(size=(n, 3)) * 0.02
    temp = rng.uniform(-10, 40, n)
    cur = {"solar": rng.uniform(0, 1, n)}
    m = CalModel(("gain_matrix", "temperature_gain", "offset", "temperature_offset"), ("solar",))
    one = StreamingFit(m)
    one.add(b, y, temp, cur)
    a, c = StreamingFit(m), StreamingFit(m)
    a.add(b[:700], y[:700], temp[:700], {"solar": cur["solar"][:700]})
    c.add(b[700:], y[700:], temp[700:], {"solar": cur["solar"][700:]})
    merged = a.merge(c)
    assert merged.n_used == n
    assert np.allclose(np.abs(merged.R), np.abs(one.R), rtol=1e-10, atol=1e-9)   # R unique up to row signs
    assert np.allclose(merged.solve().theta, one.solve().theta, rtol=1e-10, atol=1e-12)
    assert merged.coverage.temp_min_c == one.coverage.temp_min_c
    assert merged.coverage.currents_A == one.coverage.currents_A


def test_same_file_twice_is_refused(tumbling):
    from magstack.firmware.errors import FitError
    with pytest.raises(FitError, match="more than once"):
        refit([tumbling, str(tumbling)])


def test_rows_without_gps_fix_or_with_a_corrupt_quaternion_are_excluded_not_fatal(tmp_path, tumbling):
    s = read_session(tumbling)
    s.extra["pos_ecef_x_km"][:30] = 0.0
    s.extra["pos_ecef_y_km"][:30] = 0.0
    s.extra["pos_ecef_z_km"][:30] = 0.0            # receiver without fix reports zeros
    s.extra["q_body_eci_w"][30:40] = 2.0            # corrupted quaternion
    s.extra["q_body_eci_x"][40:45] = np.nan
    from magstack.data.session import write_session
    path = write_session(tmp_path / "nofix.csv", s)
    r = refit([path], options=RefitOptions(robust=False))
    assert r.counts["no or implausible position/attitude"] == 45


def test_cli_defaults_are_the_refit_defaults():
    from magstack.cli.main import build_parser
    args = build_parser().parse_args(["refit", "t.csv", "--out", "c.json"])
    d = RefitOptions()
    assert (args.robust_passes, args.holdout_block_s, args.holdout_every, args.max_current_gap_s, args.dut1,
            args.min_improvement, args.eclipse, args.model) == \
        (d.robust_passes, d.holdout_block_s, d.holdout_every, d.max_current_gap_s, d.dut1_s, d.min_improvement,
         d.selection.eclipse, d.model)
