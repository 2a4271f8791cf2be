"""Register-level LSM303DLHC magnetometer simulator (hardware-facts section 2).

Same HMC5883L-style core as :mod:`magstack.sim.hmc5983_model` (pointer rule 0x08 -> 0x03, >= 0x0C ->
0x00; first set 2/f after a mode write; RDY not latched by default; -4096 overflow outside
-2048..2047; first set after a gain change uses the old gain), with the DLHC differences:

- identity 'H','4','3' plus WHO_AM_I 0x0F = 0x3C; no HMC5983 measurement-mode / averaging bits
  (CRA bits 6:5 and 1:0 must be 0), no bias strap (no self-test), no DOW flag;
- separate Z gain per range (GN 1..7; GN 0 is not a range in the datasheet table: the write is
  ignored [I], or NACKed with the ``nack_illegal_write`` lint);
- LOCK after a mode-register read: not documented for this part [U]; off by default
  (``lock_on_mode_read=True`` models it as on the HMC5883L);
- MR power-on value 0x03 (sleep) [U]; CRA 0x10 [U];
- temperature: 12-bit left-justified at 0x31/0x32, 8 LSB/degC relative to ``temp_offset_c``.
"""
from __future__ import annotations

import math

from magstack.drivers import lsm303dlhc as D
from magstack.drivers.chip_table import TempFormat
from magstack.drivers.errors import ConfigurationError
from magstack.sim.hmc5983_model import HoneywellStyleModel
from magstack.sim.i2c_register_model import LINT_ILLEGAL_WRITE, RO, RW, Reg, default_sensor


def lsm303dlhc_registers() -> tuple[Reg, ...]:
    return (
        Reg(D.CRA_REG_M, "CRA_REG_M", RW, 0x10, fixed_mask=0x63),
        Reg(D.CRB_REG_M, "CRB_REG_M", RW, 0x20, fixed_mask=0x1F),
        Reg(D.MR_REG_M, "MR_REG_M", RW, 0x03, fixed_mask=0xFC),
        *(Reg(D.OUT_X_H_M + i, n, RO, 0x00) for i, n in enumerate(
            ("OUT_X_H_M", "OUT_X_L_M", "OUT_Z_H_M", "OUT_Z_L_M", "OUT_Y_H_M", "OUT_Y_L_M"))),
        Reg(D.SR_REG_M, "SR_REG_M", RO, 0x00),
        Reg(0x0A, "IRA_REG_M", RO, 0x48),
        Reg(0x0B, "IRB_REG_M", RO, 0x34),
        Reg(0x0C, "IRC_REG_M", RO, 0x33),
        Reg(D.WHO_AM_I_M, "WHO_AM_I_M", RO, 0x3C),
        Reg(D.TEMP_OUT_H_M, "TEMP_OUT_H_M", RO, 0x00),
        Reg(D.TEMP_OUT_L_M, "TEMP_OUT_L_M", RO, 0x00),
    )


class LSM303DLHCModel(HoneywellStyleModel):
    """Simulated LSM303DLHC magnetometer at 0x1E (the accelerometer at 0x19 is not modelled)."""

    table = D.LSM303DLHC_TABLE
    has_bias = False

    def __init__(self, clock, truth, sensor=None, *, address: int = 0x1E, drdy_latched: bool = False,
                 temp_offset_c: float = D.DEFAULT_TEMP_OFFSET_C, lock_on_mode_read: bool = False,
                 lints=None) -> None:
        super().__init__(lsm303dlhc_registers(), name="lsm303dlhc-sim", clock=clock, truth=truth,
                         sensor=sensor if sensor is not None else default_sensor("lsm303dlhc"), address=address,
                         drdy_latched=drdy_latched, lock_on_mode_read=lock_on_mode_read, lints=lints)
        if not math.isfinite(temp_offset_c):
            raise ConfigurationError(f"lsm303dlhc-sim temp_offset_c must be finite, got {temp_offset_c!r}")
        fmt = D.LSM303DLHC_TABLE.temperature
        self.temp_format = TempFormat(fmt.regs, fmt.big_endian, fmt.shift, fmt.lsb_per_c, float(temp_offset_c),
                                      fmt.separate_reads, fmt.absolute, fmt.enable)

    def _gain_code(self) -> int:
        code = self.values[D.CRB_REG_M] >> 5
        return code

    def after_single(self) -> None:
        """Back to sleep (MD = 11) after a single conversion; unlike the HMC5983 no MR7 flag (MR_REG_M
        bits 7:2 are 0 on this part)."""
        self.values[D.MR_REG_M] = (self.values[D.MR_REG_M] & ~0x03) | 0x03

    def on_write(self, reg: int, value: int, old: int) -> None:
        if reg == D.CRB_REG_M and value >> 5 == 0:
            self.values[reg] = old
            if LINT_ILLEGAL_WRITE in self.lints:
                raise self._fail(f"CRB_REG_M gain code 0 is not a valid LSM303DLHC range [lint {LINT_ILLEGAL_WRITE}]",
                                 f"write {reg:#04x}")
            return
        super().on_write(reg, value, old)
