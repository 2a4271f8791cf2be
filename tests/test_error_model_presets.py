"""Presets reproduce the checkable numbers of their papers (lab study Table 1; Belsten Tables 1-3, sec. 2.3)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from magstack.sim.coil_programs import ProgramTruth, constant_field, constant_temp, piecewise_linear, program
from magstack.sim.error_model import ErrorModel, ErrorParams
from magstack.sim.measurement_sim import simulate_measurement
from magstack.sim.presets import LAB_STUDY_TABLE1, PRESET_NAMES, preset, preset_info
from magstack.sim.truth_source import StaticTruth

DIGITAL = ("lsm303dlhc", "hmc5983", "lis3mdl")
#: Datasheet LSB/G at the lowest range (hardware-facts 1.2, 2.2, 3.2): golden values.
DATASHEET_LSB_PER_G = {"lsm303dlhc": (1100, 1100, 980), "hmc5983": (1370, 1370, 1370), "lis3mdl": (6842,) * 3}


def test_names_and_unknown_preset():
    assert PRESET_NAMES == ("hmc1053", "lis3mdl", "hmc5983", "lsm303dlhc")
    for n in PRESET_NAMES:
        assert isinstance(preset(n), ErrorParams)
        assert preset_info(n).rate_hz > 0
    with pytest.raises(ValueError, match="valid: hmc1053, lis3mdl, hmc5983, lsm303dlhc"):
        preset("hmc5883")


@pytest.mark.parametrize("chip", DIGITAL)
def test_digital_lsb_and_range_are_the_datasheet_values(chip):
    p = preset(chip)
    np.testing.assert_allclose(p.lsb_uT, 100.0 / np.array(DATASHEET_LSB_PER_G[chip]))
    assert p.range_uT == {"lsm303dlhc": 130.0, "hmc5983": 88.0, "lis3mdl": 400.0}[chip]


@pytest.mark.parametrize("chip", DIGITAL)
def test_digital_noise_sigma_matches_lab_study_table1(chip):
    """Zero-field noise in true nT (counts x measured nT/LSB), averaged over quantisation phases."""
    p = preset(chip)
    t1 = LAB_STUDY_TABLE1[chip]
    rate = t1["rate_hz"]
    sens = np.array(t1["sensitivity_nT_per_lsb"])
    if chip == "lis3mdl":  # 1/f part: use the paper's 5 min record length so the slow components count
        t = np.arange(0.0, 300.0, 1.0 / rate)
        out = ErrorModel(p, seed=1, effects=["gain", "noise", "quantization"]).sense_series(t, StaticTruth((0, 0, 0)))
        sigma_nT = (out / p.lsb_uT * sens).std(axis=0)
        np.testing.assert_allclose(sigma_nT, t1["noise_sigma_nT"], rtol=0.15)
        return
    t = np.arange(0.0, 60.0, 1.0 / rate)
    rng = np.random.default_rng(0)
    var = []
    for k in range(12):  # different static fields -> different quantisation phases
        truth = StaticTruth(rng.uniform(-20, 20, 3))
        out = ErrorModel(p, seed=k, effects=["gain", "noise", "quantization"]).sense_series(t, truth)
        var.append((out / p.lsb_uT * sens).var(axis=0))
    np.testing.assert_allclose(np.sqrt(np.mean(var, axis=0)), t1["noise_sigma_nT"], rtol=0.05)


# HMC5983 is left out: Table 1's sigma (54.3 nT at 75 Hz) and its "white" 1 Hz density (11.5 nT/rtHz)
# are mutually inconsistent for a white spectrum (sigma/sqrt(37.5 Hz) = 8.9 nT/rtHz); the preset follows sigma.
@pytest.mark.parametrize("chip", ("lsm303dlhc", "lis3mdl"))
def test_digital_noise_density_at_1hz_matches_lab_study(chip):
    from scipy.signal import welch
    p = preset(chip)
    t1 = LAB_STUDY_TABLE1[chip]
    rate = t1["rate_hz"]
    t = np.arange(0.0, 600.0, 1.0 / rate)
    out = ErrorModel(p, seed=2, effects=["gain", "noise"]).sense_series(t, StaticTruth((0, 0, 0)))
    true_nT = out / p.gain_matrix.diagonal() * 1000.0
    f, pxx = welch(true_nT, fs=rate, nperseg=4096, axis=0)
    near = (f > 0.7) & (f < 1.4)
    if chip != "lis3mdl":  # white: the density is flat; compare directly
        density = np.sqrt(pxx[near].mean(axis=0))
    else:  # 1/f + white: evaluate w + p/f at 1 Hz from the band via a two-term fit
        a = np.column_stack([np.ones(near.sum()), 1.0 / f[near]])
        coef, *_ = np.linalg.lstsq(a, pxx[near], rcond=None)
        density = np.sqrt(coef.sum(axis=0))
    print(chip, "density at 1 Hz (nT/rtHz):", density)
    # paper density (Table 1) vs its sigma: the digital presets follow sigma; density within 25 %
    np.testing.assert_allclose(density, t1["noise_density_1hz_nT"], rtol=0.25)


@pytest.mark.parametrize("chip", DIGITAL)
def test_digital_sensitivity_misalignment_and_tempcos(chip):
    p = preset(chip)
    t1 = LAB_STUDY_TABLE1[chip]
    sens = np.array(t1["sensitivity_nT_per_lsb"])
    # counts per true nT along each axis = 1 / measured sensitivity (Table 1)
    for i in range(3):
        b = np.zeros(3)
        b[i] = 30.0
        out = ErrorModel(p, effects=["gain"]).sense(0.0, StaticTruth(b))
        assert out[i] / p.lsb_uT[i] / 30000.0 == pytest.approx(1.0 / sens[i], rel=1e-9)
    # misalignment: every pair of sensor axes is off 90 deg by the Table 1 median angle
    m = ErrorModel(p, effects=["misalignment"])
    rows = np.array([m.sense(0.0, StaticTruth(np.eye(3)[j])) for j in range(3)]).T  # sensor axes in body frame
    for i, j in ((0, 1), (0, 2), (1, 2)):
        cosang = rows[i] @ rows[j] / np.linalg.norm(rows[i]) / np.linalg.norm(rows[j])
        assert abs(90.0 - math.degrees(math.acos(cosang))) == pytest.approx(t1["misalignment_median_deg"], rel=1e-6)
    # offset temperature drift (nT/K) = Table 1 mean
    mo = ErrorModel(p, effects=["temperature_offset"])
    d = (mo.sense(0.0, StaticTruth((0, 0, 0), temp_c=35.0)) - mo.sense(1.0, StaticTruth((0, 0, 0), temp_c=15.0))) / 20
    np.testing.assert_allclose(d * 1000.0, t1["offset_drift_nT_per_K"], rtol=1e-9)
    # sensitivity drift at 25 degC (pT/LSB/K): S = field / counts, central difference
    mg = ErrorModel(p, effects=["gain", "temperature_gain"])
    b = np.array([30.0, 30.0, 30.0])
    s_of_t = [1e6 * 30.0 / (mg.sense(k, StaticTruth(b, temp_c=tc)) / p.lsb_uT) for k, tc in enumerate((24.5, 25.5))]
    drift_pT = (s_of_t[1] - s_of_t[0]) / 1.0 * 1.0  # pT per LSB per K (1e6: uT -> pT)
    np.testing.assert_allclose(drift_pT, t1["sens_drift_25c_pT_per_lsb_K"], rtol=0.02, atol=0.05)


def test_hmc1053_zero_field_offsets_and_noise_match_belsten_table1():
    p = preset("hmc1053")
    run = simulate_measurement(p, program("zero_field", 120.0, sessions=1), duration_s=120.0, rate_hz=4.0, seed=3)
    delta = run.dut_uT - run.ref_uT
    np.testing.assert_allclose(delta.mean(axis=0), [0.328, 0.034, -0.467], atol=0.004)  # [B T1] average delta
    # [B T1] RMS delta - offset; the simulated reference adds its own noise (z: 6 nT), within 10 %
    np.testing.assert_allclose(delta.std(axis=0), [0.013, 0.024, 0.018], rtol=0.12)


def test_hmc1053_single_axis_gains_match_belsten_table2():
    p = preset("hmc1053")
    for i, axis in enumerate("xyz"):
        run = simulate_measurement(p, program(f"steps_{axis}", 420.0, sessions=1), duration_s=420.0, rate_hz=2.5,
                                   seed=i)
        slope = np.polyfit(run.ref_uT[:, i], run.dut_uT[:, i], 1)[0]
        assert slope == pytest.approx((1.095, 1.120, 1.115)[i], abs=0.002)  # [B T2]


def test_hmc1053_off_axis_coupling_matches_belsten_table3():
    p = preset("hmc1053")
    run = simulate_measurement(p, program("steps_xyz", 1260.0, sessions=1), duration_s=1260.0, rate_hz=2.5, seed=5)
    a = np.column_stack([run.ref_uT, np.ones(len(run.t_s))])
    coef, *_ = np.linalg.lstsq(a, run.dut_uT, rcond=None)
    table3 = np.array([[1.0949, 0.0939, -0.0342], [0.0477, 1.1200, -0.0703], [0.0165, 0.0317, 1.1150]])
    np.testing.assert_allclose(coef[:3], table3, atol=0.002)  # rows incident, columns affected


def test_hmc1053_hysteresis_difference_is_50_nT_after_pm150_uT():
    p = preset("hmc1053")
    d = 100.0
    rows = np.array([[0, 0, 0], [150, 0, 0], [0, 0, 0], [-150, 0, 0], [0, 0, 0]], float)
    tk = [0, 18, 20, 38, 40, 58, 60, 78, 80, 100]
    vals = np.repeat(rows, 2, axis=0)
    truth = ProgramTruth("exc", d, piecewise_linear(tk, vals), constant_temp(25.0))
    run = simulate_measurement(p, truth, duration_s=d, rate_hz=2.5, seed=1)
    delta = run.dut_uT[:, 0] - run.ref_uT[:, 0]
    t = run.t_s
    after_pos = delta[(t > 42) & (t < 58)].mean()
    after_neg = delta[(t > 82) & (t < 100)].mean()
    assert after_pos - after_neg == pytest.approx(0.050, abs=0.006)  # [B s.2.3.4] additional 50 nT


def test_hmc1053_heating_slope_consistent_with_belsten_minus_140_nT_per_degC():
    """Belsten 2.3.3: -140 nT/degC on X with a constant X field (magnitude not stated; bench fields are
    +-50 uT). The datasheet tempco (-2700 ppm/degC) x gain 1.095 at 50 uT gives -148 nT/degC."""
    p = preset("hmc1053")
    truth = program("heating", 1800.0, sessions=1)
    run = simulate_measurement(p, truth, duration_s=1800.0, rate_hz=2.5, seed=0)
    slope = np.polyfit(run.temp_c, run.dut_uT[:, 0], 1)[0]
    assert slope == pytest.approx(-0.140, rel=0.1)
    assert np.ptp(run.temp_c) == pytest.approx(40.0, abs=0.5)


def test_hmc1053_time_skew_is_one_20sps_conversion_per_axis():
    p = preset("hmc1053")
    np.testing.assert_allclose(p.axis_delay_s, [0.0, 0.050822, 0.101644])  # hardware-facts 4.2: 50.822 ms/channel
    # switching it off (as the register-level ADC simulator does) leaves every other effect unchanged
    truth = program("sweeps", 60.0, sessions=1)
    t = np.arange(0, 60, 0.4)
    a = ErrorModel(dataclasses.replace(p, axis_delay_s=(0, 0, 0)), seed=1).sense_series(t, truth)
    b = ErrorModel(p, seed=1, effects=[e for e in ErrorModel(p).enabled if e != "time_skew"]).sense_series(t, truth)
    np.testing.assert_array_equal(a, b)


def test_presets_saturate_at_their_range():
    for n in PRESET_NAMES:
        p = preset(n)
        out = ErrorModel(p).sense(0.0, StaticTruth((3 * p.range_uT, -3 * p.range_uT, 0.0)))
        assert abs(out[0]) <= p.range_uT and abs(out[1]) <= p.range_uT
        assert out[0] > 0.99 * p.range_uT and out[1] < -0.99 * p.range_uT


def test_constant_field_truth_through_each_preset_is_finite():
    truth = ProgramTruth("c", 10.0, constant_field((25.0, -10.0, 40.0)))
    for n in PRESET_NAMES:
        out = ErrorModel(preset(n), seed=0).sense_series(np.linspace(0, 10, 50), truth)
        assert np.isfinite(out).all()
