"""Register-level HMC5983 simulator (hardware-facts section 3), plus the HMC5883L-style core
shared with the LSM303DLHC magnetometer model.

- registers with power-on values (CRA 0x10, CRB 0x20, MR 0x01); CRB bits 4:0 must be 0.
- pointer auto-increments on its own: after 0x08 it returns to 0x03, at or above 0x0C the
  next address is 0x00 (so temperature 0x31/0x32 is read as two single-byte reads).
- continuous mode: first set 2/f after the mode/config write, then every 1/f [F2:HMC-DDS];
  single mode: one set ``SINGLE_CONVERSION_S`` after the write, then MD = idle and MR7 set.
- RDY: ``drdy_latched=False`` (datasheet reading): low for 250 us while a new set is written,
  high otherwise; True: set by a conversion, cleared once the whole data block has been read.
  DOW when a set overwrote unread data (cleared when a data read starts); LOCK while a data
  block is part-read **or after the mode register was read** (HMC5883L datasheet p.16, status
  register; ``lock_on_mode_read``, on for the HMC5983): new sets are held until all six data
  bytes are read, CRA or MR is written.
- codes = round(B * gain); outside -2048..2047 -> -4096 on that axis (also in bias mode when
  field + bias saturates). The first set after a gain change still uses the old gain
  (HMC5883L p.13); later sets use the new one even when nobody read the first (the lazy schedule
  counts the conversions it skipped, so a read never depends on how often the host polled).
- self-test (MS=01/10): output = +-``self_test_bias_uT`` x gain; :meth:`break_self_test`.
- temperature (TS): word/128 + 25 degC from the truth temperature; MS=11 updates only it.
"""
from __future__ import annotations

import numpy as np

from magstack.drivers import hmc5983 as H
from magstack.drivers.chip_table import ChipTable, encode_axes, encode_temperature
from magstack.sim.i2c_register_model import RO, RW, MagnetometerModel, Reg, default_sensor, finite_vec3

RDY_LOW_S = 250e-6


def hmc5983_registers() -> tuple[Reg, ...]:
    return (
        Reg(H.CRA, "CRA", RW, 0x10),
        Reg(H.CRB, "CRB", RW, 0x20, fixed_mask=0x1F),
        Reg(H.MR, "MR", RW, 0x01, fixed_mask=0x58),
        *(Reg(H.DATA_X_MSB + i, n, RO, 0x00) for i, n in enumerate(
            ("DXRA", "DXRB", "DZRA", "DZRB", "DYRA", "DYRB"))),
        Reg(H.STATUS, "SR", RO, 0x00),
        Reg(0x0A, "IRA", RO, ord("H")),
        Reg(0x0B, "IRB", RO, ord("4")),
        Reg(0x0C, "IRC", RO, ord("3")),
        Reg(H.TEMP_MSB, "TEMP_OUT_MSB", RO, 0x00),
        Reg(H.TEMP_LSB, "TEMP_OUT_LSB", RO, 0x00),
    )


class HoneywellStyleModel(MagnetometerModel):
    """HMC5883L-style magnetometer core (CRA/CRB/MR, X-Z-Y big-endian, -4096 overflow)."""

    table: ChipTable
    rates_hz: tuple[float, ...] = (0.75, 1.5, 3.0, 7.5, 15.0, 30.0, 75.0, 220.0)
    single_conversion_s = H.SINGLE_CONVERSION_S
    has_bias = True
    temp_update_needs_ts = True

    def __init__(self, regs, *, name: str, clock, truth, sensor, address: int, drdy_latched: bool,
                 lock_on_mode_read: bool, lints=None) -> None:
        self.drdy_latched = drdy_latched
        self.lock_on_mode_read = bool(lock_on_mode_read)
        self._mr_lock = False
        self._gain_code_in_use = None
        self._last_conv_s = -1.0
        self._pending: bytes | None = None
        self._read_mask = 0
        self.self_test_bias_uT = np.array([116.0, 116.0, 108.0])
        self.temp_format = self.table.temperature
        super().__init__(regs, name=name, clock=clock, truth=truth, sensor=sensor, address=address, lints=lints)
        self._gain_code_in_use = self._gain_code()

    def break_self_test(self, bias_uT=(0.0, 0.0, 0.0)) -> None:
        """Make the bias strap produce ``bias_uT`` (default none: the self-test must fail)."""
        self.self_test_bias_uT = finite_vec3("self-test bias_uT", bias_uT)

    # -- pointer -----------------------------------------------------------------------
    def next_pointer(self, reg: int) -> int:
        if reg == 0x08:
            return 0x03
        if reg >= 0x0C:
            return 0x00
        return reg + 1

    # -- configuration ---------------------------------------------------------------
    def _gain_code(self) -> int:
        return self.values[H.CRB] >> 5

    def _md(self) -> int:
        return self.values[H.MR] & 0x03

    def running(self) -> bool:
        return self._md() == 0

    def period_s(self) -> float:
        if self.values[H.MR] & 0x20:   # LP: forced 0.75 Hz (HMC5983; harmless for others)
            return 1.0 / 0.75
        return 1.0 / self.rates_hz[(self.values[H.CRA] >> 2) & 0x07]

    def on_write(self, reg: int, value: int, old: int) -> None:
        if reg in (H.CRA, H.MR):
            self._read_mask = 0          # mode/CRA change unlocks the outputs
            self._mr_lock = False
            self._apply_pending()
            self._update_lock()
            md = self._md()
            if md == 0:
                self.restart(2.0 * self.period_s())
            elif md == 1 and reg == H.MR:
                self._set_rdy(False)
                self.trigger_single(self.single_conversion_s)
            elif md >= 2:
                self.stop()

    def after_single(self) -> None:
        self.values[H.MR] = (self.values[H.MR] & ~0x03) | 0x03 | 0x80

    # -- status ------------------------------------------------------------------------
    def _set_rdy(self, on: bool) -> None:
        st = self.values[H.STATUS]
        self.core_set(H.STATUS, (st | H.RDY) if on else (st & ~H.RDY))

    def update(self) -> None:
        super().update()
        if not self.drdy_latched and self.conversions and not self._single_pending:
            # RDY is low only while the chip writes the outputs (250 us after a conversion)
            self._set_rdy(self.clock.monotonic_s() >= self._last_conv_s + RDY_LOW_S)

    # -- data path -------------------------------------------------------------------
    def _encode(self, b_uT: np.ndarray, gain_code: int, ms: int) -> list[int]:
        gains = self.table.ranges[self._range_index(gain_code)].lsb_per_gauss
        lo, hi = self.table.valid_code
        if ms in (1, 2) and self.has_bias:
            bias = self.self_test_bias_uT * (1.0 if ms == 1 else -1.0)
            total = np.rint((b_uT + bias) / 100.0 * np.asarray(gains))
            out = np.rint(bias / 100.0 * np.asarray(gains))
            return [-4096 if not (lo <= t <= hi) else int(o) for t, o in zip(total, out, strict=True)]
        codes = np.rint(b_uT / 100.0 * np.asarray(gains))
        return [int(c) if lo <= c <= hi else -4096 for c in codes]

    def _range_index(self, gain_code: int) -> int:
        for i, r in enumerate(self.table.ranges):
            if r.code == gain_code:
                return i
        raise AssertionError(f"{self.name}: gain code {gain_code} not in table")

    def _locked(self) -> bool:
        return bool(self._read_mask) or self._mr_lock

    def store_sample(self, t_s: float, b_uT: np.ndarray, temp_c: float, overwrote: bool, skipped: int = 0) -> None:
        ms = self.values[H.CRA] & 0x03 if self.has_bias else 0
        self._last_conv_s = t_s
        if self.values[H.CRA] & 0x80 or not self.temp_update_needs_ts:
            tb = encode_temperature(temp_c, self.temp_format)
            self.core_set(H.TEMP_MSB, tb[0])
            self.core_set(H.TEMP_LSB, tb[1])
        if ms == 3:
            return
        # the first conversion after a gain change still uses the old gain; when the lazy schedule
        # skipped conversions, one of them already used it up
        gain = self._gain_code_in_use if skipped == 0 else self._gain_code()
        self._gain_code_in_use = self._gain_code()
        block = encode_axes(self._encode(b_uT, gain, ms), self.table)
        if self._locked():
            self._pending = block          # LOCK: hold until the block is fully read
        else:
            self.core_set_block(H.DATA_X_MSB, block)
        st = self.values[H.STATUS]
        if overwrote and self.table.overrun_mask:
            st |= self.table.overrun_mask
        self.core_set(H.STATUS, st)
        if self.drdy_latched:
            self._set_rdy(True)
        self.unread = True

    def _apply_pending(self) -> None:
        if self._pending is not None:
            self.core_set_block(H.DATA_X_MSB, self._pending)
            self._pending = None

    def on_read(self, reg: int) -> None:
        if reg == H.MR and self.lock_on_mode_read:
            self._mr_lock = True
            self._update_lock()
            return
        if H.DATA_X_MSB <= reg <= 0x08:
            if self._read_mask == 0 and self.table.overrun_mask:
                self.core_set(H.STATUS, self.values[H.STATUS] & ~self.table.overrun_mask)
            self._read_mask |= 1 << (reg - H.DATA_X_MSB)
            if self._read_mask == 0x3F:
                self._read_mask = 0
                self._mr_lock = False
                self.unread = False
                if self.drdy_latched:
                    self._set_rdy(False)
                self._apply_pending()
            self._update_lock()

    def _update_lock(self) -> None:
        st = self.values[H.STATUS]
        self.core_set(H.STATUS, (st | H.LOCK) if self._locked() else (st & ~H.LOCK))


class HMC5983Model(HoneywellStyleModel):
    """Simulated HMC5983 at 0x1E. ``sensor.sense(t_s, truth)`` gives the sensed field in uT."""

    table = H.HMC5983_TABLE

    def __init__(self, clock, truth, sensor=None, *, address: int = 0x1E, drdy_latched: bool = False,
                 lock_on_mode_read: bool = True, lints=None) -> None:
        super().__init__(hmc5983_registers(), name="hmc5983-sim", clock=clock, truth=truth,
                         sensor=sensor if sensor is not None else default_sensor("hmc5983"), address=address,
                         drdy_latched=drdy_latched, lock_on_mode_read=lock_on_mode_read, lints=lints)


def hmc5883l_registers() -> tuple[Reg, ...]:
    """HMC5883L: the HMC5983 map without temperature registers; CRA bit 7 must be 0 (p.12)."""
    return tuple(Reg(r.addr, r.name, r.mode, r.reset, fixed_mask=r.fixed_mask | 0x80, fixed_value=r.fixed_value)
                 if r.addr == H.CRA else r for r in hmc5983_registers() if r.addr not in (H.TEMP_MSB, H.TEMP_LSB))


class HMC5883LModel(HoneywellStyleModel):
    """Simulated HMC5883L (no temperature sensor): 0x31/0x32 read 0 like every invalid address,
    a write of CRA bit 7 is ignored (NACKed with the ``nack_illegal_write`` lint). Used to check
    that nothing identifies it as an HMC5983 or turns its reserved TS bit on."""

    table = H.HMC5983_TABLE

    def __init__(self, clock, truth, sensor=None, *, address: int = 0x1E, drdy_latched: bool = False,
                 lock_on_mode_read: bool = True, lints=None) -> None:
        super().__init__(hmc5883l_registers(), name="hmc5883l-sim", clock=clock, truth=truth,
                         sensor=sensor if sensor is not None else default_sensor("hmc5983"), address=address,
                         drdy_latched=drdy_latched, lock_on_mode_read=lock_on_mode_read, lints=lints)
