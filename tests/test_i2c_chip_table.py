"""Generic table code: lookup, fields, encode/decode, masked RMW with read-back."""
from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.drivers.bus.i2c import I2CDevice
from magstack.drivers.chip_table import (
    Field,
    decode_axes,
    decode_temperature,
    encode_axes,
    encode_temperature,
    lookup,
    write_field,
)
from magstack.drivers.errors import ConfigurationError, ReadbackMismatch
from magstack.drivers.hmc5983 import HMC5983_TABLE
from magstack.drivers.lis3mdl import LIS3MDL_TABLE
from magstack.drivers.lsm303dlhc import LSM303DLHC_TABLE
from magstack.sim.i2c_bus import SimI2CBus
from magstack.sim.i2c_register_model import RW, Reg, RegisterFileModel

TABLES = (LIS3MDL_TABLE, HMC5983_TABLE, LSM303DLHC_TABLE)


def test_lookup_exact_match_and_error_names_valid_values():
    assert LIS3MDL_TABLE.range_option(800).code == 1
    assert LIS3MDL_TABLE.rate_option(0.625).code == 0
    with pytest.raises(ConfigurationError) as e:
        LIS3MDL_TABLE.range_option(500)
    assert "400, 800, 1200, 1600" in str(e.value)
    assert isinstance(e.value, ValueError)
    with pytest.raises(ConfigurationError, match="continuous, single, idle"):
        HMC5983_TABLE.mode_option("sleep")
    with pytest.raises(ConfigurationError):
        lookup(LIS3MDL_TABLE.rates, "odr_hz", "fast", "rate")


def test_field_encode_decode():
    f = Field(0x20, 0x1E)
    assert f.shift == 1
    assert f.encode(0b1110) == 0x1C
    assert f.decode(0xFF) == 0x0F
    with pytest.raises(ValueError):
        f.encode(0x10)


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(TABLES), st.tuples(*[st.integers(-32768, 32767)] * 3))
def test_axes_encode_decode_roundtrip(table, codes):
    assert decode_axes(encode_axes(codes, table), table) == codes


def test_axis_order_and_endianness_golden():
    # LIS3MDL little-endian X, Y, Z
    assert decode_axes(bytes([0x01, 0x02, 0x03, 0x04, 0x05, 0x06]), LIS3MDL_TABLE) == (0x0201, 0x0403, 0x0605)
    # HMC5983 / LSM303DLHC big-endian X, Z, Y
    for t in (HMC5983_TABLE, LSM303DLHC_TABLE):
        assert decode_axes(bytes([0x01, 0x02, 0x03, 0x04, 0x05, 0x06]), t) == (0x0102, 0x0506, 0x0304)
    assert decode_axes(bytes([0xF0, 0x00] * 3), HMC5983_TABLE) == (-4096, -4096, -4096)


def test_temperature_golden():
    # LIS3MDL: raw/8 + 25 (little-endian)
    assert decode_temperature(bytes([0x08, 0x00]), LIS3MDL_TABLE.temperature) == 26.0
    assert decode_temperature(bytes([0xF8, 0xFF]), LIS3MDL_TABLE.temperature) == 24.0
    # HMC5983: (MSB*256 + LSB)/128 + 25
    assert decode_temperature(bytes([0x01, 0x00]), HMC5983_TABLE.temperature) == 27.0
    # LSM303DLHC: 12-bit left-justified, 8 LSB/degC, relative (offset supplied per unit)
    assert decode_temperature(bytes([0x01, 0x00]), LSM303DLHC_TABLE.temperature, 0.0) == 2.0
    assert decode_temperature(bytes([0xFF, 0xF0]), LSM303DLHC_TABLE.temperature, 0.0) == -0.125


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(TABLES), st.floats(-40, 85))
def test_temperature_roundtrip(table, temp_c):
    fmt = table.temperature
    back = decode_temperature(encode_temperature(temp_c, fmt), fmt)
    assert abs(back - temp_c) <= 0.5 / fmt.lsb_per_c + 1e-9


class _Flaky(RegisterFileModel):
    """A register that does not keep bit 0 (to exercise read-back checking)."""

    def on_write(self, reg, value, old):
        self.values[reg] = value & 0xFE


def test_write_field_masked_rmw_and_readback():
    bus = SimI2CBus()
    model = RegisterFileModel([Reg(0x10, "A", RW, 0xA5)], name="m")
    bus.attach(0x30, model)
    dev = I2CDevice(bus, 0x30)
    assert write_field(dev, Field(0x10, 0x0C), 0b10) == 0xA9
    assert model.values[0x10] == 0xA9
    flaky = _Flaky([Reg(0x10, "A", RW, 0x00)], name="flaky")
    bus.attach(0x31, flaky)
    with pytest.raises(ReadbackMismatch):
        write_field(I2CDevice(bus, 0x31), Field(0x10, 0x01), 1)


def test_golden_datasheet_values():
    # LIS3MDL 6842/3421/2281/1711 LSB/G (hardware-facts 1.2)
    assert [r.lsb_per_gauss[0] for r in LIS3MDL_TABLE.ranges] == [6842, 3421, 2281, 1711]
    assert [r.range_uT for r in LIS3MDL_TABLE.ranges] == [400, 800, 1200, 1600]
    # Adafruit rate codes: 80 Hz 0b1110, 155 0b0001, 300 0b0011, 560 0b0101, 1000 0b0111
    codes = {r.odr_hz: r.code for r in LIS3MDL_TABLE.rates}
    assert (codes[80], codes[155], codes[300], codes[560], codes[1000]) == (0b1110, 1, 3, 5, 7)
    assert LIS3MDL_TABLE.id_checks == ((0x0F, b"\x3d"),)
    # LSM303DLHC own Z gain: +-1.3 G X/Y 1100, Z 980; +-8.1 G 230/205
    r13 = LSM303DLHC_TABLE.range_option(130)
    assert r13.lsb_per_gauss == (1100, 1100, 980) and r13.code == 1
    assert LSM303DLHC_TABLE.range_option(810).lsb_per_gauss == (230, 230, 205)
    assert LSM303DLHC_TABLE.slot_axes == (0, 2, 1) and LSM303DLHC_TABLE.big_endian
    # HMC5983 gains 1370..230, big-endian X-Z-Y, -4096 overflow, 220 Hz top rate
    assert [r.lsb_per_gauss[0] for r in HMC5983_TABLE.ranges] == [1370, 1090, 820, 660, 440, 390, 330, 230]
    assert HMC5983_TABLE.range_option(470).code == 5
    assert HMC5983_TABLE.slot_axes == (0, 2, 1) and HMC5983_TABLE.big_endian
    assert HMC5983_TABLE.overflow_code == -4096 and LSM303DLHC_TABLE.overflow_code == -4096
    assert max(r.odr_hz for r in HMC5983_TABLE.rates) == 220
    assert HMC5983_TABLE.id_checks == ((0x0A, b"H43"),)
    assert LSM303DLHC_TABLE.id_checks == ((0x0A, b"H43"), (0x0F, b"\x3c"))
