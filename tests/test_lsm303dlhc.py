"""LSM303DLHC magnetometer driver against the register-level simulator (and hardware with --hil)."""
from __future__ import annotations

import math
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.drivers.clock import SystemClock, VirtualClock
from magstack.drivers.errors import (
    BusError,
    BusTimeout,
    ConfigurationError,
    DeviceIdMismatch,
    DeviceNotFound,
    StaleData,
)
from magstack.drivers.lsm303dlhc import LSM303DLHC, LSM303DLHC_TABLE
from magstack.sim.hmc5983_model import HMC5983Model
from magstack.sim.i2c_bus import SimI2CBus
from magstack.sim.i2c_register_model import IdealSensor, default_sensor
from magstack.sim.lsm303dlhc_model import LSM303DLHCModel
from magstack.sim.truth_source import StaticTruth

#: every test runs against the part-faithful simulator and against the strict lints
pytestmark = pytest.mark.usefixtures("sim_profile")


def rig(b_uT=(20.0, -5.0, 40.0), temp_c=25.0, sensor=None, model_temp_offset_c=20.0, **driver_kw):
    clock = VirtualClock()
    truth = StaticTruth(b_uT, temp_c=temp_c)
    model = LSM303DLHCModel(clock, truth, sensor if sensor is not None else IdealSensor(),
                            temp_offset_c=model_temp_offset_c)
    bus = SimI2CBus()
    bus.attach(0x1E, model)
    driver_kw.setdefault("stuck_limit", None)
    return LSM303DLHC(bus, clock, **driver_kw), model, truth, bus, clock


def test_identity_and_defaults():
    d, model, *_ = rig()
    assert d.identity == b"H43<"
    assert (d.range_uT, d.odr_hz, d.mode) == (130.0, 75.0, "continuous")
    assert model.values[0x00] == 0x80 | (6 << 2) and model.values[0x01] == 0x20 and model.values[0x02] == 0


def test_hmc5983_is_not_an_lsm303dlhc_and_absent_chip():
    clock = VirtualClock()
    bus = SimI2CBus()
    with pytest.raises(DeviceNotFound):
        LSM303DLHC(bus, clock)
    bus.attach(0x1E, HMC5983Model(clock, StaticTruth(), IdealSensor()))
    with pytest.raises(DeviceIdMismatch):
        LSM303DLHC(bus, clock)


def test_configure_rejects_invalid_values():
    d, model, *_ = rig()
    with pytest.raises(ValueError, match="130, 190, 250, 400, 470, 560, 810"):
        d.configure(range_uT=88)          # GN=0 exists on the HMC5983 only
    with pytest.raises(ConfigurationError, match="220"):
        d.configure(odr_hz=100)
    with pytest.raises(TypeError):
        d.configure(averaging=8)          # no averaging field on the DLHC


def test_separate_z_gain_and_axis_order():
    d, model, truth, *_ = rig(b_uT=(100.0, 50.0, -100.0))
    s = d.read()
    assert s.extra["raw"] == (1100, 550, -980)
    # X at 0x03/0x04, Z at 0x05/0x06, Y at 0x07/0x08, big-endian
    assert bytes(model.values[0x03:0x09]) == (1100).to_bytes(2, "big") + (-980).to_bytes(2, "big", signed=True) \
        + (550).to_bytes(2, "big")
    assert s.b_uT == pytest.approx((100.0, 50.0, -100.0))


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([r.range_uT for r in LSM303DLHC_TABLE.ranges]), st.data())
def test_in_range_field_round_trips_within_one_lsb(range_uT, data):
    b = data.draw(st.tuples(*[st.floats(-range_uT, range_uT)] * 3))
    d, *_ = rig(b_uT=b, range_uT=range_uT)
    s = d.read()
    lsb = np.asarray(LSM303DLHC_TABLE.range_option(range_uT).uT_per_lsb)
    assert s.valid
    assert np.all(np.abs(np.asarray(s.b_uT) - b) <= lsb)


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([130.0, 810.0]), st.data())
def test_out_of_range_field_is_flagged_never_a_number(range_uT, data):
    axis = data.draw(st.integers(0, 2))
    limit = 2048 / LSM303DLHC_TABLE.range_option(range_uT).lsb_per_gauss[axis] * 100.0
    b = [1.0, -2.0, 3.0]
    b[axis] = data.draw(st.sampled_from([-1.0, 1.0])) * data.draw(st.floats(limit * 1.001, limit * 4))
    d, *_ = rig(b_uT=b, range_uT=range_uT)
    s = d.read()
    assert s.overflow == (axis,) and math.isnan(s.b_uT[axis]) and s.extra["raw"][axis] == -4096


def test_corrupt_code_outside_12_bit_span_is_flagged():
    d, model, *_ = rig()
    d.read()
    model.inject_bit_flip(0x05, 0x40)     # Z high byte bit 6 -> |code| > 2047, not a real measurement
    s = d.read()
    assert 2 in s.overflow and math.isnan(s.b_uT[2])


def test_relative_temperature_with_unit_offset():
    d, *_ = rig(temp_c=30.0, model_temp_offset_c=25.0, temp_offset_c=25.0)
    assert d.read().temp_c == pytest.approx(30.0, abs=0.125)
    d2, *_ = rig(temp_c=30.0, model_temp_offset_c=25.0)      # default 20 degC offset: 5 degC low
    assert d2.read().temp_c == pytest.approx(25.0, abs=0.125)


def test_no_self_test():
    d, *_ = rig()
    assert d.supports_self_test is False
    with pytest.raises(ConfigurationError, match="no documented self-test"):
        d.self_test()


def test_never_same_sample_twice_and_faults():
    d, model, truth, bus, clock = rig(sensor=default_sensor("lsm303dlhc"), stuck_limit=4, timeout_s=0.2)
    seen = []
    for _ in range(20):
        d.read()
        seen.append(model.conversions)
    assert all(b > a for a, b in pairwise(seen))
    bus.inject_nack(0x1E)
    with pytest.raises(BusError):
        d.read()
    model.inject_stuck(range(0x03, 0x09))
    with pytest.raises(StaleData):
        for _ in range(10):
            d.read()
    model.clear_faults()
    model.stop()          # chip stops converting: RDY timing no longer advances
    model.core_set(0x09, 0)
    model.inject_stuck([0x09])
    with pytest.raises(BusTimeout):
        d.read()


def test_reinit_after_power_cycle():
    d, model, *_ = rig()
    d.configure(range_uT=470, odr_hz=30)
    model.reset_registers()
    model.stop()
    d.reinit()
    assert model.values[0x01] == 0xA0 and model.values[0x00] & 0x1C == 5 << 2
    assert d.read().valid


@pytest.mark.hil
def test_hil_lsm303dlhc(request):
    from magstack.drivers.i2c_probe import probe
    from magstack.drivers.registry import open_i2c_bus

    bus = open_i2c_bus(request.config.getoption("--i2c-bus"))
    if not any(r.chip == "lsm303dlhc" for r in probe(bus, (0x1E,))):
        pytest.skip("no LSM303DLHC on the bus")
    d = LSM303DLHC(bus, SystemClock())
    samples = [d.read() for _ in range(20)]
    assert all(s.valid for s in samples)
    assert np.all(np.diff([s.t_s for s in samples]) > 0)
    assert 5.0 < np.linalg.norm(np.mean([s.b_uT for s in samples], axis=0)) < 200.0


def test_single_conversion_mode_returns_to_sleep_without_mr7():
    d, model, *_ = rig(b_uT=(30.0, -20.0, 10.0))
    d.configure(mode="single")
    n0 = model.conversions
    s1, s2 = d.read(), d.read()
    assert model.conversions == n0 + 2 and s2.t_s > s1.t_s
    assert s2.b_uT == pytest.approx((30.0, -20.0, 10.0), abs=100 / 980)
    # back to sleep (MD = 11); MR_REG_M bits 7:2 stay 0 (the HMC5983's MR7 flag is not this part's)
    assert model.values[0x02] == 0x03


def test_non_finite_temperature_offset_is_refused():
    with pytest.raises(ConfigurationError, match="temp_offset_c"):
        rig(temp_offset_c=float("nan"))
    with pytest.raises(ConfigurationError, match="temp_offset_c"):
        rig(model_temp_offset_c=float("inf"))
