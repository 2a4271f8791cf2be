"""ADS1248 temperature channel of the HMC1053 front end: part of the board table,
unverified diode figures marked as such, and a bench calibration against a reference thermometer."""
from __future__ import annotations

import math

import numpy as np
import pytest

from magstack.data.session import read_session
from magstack.drivers.errors import ConfigurationError
from magstack.drivers.hmc1053 import FRONT_ENDS, TempCalibration, TempChannel
from magstack.sim.hmc1053_bridge import IdealSensor, build_sim_hmc1053
from magstack.sim.truth_source import StaticTruth

#: a simulated ADS1248 whose diode is NOT the forum's 118 mV / 405 uV/degC (the poster measured
#: ~732 mV, falling with temperature): values chosen only to differ clearly
OTHER_DIODE = {"diode_v_at_25c_V": 0.732, "diode_V_per_c": -1.9e-3}


def test_board_tables_carry_the_temperature_channel_and_mark_unverified_figures():
    diode = FRONT_ENDS["hf8.2"].temperature
    assert diode.kind == "adc_diode" and diode.verified is False and "unverified" in diode.source
    assert diode.coefficients() == (0.118, 405e-6)
    ext = FRONT_ENDS["hf8.2-ext-temp"].temperature
    assert (ext.kind, ext.pos, ext.neg, ext.verified) == ("linear", 6, 7, False)


def _rig(temp_c, table="hf8.2", adc_kwargs=None):
    truth = StaticTruth(temp_c=temp_c)
    rig = build_sim_hmc1053(truth=truth, sensor=IdealSensor(), table=table, adc_kwargs=adc_kwargs)
    return rig, truth


def test_two_point_calibration_against_a_reference_recovers_a_part_unlike_the_forum():
    rig, truth = _rig(15.0, adc_kwargs=OTHER_DIODE)
    fe = rig.front_end
    reported, reference = [], []
    for t in (15.0, 35.0):
        truth.temperature_c = t
        s = fe.read()
        assert s.extra["temp_verified"] is False
        reported.append(s.temp_c)
        reference.append(t)                     # the bench thermometer
    assert abs(reported[0] - 15.0) > 100.0       # the forum coefficients are far off for this part
    cal = TempCalibration.fit(reported, reference, source="two-point, bench thermometer")
    fe.calibrate_temperature(cal)
    assert fe.table.temperature.verified and "two-point" in fe.table.temperature.source
    for t in (-10.0, 25.0, 60.0):
        truth.temperature_c = t
        s = fe.read()
        assert s.extra["temp_verified"] is True
        assert s.temp_c == pytest.approx(t, abs=0.02)


def test_external_linear_sensor_on_a_mux_channel_with_its_own_transfer_function():
    tab = FRONT_ENDS["hf8.2-ext-temp"]
    # the board's sensor really has 0.500 V at 25 degC and 19.5 mV/degC, not the table placeholders
    rig, truth = _rig(30.0, table=tab, adc_kwargs=None)
    rig.bridge._temp_v25, rig.bridge._temp_slope = 0.500, 0.0195
    fe = rig.front_end
    reported = []
    temps = (18.0, 24.0, 30.0, 41.0)
    for t in temps:
        truth.temperature_c = t
        reported.append(fe.read().temp_c)
    cal = TempCalibration.fit(reported, temps)
    assert cal.n_points == 4 and cal.rms_c < 0.01
    fe.calibrate_temperature(cal)
    truth.temperature_c = 50.0
    assert fe.read().temp_c == pytest.approx(50.0, abs=0.02)


def test_fit_from_a_session_interpolates_at_the_reference_instants():
    t = np.linspace(0.0, 100.0, 201)
    true_c = 20.0 + 0.1 * t
    reported = 2.0 * true_c - 10.0           # a channel with gain and offset errors
    ref_t = np.array([-5.0, 12.3, 47.9, 88.0, 130.0])   # two readings outside the session are ignored
    cal = TempCalibration.fit_session(t, reported, ref_t, 20.0 + 0.1 * ref_t)
    assert cal.n_points == 3
    assert cal.gain == pytest.approx(0.5) and cal.offset_c == pytest.approx(5.0)
    assert cal.apply(reported[50]) == pytest.approx(true_c[50])
    assert cal.apply(None) is None


@pytest.mark.parametrize("rep, ref, match", [([25.0], [25.0], "at least 2"),
                                             ([25.0, 25.2], [25.0, 26.0], "span"),
                                             ([20.0, 30.0], [25.0, 25.0], "cannot be inverted"),
                                             ([20.0, 30.0], [float("nan"), 1.0], "at least 2"),
                                             ([20.0, 30.0, 40.0], [1.0, 2.0], "reported vs")])
def test_fit_refuses_data_that_cannot_determine_a_line(rep, ref, match):
    with pytest.raises(ConfigurationError, match=match):
        TempCalibration.fit(rep, ref)


def test_channel_transfer_composition_is_exact():
    ch = TempChannel("linear", pos=6, neg=7, v_at_25c_V=0.6, V_per_c=0.01)
    cal = TempCalibration(gain=1.1, offset_c=-2.0, n_points=2, rms_c=0.0, span_c=10.0)
    new = cal.apply_to_channel(ch)
    for v in (0.3, 0.6, 0.9):
        assert new.temp_c(v) == pytest.approx(cal.apply(ch.temp_c(v)))


def test_bench_runner_uses_the_temperature_calibration(tmp_path):
    from magstack.hil.bench import build_sim_bench, run_bench

    sb = build_sim_bench("hmc1053", program="steps_x", seconds=6.0, instrument_name="t_temp_cal")
    cal = TempCalibration(gain=1.0, offset_c=-3.0, n_points=2, rms_c=0.0, span_c=10.0, source="unit test")
    out = tmp_path / "s.csv"
    run_bench(sb.dut, sb.ref, sb.clock, out, seconds=6.0, ref_clock=sb.ref_clock, temp_calibration=cal)
    s = read_session(out)
    assert "unit test" in s.metadata["temp_calibration"]
    dut = np.isfinite(s.dut_uT[:, 0])
    truth_c = sb.truth.temp_c(0.0)
    assert np.all(np.abs(s.temp_c[dut] - (truth_c - 3.0)) < 0.5)
    assert sb.dut.table.temperature.verified

    # a DUT without a board table: the correction is applied to the rows
    sb2 = build_sim_bench("lis3mdl", program="steps_x", seconds=3.0, instrument_name="t_temp_cal2")
    out2 = tmp_path / "s2.csv"
    run_bench(sb2.dut, sb2.ref, sb2.clock, out2, seconds=3.0, ref_clock=sb2.ref_clock, temp_calibration=cal)
    s2 = read_session(out2)
    d2 = np.isfinite(s2.dut_uT[:, 0])
    assert np.all(np.abs(s2.temp_c[d2] - (sb2.truth.temp_c(0.0) - 3.0)) < 0.2)
    assert not any(math.isnan(x) for x in s2.temp_c[d2])
