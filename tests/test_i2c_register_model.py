"""Generic register model: access modes, power-on values, pointer rules, faults, loud failures."""
from __future__ import annotations

import pytest

from magstack.drivers.bus.i2c import I2CDevice, I2CRead, I2CWrite
from magstack.drivers.errors import BusError
from magstack.sim.hmc5983_model import HMC5983Model
from magstack.sim.i2c_bus import SimI2CBus
from magstack.sim.i2c_register_model import (
    LINTS,
    PART_FAITHFUL,
    RO,
    RW,
    STRICT,
    WO,
    IdealSensor,
    Reg,
    RegisterFileModel,
    default_lints,
)
from magstack.sim.lis3mdl_model import LIS3MDLModel
from magstack.sim.lsm303dlhc_model import LSM303DLHCModel
from magstack.sim.truth_source import StaticTruth


def _dev(model, address=0x40):
    bus = SimI2CBus()
    bus.attach(address, model)
    return bus, I2CDevice(bus, address)


def _model(lints=None):
    return RegisterFileModel([Reg(0x00, "CFG", RW, 0x12, fixed_mask=0x80), Reg(0x01, "ID", RO, 0x5A),
                              Reg(0x02, "CMD", WO, 0x00)], name="toy", address=0x40, lints=lints)


def test_power_on_values_and_strict_lints():
    """With every lint on, illegal accesses NACK loudly (opt-in, stricter than the parts)."""
    bus, dev = _dev(_model(lints=STRICT))
    assert dev.read_registers(0x00, 2) == b"\x12\x5a"
    dev.write_register(0x02, 0x33)
    with pytest.raises(BusError, match="read-only.*nack_illegal_write"):
        dev.write_register(0x01, 0x00)
    with pytest.raises(BusError, match="write-only.*nack_invalid_address"):
        dev.read_register(0x02)
    with pytest.raises(BusError, match="unmapped"):
        dev.read_register(0x07)
    with pytest.raises(BusError, match="unmapped"):
        dev.write_register(0x07, 1)
    with pytest.raises(BusError, match="fixed bits"):
        dev.write_register(0x00, 0x80)
    assert dev.read_register(0x00) == 0x12


def test_default_is_the_parts_behaviour_invalid_reads_zero_writes_ignored():
    """HMC5883L p.11 / LSM303DLHC p.21: an invalid address reads 0's; a write to an invalid address
    or an undefined bit is ignored (and acknowledged), not NACKed."""
    model = _model()
    bus, dev = _dev(model)
    assert model.lints == frozenset()
    assert dev.read_register(0x07) == 0x00            # unmapped
    assert dev.read_register(0x02) == 0x00            # write-only
    assert dev.read_registers(0x00, 4) == b"\x12\x5a\x00\x00"
    dev.write_register(0x07, 0x55)                    # ignored, no NACK
    assert dev.read_register(0x07) == 0x00
    dev.write_register(0x01, 0x00)                    # read-only: ignored
    assert dev.read_register(0x01) == 0x5A
    dev.write_register(0x00, 0x93)                    # undefined bit 7 ignored, the rest stored
    assert dev.read_register(0x00) == 0x13


def test_lint_names_are_checked_and_the_default_profile_can_be_switched(clock):
    from magstack.drivers.errors import ConfigurationError

    with pytest.raises(ConfigurationError, match="nack_invalid_address"):
        _model(lints=("nack_everything",))
    with default_lints(STRICT):
        assert HMC5983Model(clock, StaticTruth(), IdealSensor()).lints == LINTS
        assert LIS3MDLModel(clock, StaticTruth(), IdealSensor()).strict_auto_increment
    assert HMC5983Model(clock, StaticTruth(), IdealSensor()).lints == PART_FAITHFUL


def test_bus_error_carries_address():
    bus, dev = _dev(_model(lints=STRICT))
    with pytest.raises(BusError) as e:
        dev.read_register(0x09)
    assert e.value.address == 0x40
    assert "0x40" in str(e.value)


def test_quick_write_is_acknowledged_without_effect():
    model = _model()
    bus, dev = _dev(model)
    bus.transfer(0x40, [I2CWrite(b"")])
    assert model.values[0x00] == 0x12


def test_stuck_and_bit_flip_faults():
    model = _model()
    bus, dev = _dev(model)
    model.inject_bit_flip(0x01, 0x01, count=2)
    assert [dev.read_register(0x01) for _ in range(3)] == [0x5B, 0x5B, 0x5A]
    model.inject_stuck([0x01])
    assert model.core_set(0x01, 0x00) is False
    assert dev.read_register(0x01) == 0x5A
    model.clear_faults()
    assert model.core_set(0x01, 0x00) is True
    with pytest.raises(ValueError):
        model.inject_stuck([0x55])


def test_nack_injection_and_absent_device():
    model = _model()
    bus, dev = _dev(model)
    bus.inject_nack(0x40)
    with pytest.raises(BusError, match="NACK"):
        dev.read_register(0x00)
    assert dev.read_register(0x00) == 0x12
    with pytest.raises(BusError, match="no ACK"):
        I2CDevice(bus, 0x41).read_register(0x00)


def test_lis3mdl_auto_increment_rules(clock):
    truth = StaticTruth()
    strict = LIS3MDLModel(clock, truth, IdealSensor(), strict_auto_increment=True)
    bus = SimI2CBus()
    bus.attach(0x1C, strict)
    # opt-in lint: a multi-byte read without the 0x80 flag fails loudly
    with pytest.raises(BusError, match="auto-increment.*strict_auto_increment"):
        bus.transfer(0x1C, [I2CWrite(b"\x28"), I2CRead(6)])
    # with the flag, the output block wraps 0x2D -> 0x28 (8 bytes = X, Y, Z, X again)
    strict.values[0x28:0x2E] = bytes([1, 2, 3, 4, 5, 6])
    (data,) = bus.transfer(0x1C, [I2CWrite(b"\xa8"), I2CRead(8)])
    assert data == bytes([1, 2, 3, 4, 5, 6, 1, 2])


def test_lis3mdl_default_auto_increments_without_the_flag_like_the_part(clock):
    """ArduPilot/PX4/Adafruit read 0x28 without SUB bit 7 on I2C; PX4 issue #12514 shows the part
    incrementing and wrapping 0x2D -> 0x28. The model accepts this by default."""
    m = LIS3MDLModel(clock, StaticTruth(), IdealSensor())
    bus = SimI2CBus()
    bus.attach(0x1C, m)
    assert not m.strict_auto_increment
    m.values[0x28:0x2E] = bytes([1, 2, 3, 4, 5, 6])
    (data,) = bus.transfer(0x1C, [I2CWrite(b"\x28"), I2CRead(8)])
    assert data == bytes([1, 2, 3, 4, 5, 6, 1, 2])


@pytest.mark.parametrize("cls", [HMC5983Model, LSM303DLHCModel])
def test_honeywell_pointer_rules(clock, cls):
    m = cls(clock, StaticTruth(), IdealSensor())
    bus = SimI2CBus()
    bus.attach(0x1E, m)
    # after 0x08 the pointer returns to 0x03 (data block re-read)
    m.values[0x03:0x09] = bytes([1, 2, 3, 4, 5, 6])
    (data,) = bus.transfer(0x1E, [I2CWrite(b"\x03"), I2CRead(8)])
    assert data == bytes([1, 2, 3, 4, 5, 6, 1, 2])
    # at 0x0C the next address is 0x00 (CRA)
    (data,) = bus.transfer(0x1E, [I2CWrite(b"\x0a"), I2CRead(4)])
    assert data[:3] == b"H43" and data[3] == m.values[0x00]


def test_model_power_on_values(clock):
    lis = LIS3MDLModel(clock, StaticTruth(), IdealSensor())
    assert (lis.values[0x20], lis.values[0x22], lis.values[0x30], lis.values[0x0F]) == (0x10, 0x03, 0xE8, 0x3D)
    hmc = HMC5983Model(clock, StaticTruth(), IdealSensor())
    assert (hmc.values[0], hmc.values[1], hmc.values[2]) == (0x10, 0x20, 0x01)
    dl = LSM303DLHCModel(clock, StaticTruth(), IdealSensor())
    assert (dl.values[0], dl.values[1], dl.values[2], dl.values[0x0F]) == (0x10, 0x20, 0x03, 0x3C)


def test_conversions_only_at_output_rate(clock):
    """Lazy conversion: many register reads within one period cost one sense() call."""
    calls = []

    class Counting(IdealSensor):
        def sense(self, t_s, truth):
            calls.append(t_s)
            return super().sense(t_s, truth)

    m = LIS3MDLModel(clock, StaticTruth(), Counting())
    bus = SimI2CBus()
    bus.attach(0x1C, m)
    dev = I2CDevice(bus, 0x1C, auto_increment_flag=0x80)
    dev.write_register(0x20, 0x1C)   # 80 Hz (DO=111)
    dev.write_register(0x22, 0x00)   # continuous
    for _ in range(50):
        dev.read_registers(0x28, 6)
    assert calls == []
    clock.advance_s(0.0126)
    for _ in range(50):
        dev.read_registers(0x28, 6)
    assert len(calls) == 1 and calls[0] == pytest.approx(0.0125)
    clock.advance_s(1.0)       # 80 conversions' worth: only the latest is evaluated
    dev.read_register(0x27)
    assert len(calls) == 2
    assert dev.read_register(0x27) & 0x80   # ZYXOR: unread data overwritten


@pytest.mark.parametrize("chip", ["lis3mdl", "hmc5983", "lsm303dlhc"])
def test_non_finite_truth_fails_loudly_with_a_typed_error(clock, chip):
    """NaN from the truth (field or temperature) is never encoded as a register value."""
    from magstack.drivers.errors import ConfigurationError
    from magstack.drivers.hmc5983 import HMC5983
    from magstack.drivers.lis3mdl import LIS3MDL
    from magstack.drivers.lsm303dlhc import LSM303DLHC

    cls, drv, addr = {"lis3mdl": (LIS3MDLModel, LIS3MDL, 0x1C), "hmc5983": (HMC5983Model, HMC5983, 0x1E),
                      "lsm303dlhc": (LSM303DLHCModel, LSM303DLHC, 0x1E)}[chip]
    for truth, word in ((StaticTruth((1.0, float("nan"), 2.0)), "sensor returned"),
                        (StaticTruth(temp_c=float("nan")), "temperature")):
        m = cls(clock, truth, IdealSensor())
        bus, _ = _dev(m, addr)
        d = drv(bus, clock, stuck_limit=None)
        with pytest.raises(ConfigurationError, match=word):
            d.read()


def test_self_test_fault_knobs_refuse_non_finite_values(clock):
    from magstack.drivers.errors import ConfigurationError

    with pytest.raises(ConfigurationError, match="delta_uT"):
        LIS3MDLModel(clock, StaticTruth(), IdealSensor()).break_self_test((float("nan"), 0.0, 0.0))
    with pytest.raises(ConfigurationError, match="bias_uT"):
        HMC5983Model(clock, StaticTruth(), IdealSensor()).break_self_test((1.0, 2.0))
