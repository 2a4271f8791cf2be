"""Chips described as data: frozen settings tables plus the generic code that uses them.

A :class:`ChipTable` holds everything register-level about one magnetometer: identity
registers, data block layout (byte order, axis order, overflow code), the range / rate /
mode option tables and the register fields they live in, the status flags and the
temperature format. Generic helpers do the rest: :func:`lookup` (exact match, raising
:class:`~magstack.drivers.errors.ConfigurationError` that names the valid values),
:func:`write_field` (masked read-modify-write with read-back check), :func:`decode_axes`
and :class:`TableMagnetometer`, the shared read path (wait for a *new* sample through
the injected clock, decode, flag overflow, detect stuck data).

Units: field in uT (1 G = 100 uT), sensitivities in LSB/G as the datasheets give them,
rates in Hz, times in s, temperature in degC.
"""
from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from magstack.drivers.bus.i2c import I2CBus, I2CDevice
from magstack.drivers.errors import (
    BusError,
    BusTimeout,
    ConfigurationError,
    DeviceIdMismatch,
    DeviceNotFound,
    ReadbackMismatch,
    StaleData,
)
from magstack.drivers.magnetometer import MagSample

UT_PER_GAUSS = 100.0


# --------------------------------------------------------------------------- table types
@dataclass(frozen=True)
class Field:
    """A bit field: ``mask`` within register ``reg``; codes are right-justified."""

    reg: int
    mask: int

    @property
    def shift(self) -> int:
        return (self.mask & -self.mask).bit_length() - 1

    def encode(self, code: int) -> int:
        """Register bits for ``code`` (raises ValueError if it does not fit the field)."""
        bits = code << self.shift
        if bits & ~self.mask:
            raise ValueError(f"code {code} does not fit mask {self.mask:#04x}")
        return bits

    def decode(self, value: int) -> int:
        return (value & self.mask) >> self.shift


@dataclass(frozen=True)
class RangeOption:
    """A full-scale range. ``lsb_per_gauss`` per axis X, Y, Z (LSM303DLHC has its own Z gain)."""

    range_uT: float
    code: int
    lsb_per_gauss: tuple[float, float, float]

    @property
    def uT_per_lsb(self) -> tuple[float, float, float]:
        return tuple(UT_PER_GAUSS / s for s in self.lsb_per_gauss)  # type: ignore[return-value]


@dataclass(frozen=True)
class RateOption:
    """An output data rate. ``code`` goes into the table's rate field; ``perf`` (LIS3MDL fast
    rates) is the operating-mode name the rate forces, or None when the rate allows any."""

    odr_hz: float
    code: int
    perf: str | None = None


@dataclass(frozen=True)
class NamedOption:
    """A named register code (operating mode, performance mode, averaging...)."""

    name: str
    code: int


@dataclass(frozen=True)
class TempFormat:
    """On-chip temperature: ``regs`` read as single bytes (``separate_reads``) or one burst;
    ``big_endian`` order of the 16-bit word; ``shift`` right-justifies it; degC = word / lsb_per_c
    + offset_c. ``absolute`` False means the offset is a per-unit calibration, not a datasheet value."""

    regs: tuple[int, int]
    big_endian: bool
    shift: int
    lsb_per_c: float
    offset_c: float
    separate_reads: bool
    absolute: bool = True
    enable: Field | None = None


@dataclass(frozen=True)
class ChipTable:
    """Everything register-level about one magnetometer.

    ``slot_axes[i]`` is the axis (0=X, 1=Y, 2=Z) stored in the i-th 16-bit word of the data
    block. ``overflow_code`` is the code the chip writes on ADC overflow (None: no such code);
    ``valid_code`` the inclusive span of real measurement codes. ``drdy_latched`` True means the
    status data-ready flag stays set until the data block is read (ST behaviour); False means it
    only drops while the chip writes the output registers (Honeywell datasheet reading), so a new
    sample cannot be told from an old one by the flag and the driver times reads instead.
    """

    name: str
    addresses: tuple[int, ...]
    id_checks: tuple[tuple[int, bytes], ...]
    auto_increment_flag: int
    data_reg: int
    big_endian: bool
    slot_axes: tuple[int, int, int]
    overflow_code: int | None
    valid_code: tuple[int, int]
    ranges: tuple[RangeOption, ...]
    rates: tuple[RateOption, ...]
    modes: tuple[NamedOption, ...]
    range_field: Field
    rate_field: Field
    mode_field: Field
    status_reg: int
    drdy_mask: int
    overrun_mask: int
    drdy_latched: bool
    temperature: TempFormat | None
    default_range_uT: float
    default_odr_hz: float
    odr_tolerance: float = 0.1
    reset_values: tuple[tuple[int, int], ...] = ()
    notes: str = ""

    def range_option(self, range_uT: float) -> RangeOption:
        return lookup(self.ranges, "range_uT", range_uT, f"{self.name} range_uT")

    def rate_option(self, odr_hz: float) -> RateOption:
        return lookup(self.rates, "odr_hz", odr_hz, f"{self.name} odr_hz")

    def mode_option(self, mode: str) -> NamedOption:
        return lookup(self.modes, "name", mode, f"{self.name} mode")


# --------------------------------------------------------------------------- generic helpers
def lookup(options: Sequence, key: str, value, what: str):
    """The option whose attribute ``key`` equals ``value`` exactly; else ConfigurationError
    naming the valid values."""
    for opt in options:
        ref = getattr(opt, key)
        if isinstance(ref, str):
            if isinstance(value, str) and value == ref:
                return opt
        else:
            try:
                v = float(value)
            except (TypeError, ValueError):
                continue
            if v == float(ref):
                return opt
    valid = ", ".join(_fmt(getattr(o, key)) for o in options)
    raise ConfigurationError(f"invalid {what} {value!r}; valid: {valid}")


def _fmt(v) -> str:
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    return str(v)


def write_field(dev: I2CDevice, fld: Field, code: int, *, verify: bool = True) -> int:
    """Masked read-modify-write of ``code`` into ``fld``; returns the new register value.

    With ``verify`` the register is read back and a differing field raises ReadbackMismatch.
    """
    new = dev.update_bits(fld.reg, fld.mask, fld.encode(code))
    if verify:
        back = dev.read_register(fld.reg)
        if (back & fld.mask) != (new & fld.mask):
            raise ReadbackMismatch(
                f"register {fld.reg:#04x} at {dev.address:#04x}: wrote {new & fld.mask:#04x} in mask "
                f"{fld.mask:#04x}, read back {back & fld.mask:#04x}")
    return new


def write_checked(dev: I2CDevice, reg: int, value: int, *, verify: bool = True) -> None:
    """Write a whole register and (optionally) read it back."""
    dev.write_register(reg, value)
    if verify:
        back = dev.read_register(reg)
        if back != value:
            raise ReadbackMismatch(f"register {reg:#04x} at {dev.address:#04x}: wrote {value:#04x}, "
                                   f"read back {back:#04x}")


def check_identity(dev: I2CDevice, table: ChipTable, *, known_present: bool = False) -> bytes:
    """Read every identity register of ``table``; DeviceIdMismatch if any differs. Returns the bytes.

    A NACK on the first register means DeviceNotFound at open; with ``known_present`` (a
    re-initialisation of a device that answered before) it stays the BusError it is."""
    got = b""
    for reg, expected in table.id_checks:
        try:
            data = dev.read_registers(reg, len(expected))
        except BusError as exc:
            if known_present:
                raise
            if not got:
                raise DeviceNotFound(f"{table.name}: no answer at {dev.address:#04x} ({exc})") from exc
            raise DeviceIdMismatch(f"{table.name}: device at {dev.address:#04x} answered {got!r} but not "
                                   f"identity register {reg:#04x} ({exc})") from exc
        got += data
        if data != expected:
            raise DeviceIdMismatch(
                f"{table.name}: identity at {dev.address:#04x} reg {reg:#04x} is {data.hex()} "
                f"({data!r}), expected {expected.hex()} ({expected!r})")
    return got


def decode_axes(raw: bytes, table: ChipTable) -> tuple[int, int, int]:
    """Signed codes in X, Y, Z order from the 6-byte data block."""
    words = struct.unpack(">hhh" if table.big_endian else "<hhh", raw)
    out = [0, 0, 0]
    for slot, axis in enumerate(table.slot_axes):
        out[axis] = words[slot]
    return out[0], out[1], out[2]


def encode_axes(codes: Iterable[int], table: ChipTable) -> bytes:
    """Inverse of :func:`decode_axes` (used by the simulators): X, Y, Z codes -> data block."""
    xyz = list(codes)
    words = [xyz[axis] for axis in table.slot_axes]
    return struct.pack(">hhh" if table.big_endian else "<hhh", *words)


def decode_temperature(raw_hi_lo: bytes, fmt: TempFormat, offset_c: float | None = None) -> float:
    """degC from the two temperature bytes, given in register order ``fmt.regs``."""
    b0, b1 = raw_hi_lo[0], raw_hi_lo[1]
    word = (b0 << 8 | b1) if fmt.big_endian else (b1 << 8 | b0)
    if word & 0x8000:
        word -= 0x10000
    word >>= fmt.shift
    return word / fmt.lsb_per_c + (fmt.offset_c if offset_c is None else offset_c)


def encode_temperature(temp_c: float, fmt: TempFormat, offset_c: float | None = None) -> bytes:
    """Inverse of :func:`decode_temperature` (simulators): two bytes in register order."""
    off = fmt.offset_c if offset_c is None else offset_c
    bits = 16 - fmt.shift
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    word = int(max(lo, min(hi, round((temp_c - off) * fmt.lsb_per_c)))) << fmt.shift
    word &= 0xFFFF
    return bytes([word >> 8, word & 0xFF]) if fmt.big_endian else bytes([word & 0xFF, word >> 8])


# --------------------------------------------------------------------------- shared driver
class TableMagnetometer:
    """Generic table-driven I2C magnetometer; chip modules subclass it for chip-specific fields.

    ``timeout_s`` bounds how long :meth:`read` waits for a new sample (default: 3 output
    periods + the first-sample delay + 0.1 s). ``stuck_limit`` consecutive bit-identical samples raise StaleData (the
    data registers are frozen although the chip reports new data); ``extra["repeats"]`` counts
    them. None disables the check: needed for noise-free input, and advisable on a coarse
    range in a quiet static field where the chip's noise is well below one LSB.
    ``extra["overrun"]`` (chips with an overrun flag: LIS3MDL ZYXOR, HMC5983 DOW) is True when the
    chip overwrote a set that was never read, i.e. samples were lost before this one.
    """

    table: ChipTable

    def __init__(self, bus: I2CBus, clock, *, address: int | None = None, timeout_s: float | None = None,
                 stuck_limit: int | None = 200, verify: bool = True) -> None:
        t = self.table
        if timeout_s is not None and not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ConfigurationError(f"{t.name} timeout_s must be a finite number > 0, got {timeout_s!r}")
        if stuck_limit is not None and (not isinstance(stuck_limit, int) or stuck_limit < 1):
            raise ConfigurationError(f"{t.name} stuck_limit must be an int >= 1 or None, got {stuck_limit!r}")
        self.address = t.addresses[0] if address is None else address
        if self.address not in t.addresses:
            raise ConfigurationError(f"{t.name} cannot sit at address {self.address:#04x}; valid: "
                                     + ", ".join(f"{a:#04x}" for a in t.addresses))
        self.dev = I2CDevice(bus, self.address, auto_increment_flag=t.auto_increment_flag)
        self.clock = clock
        self.name = t.name
        self.verify = verify
        self.stuck_limit = stuck_limit
        self._timeout_s = timeout_s
        self._range = t.range_option(t.default_range_uT)
        self._rate = t.rate_option(t.default_odr_hz)
        self._mode = "continuous"
        self._last_new_s: float | None = None   # host time the last new sample was seen
        self._last_raw: bytes | None = None
        self._same_count = 0
        self._discard_next = 0
        self._last_status = 0                   # status register seen with data-ready set
        self.identity = check_identity(self.dev, t)
        self._check_not_other_chip()

    def _check_not_other_chip(self) -> None:
        """Hook: raise DeviceIdMismatch when another chip shares these identity bytes."""

    # -- properties --------------------------------------------------------------------
    @property
    def range_uT(self) -> float:
        return self._range.range_uT

    @property
    def odr_hz(self) -> float:
        return self._rate.odr_hz

    @property
    def mode(self) -> str:
        return self._mode

    @property
    def period_s(self) -> float:
        return 1.0 / self._rate.odr_hz

    @property
    def timeout_s(self) -> float:
        if self._timeout_s is not None:
            return self._timeout_s
        return 3.0 * self.period_s + self._first_sample_delay_s() + 0.1

    def _first_sample_delay_s(self) -> float:
        return self.period_s

    def _poll_s(self) -> float:
        return max(self.period_s / 20.0, 1e-4)

    # -- data ready ------------------------------------------------------------------
    def _status(self) -> int:
        return self.dev.read_register(self.table.status_reg)

    def data_ready(self) -> bool:
        """True when a sample not yet returned by :meth:`read` is available."""
        if not self._due():
            return False
        return bool(self._status() & self.table.drdy_mask)

    def _due(self) -> bool:
        """For chips whose DRDY is not latched: has enough time passed for a new sample?"""
        if self.table.drdy_latched or self._last_new_s is None:
            return True
        return self.clock.monotonic_s() >= self._next_due_s()

    def _next_due_s(self) -> float:
        assert self._last_new_s is not None
        return self._last_new_s + self.period_s * (1.0 + self.table.odr_tolerance)

    def _mark_restart(self) -> None:
        """A configuration change restarts the conversion schedule."""
        now = self.clock.monotonic_s()
        if not self.table.drdy_latched:
            # first new set appears after the first-sample delay from now
            self._last_new_s = now + self._first_sample_delay_s() - self.period_s * (1.0 + self.table.odr_tolerance)
        self._last_raw = None
        self._same_count = 0

    def _trigger_single(self) -> None:
        raise ConfigurationError(f"{self.name}: single-conversion mode not supported")

    def wait_data_ready(self) -> float:
        """Block (through the clock) until a new sample is available; returns the host time.

        Raises BusTimeout after :attr:`timeout_s`.
        """
        if self._mode == "idle":
            raise ConfigurationError(f"{self.name} is in idle/power-down mode; configure mode='continuous' "
                                     "or 'single' before reading")
        if self._mode == "single":
            self._trigger_single()
        start = self.clock.monotonic_s()
        deadline = start + self.timeout_s
        if self._last_new_s is not None and self._mode == "continuous":
            # no new set can exist before one period (less the rate tolerance) has passed; for a
            # non-latched data-ready flag, wait a full period plus tolerance (see _next_due_s)
            due = self._next_due_s() if not self.table.drdy_latched else \
                self._last_new_s + self.period_s * (1.0 - self.table.odr_tolerance)
            if due > start:
                self.clock.sleep_s(min(due, deadline) - start)
        poll = self._poll_s()
        while True:
            now = self.clock.monotonic_s()
            status = self._status()
            if status & self.table.drdy_mask:
                self._last_status = status
                return self.clock.monotonic_s()
            if now >= deadline:
                raise BusTimeout(f"{self.name}: no new sample within {self.timeout_s:.3g} s (data-ready "
                                 "never set)", address=self.address, operation="wait data-ready")
            self.clock.sleep_s(min(poll, max(deadline - now, 1e-6)))

    # -- read ------------------------------------------------------------------------
    def read_raw(self) -> tuple[float, bytes]:
        """Wait for a new sample; return (host time, 6-byte data block). Stuck data raises StaleData."""
        while True:
            t_s = self.wait_data_ready()
            raw = self.dev.read_registers(self.table.data_reg, 6)
            self._last_new_s = t_s
            if self._discard_next > 0:
                self._discard_next -= 1
                continue
            break
        if raw == self._last_raw:
            self._same_count += 1
            if self.stuck_limit is not None and self._same_count >= self.stuck_limit:
                raise StaleData(f"{self.name} at {self.address:#04x}: {self._same_count + 1} consecutive "
                                f"identical samples {raw.hex()} although data-ready was set: data registers "
                                "stuck")
        else:
            self._same_count = 0
        self._last_raw = raw
        return t_s, raw

    def _overflow_axes(self, codes: tuple[int, int, int]) -> tuple[int, ...]:
        lo, hi = self.table.valid_code
        return tuple(i for i, c in enumerate(codes) if c == self.table.overflow_code or not lo <= c <= hi)

    def _scale(self) -> tuple[float, float, float]:
        return self._range.uT_per_lsb

    def read_temperature_c(self) -> float | None:
        """On-chip temperature in degC (None when the chip has none or it is disabled)."""
        fmt = self.table.temperature
        if fmt is None or not self._temp_enabled():
            return None
        if fmt.separate_reads:
            raw = bytes([self.dev.read_register(fmt.regs[0]), self.dev.read_register(fmt.regs[1])])
        else:
            raw = self.dev.read_registers(fmt.regs[0], 2)
        return decode_temperature(raw, fmt, self._temp_offset_c())

    def _temp_enabled(self) -> bool:
        return True

    def _temp_offset_c(self) -> float | None:
        return None

    def _sample_extra(self, codes) -> dict:
        return {}

    def read(self) -> MagSample:
        """Wait for the next new sample and return it (field in uT, overflowed axes NaN)."""
        t_s, raw = self.read_raw()
        codes = decode_axes(raw, self.table)
        over = set(self._overflow_axes(codes))
        extra = {"raw": codes, "repeats": self._same_count}
        if self.table.overrun_mask:
            # the chip overwrote a set nobody read (ZYXOR / DOW): samples were lost before this one
            extra["overrun"] = bool(self._last_status & self.table.overrun_mask)
        extra.update(self._sample_extra(codes))
        over |= set(extra.pop("_overflow", ()))
        scale = self._scale()
        b = tuple(math.nan if i in over else codes[i] * scale[i] for i in range(3))
        temp = self.read_temperature_c()
        return MagSample(t_s=t_s, b_uT=b, temp_c=temp, axis_t_s=(t_s, t_s, t_s), overflow=tuple(sorted(over)),
                         extra=extra)
