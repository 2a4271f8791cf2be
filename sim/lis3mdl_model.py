"""Register-level LIS3MDL simulator on :class:`magstack.sim.i2c_bus.SimI2CBus` (hardware-facts section 1).

- registers with power-on values (CTRL_REG1 0x10, CTRL_REG3 0x03 power-down, INT_CFG 0xE8);
  RO registers refuse writes, unmapped registers fail the transfer.
- I2C auto-increment: the part increments on multi-byte I2C reads whether or not bit 7 of the
  sub-address is set (ArduPilot and PX4 flight drivers and Adafruit read 0x28 without it; PX4
  issue #12514 logic trace), and the output block wraps 0x2D -> 0x28. ST documents bit 7 as the
  way to ask for it; the ``strict_auto_increment`` lint (opt-in, ``strict_auto_increment=True``
  or ``lints=``) refuses a multi-byte access without it.
- invalid addresses read 0 and ignored writes, as the generic model (lints make them NACK).
- conversions at the configured ODR (DO / FAST_ODR+OM / LP forces 0.625 Hz) in virtual time;
  STATUS.ZYXDA set per conversion and cleared when OUT_Z_H is read; ZYXOR when unread data is
  overwritten; BDU holds a new set until both bytes of a started axis are read.
- codes = round(B / LSB) clipped to int16; clipping sets INT_SRC.MROI (cleared on read).
- temperature raw/8 + 25 degC from the truth temperature when TEMP_EN.
- self-test: CTRL_REG1.ST adds ``self_test_delta_uT`` to the sensed field;
  :meth:`LIS3MDLModel.break_self_test` removes it.
- single conversion (MD=01) completes after one ODR period [U], then MD=11 (power-down) [U].
"""
from __future__ import annotations

import numpy as np

from magstack.drivers import lis3mdl as L
from magstack.drivers.chip_table import encode_temperature
from magstack.sim.i2c_register_model import (
    LINT_AUTO_INCREMENT,
    RO,
    RW,
    MagnetometerModel,
    Reg,
    default_sensor,
    finite_vec3,
)

_DO_HZ = (0.625, 1.25, 2.5, 5.0, 10.0, 20.0, 40.0, 80.0)
_FAST_HZ = {0: 1000.0, 1: 560.0, 2: 300.0, 3: 155.0}   # by OM


def lis3mdl_registers() -> tuple[Reg, ...]:
    regs = [
        Reg(L.WHO_AM_I, "WHO_AM_I", RO, 0x3D),
        Reg(L.CTRL_REG1, "CTRL_REG1", RW, 0x10),
        Reg(L.CTRL_REG2, "CTRL_REG2", RW, 0x00, fixed_mask=0x93),
        Reg(L.CTRL_REG3, "CTRL_REG3", RW, 0x03, fixed_mask=0xD8),
        Reg(L.CTRL_REG4, "CTRL_REG4", RW, 0x00, fixed_mask=0xF1),
        Reg(L.CTRL_REG5, "CTRL_REG5", RW, 0x00, fixed_mask=0x3F),
        Reg(L.STATUS_REG, "STATUS_REG", RO, 0x00),
        Reg(0x2E, "TEMP_OUT_L", RO, 0x00),
        Reg(0x2F, "TEMP_OUT_H", RO, 0x00),
        Reg(L.INT_CFG, "INT_CFG", RW, 0xE8, fixed_mask=0x18, fixed_value=0x08),
        Reg(L.INT_SRC, "INT_SRC", RO, 0x00),
        Reg(0x32, "INT_THS_L", RW, 0x00),
        Reg(0x33, "INT_THS_H", RW, 0x00, fixed_mask=0x80),
    ]
    for i, n in enumerate(("OUT_X_L", "OUT_X_H", "OUT_Y_L", "OUT_Y_H", "OUT_Z_L", "OUT_Z_H")):
        regs.append(Reg(L.OUT_X_L + i, n, RO, 0x00))
    return tuple(regs)


class LIS3MDLModel(MagnetometerModel):
    """Simulated LIS3MDL. ``sensor.sense(t_s, truth)`` gives the sensed field in uT."""

    #: default self-test field change, uT (inside the acceptance windows of hardware-facts 1.4;
    #: a model choice, not a measured value)
    DEFAULT_SELF_TEST_DELTA_UT = (200.0, 200.0, 50.0)

    def __init__(self, clock, truth, sensor=None, *, address: int = 0x1C, strict_auto_increment: bool = False,
                 lints=None):
        self.self_test_delta_uT = np.asarray(self.DEFAULT_SELF_TEST_DELTA_UT, dtype=float)
        self._pending: bytes | None = None
        self._half_read: set[int] = set()
        super().__init__(lis3mdl_registers(), name="lis3mdl-sim", clock=clock, truth=truth,
                         sensor=sensor if sensor is not None else default_sensor("lis3mdl"), address=address,
                         lints=lints)
        if strict_auto_increment:
            self.lints = self.lints | {LINT_AUTO_INCREMENT}

    @property
    def strict_auto_increment(self) -> bool:
        """True when the ``strict_auto_increment`` lint is on (datasheet-literal, stricter than the part)."""
        return LINT_AUTO_INCREMENT in self.lints

    def break_self_test(self, delta_uT=(0.0, 0.0, 0.0)) -> None:
        """Make the self-test response ``delta_uT`` (default none: the self-test must fail)."""
        self.self_test_delta_uT = finite_vec3("self-test delta_uT", delta_uT)

    # -- pointer rules -----------------------------------------------------------------
    def decode_subaddress(self, byte: int) -> tuple[int, bool]:
        return byte & 0x7F, bool(byte & 0x80) or not self.strict_auto_increment

    def next_pointer(self, reg: int) -> int:
        if not self._autoinc:
            return reg
        if reg == 0x2D:
            return 0x28
        return (reg + 1) & 0x7F

    # -- configuration ---------------------------------------------------------------
    def _md(self) -> int:
        return self.values[L.CTRL_REG3] & 0x03

    def running(self) -> bool:
        return self._md() == 0

    def period_s(self) -> float:
        r1 = self.values[L.CTRL_REG1]
        if self.values[L.CTRL_REG3] & 0x20:
            return 1.0 / 0.625
        if r1 & 0x02:
            return 1.0 / _FAST_HZ[(r1 >> 5) & 0x03]
        return 1.0 / _DO_HZ[(r1 >> 2) & 0x07]

    def lsb_per_uT(self) -> float:
        fs = (self.values[L.CTRL_REG2] >> 5) & 0x03
        return L.LIS3MDL_TABLE.ranges[fs].lsb_per_gauss[0] / 100.0

    def on_write(self, reg: int, value: int, old: int) -> None:
        if reg == L.CTRL_REG2:
            if value & L.SOFT_RST:
                self.reset_registers()
                self.stop()
                self._pending = None
                self._half_read.clear()
                self.unread = False
                return
            if value & L.REBOOT:
                self.values[reg] = value & ~L.REBOOT  # trimming reload: self-clearing
        if reg == L.CTRL_REG3 or (reg == L.CTRL_REG1 and (value ^ old) & 0x7E):
            md = value & 0x03 if reg == L.CTRL_REG3 else self._md()
            if md == 0:
                self.restart()
            elif md == 1:
                if reg == L.CTRL_REG3:
                    self.trigger_single(self.period_s())
            else:
                self.stop()

    def after_single(self) -> None:
        self.values[L.CTRL_REG3] |= 0x03

    # -- data path -------------------------------------------------------------------
    def store_sample(self, t_s: float, b_uT: np.ndarray, temp_c: float, overwrote: bool, skipped: int = 0) -> None:
        if self.values[L.CTRL_REG1] & L.ST_BIT:
            b_uT = b_uT + self.self_test_delta_uT
        scaled = np.rint(b_uT * self.lsb_per_uT())
        clipped = np.clip(scaled, -32768, 32767)
        if np.any(clipped != scaled):
            self.core_set(L.INT_SRC, self.values[L.INT_SRC] | L.MROI | 0x01)
        c = clipped.astype(np.int64)
        if self.values[L.CTRL_REG4] & 0x02:  # BLE: MSB at the lower address
            block = b"".join(int(v).to_bytes(2, "big", signed=True) for v in c)
        else:
            block = b"".join(int(v).to_bytes(2, "little", signed=True) for v in c)
        if (self.values[L.CTRL_REG5] & L.BDU_BIT) and self._half_read:
            self._pending = block
        else:
            self.core_set_block(L.OUT_X_L, block)
        if self.values[L.CTRL_REG1] & 0x80:
            self.core_set_block(0x2E, encode_temperature(temp_c, L.LIS3MDL_TABLE.temperature))
        status = self.values[L.STATUS_REG] | 0x0F
        if overwrote:
            status |= 0xF0
        self.core_set(L.STATUS_REG, status)
        self.unread = True

    def on_read(self, reg: int) -> None:
        if L.OUT_X_L <= reg <= 0x2D:
            axis, high = divmod(reg - L.OUT_X_L, 2)
            first_is_low = not (self.values[L.CTRL_REG4] & 0x02)
            if bool(high) != first_is_low:
                self._half_read.add(axis)
            else:
                self._half_read.discard(axis)
                if (self.values[L.CTRL_REG4] & 0x02) == 0 and high:
                    self._axis_read(axis)
                elif (self.values[L.CTRL_REG4] & 0x02) and not high:
                    self._axis_read(axis)
            if not self._half_read and self._pending is not None:
                self.core_set_block(L.OUT_X_L, self._pending)
                self._pending = None
        elif reg == L.INT_SRC:
            self.core_set(L.INT_SRC, 0x00)

    def _axis_read(self, axis: int) -> None:
        st = self.values[L.STATUS_REG] & ~((1 << axis) | (0x10 << axis))
        if not st & 0x07:
            st &= ~(L.ZYXDA | L.ZYXOR)
            self.unread = False
        self.core_set(L.STATUS_REG, st)
