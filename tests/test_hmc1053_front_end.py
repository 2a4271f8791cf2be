"""HMC1053 front end on the simulated ADS1248: offset removal, timing, skew, faults, factory."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.drivers.ads1248 import ADS1248, DATA_RATES
from magstack.drivers.errors import BusError, BusTimeout, ConfigurationError, ReadbackMismatch
from magstack.drivers.hmc1053 import FRONT_ENDS, FrontEndTable, TempChannel
from magstack.drivers.magnetometer import Magnetometer
from magstack.sim.hmc1053_bridge import HMC1053Bridge, IdealSensor, build_sim_hmc1053
from magstack.sim.truth_source import StaticTruth

T20 = DATA_RATES[20].first_after_write_s  # 50.822 ms [TI-DS Table 16]
SETTLE = FRONT_ENDS["hf8.2"].strap_settle_s
LSB_UT = 2.048 / 128 / (2**23 - 1) / (3.3 * 1e-3 / 100)  # one ADC LSB in uT at PGA 128, 3.3 V, 1 mV/V/G


class RampTruth(StaticTruth):
    """Field changing linearly in time: b0 + rate * t."""

    def __init__(self, b0_uT, rate_uT_per_s, temp_c=25.0):
        super().__init__(b0_uT, temp_c)
        self.rate = np.asarray(rate_uT_per_s, dtype=float)

    def field_uT(self, t_s):
        return self.b_uT + self.rate * t_s


def ideal_rig(b_uT=(20.0, -5.0, 40.0), offsets=(0.4, -0.9, 1.2), table="hf8.2", truth=None, **kw):
    truth = truth if truth is not None else StaticTruth(b_uT)
    bridge_kwargs = dict(offset_mV_per_V=offsets, **kw.pop("bridge_kwargs", {}))
    return build_sim_hmc1053(truth=truth, sensor=IdealSensor(), table=table, bridge_kwargs=bridge_kwargs, **kw)


def test_front_end_is_a_magnetometer():
    rig = ideal_rig()
    assert isinstance(rig.front_end, Magnetometer) and rig.front_end.data_ready()


def test_recovers_field_and_reports_bridge_offset_telemetry():
    rig = ideal_rig()
    s = rig.front_end.read()
    assert s.b_uT == pytest.approx((20.0, -5.0, 40.0), abs=2 * LSB_UT)
    assert s.extra["bridge_offset_mV_per_V"] == pytest.approx((0.4, -0.9, 1.2), abs=1e-5)
    assert s.temp_c == pytest.approx(25.0, abs=0.01)
    assert s.valid and s.overflow == ()
    assert rig.bridge.set_pulses == rig.bridge.reset_pulses == 1


@settings(max_examples=60, deadline=None)
@given(offsets=st.tuples(*[st.floats(-1.25, 1.25)] * 3), field=st.tuples(*[st.floats(-200.0, 200.0)] * 3))
def test_recovered_field_independent_of_bridge_offset(offsets, field):
    with_offset = ideal_rig(field, offsets).front_end.read()
    without = ideal_rig(field, (0.0, 0.0, 0.0)).front_end.read()
    assert with_offset.b_uT == pytest.approx(field, abs=2 * LSB_UT)
    assert np.max(np.abs(np.subtract(with_offset.b_uT, without.b_uT))) <= 2 * LSB_UT
    assert with_offset.extra["bridge_offset_mV_per_V"] == pytest.approx(offsets, abs=1e-5)


def test_single_polarity_reading_would_carry_the_offset():
    # the offset is far larger than the field: only the set/reset difference removes it
    s = ideal_rig((1.0, 1.0, 1.0), (1.2, 1.2, 1.2)).front_end.read()
    v_set_uT = np.array(s.extra["v_set_V"]) / (3.3e-3 / 100)
    assert np.all(v_set_uT > 100.0)
    assert s.b_uT == pytest.approx((1.0, 1.0, 1.0), abs=2 * LSB_UT)


# ---------------------------------------------------------------- timing (datasheet arithmetic)

@pytest.mark.parametrize("table, n_conv", [("hf8.2", 7), ("hf8.2-8conv", 8)])
def test_vector_period_at_20_sps(table, n_conv):
    rig = ideal_rig(table=table)
    fe = rig.front_end
    samples = [fe.read() for _ in range(4)]
    period = n_conv * T20 + 2 * SETTLE
    assert fe.table.nominal_cycle_s() == pytest.approx(period)
    for a, b in zip(samples[:-1], samples[1:], strict=True):
        assert b.t_s - a.t_s == pytest.approx(period, abs=1e-9)
        assert b.extra["cycle_start_s"] - a.extra["cycle_start_s"] == pytest.approx(period, abs=1e-9)
    # 8 conversions x 50.822 ms = 0.4066 s, the paper's ~0.4 s; 7 conversions = 0.3558 s
    assert period == pytest.approx({7: 0.355854, 8: 0.406676}[n_conv], abs=1e-6)


def test_per_axis_instants_and_skew_at_20_sps():
    rig = ideal_rig()
    s = rig.front_end.read()
    t0 = s.extra["cycle_start_s"]
    for k in range(3):
        assert s.extra["axis_t_set_s"][k] - t0 == pytest.approx(SETTLE + (k + 0.5) * T20, abs=1e-9)
        assert s.extra["axis_t_reset_s"][k] - t0 == pytest.approx(2 * SETTLE + (k + 3.5) * T20, abs=1e-9)
        assert s.axis_t_s[k] == pytest.approx(0.5 * (s.extra["axis_t_set_s"][k] + s.extra["axis_t_reset_s"][k]))
    assert s.axis_t_s[1] - s.axis_t_s[0] == pytest.approx(T20, abs=1e-9)  # 50.822 ms
    assert s.axis_t_s[2] - s.axis_t_s[0] == pytest.approx(2 * T20, abs=1e-9)  # 101.644 ms
    assert s.t_s == pytest.approx(s.axis_t_s[1])
    assert s.extra["temp_t_s"][0] - t0 == pytest.approx(2 * SETTLE + 6.5 * T20, abs=1e-9)


@pytest.mark.parametrize("sps", [5, 10, 40, 160, 640, 2000])
def test_other_data_rates(sps):
    table = FrontEndTable(f"r{sps}", data_rate_sps=sps)
    rig = ideal_rig(table=table)
    a, b = rig.front_end.read(), rig.front_end.read()
    t = DATA_RATES[sps].first_after_write_s
    assert b.t_s - a.t_s == pytest.approx(7 * t + 2 * SETTLE, abs=1e-9)
    assert a.axis_t_s[1] - a.axis_t_s[0] == pytest.approx(t, abs=1e-9)
    assert a.b_uT == pytest.approx((20.0, -5.0, 40.0), abs=2 * LSB_UT)


def test_axis_times_are_the_instants_the_field_is_measured_at():
    # a ramping field: each axis must read the field at its own reported instant, not at t_s
    rate = np.array([50.0, -30.0, 20.0])  # uT/s
    rig = ideal_rig(truth=RampTruth((10.0, 10.0, 10.0), rate))
    for _ in range(3):
        s = rig.front_end.read()
        expect = [10.0 + rate[k] * s.axis_t_s[k] for k in range(3)]
        assert s.b_uT == pytest.approx(expect, abs=2 * LSB_UT)
        at_t_s = 10.0 + rate * s.t_s
        assert abs(s.b_uT[0] - at_t_s[0]) > 1.0  # skew is real: 50 uT/s * 50.8 ms = 2.5 uT


# ---------------------------------------------------------------- DRDY discipline

@pytest.mark.parametrize("sps", [5, 20, 320, 2000])
def test_driver_never_reads_before_drdy(sps):
    rig = build_sim_hmc1053(table=FrontEndTable(f"r{sps}", data_rate_sps=sps), seed=3)
    for _ in range(5):
        rig.front_end.read()
    m = rig.adc_model
    assert m.reads_before_drdy == 0 and m.blended_reads == 0
    assert rig.adc.conversions == 5 * 7 == m.sample_calls
    assert rig.bridge.sense_calls == 5 * 6  # sense() once per bridge conversion


class HastyADS1248(ADS1248):
    """A buggy driver that reads right after the MUX write (no DRDY wait)."""

    def wait_drdy(self, t_from_s, expected_s, timeout_s=None):
        self.clock.sleep_s(expected_s * 0.25)
        return self.clock.monotonic_s()


def test_simulator_catches_a_driver_that_reads_before_drdy():
    rig = ideal_rig()
    good = rig.front_end.read()
    m = rig.adc_model
    hasty = HastyADS1248(rig.spi, rig.clock, start=m.start_line, drdy=m.drdy_line, reset=m.reset_line)
    hasty.reset = lambda: None
    from magstack.drivers.hmc1053 import HMC1053

    fe = HMC1053(hasty, rig.bridge.strap_line, rig.clock, "hf8.2", reset_adc=False)
    bad = fe.read()
    # every read is early; the 6 bridge reads blend channels, the temperature read returns the
    # previous (same-channel) temperature result unchanged
    assert m.reads_before_drdy == 7 and m.blended_reads == 6
    assert np.max(np.abs(np.subtract(bad.b_uT, good.b_uT))) > 1.0


# ---------------------------------------------------------------- faults and odd inputs

def test_spi_error_propagates_and_next_cycle_recovers():
    rig = ideal_rig()
    fe = rig.front_end
    fe.read()
    rig.spi.inject_fault()
    orig = fe.adc.convert
    calls = {"n": 0}

    def convert_then_fault(ch):  # fail in the middle of the cycle, after the SET pulse
        calls["n"] += 1
        if calls["n"] == 2:
            rig.spi.inject_fault()
        return orig(ch)

    rig.spi._fail_next = 0
    fe.adc.convert = convert_then_fault
    with pytest.raises(BusError, match="injected SPI fault"):
        fe.read()
    fe.adc.convert = orig
    s = fe.read()
    assert s.b_uT == pytest.approx((20.0, -5.0, 40.0), abs=2 * LSB_UT)


def test_drdy_never_asserting_is_a_timeout_not_a_hang():
    rig = ideal_rig()
    rig.adc_model.drdy_stuck_high = True
    t0 = rig.clock.monotonic_s()
    with pytest.raises(BusTimeout):
        rig.front_end.read()
    assert rig.clock.monotonic_s() - t0 < 0.2


def test_register_readback_mismatch_is_typed():
    rig = ideal_rig()
    rig.adc_model.inject_stuck_bits(0x00, 0x10, 0x00)  # MUX_SP bit 1 stuck low: Y (MUX0 0x13) reads 0x03
    with pytest.raises(ReadbackMismatch, match="MUX0.*0x13.*0x03"):
        rig.front_end.read()


def test_overflow_axis_is_nan_and_flagged():
    # Z: 1.2 mV/V offset + 400 uT * 3.3 mV/G... exceeds the +-16 mV PGA-128 range
    rig = ideal_rig((20.0, -5.0, 450.0), (0.0, 0.0, 1.2))
    s = rig.front_end.read()
    assert s.overflow == (2,) and not s.valid and math.isnan(s.b_uT[2])
    assert s.b_uT[:2] == pytest.approx((20.0, -5.0), abs=2 * LSB_UT)


def test_temperature_follows_truth_with_internal_diode():
    rig = ideal_rig(truth=StaticTruth((1.0, 2.0, 3.0), temp_c=-20.0))
    assert rig.front_end.read().temp_c == pytest.approx(-20.0, abs=0.01)


def test_internal_diode_takes_a_per_board_calibration():
    """The diode coefficients are forum values [F2]; a table can carry the board's own calibration."""
    truth = StaticTruth((1.0, 2.0, 3.0), temp_c=40.0)
    # the simulated diode follows the forum values: a calibration 4 mV higher at 25 degC reads
    # 4 mV / 405 uV/degC lower
    cal = FrontEndTable("diode-cal", temperature=TempChannel("adc_diode", v_at_25c_V=0.122, V_per_c=405e-6))
    assert ideal_rig(truth=truth, table=cal).front_end.read().temp_c == pytest.approx(40.0 - 4e-3 / 405e-6,
                                                                                       abs=0.01)
    with pytest.raises(ConfigurationError, match="both v_at_25c_V and V_per_c"):
        FrontEndTable("half", temperature=TempChannel("adc_diode", v_at_25c_V=0.12)).validate()


def test_linear_temperature_sensor_table_and_ratiometric_reference():
    table = FrontEndTable("lin", reference="REF0", temperature=TempChannel("linear", 6, 7, 1, 0.75, 0.01),
                          temp_in_both_states=True)
    rig = ideal_rig(truth=StaticTruth((30.0, -40.0, 5.0), temp_c=70.0), table=table)
    s = rig.front_end.read()
    assert s.temp_c == pytest.approx(70.0, abs=0.01)
    lsb = 3.3 / 128 / (2**23 - 1) / (3.3e-3 / 100)
    assert s.b_uT == pytest.approx((30.0, -40.0, 5.0), abs=2 * lsb)
    assert len(s.extra["temp_t_s"]) == 2


def test_sensitivity_mismatch_shows_as_gain():
    rig = ideal_rig(bridge_kwargs=dict(sensitivity_mV_per_V_per_G=(1.1, 1.0, 0.9)))
    assert rig.front_end.read().b_uT == pytest.approx((22.0, -5.0, 36.0), abs=3 * LSB_UT)


@pytest.mark.parametrize("changes, word", [
    (dict(axis_pins=((0, 1), (1, 2), (4, 5))), "distinct"),
    (dict(pga=3), "PGA"), (dict(data_rate_sps=25), "data rate"),
    (dict(sensitivity_mV_per_V_per_G=(1.0, 0.0, 1.0)), "sensitivity"),
    (dict(excitation_V=float("nan")), "excitation_V"),
    (dict(temperature=TempChannel("thermocouple")), "temperature kind"),
    (dict(temperature=TempChannel("linear", v_at_25c_V=float("nan"), V_per_c=0.01)), "v_at_25c_V"),
])
def test_bad_table_entries_raise_configuration_error(changes, word):
    with pytest.raises(ConfigurationError, match=word):
        ideal_rig().front_end.with_table(**changes)


def test_unknown_table_name():
    with pytest.raises(ConfigurationError, match="hf8.2"):
        build_sim_hmc1053(table="nope")


def test_bridge_rejects_unwired_pins_and_bad_parameters():
    truth = StaticTruth()
    with pytest.raises(ConfigurationError):
        HMC1053Bridge(truth, sensor=IdealSensor(), offset_mV_per_V=(0.0, float("nan"), 0.0))
    for kw, word in ((dict(excitation_V=float("inf")), "excitation_V"),
                     (dict(external_gain=float("nan")), "external_gain"),
                     (dict(offset_tempco_per_c=float("nan")), "offset_tempco_per_c"),
                     (dict(temp_pins=(6, 7), temp_v_at_25c_V=float("nan"), temp_V_per_c=0.01), "temp_v_at_25c_V"),
                     (dict(temp_pins=(6, 7), temp_V_per_c=0.0), "temp_V_per_c")):
        with pytest.raises(ConfigurationError, match=word):
            HMC1053Bridge(truth, sensor=IdealSensor(), **kw)
    br = HMC1053Bridge(truth, sensor=IdealSensor())
    with pytest.raises(BusError, match="not a wired pair"):
        br.differential_V(6, 7, 0.0)
    assert br.differential_V(1, 0, 0.0) == pytest.approx(-br.differential_V(0, 1, 0.0))


def test_default_sensor_is_the_shared_error_model():
    rig = build_sim_hmc1053(seed=1)
    from magstack.sim.error_model import ErrorModel

    assert isinstance(rig.bridge.sensor, ErrorModel)
    assert not {"time_skew", "quantization", "saturation"} & rig.bridge.sensor.enabled
    b = np.array([rig.front_end.read().b_uT for _ in range(10)])
    truth = np.array([20.0, -5.0, 40.0])
    assert np.all(np.abs(b.mean(axis=0) - truth) < 0.1 * np.abs(truth).max())
    assert np.all(b.std(axis=0) > 0)  # noise from the error model reaches the output


def test_default_sensor_output_noise_and_offset_reproduce_the_preset():
    # the preset describes the reported value; the set/reset half-difference of two conversions
    # must come out with the preset's white sigma and keep its (magnetic) offset
    from magstack.sim.presets import preset

    p = preset("hmc1053")
    rig = build_sim_hmc1053(seed=7, truth=StaticTruth((0.0, 0.0, 0.0)))
    b = np.array([rig.front_end.read().b_uT for _ in range(300)])
    sigma = np.asarray(p.noise_white_uT)
    assert b.std(axis=0) == pytest.approx(sigma, rel=0.2)
    assert np.all(np.abs(b.mean(axis=0) - np.asarray(p.offset_uT)) < 5 * sigma / np.sqrt(len(b)))


def test_falling_edge_strap_circuit_recovers_the_field_with_its_sign():
    """A table with ``set_on_rising_edge=False`` drives an inverted pulse circuit; the simulated rig
    follows the table, so the field keeps its sign (it was silently negated before)."""
    import dataclasses

    tab = dataclasses.replace(FRONT_ENDS["hf8.2"], name="falling-edge", set_on_rising_edge=False)
    rig = ideal_rig(b_uT=(10.0, -20.0, 30.0), table=tab)
    s = rig.front_end.read()
    assert s.b_uT == pytest.approx((10.0, -20.0, 30.0), abs=3 * LSB_UT)
    assert rig.bridge.set_pulses == rig.bridge.reset_pulses == 1
    assert rig.bridge.strap_line.level is True          # idles high: SET is the falling edge
