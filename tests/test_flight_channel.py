"""Magnetometer channel: what may be published as good and calibrated, fault classes,
re-initialisation (a NACK during re-init is a bus error), degradation and recovery."""
from __future__ import annotations

import math

import numpy as np
import pytest

from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import BusError, BusTimeout
from magstack.drivers.magnetometer import MagSample
from magstack.drivers.registry import open_chip
from magstack.firmware import cal_table as ct
from magstack.firmware.corrector import TableCorrector
from magstack.firmware.flight.channel import ChannelLimits, MagChannel, TlmFlag
from magstack.firmware.flight.events import EventId, EventLog
from magstack.sim.i2c_bench import default_bench
from magstack.sim.truth_source import StaticTruth


def _table(validity_field_uT=100.0, temp=(0.0, 50.0)) -> ct.CalTable:
    return ct.CalTable(device_id="dev", terms=("gain_matrix", "offset"), S=np.eye(3) * 1.01, O=[0.5, -0.2, 0.1],
                       validity_field_uT=validity_field_uT, validity_temp_c=temp)


def _store(tmp_path, **kw) -> ct.CalTableStore:
    store = ct.CalTableStore("dev")
    store.load_and_activate(ct.save_table(_table(**kw), tmp_path / "cal.json"))
    return store


class Scripted:
    """A Magnetometer returning scripted samples/exceptions; ``reinit`` can fail with a NACK."""

    name = "scripted"
    range_uT = 400.0

    def __init__(self, clock, script):
        self.clock, self.script, self.reinits, self.reinit_error = clock, list(script), 0, None

    def read(self):
        self.clock.sleep_s(0.1)
        item = self.script.pop(0)
        if isinstance(item, BaseException):
            raise item
        if isinstance(item, MagSample):
            return item
        return MagSample(self.clock.monotonic_s(), tuple(item), 25.0)

    def data_ready(self):
        return True

    def reinit(self):
        self.reinits += 1
        if self.reinit_error is not None:
            raise self.reinit_error


def _channel(tmp_path, script, **limits):
    clock = VirtualClock()
    mag = Scripted(clock, script)
    ev = EventLog()
    recs = []
    ch = MagChannel("c", mag, TableCorrector(_store(tmp_path)), ev, sink=recs.append, limits=ChannelLimits(**limits))
    return ch, mag, ev, recs, clock


def test_frozen_registers_are_stale_from_the_first_repeat(tmp_path):
    """Before: identical samples were published as new until the driver's 200-sample limit."""
    script = [(10.0, 20.0, 30.0)] + [(10.5, 20.0, 30.0)] * 5 + [(11.0, 20.0, 30.0)]
    ch, _, ev, recs, clock = _channel(tmp_path, script)
    for _ in script:
        ch.run(clock.monotonic_s())
    assert [r.good for r in recs] == [True, True, False, False, False, False, True]
    assert all(r.flags & TlmFlag.STALE and r.cal_uT is None for r in recs[2:6])
    assert ch.health.stale == 4 and ev.count(EventId.CHAN_STALE) == 4


def test_corrupt_values_are_implausible_and_never_calibrated(tmp_path):
    script = [(10.0, 20.0, 30.0), (10.1, 20.0, 30.0), (10.1, 723.0, 30.0), (10.2, 20.1, 30.0),
              (10.2, 20.1, -390.0), (10.3, 20.2, 30.0)]
    ch, _, ev, recs, clock = _channel(tmp_path, script, max_rate_uT_per_s=500.0)
    for _ in script:
        ch.run(clock.monotonic_s())
    assert [r.good for r in recs] == [True, True, False, True, False, True]
    assert ch.health.implausible == 2 and ev.count(EventId.CHAN_IMPLAUSIBLE) == 2
    assert all(r.cal_uT is None for r in recs if not r.good)


def test_a_confirmed_step_is_accepted(tmp_path):
    """A real field step (a torquer switching) is confirmed by the next sample and accepted."""
    script = [(10.0, 20.0, 30.0), (10.0, 20.0, 30.1), (10.0, 120.0, 30.0), (10.0, 120.1, 30.0), (10.0, 120.2, 30.1)]
    ch, _, _, recs, clock = _channel(tmp_path, script, max_rate_uT_per_s=500.0)
    for _ in script:
        ch.run(clock.monotonic_s())
    assert [r.good for r in recs] == [True, True, False, True, True]


def test_never_calibrated_outside_the_table_validity(tmp_path):
    """Before: the corrector counted out-of-validity samples but still published them as calibrated."""
    script = [(10.0, 20.0, 30.0), (10.0, 20.0, 150.0), (10.0, 20.0, 150.1), (10.0, 20.0, 30.0)]
    ch, _, ev, recs, clock = _channel(tmp_path, script, max_rate_uT_per_s=1e6)
    for _ in script:
        ch.run(clock.monotonic_s())
    assert [r.calibrated for r in recs] == [True, False, False, True]
    assert all(r.good for r in recs)
    assert recs[1].flags & TlmFlag.OUT_OF_VALIDITY and ch.health.out_of_validity == 2
    np.testing.assert_allclose(recs[0].cal_uT, np.array([10.0, 20.0, 30.0]) * 1.01 + [0.5, -0.2, 0.1], atol=1e-5)


def test_foreign_exceptions_and_absurd_values_are_counted_not_raised(tmp_path):
    script = [ValueError("invalid literal for int()"), (1e308, 0.0, 0.0), (math.nan, 1.0, 2.0),
              OverflowError("int too large"), (10.0, 20.0, 30.0)]
    ch, _, ev, recs, clock = _channel(tmp_path, script, reinit_after=10)
    for _ in script:
        ch.run(clock.monotonic_s())
    assert ch.health.exceptions == 2 and ev.count(EventId.CHAN_EXCEPTION) == 2
    assert "ValueError" in recs[0].fault and "OverflowError" in recs[3].fault
    assert ch.health.implausible == 2
    assert recs[-1].good and recs[-1].calibrated


def test_nack_during_reinit_counts_as_bus_error_then_degraded_and_recovery(tmp_path):
    script = [BusError("NACK")] * 9 + [(10.0, 20.0, 30.0)]
    ch, mag, ev, recs, clock = _channel(tmp_path, script, reinit_after=3, degrade_after=2)
    mag.reinit_error = BusError("NACK during reinit")
    for _ in range(6):
        ch.run(clock.monotonic_s())
    assert mag.reinits == 2 and ch.health.reinit_failures == 2
    assert ch.health.bus_errors == 6 + 2 and ch.health.other_errors == 0
    assert ch.degraded and ev.count(EventId.CHAN_DEGRADED) == 1
    mag.reinit_error = None
    for _ in range(4):
        ch.run(clock.monotonic_s())
    assert recs[-1].good and not ch.degraded and ev.count(EventId.CHAN_RECOVERED) == 1
    assert recs[-2].flags & TlmFlag.DEGRADED


def test_real_driver_on_the_simulated_bus_timeout_and_nack(tmp_path):
    """The same channel on the LIS3MDL driver and simulated bus: a NACK and stuck data registers."""
    clock = VirtualClock()
    bench = default_bench(clock, StaticTruth((20.0, -5.0, 40.0)))
    mag = open_chip("lis3mdl", "sim", clock, bench=bench, odr_hz=20.0)
    ev, recs = EventLog(), []
    ch = MagChannel("lis", mag, None, ev, sink=recs.append)
    bus = bench.bus_for("lis3mdl")
    for k in range(40):
        if k == 10:
            bus.inject_nack(bench.address("lis3mdl"), 1)
        if k == 20:
            bench.model("lis3mdl").inject_stuck(range(0x28, 0x2E))
        ch.run(clock.monotonic_s())
    assert ch.health.bus_errors == 1 and ev.count(EventId.CHAN_BUS_ERROR) == 1
    stuck = recs[21:]
    assert stuck and not any(r.good for r in stuck)      # frozen data never published as good
    assert all(r.good for r in recs[:10])


@pytest.mark.parametrize("exc, counter", [(BusTimeout("drdy"), "timeouts"), (BusError("x"), "bus_errors")])
def test_each_typed_fault_has_its_counter(tmp_path, exc, counter):
    ch, _, _, recs, clock = _channel(tmp_path, [exc, (1.0, 2.0, 3.0)])
    ch.run(clock.monotonic_s())
    ch.run(clock.monotonic_s())
    assert getattr(ch.health, counter) == 1 and recs[0].flags & TlmFlag.NO_SAMPLE and recs[1].good


def test_stale_threshold_follows_the_sensor_resolution(tmp_path):
    """A sensor whose noise spans many counts flags the first repeat; a coarse one tolerates single repeats
    (a repeat of all three axes is then a normal event) but flags a run that is unlikely by chance."""
    rng = np.random.default_rng(1)

    def run(sigma_counts):
        counts = [tuple(int(v) for v in np.round(rng.normal(0, sigma_counts, 3)) + 500) for _ in range(400)]
        script = [MagSample(0.1 * k, tuple(c * 0.1 for c in counts[k]), 25.0, extra={"raw": counts[k]})
                  for k in range(400)]
        ch, _, _, _, clock = _channel(tmp_path, script, max_rate_uT_per_s=1e6)
        for _ in script:
            ch.run(clock.monotonic_s())
        return ch.stale_threshold()

    assert run(40.0) == 1
    assert run(1.0) >= 2

