"""Simulators as faithful as the parts: what a read returns must not depend on how often
the host touched the bus; the HMC5883L-family LOCK rule; the drivers' first read after open."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.drivers.bus.i2c import I2CDevice
from magstack.drivers.clock import VirtualClock
from magstack.drivers.hmc5983 import HMC5983
from magstack.drivers.lsm303dlhc import LSM303DLHC
from magstack.sim.hmc5983_model import HMC5983Model
from magstack.sim.i2c_bus import SimI2CBus
from magstack.sim.i2c_register_model import IdealSensor
from magstack.sim.lis3mdl_model import LIS3MDLModel
from magstack.sim.lsm303dlhc_model import LSM303DLHCModel
from magstack.sim.truth_source import StaticTruth

B_UT = (150.0, -30.0, 60.0)   # beyond the smallest Honeywell ranges: a wrong gain shows as -4096

HONEYWELL_RATES = (0.75, 1.5, 3.0, 7.5, 15.0, 30.0, 75.0, 220.0)
LIS_RATES = {0: 0.625, 1: 1.25, 2: 2.5, 3: 5.0, 4: 10.0, 5: 20.0, 6: 40.0, 7: 80.0}


class Chip:
    """Writes of one chip's range / rate fields and how its status and data block are read."""

    def __init__(self, kind, clock):
        truth = StaticTruth(B_UT)
        self.kind = kind
        if kind == "lis3mdl":
            self.model = LIS3MDLModel(clock, truth, IdealSensor())
            addr, flag = 0x1C, 0x80
        else:
            cls = HMC5983Model if kind == "hmc5983" else LSM303DLHCModel
            self.model = cls(clock, truth, IdealSensor())
            addr, flag = 0x1E, 0
        bus = SimI2CBus()
        bus.attach(addr, self.model)
        self.dev = I2CDevice(bus, addr, auto_increment_flag=flag)
        if kind == "lis3mdl":
            self.dev.write_register(0x20, 7 << 2)   # 80 Hz
            self.dev.write_register(0x22, 0x00)     # continuous
        else:
            self.dev.write_register(0x02, 0x00)     # continuous

    def gain(self, code):
        if self.kind == "lis3mdl":
            self.dev.write_register(0x21, (code % 4) << 5)
        else:
            self.dev.write_register(0x01, (max(code, 1) if self.kind == "lsm303dlhc" else code) << 5)

    def rate(self, code):
        if self.kind == "lis3mdl":
            self.dev.write_register(0x20, code << 2)
        else:
            self.dev.write_register(0x00, code << 2)

    def period_s(self):
        return self.model.period_s()

    def partial(self, n):
        """Read the first ``n`` bytes of the data block (n < 6 leaves LOCK / BDU holding)."""
        self.dev.read_registers(0x28 if self.kind == "lis3mdl" else 0x03, n)

    def read_mode(self):
        self.dev.read_register(0x22 if self.kind == "lis3mdl" else 0x02)

    def poll(self):
        self.dev.read_register(0x27 if self.kind == "lis3mdl" else 0x09)

    def snapshot(self):
        status = self.dev.read_register(0x27 if self.kind == "lis3mdl" else 0x09)
        return status, self.dev.read_registers(0x28 if self.kind == "lis3mdl" else 0x03, 6)


def _run(kind, ops, poll_fraction):
    clock = VirtualClock()
    chip = Chip(kind, clock)
    for op, arg in ops:
        if op == "gain":
            chip.gain(arg)
        elif op == "rate":
            chip.rate(arg)
        elif op == "partial":
            chip.partial(arg)
        elif op == "mode":
            chip.read_mode()
        else:
            remaining = arg * chip.period_s()
            step = poll_fraction * chip.period_s() if poll_fraction else remaining
            while remaining > 0:
                dt = min(step, remaining)
                clock.advance_s(dt)
                remaining -= dt
                if poll_fraction:
                    chip.poll()
    return chip.snapshot()


OPS = st.lists(st.one_of(st.tuples(st.just("gain"), st.integers(0, 7)),
                         st.tuples(st.just("rate"), st.integers(3, 7)),
                         st.tuples(st.just("partial"), st.integers(1, 6)),   # LOCK / BDU hold
                         st.tuples(st.just("mode"), st.just(0)),             # HMC5983: LOCK on MR read
                         # whole periods + 0.37: never exactly on a conversion instant, where summing
                         # the polling steps in floating point could land either side of it
                         st.tuples(st.just("idle"), st.integers(0, 6).map(lambda n: n + 0.37))),
               min_size=1, max_size=8)


@pytest.mark.parametrize("kind", ["hmc5983", "lsm303dlhc", "lis3mdl"])
@settings(max_examples=60, deadline=None)
@given(ops=OPS, poll=st.sampled_from([0.05, 0.3, 0.9]))
def test_a_read_does_not_depend_on_how_often_the_host_polled(kind, ops, poll):
    """Status register and data block after any sequence of range/rate writes, partial data reads,
    mode-register reads and idle times are the same whether the host polled the status register in
    between or never touched the bus (gain lag, data-ready, overrun, LOCK/BDU hold)."""
    ops = [*ops, ("idle", 3.37)]
    assert _run(kind, ops, 0.0) == _run(kind, ops, poll)


def _hmc(clock, truth, **kw):
    model = HMC5983Model(clock, truth, IdealSensor(), **kw)
    bus = SimI2CBus()
    bus.attach(0x1E, model)
    return model, bus, I2CDevice(bus, 0x1E)


def test_reading_the_mode_register_locks_the_outputs():
    """HMC5883L datasheet p.16: LOCK is set when the mode register has been read; new data do not
    reach the outputs until all six data bytes are read (or CRA/MR is written)."""
    clock = VirtualClock()
    truth = StaticTruth((20.0, 0.0, 0.0))
    model, bus, dev = _hmc(clock, truth)
    dev.write_register(0x02, 0x00)
    clock.advance_s(0.2)
    first = dev.read_registers(0x03, 6)
    assert dev.read_register(0x02) == 0x00           # mode register read: LOCK
    assert dev.read_register(0x09) & 0x02
    truth.b_uT[:] = (40.0, 0.0, 0.0)
    clock.advance_s(0.3)                             # many conversions while locked
    assert dev.read_registers(0x03, 6) == first      # the frozen set; reading all six unlocks
    assert dev.read_register(0x09) & 0x02 == 0
    assert dev.read_registers(0x03, 6) != first      # the held newer set is now visible
    # writing MR or CRA also unlocks
    dev.read_register(0x02)
    dev.write_register(0x00, 0x18)
    assert dev.read_register(0x09) & 0x02 == 0


@pytest.mark.parametrize("lock_on_mode_read", [True, False])
def test_hmc5983_driver_first_read_is_fresh_after_open_configure_and_reinit(lock_on_mode_read):
    """The driver reads MR back after writing it; on a part that follows the LOCK rule its first
    read returned the frozen power-on zeros as a valid 0 uT field. Now each read-back is followed by
    one discarded six-byte read."""
    clock = VirtualClock()
    truth = StaticTruth((20.0, -5.0, 40.0))
    model, bus, _ = _hmc(clock, truth, lock_on_mode_read=lock_on_mode_read)
    d = HMC5983(bus, clock, stuck_limit=None)
    np.testing.assert_allclose(d.read().b_uT, truth.b_uT, atol=0.1)
    truth.b_uT[:] = (-30.0, 10.0, 5.0)
    d.configure(odr_hz=30.0)
    np.testing.assert_allclose(d.read().b_uT, truth.b_uT, atol=0.1)
    truth.b_uT[:] = (12.0, 34.0, -56.0)
    d.reinit()
    np.testing.assert_allclose(d.read().b_uT, truth.b_uT, atol=0.1)
    assert model.values[0x09] & 0x02 == 0


def test_lsm303dlhc_driver_is_fresh_even_if_its_mode_read_locks():
    """The DLHC's LOCK rule is undocumented: the driver must be right either way."""
    clock = VirtualClock()
    truth = StaticTruth((20.0, -5.0, 40.0))
    model = LSM303DLHCModel(clock, truth, IdealSensor(), lock_on_mode_read=True)
    bus = SimI2CBus()
    bus.attach(0x1E, model)
    d = LSM303DLHC(bus, clock, stuck_limit=None)
    np.testing.assert_allclose(d.read().b_uT, truth.b_uT, atol=0.15)
    truth.b_uT[:] = (-30.0, 10.0, 5.0)
    d.configure(range_uT=810.0)
    np.testing.assert_allclose(d.read().b_uT, truth.b_uT, atol=0.5)


def test_invalid_gain_code_is_ignored_by_default_and_refused_by_the_lint():
    from magstack.drivers.errors import BusError

    clock = VirtualClock()
    m = LSM303DLHCModel(clock, StaticTruth(), IdealSensor())
    bus = SimI2CBus()
    bus.attach(0x1E, m)
    dev = I2CDevice(bus, 0x1E)
    dev.write_register(0x01, 0x00)
    assert dev.read_register(0x01) == 0x20
    strict = LSM303DLHCModel(clock, StaticTruth(), IdealSensor(), lints=("nack_illegal_write",))
    bus2 = SimI2CBus()
    bus2.attach(0x1E, strict)
    with pytest.raises(BusError, match="nack_illegal_write"):
        I2CDevice(bus2, 0x1E).write_register(0x01, 0x00)


def test_hmc5883l_is_probed_honestly_and_the_driver_never_turns_its_ts_bit_on():
    """An HMC5883L answers 0 at 0x31/0x32 (invalid address) and CRA7 must stay 0: the probe does not
    call it an HMC5983; the HMC5983 driver with temperature=False runs on it and reports no
    temperature; with temperature=True the ignored TS write fails the read-back at open (never a
    constant fake 25 degC)."""
    from magstack.drivers.errors import BusError, ReadbackMismatch
    from magstack.drivers.i2c_probe import identify
    from magstack.sim.hmc5983_model import HMC5883LModel

    clock = VirtualClock()
    truth = StaticTruth((20.0, -5.0, 40.0), temp_c=21.0)
    model = HMC5883LModel(clock, truth, IdealSensor())
    bus = SimI2CBus()
    bus.attach(0x1E, model)
    assert identify(bus, 0x1E).chip == "hmc5883l_or_hmc5983"
    d = HMC5983(bus, clock, temperature=False, stuck_limit=None)
    s = d.read()
    assert s.temp_c is None and model.values[0x00] & 0x80 == 0
    np.testing.assert_allclose(s.b_uT, truth.b_uT, atol=0.1)
    assert identify(bus, 0x1E).chip == "hmc5883l_or_hmc5983"
    with pytest.raises(ReadbackMismatch):
        HMC5983(bus, clock, temperature=True)
    strict = HMC5883LModel(clock, truth, IdealSensor(), lints=("nack_illegal_write",))
    bus2 = SimI2CBus()
    bus2.attach(0x1E, strict)
    with pytest.raises(BusError, match="nack_illegal_write"):
        HMC5983(bus2, clock, temperature=True)
