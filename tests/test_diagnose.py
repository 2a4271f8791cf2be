"""Sim-to-real gap diagnosis: ranking on held-out blocks, significance, confounding,
not-testable effects, fixed-parameter paths, JSON, report and CLI.

The generators here are written in this file (plain numpy forward models of the catalogue's physics),
not the project's error model, so a pass does not come from the diagnoser and the generator sharing
code; the withheld-effect harness with the project's simulator is tested in test_diagnose_validate.py.
"""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from magstack.data.session import Session, write_session
from magstack.ground.diagnose import Options, check_rows, diagnose, diagnose_model, fixed_gap
from magstack.ground.diagnose.search import holm, sign_flip_p

RATE_HZ = 2.0
G = np.array([[1.09, 0.05, -0.03], [0.04, 1.11, 0.02], [-0.02, 0.03, 1.10]])
O = np.array([0.3, -0.1, 0.45])


def bench(seconds=2400.0, sessions=3, temp=True, currents=True, seed=0, noise_uT=0.02, rate_hz=RATE_HZ):
    """Independent stimulus: smooth tumbling field (|B| 20-60 uT), excursions to +-140 uT, slow thermal
    cycle, a square-wave current; returns truth pieces."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, seconds, 1 / rate_hz)
    w = 2 * np.pi * np.array([1 / 97.0, 1 / 131.0, 1 / 173.0])
    b = np.column_stack([40 * np.sin(w[0] * t), 35 * np.cos(w[1] * t + 0.3), 30 * np.sin(w[2] * t + 1.1)])
    for k, t0 in enumerate((0.3, 0.55, 0.8)):   # excursions, one axis at a time, +peak then -peak
        for sign, dt in ((1, 0.0), (-1, 0.05)):
            m = (t > (t0 + dt) * seconds) & (t < (t0 + dt) * seconds + 20)
            b[m, k] = sign * 140.0
    temp_c = 30 + 20 * np.sin(2 * np.pi * t / seconds) if temp else np.full(t.size, np.nan)
    cur = {"heater_A": 0.4 * ((t // 45) % 2)} if currents else {}
    sess = np.minimum((t / seconds * sessions).astype(int), sessions - 1)
    return t, b, temp_c, cur, sess, rng, noise_uT


def make(effect=None, strength=1.0, **kw):
    t, b, temp_c, cur, sess, rng, noise = bench(**kw)
    effects = (effect,) if effect is None or isinstance(effect, str) else tuple(effect)
    dut = b @ G.T
    if "mount_rotation" in effects:   # session s senses R_s^T B (session 0 is the frame)
        from scipy.spatial.transform import Rotation
        for k, rv in ((1, [0.003, -0.002, 0.004]), (2, [-0.004, 0.003, 0.002])):
            m = sess == k
            dut[m] = Rotation.from_rotvec(strength * np.array(rv)).inv().apply(b[m]) @ G.T
    if "time_skew" in effects:
        d = strength * np.array([0.0, 0.05, 0.1])
        dut = np.column_stack([np.column_stack([np.interp(t + d[j], t, b[:, k]) for k in range(3)]) @ G[j]
                               for j in range(3)])
    if "temperature_offset" in effects:
        dut = dut + strength * np.outer(temp_c - 25, [-0.14, 0.02, 0.03])
    if "interference" in effects:
        dut = dut + strength * np.outer(cur["heater_A"], [0.5, -0.4, 0.6])
    if "session_offset" in effects:
        dut = dut + strength * np.array([[0.1, -0.08, 0.06], [-0.05, 0.1, -0.1], [0.0, -0.03, 0.08]])[sess]
    if "hysteresis" in effects:
        # a magnetised part starts in a state (+ or -, never 0) that the file does not record
        st = np.zeros_like(b)
        initial = (1.0, -1.0, -1.0)
        for j in range(3):
            e = np.where(np.abs(dut[:, j]) >= 120, np.sign(dut[:, j]), 0.0)
            last = np.maximum.accumulate(np.where(e != 0, np.arange(t.size), -1))
            st[:, j] = np.where(last >= 0, e[np.maximum(last, 0)], initial[j])
        dut = dut + strength * 0.06 * st
    dut = dut + O + rng.standard_normal(dut.shape) * noise
    ref = b + rng.standard_normal(b.shape) * 0.001
    return Session(1.6e9 + t, ref, dut, temp_c, sess, cur, {"device_id": "test"})


# ----------------------------------------------------------------------------- statistics
def test_sign_flip_test_is_calibrated_under_the_null():
    rng = np.random.default_rng(1)
    p = np.array([sign_flip_p(rng.standard_normal(30), seed=k) for k in range(200)])
    assert 0.02 <= np.mean(p < 0.05) <= 0.09
    assert sign_flip_p(rng.standard_normal(30) + 1.0) < 0.001


def test_holm_adjusts_and_keeps_order():
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])


# ----------------------------------------------------------------------------- verdicts
@pytest.mark.parametrize("effect", ["time_skew", "temperature_offset", "interference", "session_offset",
                                    "hysteresis"])
def test_an_effect_the_model_leaves_out_is_named_and_closes_the_gap(effect):
    d = diagnose_model(make(effect), "gain_offset")
    j = d.to_dict()
    assert j["verdict"] == effect, d.text()
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"], d.text()
    assert j["baseline_rmse_nT"] > 1.5 * j["after_rmse_nT"]
    top = j["ranking"][0]
    assert top["effect"] == effect and top["significant"]


def test_nothing_unmodelled_gives_none():
    for seed in range(3):
        d = diagnose_model(make(None, seed=seed), "gain_offset")
        assert d.verdict == "none", d.text()
        assert d.to_dict()["after_rmse_nT"] == d.to_dict()["baseline_rmse_nT"]


def test_time_skew_parameters_recovered_with_standard_errors():
    p = diagnose_model(make("time_skew"), "gain_offset").parameters
    for a, true in zip("xyz", (0.0, 0.05, 0.1), strict=True):
        v = p[f"dt[{a}]"]
        assert v["unit"] == "s"
        assert abs(v["value"] - true) < max(5 * v["se"], 0.004), p


def test_interference_parameters_in_catalogue_units():
    p = diagnose_model(make("interference"), "gain_offset").parameters
    # forward (simulator side): the field per amp the DUT reads
    want = np.array([0.5, -0.4, 0.6])
    got = np.array([p[f"D_heater_A[{a}]"]["value"] for a in "xyz"])
    assert np.allclose(got, want, atol=0.01)
    assert all(p[f"D_heater_A[{a}]"]["unit"] == "uT/A" for a in "xyz")


def test_hysteresis_is_told_apart_from_a_per_session_offset():
    d = diagnose_model(make("hysteresis"), "gain_offset")
    assert d.verdict == "hysteresis"
    so = next(t for t in d.result.trials if t.effect == "session_offset")
    assert so.rmse_norm_uT > d.after_trial.rmse_norm_uT * 1.3
    d2 = diagnose_model(make("session_offset"), "gain_offset")
    assert d2.verdict == "session_offset"


def test_offset_and_per_session_offset_indistinguishable_names_the_simpler_and_says_so():
    s = make(None)
    d = diagnose_model(s, "gain")   # the model leaves the (common) offset out
    j = d.to_dict()
    assert j["verdict"] == "offset"
    # every offset-like candidate carries the constant when the model has none (it contains "offset")
    assert any("simpler" in n for n in j["notes"]) or j["runner_up"] in ("session_offset", "hysteresis", "drift",
                                                                         "temperature_offset")


# ----------------------------------------------------------------------------- not testable
def test_columns_that_cannot_test_an_effect_are_listed_not_crashed():
    s = make(None, temp=False, currents=False, sessions=1)
    j = diagnose_model(s, "gain_offset").to_dict()
    nt = {n["effect"]: n["reason"] for n in j["not_testable"]}
    assert {"temperature_gain", "temperature_offset", "interference", "session_offset"} <= set(nt)
    assert "one session" in nt["session_offset"]
    assert j["verdict"] == "none"


def test_too_few_rows_is_a_clean_error():
    from magstack.ground.errors import DiagnosisError
    s = make(None).select(np.arange(20))
    with pytest.raises(DiagnosisError):
        check_rows(s)


# ----------------------------------------------------------------------------- fixed path (b)
def test_fixed_table_path_names_the_effect_that_changed():
    from magstack.firmware.cal_table import table_from_fit
    from magstack.firmware.calibration import FitData, FitOptions, fit
    from magstack.ground.diagnose.spec import table_gap
    clean = make(None, seed=5)
    table = table_from_fit(fit(FitData.from_session(clean), "eq3", options=FitOptions(holdout=False)), "test")
    later = make("temperature_offset", seed=6)
    full, keep, _ = check_rows(later, exclude_bends=10.0)
    d = diagnose(table_gap(full.select(keep), table, "table"), Options())
    assert d.verdict == "temperature_offset", d.text()
    unchanged = make(None, seed=7)
    full, keep, _ = check_rows(unchanged, exclude_bends=10.0)
    assert diagnose(table_gap(full.select(keep), table, "table"), Options()).verdict == "none"


def _table_diagnosis(later, table):
    from magstack.ground.diagnose.spec import table_gap
    full, keep, _ = check_rows(later, exclude_bends=10.0)
    return diagnose(table_gap(full.select(keep), table, "table"), Options())


def test_fixed_table_path_names_a_drift_since_the_fit_and_a_temperature_offset_about_another_pivot():
    from magstack.firmware.cal_table import table_from_fit
    from magstack.firmware.calibration import FitData, FitOptions, fit
    table = table_from_fit(fit(FitData.from_session(make(None, seed=5)), "eq3", options=FitOptions(holdout=False)),
                           "test")
    # the offset has drifted since the table was fitted an hour earlier: non-zero mean, and a slope
    later = make(None, seed=6)
    t = later.t_s - later.t_s[0] + 3600.0
    later.dut_uT = later.dut_uT + np.outer(t, [1.0e-4, -8e-5, 6e-5])
    d = _table_diagnosis(later, table)
    assert d.verdict == "drift", d.text()
    assert d.to_dict()["after_rmse_nT"] <= 1.2 * d.to_dict()["noise_floor_nT"], d.text()
    # a temperature offset that appeared since, about 40 degC (not the table's 25 degC)
    later = make(None, seed=7)
    later.dut_uT = later.dut_uT + np.outer(later.temp_c - 40.0, [-0.03, 0.02, 0.025])
    d = _table_diagnosis(later, table)
    assert d.verdict == "temperature_offset", d.text()
    assert d.to_dict()["after_rmse_nT"] <= 1.2 * d.to_dict()["noise_floor_nT"], d.text()


def test_fixed_gap_nan_rows_are_left_out_with_a_note():
    s = make(None)
    gap = s.ref_uT - (s.dut_uT - O) @ np.linalg.inv(G).T
    gap[:10] = np.nan
    g = fixed_gap(s, gap, s.ref_uT, ("gain", "offset"), "test")
    assert g.n == len(s) - 10 and g.notes


# ----------------------------------------------------------------------------- JSON, where, report
def test_json_has_the_stable_keys_and_breakdowns():
    j = diagnose_model(make("temperature_offset"), "gain_offset").to_dict()
    for k in ("verdict", "baseline_rmse_nT", "after_rmse_nT", "noise_floor_nT", "ranking", "not_testable",
              "where", "parameters"):
        assert k in j
    for r in j["ranking"]:
        assert set(r) >= {"effect", "rmse_nT", "shrink", "significant"}
    for k in ("axis", "temperature_c", "field_magnitude_uT", "field_rate_uT_per_s", "session", "time_blocks",
              "spectrum"):
        assert k in j["where"]
    # the temperature bands show the gap growing away from 25 degC
    bands = j["where"]["temperature_c"]
    assert bands[0]["rms_norm_nT"] > 2 * min(b["rms_norm_nT"] for b in bands)
    json.dumps(j)


def test_noise_floor_and_spectrum_match_injected_white_noise():
    d = diagnose_model(make(None, noise_uT=0.03), "gain_offset")
    nf = d.to_dict()["noise_floor_axes_nT"]
    assert np.allclose(nf, 30.0 / np.diag(G), rtol=0.15)
    white = d.where["spectrum"]["spectral_white_nT"]
    assert np.allclose(white, 30.0 / np.diag(G), rtol=0.25)


def test_noise_floor_for_sparse_rows_and_with_an_aliased_tone():
    # 0.5 Hz telemetry: rows 2 s apart (a 1 s differencing lag found no pairs: null)
    d = diagnose_model(make(None, noise_uT=0.03, rate_hz=0.5, seconds=9600.0), "gain_offset")
    j = d.to_dict()
    assert j["noise_floor_nT"] is not None, d.text()
    assert np.allclose(j["noise_floor_axes_nT"], 30.0, rtol=0.15)      # DUT units (forward gap)
    assert j["where"]["noise_floor_lag_s"] == pytest.approx(3.0)
    # a mains alias: a 0.41 Hz tone of 80 nT in the DUT reading at 2 Hz (differences pass it almost whole)
    s = make(None, noise_uT=0.03)
    s.dut_uT = s.dut_uT + 0.08 * np.sin(2 * np.pi * 0.41 * s.t_s + 0.3)[:, None]
    d = diagnose_model(s, "gain_offset")
    j = d.to_dict()
    assert np.allclose(j["noise_floor_axes_nT"], 30.0, rtol=0.15), j["noise_floor_axes_nT"]
    tones = j["where"]["tones"]
    assert len(tones) >= 1 and tones[0]["freq_hz"] == pytest.approx(0.41, abs=1e-4)
    assert np.allclose(tones[0]["amplitude_nT"], 80.0, rtol=0.1)
    assert "tone" in d.text()


@pytest.mark.slow
def test_report_is_one_self_contained_html_page(tmp_path):
    pytest.importorskip("matplotlib")
    from magstack.ground.diagnose.figures import write_report
    path = write_report(diagnose_model(make("interference"), "gain_offset"), tmp_path / "rep")
    html = path.read_text()
    assert html.count("data:image/png;base64,") >= 5 and "interference" in html
    assert "src=\"http" not in html and not list((tmp_path / "rep").glob("*.part"))


# ----------------------------------------------------------------------------- CLI
def _cli(*args):
    return subprocess.run([sys.executable, "-m", "magstack", *args], capture_output=True, text=True)


@pytest.mark.slow
def test_cli_diagnose_writes_json_and_sim_path_round_trips(tmp_path):
    s1 = tmp_path / "s.csv"
    p = tmp_path / "p.json"
    r = _cli("simulate", "--program", "full", "--seconds", "900", "--effects",
             "gain,offset,noise,quantization,temperature_gain", "--out", str(s1), "--save-params", str(p))
    assert r.returncode == 0, r.stderr
    out = tmp_path / "d.json"
    r = _cli("diagnose", str(s1), "--json", str(out), "--block-s", "30")
    assert r.returncode == 0, r.stderr
    assert json.loads(out.read_text())["verdict"] == "temperature_gain"
    r = _cli("diagnose", str(s1), "--sim", str(p), "--block-s", "30", "--json", str(out))
    assert r.returncode == 0, r.stderr
    assert json.loads(out.read_text())["verdict"] == "none"


@pytest.mark.parametrize("args, code, text", [
    (["diagnose", "MISSING.csv"], 3, "no such session file"),
    (["diagnose", "{s}", "--model", "bogus"], 2, "unknown model or effect"),
    (["diagnose", "{s}", "--block-s", "0"], 2, "--block-s"),
    (["diagnose", "{s}", "--null", "bogus"], 2, "--null"),
    (["diagnose", "{s}", "--sim", "{bad}"], 3, "line 1"),
    (["diagnose", "{s}", "--table", "{bad}"], 3, "not valid JSON"),
    (["diagnose", "{short}"], 3, "usable rows"),
    (["diagnose", "{garbled}"], 3, "cells, header has"),
    (["validate-diagnosis", "--seeds", "0", "--out", "{tmp}"], 2, "--seeds"),
])
def test_cli_bad_input_is_one_clean_line_with_the_documented_exit_code(tmp_path, args, code, text):
    s = tmp_path / "s.csv"
    write_session(s, make(None, seconds=600))
    short = tmp_path / "short.csv"
    write_session(short, make(None, seconds=600).select(np.arange(10)))
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    garbled = tmp_path / "g.csv"
    lines = s.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    garbled.write_text("\n".join(lines[:k + 1] + ["1,2,x"] + lines[k + 2:]) + "\n")
    args = [a.format(s=s, bad=bad, short=short, garbled=garbled, tmp=tmp_path / "v") for a in args]
    r = _cli(*args)
    assert r.returncode == code, (r.stdout, r.stderr)
    assert text in r.stderr and "Traceback" not in r.stderr
    errors = [line for line in r.stderr.strip().splitlines() if line.startswith("magstack ")]
    assert len(errors) == 1 and text in errors[0]   # argparse usage errors add the usage lines above it


def test_block_grouping_follows_the_correlation_of_block_means():
    from magstack.ground.diagnose.search import block_group, grouped
    rng = np.random.default_rng(3)
    nb, per = 60, 50
    blocks = np.repeat(np.arange(nb), per)
    bsess = np.repeat([0, 1], nb // 2)
    white = rng.standard_normal((nb * per, 3))
    assert block_group(white, blocks, bsess) == 1
    slow = np.zeros((nb, 3))
    for k in range(1, nb):   # AR(1) block means, rho = 0.8
        slow[k] = 0.8 * slow[k - 1] + rng.standard_normal(3)
    g = block_group(np.repeat(slow, per, axis=0) + 0.01 * white, blocks, bsess)
    assert 5 <= g <= 15   # (1 + 0.8) / (1 - 0.8) = 9
    d = np.arange(nb, dtype=float)
    assert grouped(d, bsess, 4).sum() == d.sum() and grouped(d, bsess, 4).size == 16   # 8 units per session


@pytest.mark.slow
def test_windows_select_rows_and_mount_rotation_is_tried(tmp_path):
    s = tmp_path / "s.csv"
    write_session(s, make("temperature_offset", seconds=1200))
    out = tmp_path / "d.json"
    r = _cli("diagnose", str(s), "--window", "0:250", "--json", str(out), "--block-s", "30")
    assert r.returncode == 0, r.stderr
    j = json.loads(out.read_text())
    assert j["n_rows"] <= 3 * (250 * RATE_HZ + 1) and "keep 0:250" in j["windows"]   # relative to each session
    assert j["verdict"] == "temperature_offset"
    assert "mount_rotation" in {t["effect"] for t in j["ranking"]}   # 3 sessions: tried, not significant
    r = _cli("diagnose", str(s), "--window", "0:250", "--model", "gain+offset+mount_rotation")
    assert r.returncode == 0, r.stderr   # 3 sessions: the rotation can be modelled
    one = tmp_path / "one.csv"
    write_session(one, make(None, seconds=600, sessions=1))
    r = _cli("diagnose", str(one), "--model", "gain+offset+mount_rotation")
    assert r.returncode == 3 and "mount_rotation" in r.stderr and "one session" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


# ----------------------------------------------------------------------------- hardening (independent findings)
def test_hysteresis_state_before_the_first_excursion_is_a_sign_not_zero():
    from magstack.ground.diagnose.nonlinear import hysteresis_state
    b = np.zeros((6, 3))
    b[3, 0] = 200.0
    st = hysteresis_state(b, np.array([100.0, np.inf, np.inf]), initial=(-1.0, 1.0, 1.0))
    assert st[:3, 0].tolist() == [-1.0, -1.0, -1.0] and st[3:, 0].tolist() == [1.0, 1.0, 1.0]


def test_hysteresis_found_when_the_reference_is_missing_at_the_excursions():
    """The excursion that sets the remanence state is where the reference saturates: its DUT readings
    still build the state (rows without a reference are only left out of the fit)."""
    s = make("hysteresis")
    sat = np.any(np.abs(s.ref_uT) > 100.0, axis=1)
    s.ref_uT[sat] = np.nan
    j = diagnose_model(s, "gain_offset").to_dict()
    assert j["verdict"] == "hysteresis"
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"]


def test_folds_spread_each_axis_excursions_over_folds_on_a_program_repeated_per_session():
    from magstack.ground.diagnose.gap import folds_from_blocks, time_blocks
    t = np.tile(np.arange(0.0, 600.0, 0.5), 3)
    sess = np.repeat(np.arange(3), t.size // 3)
    b = np.full((t.size, 3), 20.0)
    for j, at in enumerate((125.0, 245.0, 365.0)):     # one excursion per axis, same time in every session
        b[(t >= at) & (t < at + 10.0), j] = 150.0
    blocks = time_blocks(t, sess, 60.0)
    fold = folds_from_blocks(blocks, sess, 5, b, seed=0)
    for j in range(3):
        assert np.unique(fold[b[:, j] > 100.0]).size >= 2
    old = folds_from_blocks(blocks, sess, 5)
    assert any(np.unique(old[b[:, j] > 100.0]).size == 1 for j in range(3))   # what plain blocks-to-folds gives


def test_rows_at_the_edges_of_a_run_are_left_out():
    from magstack.ground.diagnose.gap import run_edge_rows
    t = np.r_[np.arange(0.0, 10.0, 0.5), np.arange(30.0, 40.0, 0.5)]
    edge = run_edge_rows(t, np.zeros(t.size, dtype=np.int64))
    assert np.flatnonzero(edge).tolist() == [0, 1, 18, 19, 20, 21, 38, 39]


def test_mount_rotation_is_named_and_its_angles_recovered():
    d = diagnose_model(make("mount_rotation"), "gain_offset")
    j = d.to_dict()
    assert j["verdict"] == "mount_rotation", d.text()
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"]
    truth = {"omega[1][x]": 0.003, "omega[1][y]": -0.002, "omega[1][z]": 0.004,
             "omega[2][x]": -0.004, "omega[2][y]": 0.003, "omega[2][z]": 0.002}
    for name, v in truth.items():
        p = j["parameters"][name]
        assert p["unit"] == "rad" and abs(p["value"] - v) < max(5 * p["se"], 2e-4), (name, p)


def test_modelled_mount_rotation_is_fitted_jointly_and_the_other_effect_named():
    """--model gain_offset+mount_rotation on a bench remounted between sessions that also has an
    unmodelled temperature offset: the rotation is fitted jointly with the base in every trial, so the
    temperature offset is named, closes the gap to the noise floor and its slopes are recovered."""
    s = make(("mount_rotation", "temperature_offset"))
    d = diagnose_model(s, "gain_offset+mount_rotation")
    j = d.to_dict()
    assert "mount_rotation" in j["modelled"] and "mount_rotation" not in {t["effect"] for t in j["ranking"]}
    assert j["verdict"] == "temperature_offset", d.text()
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"], d.text()
    # fitted on the simulator side (dut = G ref + o + K_O dT, the forward gap): the DUT's own slopes
    want = np.array([-0.14, 0.02, 0.03])
    for a, v in zip("xyz", want, strict=True):
        p = j["parameters"][f"K_O[{a}]"]
        assert abs(p["value"] - v) < max(5 * p["se"], 2e-3), (a, p)
    # the same data without the rotation modelled: the rotation's misfit stays in the gap after the
    # temperature offset (in quadrature with a 2.2 uT baseline it moves that by only a few nT)
    j0 = diagnose_model(s, "gain_offset").to_dict()
    to = next(r for r in j0["ranking"] if r["effect"] == "temperature_offset")
    assert to["rmse_nT"] > 2.0 * j["after_rmse_nT"], (to, j["after_rmse_nT"])


def test_modelled_mount_rotation_alone_leaves_nothing():
    j = diagnose_model(make("mount_rotation"), "gain_offset+mount_rotation").to_dict()
    assert j["verdict"] == "none", j["ranking"]
    assert j["baseline_rmse_nT"] <= 1.2 * j["noise_floor_nT"]


def test_mount_rotation_needs_two_sessions():
    j = diagnose_model(make(None, sessions=1), "gain_offset").to_dict()
    nt = {n["effect"]: n["reason"] for n in j["not_testable"]}
    assert "one session" in nt["mount_rotation"]


def test_few_test_units_can_still_be_significant():
    """Six consistent units: the sign-flip floor is 2^-6 = 0.016 (never below Holm's level for 9
    effects); unit_p uses Student's t there, so a large consistent shrink can pass."""
    from magstack.ground.diagnose.search import unit_p
    d = np.array([1.0, 1.2, 0.9, 1.1, 1.05, 0.95])
    assert sign_flip_p(d) > 0.01
    assert unit_p(d) < 1e-4
    assert unit_p(-d) > 0.99
    rng = np.random.default_rng(3)
    p = np.array([unit_p(rng.standard_normal(6)) for _ in range(400)])
    assert 0.02 <= np.mean(p < 0.05) <= 0.09     # calibrated under the null


def test_saturated_reference_rows_are_left_out_and_counted():
    # the reference clips at the FVM400's +-100 uT while the DUT reads the real field (excursions to 140 uT)
    s = make(None)
    s.ref_uT = np.clip(s.ref_uT, -100.0, 100.0)
    s.metadata["reference"] = "fvm400"
    j = diagnose_model(s, "gain_offset").to_dict()
    assert j["verdict"] == "none", j["ranking"][:3]
    assert j["reference"]["reference"] == "fvm400" and j["reference"]["range_uT"] == 100.0
    assert j["reference"]["saturated_rows"] > 100 and j["reference"]["saturated_excluded"]
    assert any("beyond its range" in n for n in j["notes"])
    # a reference that reads beyond its nominal range but follows the DUT there is not pinned: rows kept
    wide = make(None)
    wide.metadata["reference"] = "fvm400"
    g = diagnose_model(wide, "gain_offset").to_dict()["reference"]
    assert g["saturated_rows"] == 0 and "not pinned" in g["note"]
    kept = diagnose_model(s, "gain_offset", Options(include_saturated=True)).to_dict()
    assert kept["reference"]["saturated_rows"] == j["reference"]["saturated_rows"]
    assert not kept["reference"]["saturated_excluded"] and kept["verdict"] != "none"


def _trial(effect, rmse, block_sse, n_params):
    from magstack.ground.diagnose.search import Trial
    t = Trial(effect, "linear", np.full(3, rmse / np.sqrt(3)), None, np.asarray(block_sse, float))
    t.extra.update(n_params=n_params, group=1)
    return t


def test_a_simpler_candidate_is_not_preferred_by_one_outlier_block_or_when_it_closes_much_less():
    from magstack.ground.diagnose.search import choose_verdict
    bs = np.zeros(10, dtype=np.int64)
    # the richer model is better in 9 of 10 blocks; one outlier block favours the simpler by far (a t test
    # on the mean difference calls the simpler "not worse")
    rich = _trial("temperature_gain", 0.40, np.full(10, 1.0), 9)
    simple = _trial("misalignment", 0.41, np.r_[np.full(9, 3.0), -200.0 + 1.0], 6)
    v, note = choose_verdict([rich, simple], 4.3, bs, 0.05)
    assert v is rich and note is None
    # never prefer a candidate that closes much less of the gap, even when the blocks cannot tell them apart
    far = _trial("misalignment", 1.9, np.r_[np.full(5, 3.0), np.full(5, -1.0)], 6)
    v, _ = choose_verdict([rich, far], 4.3, bs, 0.05)
    assert v is rich
    # equal fits: the simpler is named, with the reason
    twin = _trial("offset", 0.40, rich.block_sse + np.r_[0.1, -0.1] .repeat(5), 3)
    v, note = choose_verdict([rich, twin], 4.3, bs, 0.05)
    assert v is twin and "simpler" in note


def test_an_unexplained_remainder_is_said_plainly_with_where_it_lies(tmp_path):
    # an even-order error no catalogue effect has: |B_x| mixed into every axis, largest at high field
    s = make(None)
    s.dut_uT = s.dut_uT + 0.004 * np.abs(s.ref_uT[:, [0]]) * np.array([1.0, -0.5, 0.7])
    d = diagnose_model(s, "gain_offset")
    j = d.to_dict()
    u = j["unexplained"]
    assert u["remains"] and u["after_over_floor"] >= 1.5, d.text()
    assert "UNEXPLAINED" in d.text() and "nothing unmodelled found" not in d.text()
    assert u["field_band_uT"]["rms_norm_nT"] > 0 and u["frequency_band"] is not None
    from magstack.ground.diagnose.figures import write_report
    assert "UNEXPLAINED" in write_report(d, tmp_path).read_text(encoding="utf-8")
    clean = diagnose_model(make(None), "gain_offset").to_dict()
    assert clean["unexplained"]["remains"] is False and clean["unexplained"]["after_over_floor"] < 1.5


def test_block_length_is_chosen_from_the_data_and_a_short_session_can_be_significant():
    s = make("temperature_offset", seconds=300.0, sessions=1)
    d = diagnose_model(s, "gain_offset")
    j = d.to_dict()
    bc = j["method"]["block_choice"]
    assert j["method"]["block_s"] < 60 and bc["n_blocks"] >= 12 and bc["autocorrelation_time_s"] > 0
    assert "blocks of" in d.text()
    assert j["verdict"] == "temperature_offset", d.text()
    # with a block length the data do not allow, the note says what the best candidate closes and why not
    d = diagnose_model(s, "gain_offset", Options(block_s=60.0))
    assert d.verdict == "none"
    assert "temperature_offset, closes" in d.verdict_note and "only 5 held-out blocks" in d.verdict_note, d.verdict_note
    # a long session keeps the 60 s default
    assert diagnose_model(make(None), "gain_offset").to_dict()["method"]["block_s"] == 60.0


def test_hysteresis_with_one_excursion_per_power_cycle_is_not_named_a_per_session_offset():
    # one excursion early in each power cycle, its sign alternating: the remanence of the previous cycle is
    # carried over until it (per-session offsets fit each cycle's constant, but not the rows before it)
    t, b, temp_c, cur, sess, rng, noise = bench(seconds=4000.0, sessions=4)
    b = b.copy()
    for k in range(4):
        t0 = t[sess == k][0] + 200.0
        m = (t > t0) & (t < t0 + 20)
        b[m] = 0.0
        b[m, 0] = (1 if k % 2 == 0 else -1) * 140.0
    dut = b @ G.T
    e = np.where(np.abs(dut[:, 0]) >= 120, np.sign(dut[:, 0]), 0.0)
    last = np.maximum.accumulate(np.where(e != 0, np.arange(t.size), -1))
    state = np.where(last >= 0, e[np.maximum(last, 0)], -1.0)
    dut += np.outer(state, [0.08, 0.03, -0.02])     # the remanence is a vector (cross-axis remanence)
    dut = dut + O + rng.standard_normal(dut.shape) * noise
    s = Session(1.6e9 + t, b + rng.standard_normal(b.shape) * 0.001, dut, temp_c, sess, cur, {"device_id": "test"})
    d = diagnose_model(s, "gain_offset")
    j = d.to_dict()
    assert j["verdict"] == "hysteresis", d.text()
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"], d.text()
    so = next(r for r in j["ranking"] if r["effect"] == "session_offset")
    assert so["rmse_nT"] > j["after_rmse_nT"]


def _first_order_lag(t, x, tau):
    """Plain Euler-exact recursion (not the diagnoser's filter): the die follows the board with tau."""
    y = np.empty_like(x)
    y[0] = x[0]
    for k in range(1, x.size):
        a = np.exp(-(t[k] - t[k - 1]) / tau)
        y[k] = a * y[k - 1] + (1 - a) * x[k]
    return y


def test_thermal_lag_is_named_with_its_time_constant():
    s = make(None, seconds=3600.0)
    die = _first_order_lag(s.t_s, s.temp_c, 150.0)
    s.dut_uT = s.dut_uT + np.outer(die - 25.0, [-0.14, 0.03, 0.05])
    d = diagnose_model(s, "gain_offset")
    j = d.to_dict()
    assert j["verdict"] == "thermal_lag", d.text()
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"], d.text()
    tau = j["parameters"]["tau_s"]
    assert tau["unit"] == "s" and 90.0 <= tau["value"] <= 250.0, tau
    to = next(r for r in j["ranking"] if r["effect"] == "temperature_offset")
    assert to["rmse_nT"] > 1.5 * j["after_rmse_nT"]


# ----------------------------------------------------------------------------- forward gap
def _one_field_thermal(chip="hmc1053", seed=3, seconds=1800.0, tempco=-2.4e-3, k_o=(0.0, 0.0, 0.0)):
    """X held at 44 uT while the unit cools 80 -> 38 degC (like the AV-MagEval thermal run), this file's own numpy
    generator: the sensitivity falls with temperature (``tempco`` /degC on every axis), plus optional
    offset tempcos ``k_o`` uT/degC; DUT noise 30 nT."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 0.5)
    temp = 38.0 + 42.0 * np.exp(-3.0 * t / seconds)
    b = np.tile([44.0, 0.0, 0.0], (t.size, 1))
    gain = 1.0 + tempco * (temp - 25.0)
    dut = (b @ G.T) * gain[:, None] + O + np.outer(temp - 25.0, k_o)
    dut = dut + rng.standard_normal(dut.shape) * 0.03
    ref = b + rng.standard_normal(b.shape) * 0.002
    meta = {"device_id": "thermal"} | ({"dut_chip": chip} if chip else {})
    return Session(1.7e9 + t, ref, dut, temp, np.zeros(t.size, int), {}, meta)


def test_one_field_thermal_run_gets_a_temperature_verdict_in_the_forward_direction():
    s = _one_field_thermal()
    d = diagnose_model(s, "gain_offset")
    j = d.to_dict()
    assert j["gap_direction"].startswith("forward")
    # the calibration direction (ref - model(dut)) measured ~ the noise here: a constant reference lets the
    # fitted gain go to zero; forward, the 4 uT drift is the gap
    assert j["baseline_rmse_nT"] > 20 * j["noise_floor_nT"], d.text()
    assert j["verdict"] == "temperature_gain", d.text()
    assert 1 - j["after_rmse_nT"] / j["baseline_rmse_nT"] >= 0.75
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"], d.text()
    # temperature gain and offset are the same column at one field level: the HMC1053 prior decides
    assert "temperature_offset" in j["confounded_with"]
    checks = {c["effect"]: c for c in j["prior_check"]}
    assert not checks["temperature_offset"]["plausible"] and checks["temperature_offset"]["parameter"] == "K_O[x]"
    assert checks["temperature_gain"]["plausible"]
    assert any("part's physics names temperature_gain" in n for n in j["notes"]), j["notes"]
    assert "prior check (temperature_offset)" in d.text()
    # the forward sensitivity tempco in the simulator's sign: G[x,x] x tempco
    k = j["parameters"]["K_S[x,x]"]
    assert k["value"] == pytest.approx(G[0, 0] * -2.4e-3, rel=0.1)


def test_one_field_base_parameters_the_session_cannot_determine_come_from_the_prior():
    j = diagnose_model(_one_field_thermal(), "gain_offset").to_dict()
    bm = j["base_model"]
    assert bm["chip"] == "hmc1053"
    by = {k: v["determined_by"] for k, v in bm["parameters"].items()}
    # one field level on X: the Y and Z columns of the gain carry no field at all -> prior
    assert by["S[x,y]"] == "prior" and by["S[y,z]"] == "prior"
    assert "S[x,y]" in bm["determined_by_prior"]
    assert bm["parameters"]["S[x,y]"]["prior_sd"] == pytest.approx(0.05)


def test_offset_tempco_at_one_field_is_named_when_the_gain_prior_rules_out_the_gain():
    # an offset tempco of 1 uT/degC at 44 uT would be a sensitivity tempco of 2.3e-2/degC: 35 prior sd on the
    # HMC1053, while 1 uT/degC is beyond its offset tempco prior too -> both implausible: data decide, said
    s = _one_field_thermal(tempco=0.0, k_o=(1.0, 0.0, 0.0))
    j = diagnose_model(s, "gain_offset").to_dict()
    assert j["verdict"] in ("temperature_offset", "temperature_gain")
    assert any("beyond the hmc1053 prior" in n for n in j["notes"]), j["notes"]
    # a generic part (no dut_chip): wide priors cannot decide; the simpler candidate is named, confounded
    g = diagnose_model(_one_field_thermal(chip=None, tempco=0.0, k_o=(0.05, 0.0, 0.0)), "gain_offset").to_dict()
    assert g["verdict"] in ("temperature_offset", "temperature_gain") and g["base_model"]["chip"] == "generic"
    assert not g["distinguishable"]


def test_cli_chip_option_reaches_the_priors(tmp_path):
    s = _one_field_thermal(chip=None)
    p = tmp_path / "thermal.csv"
    write_session(p, s)
    out = _cli("diagnose", str(p), "--chip", "hmc1053", "--json")
    assert out.returncode == 0, out.stderr
    j = json.loads(out.stdout)
    assert j["base_model"]["chip"] == "hmc1053" and j["verdict"] == "temperature_gain"


def test_one_field_thermal_run_with_a_table_fitted_earlier_gets_a_temperature_verdict():
    """The table path (b): a gain+offset table from an earlier bench run (this file's generator, same
    part), then the one-field cooling run; the temperature gain the table lacks is named and closes the gap."""
    from magstack.firmware.cal_table import table_from_fit
    from magstack.firmware.calibration import FitData, FitOptions, fit
    clean = make(None, seed=5, temp=False)
    table = table_from_fit(fit(FitData.from_session(clean), "gain_offset", options=FitOptions(holdout=False)),
                           "test")
    j = _table_diagnosis(_one_field_thermal(seconds=900.0), table).to_dict()
    # the HMC1053 prior rules out the offset tempco the data allow equally (z ~ 18)
    assert j["verdict"] == "temperature_gain", j["ranking"][:3]
    assert 1 - j["after_rmse_nT"] / j["baseline_rmse_nT"] >= 0.75
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"]
