"""LIS3MDL driver against the register-level simulator (and real hardware with --hil)."""
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
    ReadbackMismatch,
    SelfTestFailed,
    StaleData,
)
from magstack.drivers.lis3mdl import LIS3MDL, LIS3MDL_TABLE
from magstack.sim.i2c_bus import SimI2CBus
from magstack.sim.i2c_register_model import IdealSensor, default_sensor
from magstack.sim.lis3mdl_model import LIS3MDLModel
from magstack.sim.lsm303dlhc_model import LSM303DLHCModel
from magstack.sim.truth_source import StaticTruth

#: every test runs against the part-faithful simulator and against the strict lints
pytestmark = pytest.mark.usefixtures("sim_profile")


class Recording:
    """Wraps a sensor and remembers the last sensed value (uT)."""

    def __init__(self, inner):
        self.inner = inner
        self.last = None

    def sense(self, t_s, truth):
        self.last = np.asarray(self.inner.sense(t_s, truth), dtype=float)
        return self.last


def rig(b_uT=(20.0, -5.0, 40.0), temp_c=25.0, sensor=None, **driver_kw):
    clock = VirtualClock()
    truth = StaticTruth(b_uT, temp_c=temp_c)
    model = LIS3MDLModel(clock, truth, sensor if sensor is not None else IdealSensor())
    bus = SimI2CBus()
    bus.attach(0x1C, model)
    driver_kw.setdefault("stuck_limit", None)
    return LIS3MDL(bus, clock, **driver_kw), model, truth, bus, clock


def test_identity_and_defaults():
    d, model, *_ = rig()
    assert d.identity == b"\x3d"
    assert (d.range_uT, d.odr_hz, d.performance, d.mode) == (400.0, 80.0, "ultra", "continuous")
    # written configuration matches the table: OM=UHP, DO=80 Hz, TEMP_EN; OMZ=UHP; BDU; continuous
    assert model.values[0x20] == 0x80 | 0x60 | 0x1C
    assert model.values[0x23] == 0x0C
    assert model.values[0x24] == 0x40
    assert model.values[0x22] & 0x03 == 0


def test_wrong_identity_and_absent_chip():
    clock = VirtualClock()
    bus = SimI2CBus()
    model = LIS3MDLModel(clock, StaticTruth(), IdealSensor())
    bus.attach(0x1C, model)
    model.inject_bit_flip(0x0F, 0x01, count=1)
    with pytest.raises(DeviceIdMismatch, match="0x0f"):
        LIS3MDL(bus, clock)
    with pytest.raises(DeviceNotFound):
        LIS3MDL(bus, clock, address=0x1E)
    # an LSM303DLHC at 0x1E answers 0x3C at 0x0F: not a LIS3MDL
    bus.attach(0x1E, LSM303DLHCModel(clock, StaticTruth(), IdealSensor()))
    with pytest.raises(DeviceIdMismatch):
        LIS3MDL(bus, clock, address=0x1E)
    with pytest.raises(ConfigurationError, match="0x1c, 0x1e"):
        LIS3MDL(bus, clock, address=0x1D)
    with pytest.raises(ConfigurationError, match="timeout_s"):
        LIS3MDL(bus, clock, timeout_s=float("nan"))
    with pytest.raises(ConfigurationError, match="stuck_limit"):
        LIS3MDL(bus, clock, stuck_limit=0)


def test_configure_rejects_invalid_values_naming_valid_ones():
    d, *_ = rig()
    with pytest.raises(ValueError, match="400, 800, 1200, 1600"):
        d.configure(range_uT=500)
    with pytest.raises(ConfigurationError, match="0.625, 1.25, 2.5, 5, 10, 20, 40, 80, 155, 300, 560, 1000"):
        d.configure(odr_hz=100)
    with pytest.raises(ConfigurationError, match="low, medium, high, ultra"):
        d.configure(performance="max")
    with pytest.raises(ConfigurationError, match="requires performance 'low'"):
        d.configure(odr_hz=1000, performance="ultra")
    with pytest.raises(ConfigurationError, match="odr_hz <= 80"):
        d.configure(odr_hz=560, mode="single")
    assert d.range_uT == 400.0


def test_fast_rate_sets_performance_and_timing():
    d, model, *_ = rig()
    d.configure(odr_hz=1000)
    assert d.performance == "low"
    assert model.values[0x20] & 0x7E == 0x0E     # OM=LP, DO=011 (ignored), FAST_ODR
    t = [d.read().t_s for _ in range(20)]
    assert np.all(np.diff(t) > 0)
    assert np.median(np.diff(t)) == pytest.approx(1e-3, rel=0.05)


def test_never_returns_same_sample_twice():
    d, model, *_ = rig()
    seen = []
    for _ in range(30):
        d.read()
        seen.append(model.conversions)
    assert all(b > a for a, b in pairwise(seen))
    assert not d.data_ready()


def test_temperature_and_range_scaling():
    d, model, truth, *_ = rig(b_uT=(123.4, -56.7, 300.0), temp_c=31.3)
    s = d.read()
    assert s.temp_c == pytest.approx(31.25)          # 8 LSB/degC
    assert s.extra["raw"][0] == round(123.4 / 100 * 6842)
    d.configure(range_uT=1600)
    s = d.read()
    assert s.extra["raw"][2] == round(300.0 / 100 * 1711)
    assert s.b_uT[2] == pytest.approx(300.0, abs=100 / 1711)
    d.configure(temperature=False)
    assert d.read().temp_c is None


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([400.0, 800.0, 1200.0, 1600.0]), st.data())
def test_in_range_field_round_trips_within_one_lsb(range_uT, data):
    b = data.draw(st.tuples(*[st.floats(-range_uT, range_uT)] * 3))
    d, *_ = rig(b_uT=b, range_uT=range_uT)
    s = d.read()
    lsb = 100.0 / LIS3MDL_TABLE.range_option(range_uT).lsb_per_gauss[0]
    assert s.valid
    assert np.all(np.abs(np.asarray(s.b_uT) - b) <= lsb)


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([400.0, 1600.0]), st.data())
def test_out_of_range_field_is_flagged_never_a_number(range_uT, data):
    limit = 32768 / LIS3MDL_TABLE.range_option(range_uT).lsb_per_gauss[0] * 100.0
    big = data.draw(st.floats(limit * 1.001, limit * 5))
    sign = data.draw(st.sampled_from([-1.0, 1.0]))
    axis = data.draw(st.integers(0, 2))
    b = [10.0, -10.0, 5.0]
    b[axis] = sign * big
    d, *_ = rig(b_uT=b, range_uT=range_uT)
    s = d.read()
    assert axis in s.overflow and not s.valid
    assert math.isnan(s.b_uT[axis])
    assert s.extra["mroi"]


def test_round_trip_with_preset_noise_model():
    """Through the lab-study error model: the driver returns the sensed value to within 1 LSB."""
    rec = Recording(default_sensor("lis3mdl", seed=3))
    d, *_ = rig(b_uT=(20.0, 30.0, -40.0), sensor=rec)
    lsb = 100.0 / 6842
    values = []
    for _ in range(50):
        s = d.read()
        assert np.all(np.abs(np.asarray(s.b_uT) - rec.last) <= lsb)
        values.append(s.b_uT)
    assert np.std(np.asarray(values)[:, 0]) > 0.05       # lab-study noise is visible (sigma ~0.33 uT)


def test_stale_data_times_out():
    d, model, *_ = rig(timeout_s=0.1)
    d.read()
    model.inject_stuck([0x27])          # STATUS frozen with ZYXDA clear
    with pytest.raises(BusTimeout) as e:
        d.read()
    assert isinstance(e.value, BusError) and e.value.address == 0x1C


def test_stuck_data_registers_raise_stale_data():
    d, model, *_ = rig(sensor=default_sensor("lis3mdl"), stuck_limit=5)
    d.read()
    model.inject_stuck(range(0x28, 0x2E))
    with pytest.raises(StaleData, match="identical"):
        for _ in range(10):
            d.read()


def test_nack_gives_bus_error_and_driver_recovers():
    d, model, truth, bus, _ = rig()
    d.read()
    bus.inject_nack(0x1C)
    with pytest.raises(BusError, match="NACK"):
        d.read()
    assert d.read().valid


def test_flipped_bit_in_readback_detected():
    d, model, *_ = rig()
    model.inject_bit_flip(0x21, 0x20, count=1)
    with pytest.raises(ReadbackMismatch):
        d.configure(range_uT=800)


def test_self_test_passes_and_fails_when_broken():
    d, model, *_ = rig(b_uT=(20.0, -5.0, 40.0))
    res = d.self_test()
    assert res.passed
    assert all(lo <= x <= hi for x, (lo, hi) in zip(res.delta_uT, res.window_uT, strict=True))
    # configuration restored afterwards
    assert (d.range_uT, d.odr_hz, d.performance, d.mode) == (400.0, 80.0, "ultra", "continuous")
    assert d.read().valid
    model.break_self_test()
    with pytest.raises(SelfTestFailed) as e:
        d.self_test()
    assert not e.value.result.passed
    model.break_self_test((200.0, 200.0, 150.0))     # Z above its 10..100 uT window
    with pytest.raises(SelfTestFailed):
        d.self_test()


def test_soft_reset_and_reinit_restore_configuration():
    d, model, *_ = rig()
    d.configure(range_uT=1200, odr_hz=10)
    model.reset_registers()          # chip power-cycled behind the driver's back
    model.stop()
    d.reinit()
    assert model.values[0x21] == 0x40 and model.values[0x20] & 0x1E == 0x10
    assert d.read().valid
    d.soft_reset()
    assert model.values[0x22] == 0x03 and d.mode == "idle"
    with pytest.raises(ConfigurationError, match="idle"):
        d.read()


def test_single_conversion_mode():
    d, model, *_ = rig()
    d.configure(mode="single", odr_hz=40)
    n0 = model.conversions
    s1 = d.read()
    s2 = d.read()
    assert model.conversions == n0 + 2 and s2.t_s > s1.t_s
    assert model.values[0x22] & 0x03 == 0x03        # back to power-down after the conversion


@pytest.mark.hil
def test_hil_lis3mdl_reads_earth_field(request):
    from magstack.drivers.i2c_probe import probe
    from magstack.drivers.registry import open_i2c_bus

    bus = open_i2c_bus(request.config.getoption("--i2c-bus"))
    found = [r for r in probe(bus, (0x1C, 0x1E)) if r.chip == "lis3mdl"]
    if not found:
        pytest.skip("no LIS3MDL on the bus")
    d = LIS3MDL(bus, SystemClock(), address=found[0].address)
    samples = [d.read() for _ in range(20)]
    assert all(s.valid for s in samples)
    assert np.all(np.diff([s.t_s for s in samples]) > 0)
    norm = np.linalg.norm(np.mean([s.b_uT for s in samples], axis=0))
    assert 5.0 < norm < 200.0              # Earth field plus bench offsets, far below full scale
    assert -20.0 < samples[-1].temp_c < 70.0
    assert d.self_test().passed


def test_overrun_flag_reports_lost_samples():
    d, model, *_ = rig()
    assert d.read().extra["overrun"] is False
    s = d.read()
    assert s.extra["overrun"] is False
    d.clock.sleep_s(5 * d.period_s)          # the chip converts 5 sets nobody reads
    assert d.read().extra["overrun"] is True
    assert d.read().extra["overrun"] is False
