"""The flight loop counts every fault class, keeps running, and re-initialises after persistent faults."""
from __future__ import annotations

import pytest

from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import BusError, BusTimeout, DeviceIdMismatch, StaleData
from magstack.drivers.magnetometer import MagSample
from magstack.firmware.sampling_loop import SamplingLoop


class ScriptedMag:
    """Returns or raises the scripted items in order; counts reinit calls."""

    name = "scripted"

    def __init__(self, clock, script):
        self.clock = clock
        self.script = list(script)
        self.reinits = 0

    def data_ready(self) -> bool:
        return True

    def read(self) -> MagSample:
        item = self.script.pop(0)
        if isinstance(item, Exception):
            raise item
        return item if isinstance(item, MagSample) else MagSample(self.clock.monotonic_s(), item, 25.0)

    def reinit(self) -> None:
        self.reinits += 1


def ok(b=(1.0, 2.0, 3.0)):
    return b


def test_faults_are_counted_by_class_and_loop_keeps_running():
    clock = VirtualClock()
    nan = float("nan")
    script = [ok(), BusError("nack", address=0x1E), BusTimeout("drdy"), StaleData("same"),
              DeviceIdMismatch("id"), MagSample(0.0, (nan, 1.0, 1.0), 25.0, overflow=(0,)), ok()]
    mag = ScriptedMag(clock, script)
    loop = SamplingLoop(mag, clock, period_s=0.1, reinit_after=100)
    out = loop.run(len(script))
    h = loop.health
    assert (h.samples_ok, h.bus_errors, h.timeouts, h.stale, h.other_errors, h.overflows) == (2, 1, 1, 1, 1, 1)
    assert h.error_count == 5
    assert out[-1].error_count == 5 and out[-1].fault is None
    assert out[1].fault.startswith("bus") and out[5].fault.startswith("overflow")
    assert out[5].b_uT is None  # a saturated sample is never published as a field


def test_cycle_timing_uses_injected_clock():
    clock = VirtualClock()
    mag = ScriptedMag(clock, [ok()] * 5)
    loop = SamplingLoop(mag, clock, period_s=0.25)
    ts = [p.t_s for p in loop.run(5)]
    assert ts == pytest.approx([0.0, 0.25, 0.5, 0.75, 1.0])


def test_reinit_after_consecutive_faults_then_recovers():
    clock = VirtualClock()
    mag = ScriptedMag(clock, [BusError("x")] * 3 + [ok()])
    loop = SamplingLoop(mag, clock, period_s=0.1, reinit_after=3)
    out = loop.run(4)
    assert mag.reinits == 1 and loop.health.reinits == 1
    assert out[-1].raw_uT == (1.0, 2.0, 3.0)


def test_corrector_applied_and_missing_table_counted():
    clock = VirtualClock()
    mag = ScriptedMag(clock, [ok(), ok()])
    tables = iter([None, (10.0, 20.0, 30.0)])
    loop = SamplingLoop(mag, clock, period_s=0.1, corrector=lambda s: next(tables))
    a, b = loop.run(2)
    assert not a.calibrated and loop.health.uncalibrated == 1
    assert b.calibrated and b.b_uT == (10.0, 20.0, 30.0)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_period_rejected(bad):
    with pytest.raises(ValueError):
        SamplingLoop(ScriptedMag(VirtualClock(), []), VirtualClock(), period_s=bad)


@pytest.mark.parametrize("bad", [0, -3])
def test_reinit_after_must_be_at_least_one(bad):
    with pytest.raises(ValueError, match="reinit_after"):
        SamplingLoop(ScriptedMag(VirtualClock(), []), VirtualClock(), period_s=0.1, reinit_after=bad)


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
    loop = SamplingLoop(mag, clock, period_s=0.1, reinit_after=2)
    bus.inject_nack(0x1E, 5)          # read, read -> reinit (NACKed), read -> reinit (NACKed)
    out = loop.run(3)
    h = loop.health
    assert all(p.fault and p.fault.startswith("bus") for p in out)
    assert (h.bus_errors, h.other_errors, h.reinit_failures, h.reinits) == (5, 0, 2, 0)
    assert loop.run(1)[0].raw_uT is not None       # NACKs exhausted: samples flow again


def test_hmc1053_front_end_can_be_reset_by_the_loop():
    """The HMC1053 front end had no reinit(): the loop could never reset it after persistent faults."""
    from magstack.sim.hmc1053_bridge import build_sim_hmc1053

    rig = build_sim_hmc1053()
    fe = rig.front_end
    assert callable(getattr(fe, "reinit", None))
    loop = SamplingLoop(fe, rig.clock, period_s=0.4, reinit_after=3)
    rig.spi.inject_fault(3)            # three cycles fail on the SPI bus
    resets_before = rig.adc_model.command_log.count(0x16)   # SDATAC is sent once per ADC reset
    out = loop.run(5)
    assert [p.fault is not None for p in out] == [True, True, True, False, False]
    assert loop.health.reinits == 1 and loop.health.bus_errors == 3
    assert rig.adc_model.command_log.count(0x16) == resets_before + 1
    assert out[-1].raw_uT is not None and all(v == v for v in out[-1].raw_uT)


def test_nan_from_the_simulated_hmc1053_is_an_overflow_not_an_escape():
    """NaN from the simulated sensor raised ValueError inside the simulated ADC and took the loop down;
    the ADC now reads at the rail and the driver flags the clipped axes."""
    import numpy as np

    from magstack.sim.hmc1053_bridge import build_sim_hmc1053

    class NanSensor:
        def sense(self, t_s, truth):
            return np.array([np.nan, 10.0, np.inf])

    rig = build_sim_hmc1053(sensor=NanSensor())
    loop = SamplingLoop(rig.front_end, rig.clock, period_s=0.4)
    (p,) = loop.run(1)
    assert loop.health.overflows == 1 and loop.health.other_errors == 0
    assert p.b_uT is None and p.fault.startswith("overflow on axes (0, 2)")


def test_no_catch_up_burst_after_a_blocking_read():
    """Issue 17 item 9: after a read that blocks several periods the loop skips the missed slots
    (counted) instead of running them back to back; a clock stepped back re-anchors at once."""
    from magstack.drivers.clock import VirtualClock
    from magstack.drivers.magnetometer import MagSample
    from magstack.firmware.sampling_loop import SamplingLoop

    clock = VirtualClock()

    class Slow:
        name = "slow"
        n = 0

        def read(self):
            self.n += 1
            if self.n == 3:
                clock.sleep_s(0.45)          # blocks 4.5 periods
            return MagSample(clock.monotonic_s(), (1.0 + self.n, 2.0, 3.0), 25.0)

        def data_ready(self):
            return True

    loop = SamplingLoop(Slow(), clock, period_s=0.1)
    starts = []
    for _ in range(12):
        loop.step()
        starts.append(loop._next_s - loop.period_s)
    gaps = [b - a for a, b in zip(starts, starts[1:], strict=False)]
    assert min(gaps) >= 0.1 - 1e-9
    assert loop.health.missed_slots == 4
    clock._t_s -= 100.0                       # the clock steps back 100 s
    t0 = clock.monotonic_s()
    loop.step()
    assert clock.monotonic_s() - t0 < 0.2     # no 100 s stall
