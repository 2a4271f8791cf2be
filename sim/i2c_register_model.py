"""Generic register-file model of an I2C chip, and the converting magnetometer core on top.

:class:`RegisterFileModel` is an :class:`magstack.sim.i2c_bus.I2CTarget`: the first byte of a write
message sets the register pointer, further bytes are written at the pointer, reads return
bytes from the pointer; after each byte the pointer moves by the chip's auto-increment rule
(:meth:`RegisterFileModel.next_pointer`). Registers are declared with :class:`Reg` (RO / RW /
WO mode, power-on value, bits that must keep a fixed value).

Default: behave as the parts do (HMC5883L datasheet p.11, LSM303DLHC DocID018771 p.21): a
read of an invalid (unmapped or write-only) address returns 0, a write to an invalid address,
to a read-only register or to an undefined bit is ignored, and every byte is acknowledged.
Stricter checks are opt-in **lints** (``lints=...``, names in :data:`LINTS`), which fail the
transfer with :class:`~magstack.drivers.errors.BusError` (a NACK) so a driver that relies on
undefined behaviour shows up on the host:

- ``nack_invalid_address``: reads/writes of unmapped registers, reads of write-only ones;
- ``nack_illegal_write``: writes to read-only registers, fixed-bit violations, invalid codes;
- ``strict_auto_increment``: multi-byte access without the chip's documented auto-increment
  flag (LIS3MDL SUB bit 7).

:func:`default_lints` sets the lints of models built without ``lints=`` (tests run the
project's drivers under both profiles).

Fault injection: :meth:`RegisterFileModel.inject_stuck` freezes registers (the chip core can
no longer update them), :meth:`RegisterFileModel.inject_bit_flip` XORs a mask into the value
the controller reads. NACKs are injected on the bus (:meth:`magstack.sim.i2c_bus.SimI2CBus.inject_nack`).

:class:`MagnetometerModel` adds the conversion schedule: conversions happen only at the
configured output rate in virtual time, evaluated lazily at the start of each bus message
(never one ``sense()`` per register read), from a ``sensor`` object with
``sense(t_s, truth) -> ndarray(3) in uT`` and a :class:`magstack.sim.truth_source.TruthSource`.
"""
from __future__ import annotations

import contextlib
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from magstack.drivers.errors import BusError, ConfigurationError

RO, RW, WO = "RO", "RW", "WO"

LINT_INVALID_ADDRESS = "nack_invalid_address"
LINT_ILLEGAL_WRITE = "nack_illegal_write"
LINT_AUTO_INCREMENT = "strict_auto_increment"
#: Every opt-in lint (stricter than the parts).
LINTS = frozenset({LINT_INVALID_ADDRESS, LINT_ILLEGAL_WRITE, LINT_AUTO_INCREMENT})
#: Profiles: the part's behaviour, and every lint on.
PART_FAITHFUL: frozenset[str] = frozenset()
STRICT = LINTS

_default_lints: frozenset[str] = PART_FAITHFUL


def check_lints(lints: Iterable[str]) -> frozenset[str]:
    """``lints`` as a frozenset; ConfigurationError naming the valid ones for an unknown name."""
    if isinstance(lints, str):
        lints = (lints,)
    out = frozenset(lints)
    bad = out - LINTS
    if bad:
        raise ConfigurationError(f"unknown simulator lint(s) {sorted(bad)}; valid: {', '.join(sorted(LINTS))}")
    return out


@contextlib.contextmanager
def default_lints(lints: Iterable[str]) -> Iterator[frozenset[str]]:
    """Within the block, models built without ``lints=`` use ``lints`` (tests: strict profile)."""
    global _default_lints
    old, _default_lints = _default_lints, check_lints(lints)
    try:
        yield _default_lints
    finally:
        _default_lints = old


@dataclass(frozen=True)
class Reg:
    """One register: address, name, access mode, power-on value, fixed bits (mask/value)."""

    addr: int
    name: str
    mode: str = RW
    reset: int = 0x00
    fixed_mask: int = 0x00
    fixed_value: int = 0x00

    def __post_init__(self) -> None:
        if self.mode not in (RO, RW, WO):
            raise ValueError(f"register mode must be RO, RW or WO, got {self.mode!r}")


class IdealSensor:
    """A sensor that reports the true field exactly (tests, and the ideal-physics reference)."""

    def sense(self, t_s: float, truth) -> np.ndarray:
        return np.asarray(truth.field_uT(t_s), dtype=float)


def default_sensor(chip: str, seed: int = 0):
    """The default sensed-value model of ``chip``: ``ErrorModel(preset(chip), seed=seed)`` with
    quantization and saturation off (the chip model quantises to its LSB and saturates itself)."""
    from magstack.sim.error_model import ErrorModel, without
    from magstack.sim.presets import preset

    return ErrorModel(preset(chip), seed=seed, effects=without("quantization", "saturation"))


class RegisterFileModel:
    """Register file with pointer, auto-increment hook, access checks and fault injection."""

    def __init__(self, regs: Iterable[Reg], *, name: str, address: int | None = None,
                 lints: Iterable[str] | None = None) -> None:
        self.name = name
        self.address = address
        self.lints = check_lints(_default_lints if lints is None else lints)
        self.regs: dict[int, Reg] = {}
        for r in regs:
            if r.addr in self.regs:
                raise ValueError(f"{name}: register {r.addr:#04x} declared twice")
            self.regs[r.addr] = r
        self.values = bytearray(256)
        self.pointer = 0
        self._autoinc = True
        self._stuck: set[int] = set()
        self._flips: dict[int, list] = {}
        self.reset_registers()

    # -- errors ----------------------------------------------------------------------
    def _fail(self, message: str, operation: str) -> BusError:
        return BusError(f"{self.name}: {message}", address=self.address, operation=operation)

    # -- hooks for chip models ---------------------------------------------------------
    def decode_subaddress(self, byte: int) -> tuple[int, bool]:
        """(register, auto-increment allowed) from the sub-address byte of a write message."""
        return byte, True

    def next_pointer(self, reg: int) -> int:
        """Register the pointer moves to after a byte at ``reg`` was accessed."""
        return (reg + 1) & 0xFF

    def update(self) -> None:
        """Called at every (repeated) start: chip models bring their state up to 'now'."""

    def on_read(self, reg: int) -> None:
        """Side effects of the controller reading ``reg`` (after its byte was returned)."""

    def on_write(self, reg: int, value: int, old: int) -> None:
        """Side effects of the controller writing ``value`` to ``reg`` (already stored)."""

    # -- register file -----------------------------------------------------------------
    def reset_registers(self) -> None:
        """Power-on values (stuck registers keep their frozen value)."""
        for a, r in self.regs.items():
            if a not in self._stuck:
                self.values[a] = r.reset

    def core_set(self, reg: int, value: int) -> bool:
        """The chip core updates a register (ignored when the register is stuck). True if stored."""
        if reg in self._stuck:
            return False
        self.values[reg] = value & 0xFF
        return True

    def core_set_block(self, reg: int, data: bytes) -> bool:
        """The chip core updates consecutive registers from ``reg``; False if any is stuck."""
        ok = True
        for i, b in enumerate(data):
            ok &= self.core_set(reg + i, b)
        return ok

    # -- fault injection -----------------------------------------------------------------
    def inject_stuck(self, registers: Iterable[int]) -> None:
        """Freeze ``registers`` at their present value: the core can no longer change them."""
        for r in registers:
            if r not in self.regs:
                raise ValueError(f"{self.name}: no register {r:#04x}")
            self._stuck.add(r)

    def inject_bit_flip(self, reg: int, mask: int, count: int | None = None) -> None:
        """XOR ``mask`` into the next ``count`` controller reads of ``reg`` (None: every read)."""
        if reg not in self.regs:
            raise ValueError(f"{self.name}: no register {reg:#04x}")
        self._flips[reg] = [mask & 0xFF, count]

    def clear_faults(self) -> None:
        self._stuck.clear()
        self._flips.clear()

    # -- I2CTarget ----------------------------------------------------------------------
    def i2c_start(self) -> None:
        self.update()

    def i2c_write(self, data: bytes) -> None:
        if not data:
            return  # address-only "quick write" (bus scan): acknowledged, no effect
        reg, autoinc = self.decode_subaddress(data[0])
        if len(data) > 2 and not autoinc:
            # only reachable with the strict_auto_increment lint (decode_subaddress decides)
            raise self._fail(f"multi-byte write at {reg:#04x} without auto-increment "
                             f"[lint {LINT_AUTO_INCREMENT}]", f"write {reg:#04x}")
        self.pointer = reg
        self._autoinc = autoinc
        for value in data[1:]:
            self._write_byte(reg, value)
            reg = self.next_pointer(reg)
            self.pointer = reg

    def _write_byte(self, reg: int, value: int) -> None:
        r = self.regs.get(reg)
        op = f"write {reg:#04x}"
        if r is None:
            if LINT_INVALID_ADDRESS in self.lints:
                raise self._fail(f"write to unmapped register {reg:#04x} [lint {LINT_INVALID_ADDRESS}]", op)
            return  # the part ignores writes to invalid addresses
        if r.mode == RO:
            if LINT_ILLEGAL_WRITE in self.lints:
                raise self._fail(f"write to read-only register {r.name} ({reg:#04x}) [lint {LINT_ILLEGAL_WRITE}]",
                                 op)
            return  # ignored
        if (value & r.fixed_mask) != r.fixed_value:
            if LINT_ILLEGAL_WRITE in self.lints:
                raise self._fail(f"write {value:#04x} to {r.name} violates fixed bits (mask {r.fixed_mask:#04x} "
                                 f"must be {r.fixed_value:#04x}) [lint {LINT_ILLEGAL_WRITE}]", op)
            value = (value & ~r.fixed_mask & 0xFF) | r.fixed_value  # undefined bits: the write is ignored
        old = self.values[reg]
        self.values[reg] = value
        self.on_write(reg, value, old)

    def i2c_read(self, length: int) -> bytes:
        if length > 1 and not self._autoinc:
            raise self._fail(f"{length}-byte read at {self.pointer:#04x} without auto-increment flag "
                             f"[lint {LINT_AUTO_INCREMENT}]", f"read {self.pointer:#04x}")
        out = bytearray(length)
        reg = self.pointer
        values, regs, flips = self.values, self.regs, self._flips
        for i in range(length):
            r = regs.get(reg)
            if r is None or r.mode == WO:
                if LINT_INVALID_ADDRESS in self.lints:
                    what = f"unmapped register {reg:#04x}" if r is None else \
                        f"write-only register {r.name} ({reg:#04x})"
                    raise self._fail(f"read of {what} [lint {LINT_INVALID_ADDRESS}]", f"read {reg:#04x}")
                out[i] = 0  # an invalid address reads as 0
                reg = self.next_pointer(reg)
                continue
            v = values[reg]
            if flips and reg in flips:
                f = flips[reg]
                v ^= f[0]
                if f[1] is not None:
                    f[1] -= 1
                    if f[1] <= 0:
                        del flips[reg]
            out[i] = v
            self.on_read(reg)
            reg = self.next_pointer(reg)
        self.pointer = reg
        return bytes(out)


#: Conversion instants evaluated per prefetch of a memoising truth source.
PREFETCH = 256


class MagnetometerModel(RegisterFileModel):
    """A register file plus a lazily evaluated conversion schedule in virtual time.

    Subclasses define ``running()`` (is the chip converting continuously), ``period_s()``,
    and ``store_sample(t_s, b_uT, temp_c, overwrote)`` (encode into output registers and
    status). :meth:`restart` (re)starts the schedule with the first conversion after
    ``first_delay_s``; :meth:`trigger_single` schedules one conversion.
    """

    def __init__(self, regs: Iterable[Reg], *, name: str, clock, truth, sensor, address: int | None = None,
                 lints: Iterable[str] | None = None):
        self.clock = clock
        self.truth = truth
        self.sensor = sensor
        self._next_conv_s = math.inf
        self._single_pending = False
        self.unread = False          # a converted set has not been fully read yet
        self.conversions = 0
        self._prefetched_s = -math.inf   # conversion instants up to here were handed to the truth's prefetch
        super().__init__(regs, name=name, address=address, lints=lints)

    # to override
    def running(self) -> bool:
        raise NotImplementedError

    def period_s(self) -> float:
        raise NotImplementedError

    def store_sample(self, t_s: float, b_uT: np.ndarray, temp_c: float, overwrote: bool, skipped: int = 0) -> None:
        """Encode one conversion at ``t_s``. ``skipped``: conversions the chip completed since the last
        evaluated one (the lazy schedule evaluates only the latest; rules that change state per
        conversion must account for them, so a read never depends on how often the host polled)."""
        raise NotImplementedError

    def after_single(self) -> None:
        """Mode change after a single conversion completed (chip-specific)."""

    # schedule
    def restart(self, first_delay_s: float | None = None) -> None:
        """Start continuous conversions: first one ``first_delay_s`` from now (default one period)."""
        now = self.clock.monotonic_s()
        self._single_pending = False
        self._next_conv_s = now + (self.period_s() if first_delay_s is None else first_delay_s)

    def stop(self) -> None:
        self._next_conv_s = math.inf
        self._single_pending = False

    def trigger_single(self, delay_s: float) -> None:
        self._single_pending = True
        self._next_conv_s = self.clock.monotonic_s() + delay_s

    def update(self) -> None:
        now = self.clock.monotonic_s()
        if now < self._next_conv_s:
            return
        if self._single_pending:
            t_c = self._next_conv_s
            self._single_pending = False
            self._next_conv_s = math.inf
            self._convert(t_c)
            self.after_single()
            return
        if not self.running():
            self._next_conv_s = math.inf
            return
        period = self.period_s()
        k = math.floor((now - self._next_conv_s) / period)
        t_c = self._next_conv_s + k * period
        self._next_conv_s = t_c + period
        if t_c > self._prefetched_s:
            self._prefetch(t_c, period)
        self._convert(t_c, skipped=k)

    def _prefetch(self, t_c: float, period: float) -> None:
        """Let a memoising truth (:class:`~magstack.sim.truth_memo.TruthMemo`) evaluate the next conversion
        instants in one call: ``t_c``, ``t_c + period``, ... by the same float additions as the schedule."""
        ahead = getattr(self.sensor, "prefetch", None)
        if ahead is None or not hasattr(self.truth, "prefetch"):
            self._prefetched_s = math.inf
            return
        ts = [t_c]
        for _ in range(PREFETCH - 1):
            ts.append(ts[-1] + period)
        ahead(ts, self.truth)
        self._prefetched_s = ts[-2]

    def _convert(self, t_c: float, skipped: int = 0) -> None:
        b = np.asarray(self.sensor.sense(t_c, self.truth), dtype=float)
        if b.shape != (3,) or not np.all(np.isfinite(b)):
            raise ConfigurationError(f"{self.name}: sensor returned {b!r} at t_s={t_c!r}, expected 3 finite "
                                     "values in uT")
        temp_c = float(self.truth.temp_c(t_c))
        if not math.isfinite(temp_c):
            raise ConfigurationError(f"{self.name}: truth temperature {temp_c!r} degC at t_s={t_c!r} is not finite")
        overwrote = self.unread or skipped > 0
        self.conversions += 1
        self.store_sample(t_c, b, temp_c, overwrote, skipped)


def finite_vec3(name: str, value) -> np.ndarray:
    """``value`` as a finite (3,) float array; ConfigurationError naming ``name`` otherwise."""
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ConfigurationError(f"{name} must be 3 finite values, got {value!r}")
    return arr

