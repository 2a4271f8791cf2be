"""HMC5983 driver against the register-level simulator (and real hardware with --hil)."""
from __future__ import annotations

import math
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.drivers.bus.i2c import I2CDevice
from magstack.drivers.clock import SystemClock, VirtualClock
from magstack.drivers.errors import (
    BusError,
    BusTimeout,
    ConfigurationError,
    DeviceIdMismatch,
    DeviceNotFound,
    SelfTestFailed,
    StaleData,
)
from magstack.drivers.hmc5983 import HMC5983, HMC5983_TABLE, HMC5983_TABLE_LATCHED, expected_self_test_counts
from magstack.sim.hmc5983_model import HMC5983Model
from magstack.sim.i2c_bus import SimI2CBus
from magstack.sim.i2c_register_model import IdealSensor, default_sensor
from magstack.sim.lsm303dlhc_model import LSM303DLHCModel
from magstack.sim.truth_source import StaticTruth

#: every test runs against the part-faithful simulator and against the strict lints
pytestmark = pytest.mark.usefixtures("sim_profile")


def rig(b_uT=(20.0, -5.0, 40.0), temp_c=25.0, sensor=None, drdy_latched=False, **driver_kw):
    clock = VirtualClock()
    truth = StaticTruth(b_uT, temp_c=temp_c)
    model = HMC5983Model(clock, truth, sensor if sensor is not None else IdealSensor(), drdy_latched=drdy_latched)
    bus = SimI2CBus()
    bus.attach(0x1E, model)
    driver_kw.setdefault("stuck_limit", None)
    if drdy_latched:
        driver_kw["table"] = HMC5983_TABLE_LATCHED
    return HMC5983(bus, clock, **driver_kw), model, truth, bus, clock


def test_identity_defaults_and_register_values():
    d, model, *_ = rig()
    assert d.identity == b"H43"
    assert (d.range_uT, d.odr_hz, d.averaging, d.mode) == (130.0, 75.0, 1, "continuous")
    assert model.values[0x00] == 0x80 | (6 << 2)    # TS on, 75 Hz, 1 average, normal measurement
    assert model.values[0x01] == 0x20
    assert model.values[0x02] == 0x00


def test_wrong_identity_absent_and_lsm303dlhc_refused():
    clock = VirtualClock()
    bus = SimI2CBus()
    with pytest.raises(DeviceNotFound):
        HMC5983(bus, clock)
    dl = LSM303DLHCModel(clock, StaticTruth(), IdealSensor())
    bus.attach(0x1E, dl)
    with pytest.raises(DeviceIdMismatch, match="LSM303DLHC"):
        HMC5983(bus, clock)
    bus2 = SimI2CBus()
    m = HMC5983Model(clock, StaticTruth(), IdealSensor())
    bus2.attach(0x1E, m)
    m.inject_bit_flip(0x0B, 0x40, count=1)
    with pytest.raises(DeviceIdMismatch):
        HMC5983(bus2, clock)


def test_configure_rejects_invalid_values():
    d, *_ = rig()
    with pytest.raises(ValueError, match="88, 130, 190, 250, 400, 470, 560, 810"):
        d.configure(range_uT=100)
    with pytest.raises(ConfigurationError, match="0.75, 1.5, 3, 7.5, 15, 30, 75, 220"):
        d.configure(odr_hz=80)
    with pytest.raises(ConfigurationError, match="1, 2, 4, 8"):
        d.configure(averaging=3)
    with pytest.raises(ConfigurationError, match="continuous, single, idle"):
        d.configure(mode="fast")


@pytest.mark.parametrize("latched", [False, True])
def test_never_returns_same_sample_twice(latched):
    d, model, *_ = rig(drdy_latched=latched)
    seen = []
    for _ in range(30):
        d.read()
        seen.append(model.conversions)
    assert all(b > a for a, b in pairwise(seen))
    # latched RDY: every conversion is delivered; timed (not latched): none twice, some skipped
    if latched:
        assert seen[-1] - seen[0] == 29


def test_first_set_two_periods_after_mode_write():
    d, model, truth, bus, clock = rig()
    t0 = clock.monotonic_s()
    d.configure(odr_hz=15)
    s = d.read()
    assert s.t_s - t0 >= 2 / 15


def test_gain_change_first_sample_discarded():
    d, model, truth, *_ = rig(b_uT=(50.0, -20.0, 10.0))
    d.read()
    d.configure(range_uT=810)
    s = d.read()
    assert s.extra["raw"][0] == round(50.0 / 100 * 230)
    assert s.b_uT[0] == pytest.approx(50.0, abs=100 / 230)


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([r.range_uT for r in HMC5983_TABLE.ranges]), st.data())
def test_in_range_field_round_trips_within_one_lsb(range_uT, data):
    b = data.draw(st.tuples(*[st.floats(-range_uT, range_uT)] * 3))
    d, *_ = rig(b_uT=b, range_uT=range_uT)
    s = d.read()
    lsb = 100.0 / HMC5983_TABLE.range_option(range_uT).lsb_per_gauss[0]
    assert s.valid
    assert np.all(np.abs(np.asarray(s.b_uT) - b) <= lsb)


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([88.0, 400.0, 810.0]), st.data())
def test_out_of_range_field_is_flagged_never_a_number(range_uT, data):
    limit = 2048 / HMC5983_TABLE.range_option(range_uT).lsb_per_gauss[0] * 100.0
    axis = data.draw(st.integers(0, 2))
    b = [1.0, -2.0, 3.0]
    b[axis] = data.draw(st.sampled_from([-1.0, 1.0])) * data.draw(st.floats(limit * 1.001, limit * 4))
    d, *_ = rig(b_uT=b, range_uT=range_uT)
    s = d.read()
    assert s.overflow == (axis,)
    assert math.isnan(s.b_uT[axis])
    assert s.extra["raw"][axis] == -4096


def test_round_trip_with_preset_noise_model():
    class Recording:
        def __init__(self, inner):
            self.inner, self.last = inner, None

        def sense(self, t_s, truth):
            self.last = np.asarray(self.inner.sense(t_s, truth))
            return self.last

    rec = Recording(default_sensor("hmc5983", seed=1))
    d, *_ = rig(sensor=rec, drdy_latched=True)
    lsb = 100.0 / 1090
    for _ in range(30):
        s = d.read()
        assert np.all(np.abs(np.asarray(s.b_uT) - rec.last) <= lsb)


def test_temperature():
    d, *_ = rig(temp_c=-12.3)
    assert d.read().temp_c == pytest.approx(-12.3, abs=1 / 128)
    d.configure(temperature=False)
    assert d.read().temp_c is None


def test_stale_status_times_out_and_stuck_data_raises():
    d, model, *_ = rig(timeout_s=0.2, drdy_latched=True)
    d.read()
    model.inject_stuck([0x09])
    with pytest.raises(BusTimeout):
        d.read()
    model.clear_faults()
    d2, m2, *_ = rig(sensor=default_sensor("hmc5983"), stuck_limit=4)
    d2.read()
    m2.inject_stuck(range(0x03, 0x09))
    with pytest.raises(StaleData):
        for _ in range(10):
            d2.read()


def test_nack_gives_bus_error():
    d, model, truth, bus, _ = rig()
    bus.inject_nack(0x1E, 2)
    with pytest.raises(BusError):
        d.read()
    with pytest.raises(BusError):
        d.read()
    assert d.read().valid


def test_lock_holds_partially_read_block_and_dow():
    d, model, truth, bus, clock = rig(drdy_latched=True)
    d.read()
    dev = I2CDevice(bus, 0x1E)
    old = bytes(model.values[0x03:0x09])
    truth.b_uT[:] = (60.0, 0.0, 0.0)
    first = dev.read_registers(0x03, 2)          # X only: outputs locked
    assert dev.read_register(0x09) & 0x02
    clock.advance_s(0.05)                          # several conversions while locked
    rest = dev.read_registers(0x05, 4)
    assert first + rest == old                     # one consistent (old) set
    # the held set appears once the block was completed
    assert dev.read_register(0x09) & 0x02 == 0
    assert bytes(model.values[0x03:0x09]) != old
    clock.advance_s(0.02)
    assert dev.read_register(0x09) & 0x10          # DOW: a set was overwritten unread
    s = d.read()
    assert s.b_uT[0] == pytest.approx(60.0, abs=0.1)


def test_self_test_passes_and_fails_when_broken():
    d, model, *_ = rig()
    res = d.self_test()
    assert res.passed and res.counts == (452, 452, 421)     # 1.16/1.16/1.08 G x 390 LSB/G
    assert tuple(expected_self_test_counts()) == res.counts
    assert (d.range_uT, d.odr_hz, d.mode) == (130.0, 75.0, "continuous")
    assert model.values[0x00] & 0x03 == 0
    model.break_self_test()
    with pytest.raises(SelfTestFailed):
        d.self_test()
    model.break_self_test((116.0, 116.0, 108.0))
    # a strong external field saturates the biased measurement (-4096) -> fails
    model.truth.b_uT[:] = (450.0, 0.0, 0.0)
    with pytest.raises(SelfTestFailed, match="overflow"):
        d.self_test()


def test_single_mode_and_reinit():
    d, model, *_ = rig()
    d.configure(mode="single")
    n0 = model.conversions
    d.read()
    d.read()
    assert model.conversions == n0 + 2
    assert model.values[0x02] & 0x03 == 0x03 and model.values[0x02] & 0x80
    d.configure(mode="continuous", range_uT=250)
    model.reset_registers()
    d.reinit()
    assert model.values[0x01] == 0x60 and model.values[0x02] == 0x00
    assert d.read().valid


@pytest.mark.hil
def test_hil_hmc5983(request):
    from magstack.drivers.i2c_probe import probe
    from magstack.drivers.registry import open_i2c_bus

    bus = open_i2c_bus(request.config.getoption("--i2c-bus"))
    if not any(r.chip == "hmc5983" for r in probe(bus, (0x1E,))):
        pytest.skip("no HMC5983 on the bus")
    d = HMC5983(bus, SystemClock())
    samples = [d.read() for _ in range(20)]
    assert all(s.valid for s in samples)
    assert np.all(np.diff([s.t_s for s in samples]) > 0)
    assert 5.0 < np.linalg.norm(np.mean([s.b_uT for s in samples], axis=0)) < 200.0
    assert d.self_test().passed


@pytest.mark.parametrize("latched", [False, True])
def test_dow_flag_reports_lost_samples(latched):
    d, model, *_ = rig(drdy_latched=latched)
    d.read()
    assert d.read().extra["overrun"] is False
    d.clock.sleep_s(4 * d.period_s)          # sets overwritten unread: DOW
    assert d.read().extra["overrun"] is True
    assert d.read().extra["overrun"] is False
