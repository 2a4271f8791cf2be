"""Command- and register-level model of the TI ADS1248 on :class:`magstack.sim.spi_bus.SimSpiBus`.

What it checks (fails loudly with :class:`magstack.drivers.errors.BusError`): illegal command bytes
(e.g. the restricted 0xF1), SYS0 bit 7 set, DR codes above 1001, invalid IDAC1 codes, WREG
past 0x0E or to address 0x0F, register access in RDATAC mode, commands while RESET is
held low or within 0.6 ms after a reset, RDATA without 24 SCLKs of NOP, a SYNC not sent
twice, unmodelled monitors (MUXCAL gain / supply / reference monitors, burn-out sources).

Timing in virtual time via the injected clock (tables in :mod:`magstack.drivers.ads1248`): a filter
restart (RESET, START rising, WAKEUP, SYNC) gives the first result after
``first_after_reset_s``; a write to MUX0/VBIAS/MUX1/SYS0 after ``first_after_write_s``;
later results every ``period_s`` while START is high. DRDY falls when a result is ready
and rises when it is read or the filter restarts. SDATAC and RDATAC take effect at the
next DRDY (hardware-facts 4.1). A result is the input sampled once, at the centre of its
conversion window. A read while DRDY is high is counted (``reads_before_drdy``); if the
channel changed since the last result, it returns a blend of the old result and the new
channel weighted by the elapsed fraction of the conversion (``blended_reads``).

Codes: raw = V_in * PGA / Vref * (2**23 - 1); output = (raw - OFC) * FSC / 0x400000,
rounded and clipped to 0x7FFFFF / 0x800000 (PGA input saturation). Like the part, the model never
raises on what its inputs present: a non-finite simulated input (a broken sensor model giving
NaN or inf) reads at the rail, +inf and NaN at 0x7FFFFF, -inf at 0x800000 [I: a model choice], which
the driver flags as clipped.
"""
from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from magstack.drivers.ads1248 import (
    CALIBRATION_PERIODS,
    CODE_NEG_FS,
    CODE_POS_FS,
    DATA_RATE_BY_CODE,
    FILTER_RESTART_REGISTERS,
    FS_DIVISOR,
    INTERNAL_REF_V,
    N_REGISTERS,
    REGISTERS,
    RESET_RECOVERY_S,
    SPI_MODE,
    TEMP_DIODE_V_AT_25C,
    TEMP_DIODE_V_PER_C,
    Command,
    _finite,
)
from magstack.drivers.clock import Clock
from magstack.drivers.errors import BusError, ConfigurationError
from magstack.sim.gpio import SimInputLine, SimOutputLine

_POR = bytes(r.reset for r in REGISTERS.values())
_RO_MASK = tuple(r.ro_mask for r in REGISTERS.values())
_EPS_S = 1e-9  # float tolerance on event times (1 ns, far below any chip timing)
_FSC_UNITY = 0x400000


class AnalogInputs(Protocol):
    """What is wired to the ADC's analog pins."""

    def differential_V(self, pos: int, neg: int, t_s: float) -> float:
        """V(AINpos) - V(AINneg) at ``t_s``; raise BusError for pins not wired."""

    def temp_c(self, t_s: float) -> float:
        """Temperature of the board (used for the ADC's internal diode)."""


class ADS1248Model:
    """Simulated ADS1248. Wire ``start_line``, ``reset_line`` and ``drdy_line`` to the driver.

    ``ref0_V``/``ref1_V``: external reference voltages (None = not wired); ``adc_offset_V``:
    input-referred offset; ``noise_V_rms``: input-referred white noise per conversion;
    ``fsc``: factory-trimmed gain word; ``device_id``: IDAC0 ID nibble;
    ``calibration_conversions``: duration of SELFOCAL/SYSOCAL/SYSGCAL in first-conversion
    times (default :data:`~magstack.drivers.ads1248.CALIBRATION_PERIODS` = 16, the users' measurement;
    no datasheet figure found, see docs/hmc1053-front-end.md);
    ``diode_v_at_25c_V`` / ``diode_V_per_c``: the internal temperature diode of this simulated part
    (default: the unverified forum figures; set others to check that a board calibration recovers them);
    ``power_up_s``: time from construction (power-on) before the first command is accepted
    (users wait ~16 ms [F2]; default 0 = powered long ago).
    """

    required_mode = SPI_MODE

    def __init__(self, clock: Clock, inputs: AnalogInputs, *, ref0_V: float | None = None,
                 ref1_V: float | None = None, adc_offset_V: float = 0.0, noise_V_rms: float = 0.0,
                 fsc: int = _FSC_UNITY, device_id: int = 0x9, calibration_conversions: float = CALIBRATION_PERIODS,
                 diode_v_at_25c_V: float = TEMP_DIODE_V_AT_25C, diode_V_per_c: float = TEMP_DIODE_V_PER_C,
                 max_clock_hz: int = 2_000_000, power_up_s: float = 0.0, seed: int = 0) -> None:
        for label, v in (("ref0_V", ref0_V), ("ref1_V", ref1_V)):
            if v is not None and not (_finite(v) and v > 0):
                raise ConfigurationError(f"ADS1248Model {label} must be None (not wired) or finite > 0, got {v!r}")
        if not _finite(adc_offset_V):
            raise ConfigurationError(f"ADS1248Model adc_offset_V must be finite, got {adc_offset_V!r}")
        if not (_finite(noise_V_rms) and noise_V_rms >= 0):
            raise ConfigurationError(f"ADS1248Model noise_V_rms must be finite and >= 0, got {noise_V_rms!r}")
        if not (_finite(calibration_conversions) and calibration_conversions > 0):
            raise ConfigurationError("ADS1248Model calibration_conversions must be finite and > 0, "
                                     f"got {calibration_conversions!r}")
        if not (_finite(diode_v_at_25c_V) and _finite(diode_V_per_c)):
            raise ConfigurationError("ADS1248Model diode_v_at_25c_V and diode_V_per_c must be finite, got "
                                     f"{diode_v_at_25c_V!r}, {diode_V_per_c!r}")
        if not (_finite(power_up_s) and power_up_s >= 0):
            raise ConfigurationError(f"ADS1248Model power_up_s must be finite and >= 0, got {power_up_s!r}")
        for label, v, lo, hi in (("fsc", fsc, 0, 0xFFFFFF), ("device_id", device_id, 0, 0xF),
                                 ("max_clock_hz", max_clock_hz, 1, math.inf)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise ConfigurationError(f"ADS1248Model {label} must be an int in {lo}..{hi}, got {v!r}")
        self.clock = clock
        self.inputs = inputs
        self.ref_V = {0b00: ref0_V, 0b01: ref1_V, 0b10: INTERNAL_REF_V, 0b11: INTERNAL_REF_V}
        self.adc_offset_V = float(adc_offset_V)
        self.noise_V_rms = float(noise_V_rms)
        self.max_clock_hz = max_clock_hz
        self.calibration_conversions = float(calibration_conversions)
        self.diode_v_at_25c_V = float(diode_v_at_25c_V)
        self.diode_V_per_c = float(diode_V_per_c)
        self._rng = np.random.default_rng(seed)
        self._fsc_trim = int(fsc)
        self._device_id = int(device_id)
        self.start_line = SimOutputLine("START", self._on_start, initial=False)
        self.reset_line = SimOutputLine("RESET", self._on_reset, initial=True)
        self.drdy_line = SimInputLine("DRDY", self._drdy_level)
        # fault injection
        self.drdy_stuck_high = False
        self._stuck: dict[int, tuple[int, int]] = {}
        # counters (tests assert on them)
        self.reads_before_drdy = 0
        self.blended_reads = 0
        self.results = 0
        self.sample_calls = 0
        self.command_log: list[int] = []
        self._power_on()
        self._ready_at = clock.monotonic_s() + power_up_s

    # ------------------------------------------------------------------ state
    def _power_on(self) -> None:
        self.regs = bytearray(_POR)
        self.regs[0x0A] = (self._device_id << 4) | (self.regs[0x0A] & 0x0F)
        self.regs[0x07] = self._fsc_trim & 0xFF
        self.regs[0x08] = (self._fsc_trim >> 8) & 0xFF
        self.regs[0x09] = (self._fsc_trim >> 16) & 0xFF
        self.rdatac = True  # power-up mode
        self._pending_mode: bool | None = None
        self.sleeping = False
        self._conv_start: float | None = None
        self._conv_len = 0.0
        self._calibrating: int | None = None
        self._out_code = 0
        self._out_pending: tuple[float, bytes] | None = None
        self._out_cfg: bytes | None = None
        self._drdy_low = False
        self._ready_at = self.clock.monotonic_s() + RESET_RECOVERY_S
        self._in_reset = False
        if self.start_line.level:
            self._restart(self.clock.monotonic_s(), after_write=False)

    def inject_stuck_bits(self, address: int, mask: int, value: int) -> None:
        """Make bits ``mask`` of register ``address`` read ``value`` whatever is written (fault)."""
        self._stuck[address] = (mask, value & mask)
        self._apply_stuck()

    def _apply_stuck(self) -> None:
        for a, (m, v) in self._stuck.items():
            self.regs[a] = (self.regs[a] & ~m) | v

    @property
    def _rate(self):
        return DATA_RATE_BY_CODE[self.regs[0x03] & 0x0F]

    def _running(self) -> bool:
        return self.start_line.level and not self.sleeping and not self._in_reset

    def _restart(self, now: float, *, after_write: bool) -> None:
        """Reset the digital filter and begin a conversion (if converting is enabled)."""
        self._drdy_low = False
        if not self._running():
            self._conv_start = None
            return
        rate = self._rate
        self._conv_start = now
        self._conv_len = rate.first_after_write_s if after_write else rate.first_after_reset_s
        self._calibrating = None

    def _advance(self, now: float) -> None:
        """Complete the conversions that ended by ``now`` (only the last one is evaluated)."""
        if self._conv_start is None:
            return
        end = self._conv_start + self._conv_len
        if now + _EPS_S < end:
            return
        start_of_last = self._conv_start
        if self._calibrating is not None:
            self._finish_calibration(end)
        if self._running():
            period = self._rate.period_s
            n_more = int(math.floor((now + _EPS_S - end) / period))
            if n_more > 0:
                start_of_last = end + (n_more - 1) * period
                end = end + n_more * period
            self._complete(start_of_last, end)
            self._conv_start, self._conv_len = end, period
        else:  # START low / SLEEP: finish the conversion in progress, then power down
            self._complete(start_of_last, end)
            self._conv_start = None

    def _complete(self, t_from: float, t_end: float) -> None:
        # evaluated lazily on read (a result nobody reads costs nothing), with the
        # configuration in force during its conversion
        self._out_pending = (0.5 * (t_from + t_end), bytes(self.regs[0:10]))
        self._out_cfg = bytes(self.regs[0:4])
        self._drdy_low = True
        self.results += 1
        if self._pending_mode is not None:
            self.rdatac, self._pending_mode = self._pending_mode, None

    # ------------------------------------------------------------------ analog path
    def _input_V(self, t_s: float, regs: bytes) -> float:
        mux0, mux1 = regs[0], regs[2]
        if mux0 >> 6:
            raise BusError("burn-out current sources are not modelled by the simulator",
                           address="sim-ads1248", operation="convert")
        muxcal = mux1 & 0x07
        if muxcal == 0b000:
            return self.inputs.differential_V((mux0 >> 3) & 7, mux0 & 7, t_s)
        if muxcal == 0b001:  # offset measurement: inputs shorted internally
            return 0.0
        if muxcal == 0b011:
            return self.diode_v_at_25c_V + self.diode_V_per_c * (self.inputs.temp_c(t_s) - 25.0)
        raise BusError(f"MUXCAL={muxcal:03b} monitor is not modelled by the simulator",
                       address="sim-ads1248", operation="convert")

    def _vref(self, regs: bytes) -> float:
        mux1 = regs[2]
        refselt = (mux1 >> 3) & 0b11
        if refselt >= 0b10 and (mux1 >> 5) & 0b11 == 0:
            raise BusError("internal reference selected but VREFCON=00 (reference off)",
                           address="sim-ads1248", operation="convert")
        vref = self.ref_V[refselt]
        if vref is None:
            raise BusError(f"REFSELT={refselt:02b} selects an external reference that is not wired",
                           address="sim-ads1248", operation="convert")
        return vref

    def _raw(self, t_s: float, regs: bytes) -> float:
        self.sample_calls += 1
        v = self._input_V(t_s, regs) + self.adc_offset_V
        if self.noise_V_rms:
            v += self.noise_V_rms * self._rng.standard_normal()
        pga = 1 << ((regs[3] >> 4) & 7)
        return v * pga / self._vref(regs) * FS_DIVISOR

    @staticmethod
    def _ofc(regs: bytes) -> int:
        v = regs[4] | (regs[5] << 8) | (regs[6] << 16)
        return v - (1 << 24) if v & 0x800000 else v

    @staticmethod
    def _fsc(regs: bytes) -> int:
        return regs[7] | (regs[8] << 8) | (regs[9] << 16)

    def _code(self, t_s: float, regs: bytes | None = None) -> int:
        regs = bytes(self.regs[0:10]) if regs is None else regs
        return _to_code((self._raw(t_s, regs) - self._ofc(regs)) * self._fsc(regs) / _FSC_UNITY)

    def _output_code(self) -> int:
        if self._out_pending is not None:
            t_s, regs = self._out_pending
            self._out_pending = None
            self._out_code = self._code(t_s, regs)
        return self._out_code

    def _finish_calibration(self, t_end: float) -> None:
        kind, self._calibrating = self._calibrating, None
        regs = bytes(self.regs[0:10])
        if kind == Command.SYSGCAL:
            measured = self._raw(t_end, regs) - self._ofc(regs)
            if not math.isfinite(measured):
                measured = float(CODE_POS_FS)   # the input sits at the rail (see _to_code)
            if measured <= 0:
                raise BusError("SYSGCAL with a non-positive input", address="sim-ads1248", operation="SYSGCAL")
            self._write_word(7, min(round(_FSC_UNITY * CODE_POS_FS / measured), 0xFFFFFF))
            return
        if kind == Command.SELFOCAL:
            pga = 1 << ((regs[3] >> 4) & 7)
            raw = self.adc_offset_V * pga / self._vref(regs) * FS_DIVISOR
        else:  # SYSOCAL: whatever the selected input presents is taken as zero
            raw = self._raw(t_end, regs)
        self._write_word(4, _to_code(raw) & 0xFFFFFF)

    def _write_word(self, address: int, value: int) -> None:
        self.regs[address:address + 3] = bytes((value & 0xFF, (value >> 8) & 0xFF, (value >> 16) & 0xFF))

    # ------------------------------------------------------------------ lines
    def _on_start(self, level: bool) -> None:
        now = self.clock.monotonic_s()
        self._advance(now)
        if level:
            self._restart(now, after_write=False)
        # falling: the conversion in progress completes, then the device powers down (_advance)

    def _on_reset(self, level: bool) -> None:
        if not level:
            self._in_reset = True
            self._conv_start = None
            self._drdy_low = False
            return
        self._power_on()

    def _drdy_level(self) -> bool:
        self._advance(self.clock.monotonic_s())
        return True if self.drdy_stuck_high else not self._drdy_low

    # ------------------------------------------------------------------ SPI
    def _fail(self, msg: str, op: str) -> BusError:
        return BusError(msg, address="sim-ads1248", operation=op)

    def _read_output(self, now: float) -> int:
        if self._drdy_low and not self.drdy_stuck_high:
            self._drdy_low = False
            return self._output_code()
        self.reads_before_drdy += 1
        old = self._output_code()
        if self._conv_start is not None and self._out_cfg != bytes(self.regs[0:4]):
            frac = min(max((now - self._conv_start) / self._conv_len, 0.0), 1.0)
            self.blended_reads += 1
            return _to_code((1.0 - frac) * old + frac * self._code(now))
        return old

    def spi_transfer(self, tx: bytes) -> bytes:
        now = self.clock.monotonic_s()
        if self._in_reset:
            raise self._fail("SPI access while RESET is held low", "transfer")
        if now + _EPS_S < self._ready_at:
            raise self._fail(f"command {1e3 * (self._ready_at - now):.3f} ms too early after reset", "transfer")
        self._advance(now)
        rx = bytearray(b"\xff" * len(tx))
        i = 0
        if self.rdatac and tx and tx[0] == Command.NOP:  # RDATAC readout: 24 SCLKs of NOP
            self._need_nops(tx, 0, 3, "RDATAC readout")
            rx[0:3] = _to24(self._read_output(now))
            i = 3
        while i < len(tx):
            i = self._command(tx, i, rx, now)
        return bytes(rx)

    def _need_nops(self, tx: bytes, start: int, n: int, op: str) -> None:
        if start + n > len(tx):
            raise self._fail(f"{op} needs {n} NOP bytes in the same CS window, got {len(tx) - start}", op)
        if any(b != Command.NOP for b in tx[start:start + n]):
            raise self._fail(f"{op}: non-NOP byte while clocking out data", op)

    def _command(self, tx: bytes, i: int, rx: bytearray, now: float) -> int:
        b = tx[i]
        self.command_log.append(b)
        if self._calibrating is not None and not (b & 0xF0 == Command.RREG or b == Command.NOP):
            raise self._fail(f"command {b:#04x} while a calibration is running", "command")
        if b == Command.NOP:
            return i + 1
        if b in (0x00, 0x01):  # WAKEUP
            if self.sleeping:
                self.sleeping = False
                self._restart(now, after_write=False)
            return i + 1
        if b in (0x02, 0x03):  # SLEEP
            self.sleeping = True
            return i + 1
        if b in (0x04, 0x05):  # SYNC, sent twice
            if i + 1 >= len(tx) or tx[i + 1] not in (0x04, 0x05):
                raise self._fail("SYNC must be sent twice in one CS window", "SYNC")
            if not self._running():
                raise self._fail("SYNC while START is low / asleep starts nothing", "SYNC")
            self._restart(now, after_write=False)
            return i + 2
        if b in (0x06, 0x07):  # RESET command
            self._power_on()
            self._ready_at = now + RESET_RECOVERY_S
            if i + 1 < len(tx):
                raise self._fail("bytes after RESET within the 0.6 ms recovery time", "RESET")
            return i + 1
        if b in (0x12, 0x13):  # RDATA
            self._need_nops(tx, i + 1, 3, "RDATA")
            rx[i + 1:i + 4] = _to24(self._read_output(now))
            return i + 4
        if b in (0x14, 0x15):
            self._pending_mode = True
            return i + 1
        if b in (0x16, 0x17):
            self._pending_mode = False if self.rdatac else None
            return i + 1
        if b & 0xF0 in (Command.RREG, Command.WREG):
            return self._register_access(tx, i, rx, now)
        if b in (Command.SYSOCAL, Command.SYSGCAL, Command.SELFOCAL):
            if not self._running():
                raise self._fail("calibration command while START is low / asleep", "calibrate")
            self._drdy_low = False
            self._calibrating = b
            self._conv_start = now
            self._conv_len = self.calibration_conversions * self._rate.first_after_reset_s
            return i + 1
        raise self._fail(f"illegal command byte {b:#04x}", "command")

    def _register_access(self, tx: bytes, i: int, rx: bytearray, now: float) -> int:
        write = tx[i] & 0xF0 == Command.WREG
        op = "WREG" if write else "RREG"
        if self.rdatac and self._pending_mode is not False:
            raise self._fail(f"{op} in RDATAC mode; send SDATAC and wait for DRDY first", op)
        if self.rdatac:
            raise self._fail(f"{op} before SDATAC took effect (it does at the next DRDY)", op)
        address = tx[i] & 0x0F
        if i + 1 >= len(tx):
            raise self._fail(f"{op} without its count byte", op)
        if tx[i + 1] & 0xF0:
            raise self._fail(f"{op} count byte {tx[i + 1]:#04x} has upper bits set", op)
        n = (tx[i + 1] & 0x0F) + 1
        if address >= N_REGISTERS:
            raise self._fail(f"{op} of register address {address:#04x} (last is 0x0E)", op)
        if i + 2 + n > len(tx):
            raise self._fail(f"{op} of {n} registers needs {n} data bytes", op)
        if not write:
            self._need_nops(tx, i + 2, n, op)
            for k in range(n):
                rx[i + 2 + k] = self.regs[(address + k) % N_REGISTERS]
            return i + 2 + n
        if address + n > N_REGISTERS:
            raise self._fail(f"WREG of {n} registers from {address:#04x} runs past 0x0E", op)
        values = tx[i + 2:i + 2 + n]
        for k, v in enumerate(values):
            self._check_write(address + k, v)
        restart = False
        for k, v in enumerate(values):
            a = address + k
            ro = _RO_MASK[a]
            self.regs[a] = (self.regs[a] & ro) | (v & ~ro)
            restart |= a in FILTER_RESTART_REGISTERS
        self._apply_stuck()
        if restart:
            self._restart(now, after_write=True)
        return i + 2 + n

    def _check_write(self, address: int, value: int) -> None:
        if address == 0x03:
            if value & 0x80:
                raise self._fail(f"SYS0 write {value:#04x}: bit 7 must be 0", "WREG")
            if (value & 0x0F) not in DATA_RATE_BY_CODE:
                raise self._fail(f"SYS0 write {value:#04x}: DR code {value & 0x0F:04b} above 1001", "WREG")
        if address == 0x0B:
            for nib in (value >> 4, value & 0x0F):
                if nib in (0b1010, 0b1011):
                    raise self._fail(f"IDAC1 write {value:#04x}: direction code {nib:04b} is undefined", "WREG")


def _clip(code: int) -> int:
    return CODE_POS_FS if code > CODE_POS_FS else CODE_NEG_FS if code < CODE_NEG_FS else code


def _to_code(x: float) -> int:
    """Round and clip to the 24-bit code range; NaN and +inf -> 0x7FFFFF, -inf -> 0x800000."""
    if not math.isfinite(x):
        return CODE_NEG_FS if x < 0 else CODE_POS_FS
    return _clip(round(x))


def _to24(code: int) -> bytes:
    v = code & 0xFFFFFF
    return bytes(((v >> 16) & 0xFF, (v >> 8) & 0xFF, v & 0xFF))
