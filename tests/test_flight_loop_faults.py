"""Fault classes through the flight channel on real drivers over simulated buses (moved from the retired
single-sensor SamplingLoop tests): every class counted, re-initialisation, NaN from a simulated bridge."""
from __future__ import annotations

import math

import numpy as np
import pytest

from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import BusError, BusTimeout, DeviceIdMismatch, StaleData
from magstack.drivers.magnetometer import MagSample
from magstack.firmware.flight.channel import ChannelLimits, MagChannel
from magstack.firmware.flight.events import EventId, EventLog


class ScriptedMag:
    """Returns or raises the scripted items in order; counts reinit calls."""

    name = "scripted"

    def __init__(self, clock, script):
        self.clock, self.script, self.reinits = clock, list(script), 0

    def data_ready(self) -> bool:
        return True

    def read(self) -> MagSample:
        self.clock.sleep_s(0.1)
        item = self.script.pop(0)
        if isinstance(item, Exception):
            raise item
        return item if isinstance(item, MagSample) else MagSample(self.clock.monotonic_s(), item, 25.0)

    def reinit(self) -> None:
        self.reinits += 1


def _run(ch, clock, n):
    return [ch.run(clock.monotonic_s()) for _ in range(n)]


def test_faults_are_counted_by_class_and_the_channel_keeps_running():
    clock = VirtualClock()
    nan = float("nan")
    script = [(1.0, 2.0, 3.0), BusError("nack", address=0x1E), BusTimeout("drdy"), StaleData("same"),
              DeviceIdMismatch("id"), MagSample(0.0, (nan, 1.0, 1.0), 25.0, overflow=(0,)), (1.1, 2.0, 3.0)]
    ev = EventLog()
    ch = MagChannel("c", ScriptedMag(clock, script), None, ev, limits=ChannelLimits(reinit_after=100))
    out = _run(ch, clock, len(script))
    h = ch.health
    assert (h.samples_ok, h.bus_errors, h.timeouts, h.stale, h.other_errors, h.overflows) == (2, 1, 1, 1, 1, 1)
    assert h.error_count == 5 and out[-1].error_count == 5 and out[-1].good
    assert out[1].fault.startswith("BusError") and out[5].fault.startswith("chan_overflow")
    assert out[5].cal_uT is None and not out[5].good      # a saturated sample is never published as a field
    for eid in (EventId.CHAN_BUS_ERROR, EventId.CHAN_TIMEOUT, EventId.CHAN_STALE, EventId.CHAN_OTHER_ERROR,
                EventId.CHAN_OVERFLOW):
        assert ev.count(eid, "c") == 1, eid


def test_reinit_after_consecutive_faults_then_recovers():
    clock = VirtualClock()
    mag = ScriptedMag(clock, [BusError("x")] * 3 + [(1.0, 2.0, 3.0)])
    ch = MagChannel("c", mag, None, EventLog(), limits=ChannelLimits(reinit_after=3))
    out = _run(ch, clock, 4)
    assert mag.reinits == 1 and ch.health.reinits == 1 and out[-1].good and ch.health.consecutive_faults == 0


@pytest.mark.parametrize("kw", [{"reinit_after": 0}, {"degrade_after": 0}, {"max_rate_uT_per_s": 0.0},
                                {"max_field_uT": math.nan}])
def test_limits_are_validated(kw):
    with pytest.raises(ValueError):
        ChannelLimits(**kw)


def test_nack_during_reinit_is_a_bus_error_not_other():
    """Campaign finding: 102 of 703 'other_errors' were NACKs during a re-initialisation."""
    from magstack.drivers.lsm303dlhc import LSM303DLHC
    from magstack.sim.i2c_bus import SimI2CBus
    from magstack.sim.i2c_register_model import IdealSensor
    from magstack.sim.lsm303dlhc_model import LSM303DLHCModel
    from magstack.sim.truth_source import StaticTruth

    clock = VirtualClock()
    bus = SimI2CBus()
    bus.attach(0x1E, LSM303DLHCModel(clock, StaticTruth(), IdealSensor()))
    mag = LSM303DLHC(bus, clock, stuck_limit=None)
    ch = MagChannel("dlhc", mag, None, EventLog(), limits=ChannelLimits(reinit_after=2, degrade_after=10))
    bus.inject_nack(0x1E, 5)          # read, read -> reinit (NACKed), read, read?... every NACK is a bus error
    out = _run(ch, clock, 3)
    h = ch.health
    assert all(not r.good and r.fault.startswith("BusError") for r in out)
    assert h.other_errors == 0 and h.exceptions == 0 and h.reinit_failures >= 1
    assert h.bus_errors == 3 + h.reinit_failures
    assert _run(ch, clock, 2)[-1].raw_uT is not None       # NACKs exhausted: samples flow again


def test_hmc1053_front_end_can_be_reset_by_the_channel():
    """The HMC1053 front end had no reinit(): the loop could never reset it after persistent faults."""
    from magstack.sim.hmc1053_bridge import build_sim_hmc1053

    rig = build_sim_hmc1053()
    fe = rig.front_end
    assert callable(getattr(fe, "reinit", None))
    ch = MagChannel("hmc1053", fe, None, EventLog(), limits=ChannelLimits(reinit_after=3))
    rig.spi.inject_fault(3)            # three cycles fail on the SPI bus
    resets_before = rig.adc_model.command_log.count(0x16)   # SDATAC is sent once per ADC reset
    out = _run(ch, rig.clock, 5)
    assert [r.good for r in out] == [False, False, False, True, True]
    assert ch.health.reinits == 1 and ch.health.bus_errors == 3
    assert rig.adc_model.command_log.count(0x16) == resets_before + 1
    assert out[-1].raw_uT is not None and all(v == v for v in out[-1].raw_uT)


def test_nan_from_the_simulated_hmc1053_is_an_overflow_not_an_escape():
    """NaN from the simulated sensor raised ValueError inside the simulated ADC and took the loop down;
    the ADC now reads at the rail and the driver flags the clipped axes."""
    from magstack.sim.hmc1053_bridge import build_sim_hmc1053

    class NanSensor:
        def sense(self, t_s, truth):
            return np.array([np.nan, 10.0, np.inf])

    rig = build_sim_hmc1053(sensor=NanSensor())
    ch = MagChannel("hmc1053", rig.front_end, None, EventLog())
    (r,) = _run(ch, rig.clock, 1)
    assert ch.health.overflows == 1 and ch.health.other_errors == 0 and ch.health.exceptions == 0
    assert r.cal_uT is None and not r.good
