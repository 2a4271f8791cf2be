"""Calibration without a coil: the hand-rotation truth, the attitude-independent MAP fit, coverage, frame."""
from __future__ import annotations

import numpy as np
import pytest

from magstack.firmware.calibration import scalar_map as sm
from magstack.firmware.calibration.handcal import (
    HandCalData,
    HandCalOptions,
    calibrate,
    find_level_turns,
)
from magstack.firmware.calibration.live_coverage import LiveCoverage
from magstack.firmware.calibration.model import MODELS, CalModel
from magstack.firmware.errors import FitError
from magstack.ground.studies.hand_calibration import CHIPS, holdout_score, score, simulate_session
from magstack.sim.hand_rotation import hand_program


def _fit(sess, **kw):
    opts = HandCalOptions(chip=sess.chip, field_uT=sess.field_uT, **kw)
    return calibrate(HandCalData(sess.dut_uT, sess.temp_c, sess.t_s), opts)


def test_hand_truth_keeps_the_site_field_and_marks_level_turns():
    tr = hand_program("hand", 90.0, seed=3)
    t = np.arange(0, 90, 0.01)
    e = tr.earth_body_series_uT(t)
    assert np.ptp(np.linalg.norm(e, axis=1)) < 1e-9                 # attitude only turns it
    assert 45 < np.linalg.norm(tr.field_world_uT) < 55              # IGRF at the default site
    lv = tr.level_turn_series(t)
    assert lv.sum() > 300
    # in a level turn body z is vertical: the field's z component in the board frame is constant
    assert np.ptp(np.abs(e[lv, 2])) < 0.01 * np.linalg.norm(tr.field_world_uT)
    # scalar and series agree; the laptop adds field only while it is there
    assert np.allclose(tr.field_uT(12.3), tr.field_series_uT(np.array([12.3]))[0])
    lap = hand_program("hand_laptop", 90.0, seed=3)
    d = lap.disturbed_series(t)
    assert d.any() and not d.all()
    assert np.abs(lap.laptop_world_uT(t[~d])).max() == 0 and np.abs(lap.laptop_world_uT(t[d])).max() > 0.5


def test_gauge_parametrisation_and_prior():
    m = CalModel(MODELS["eq3"], t0_c=25.0, name="eq3")
    par = sm.parametrise(m, "symmetric")
    assert par.q == 18 and "S[x,y]" in par.names and "S[y,x]" not in par.names
    phi = np.arange(par.q, dtype=float)
    th = par.theta(phi)
    S = m.unpack(th)["S"]
    assert np.allclose(S, S.T)
    assert sm.parametrise(m, "diagonal").q == 12
    with pytest.raises(FitError):
        sm.parametrise(CalModel(MODELS["eq3"] + ("cubic",), name="x"))


@pytest.mark.parametrize("chip", CHIPS)
def test_fit_reaches_the_noise_floor_and_the_hard_iron_within_its_posterior(chip):
    sess = simulate_session(chip, "hand", seed=5, duration_s=90.0)
    res = _fit(sess)
    assert res.ok and res.model.name == "eq3"
    h = holdout_score(sess, res)
    assert h["ratio"] < 1.2, h
    assert np.max(np.abs(h["offset_z"])) < 3.5, h
    # the rotation the magnitude cannot see is named, not claimed
    assert "UNDETERMINED" in res.report() and "rotation" in res.frame.undetermined
    assert h["hidden_rotation_deg"] > 0.3                            # there is one to hide (misalignment)


def test_temperature_span_fits_the_temperature_terms_and_the_laptop_is_screened_out():
    warm = simulate_session("lis3mdl", "hand_warm", seed=2, duration_s=150.0)
    res = _fit(warm)
    rows = {r["param"]: r for r in res.parameter_rows()}
    assert rows["K_O[x]"]["determined_by"] == "data"
    assert holdout_score(warm, res)["ratio"] < 1.2
    lap = simulate_session("hmc5983", "hand_laptop", seed=2)
    res = _fit(lap)
    truth_disturbed = lap.truth.disturbed_series(lap.t_s)
    flagged = ~res.used
    assert flagged.sum() > 0.5 * truth_disturbed.sum()              # most laptop rows excluded
    assert (flagged & ~truth_disturbed).sum() < 0.05 * len(flagged)  # few clean rows lost
    assert holdout_score(lap, res)["ratio"] < 1.2


def test_flat_run_is_refused_and_says_why():
    sess = simulate_session("hmc5983", "hand_flat", seed=1)
    res = _fit(sess)
    assert res.refused
    assert any("cover" in r for r in res.refused)
    ok = _fit(sess, allow_poor_coverage=True)
    assert ok.ok and any("poor coverage accepted" in n for n in ok.notes)


def test_estimated_magnitude_says_the_scale_is_relative():
    sess = simulate_session("hmc5983", "hand", seed=4, duration_s=80.0)
    res = calibrate(HandCalData(sess.dut_uT, sess.temp_c, sess.t_s), HandCalOptions(chip="hmc5983"))
    assert res.scale == "relative" and "RELATIVE" in res.report()
    F = res.posterior.phi[-1]
    assert res.posterior.determined_by(len(res.posterior.phi) - 1) != "fixed"
    # the shape is right: |B_cal| / F is constant to the noise, whatever F is
    mag = np.linalg.norm(res.apply(sess.dut_uT, sess.temp_c), axis=1)
    assert np.std(mag / F) < 0.01


def test_level_turns_fix_the_tilt_and_the_heading_error_is_at_the_floor():
    sess = simulate_session("lsm303dlhc", "hand", seed=7, duration_s=90.0)
    res = _fit(sess)
    assert res.frame.kind == "level" and res.frame.turns
    sc = score(sess, res.apply(sess.dut_uT, sess.temp_c))
    assert sc["heading_sd_deg"] < 1.5 * sc["heading_floor_deg"]
    sensor = _fit(sess, frame="sensor")
    assert sensor.frame.kind == "sensor" and "3 angles" in sensor.frame.undetermined
    turns = find_level_turns(res.apply(sess.dut_uT, sess.temp_c), sess.t_s)
    assert all(t.sweep_deg >= 300 for t in turns)


def test_table_is_the_flight_format_with_a_posterior_and_validity(tmp_path):
    from magstack.firmware.cal_table import load_table, save_table, validate
    from magstack.firmware.float_applier import apply_float

    sess = simulate_session("hmc5983", "hand", seed=1, duration_s=80.0)
    res = _fit(sess)
    tab = res.table("dev-1")
    assert validate(tab).ok and tab.posterior is not None
    p = save_table(tab, tmp_path / "cal.json")
    back = load_table(p)
    out, _ = apply_float(back, sess.dut_uT, sess.temp_c)
    assert np.allclose(out, res.apply(sess.dut_uT, sess.temp_c), atol=1e-9)
    assert tab.validity_temp_c[0] < np.mean(sess.temp_c) < tab.validity_temp_c[1]


def test_live_coverage_recovers_cells_despite_a_large_hard_iron():
    sess = simulate_session("lis3mdl", "hand", seed=2, duration_s=60.0)
    lc = LiveCoverage()
    for b in sess.dut_uT:
        lc.add(b)
    st = lc.state()
    res = _fit(sess)
    from magstack.firmware.calibration.handcal import SphereCoverage

    final = SphereCoverage.of(res.apply(sess.dut_uT, sess.temp_c))
    assert st.shape == "ellipsoid"
    assert abs(st.cells_filled - final.cells_filled) <= 0.15 * final.cells_filled
    # raw directions, with the board's offsets, would say otherwise
    raw = SphereCoverage.of(sess.dut_uT)
    assert abs(raw.cells_filled - final.cells_filled) > abs(st.cells_filled - final.cells_filled)
