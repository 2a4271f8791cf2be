"""ST LSM303DLHC magnetometer part on I2C (hardware-facts section 2).

Register semantics only; the bus is injected. Field in uT, temperature in degC.

- identity: IRA/IRB/IRC (0x0A..0x0C) = 'H', '4', '3' *and* the undocumented WHO_AM_I (0x0F) =
  0x3C, which tells it from an HMC5983 at the same address 0x1E.
- data: X, Z, Y big-endian int16 from 0x03; 12-bit span -2048..2047; -4096 = overflow.
- ranges 130 / 190 / 250 / 400 / 470 / 560 / 810 uT, with a separate Z gain
  (e.g. +-1.3 G: X/Y 1100, Z 980 LSB/G).
- rates 0.75 ... 220 Hz; modes continuous / single / idle (sleep).
- data-ready: SR_REG_M.DRDY, same not-latched semantics as the HMC5983 (driver times reads).
- temperature: 12-bit, 8 LSB/degC, *relative*: the absolute offset is a per-unit calibration
  (``temp_offset_c``, default 20 degC after user reports [F2:DLHC-T]; ST sample code uses 25).
- no documented self-test: :meth:`LSM303DLHC.self_test` raises ConfigurationError saying so.
- no soft-reset register: :meth:`LSM303DLHC.soft_reset` writes the power-on values.
"""
from __future__ import annotations

import math

from magstack.drivers.chip_table import ChipTable, Field, NamedOption, RangeOption, RateOption, TempFormat
from magstack.drivers.errors import ConfigurationError
from magstack.drivers.hmc5983 import HoneywellStyleMagnetometer

CRA_REG_M, CRB_REG_M, MR_REG_M = 0x00, 0x01, 0x02
OUT_X_H_M = 0x03
SR_REG_M = 0x09
IRA_REG_M = 0x0A
WHO_AM_I_M = 0x0F
TEMP_OUT_H_M, TEMP_OUT_L_M = 0x31, 0x32
ACCEL_ADDRESS = 0x19

DRDY = 0x01
LOCK = 0x02

#: (range uT, GN code, X/Y LSB/G, Z LSB/G)  [F:ADA-D][F:K-ST]
_RANGES = ((130.0, 1, 1100.0, 980.0), (190.0, 2, 855.0, 760.0), (250.0, 3, 670.0, 600.0),
           (400.0, 4, 450.0, 400.0), (470.0, 5, 400.0, 355.0), (560.0, 6, 330.0, 295.0),
           (810.0, 7, 230.0, 205.0))
_RATES_HZ = (0.75, 1.5, 3.0, 7.5, 15.0, 30.0, 75.0, 220.0)

DEFAULT_TEMP_OFFSET_C = 20.0

LSM303DLHC_TABLE = ChipTable(
    name="lsm303dlhc",
    addresses=(0x1E,),
    id_checks=((IRA_REG_M, b"H43"), (WHO_AM_I_M, b"\x3c")),
    auto_increment_flag=0,
    data_reg=OUT_X_H_M,
    big_endian=True,
    slot_axes=(0, 2, 1),
    overflow_code=-4096,
    valid_code=(-2048, 2047),
    ranges=tuple(RangeOption(r, code, (xy, xy, z)) for r, code, xy, z in _RANGES),
    rates=tuple(RateOption(hz, code) for code, hz in enumerate(_RATES_HZ)),
    modes=(NamedOption("continuous", 0b00), NamedOption("single", 0b01), NamedOption("idle", 0b11)),
    range_field=Field(CRB_REG_M, 0xE0),
    rate_field=Field(CRA_REG_M, 0x1C),
    mode_field=Field(MR_REG_M, 0x03),
    status_reg=SR_REG_M,
    drdy_mask=DRDY,
    overrun_mask=0,
    drdy_latched=False,
    temperature=TempFormat(regs=(TEMP_OUT_H_M, TEMP_OUT_L_M), big_endian=True, shift=4, lsb_per_c=8.0,
                           offset_c=DEFAULT_TEMP_OFFSET_C, separate_reads=True, absolute=False,
                           enable=Field(CRA_REG_M, 0x80)),
    default_range_uT=130.0,
    default_odr_hz=75.0,
    # CRA default 0x10 (15 Hz) is believed, not confirmed [U]; MR power-on = sleep [U]
    reset_values=((CRA_REG_M, 0x10), (CRB_REG_M, 0x20), (MR_REG_M, 0x03)),
    notes="pointer: 0x08 -> 0x03, >= 0x0C -> 0x00; WHO_AM_I 0x0F = 0x3C undocumented; accel at 0x19",
)


class LSM303DLHC(HoneywellStyleMagnetometer):
    """LSM303DLHC magnetometer driver. ``temp_offset_c``: per-unit temperature offset (degC)."""

    table = LSM303DLHC_TABLE
    supports_self_test = False

    def __init__(self, bus, clock, *, temp_offset_c: float = DEFAULT_TEMP_OFFSET_C, **kw) -> None:
        self.temp_offset_c = float(temp_offset_c)
        if not math.isfinite(self.temp_offset_c):
            raise ConfigurationError(f"lsm303dlhc temp_offset_c must be finite (degC), got {temp_offset_c!r}")
        super().__init__(bus, clock, **kw)

    def _temp_offset_c(self) -> float:
        return self.temp_offset_c

    def self_test(self):
        """The LSM303DLHC magnetometer has no documented self-test: always raises ConfigurationError."""
        raise ConfigurationError("lsm303dlhc: the magnetometer has no documented self-test (no bias strap "
                                 "control in CRA_REG_M); use a known-field check instead")
