"""TI ADS1248 24-bit delta-sigma ADC (8 inputs, SPI mode 1): settings table and driver.

The chip is described as data (:data:`REGISTERS`, :data:`FIELDS`, :data:`DATA_RATES`,
:data:`PGA_CODES`, ...; hardware-facts section 4); the driver only looks values up and
does masked read-modify-write. The SPI device and the START / RESET / DRDY lines are
injected, every wait goes through the injected clock, and every configuration write is
read back and compared (:class:`magstack.drivers.errors.ReadbackMismatch`).

Conversion model used by :meth:`ADS1248.convert`: START is held high (continuous
conversion); writing MUX0..SYS0 restarts the digital filter, so the next DRDY falls
``first_after_write_s`` later (50.822 ms at 20 SPS) and that first result is settled
(single-cycle settling, hardware-facts 4.3). The driver sleeps the tabled time, then polls
DRDY; it never reads a result before DRDY is low.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from magstack.drivers.bus.gpio import InputLine, OutputLine
from magstack.drivers.bus.spi import SpiBus
from magstack.drivers.clock import Clock
from magstack.drivers.errors import BusError, BusTimeout, ConfigurationError, ReadbackMismatch

# --------------------------------------------------------------------------- settings table

#: SPI mode 1 (CPOL 0, CPHA 1) [F:TI-EX][F:MIT-DRV].
SPI_MODE = 1
#: SPI clock used by the MIT bench driver [F:MIT-DRV].
DEFAULT_SPI_HZ = 1_000_000
#: Wait after a RESET (pin or command) before the first command [F:TI-DS p.50].
RESET_RECOVERY_S = 0.6e-3
#: Internal reference voltage [F:TI-DS feature list].
INTERNAL_REF_V = 2.048
#: Full-scale code magnitude: +FS -> 0x7FFFFF, -FS -> 0x800000; LSB = (Vref/PGA)/(2**23 - 1) [F:TI-DS p.35].
CODE_POS_FS = 0x7FFFFF
CODE_NEG_FS = -0x800000
FS_DIVISOR = 2**23 - 1
#: Internal temperature diode (MUXCAL=011): ~118 mV at 25 degC, ~405 uV/degC. **Unverified** [F2:E2E-249199]:
#: the poster who quoted them measured ~732 mV, rising when cooled, which contradicts them. Calibrate
#: the temperature channel per board (:class:`magstack.drivers.hmc1053.TempCalibration`).
TEMP_DIODE_V_AT_25C = 0.118
TEMP_DIODE_V_PER_C = 405e-6
TEMP_DIODE_VERIFIED = False
#: Duration of SELFOCAL / SYSOCAL / SYSGCAL in first-conversion times. No datasheet figure was found;
#: users measure about 16 conversion periods (200 ms at 80 SPS, E2E 1158284; > 401 ms at 40 SPS,
#: E2E 164126) [F2].
CALIBRATION_PERIODS = 16
#: The driver's default bound on a calibration, in first-conversion times: twice the measured figure,
#: so a part 2x slower than the forum reports still completes (plus ``timeout_margin_s``).
CALIBRATION_TIMEOUT_PERIODS = 2 * CALIBRATION_PERIODS


class Command:
    """First command bytes [F:TI-DS Table 22]."""

    WAKEUP = 0x00
    SLEEP = 0x02
    SYNC = 0x04
    RESET = 0x06
    NOP = 0xFF
    RDATA = 0x12
    RDATAC = 0x14
    SDATAC = 0x16
    RREG = 0x20
    WREG = 0x40
    SYSOCAL = 0x60
    SYSGCAL = 0x61
    SELFOCAL = 0x62


@dataclass(frozen=True)
class Register:
    name: str
    address: int
    reset: int
    ro_mask: int = 0x00  # bits the chip ignores on write (read-only)


_REGS = (
    Register("MUX0", 0x00, 0x01),
    Register("VBIAS", 0x01, 0x00),
    Register("MUX1", 0x02, 0x00, ro_mask=0x80),  # CLKSTAT read-only
    Register("SYS0", 0x03, 0x00),
    Register("OFC0", 0x04, 0x00),
    Register("OFC1", 0x05, 0x00),
    Register("OFC2", 0x06, 0x00),
    Register("FSC0", 0x07, 0x00),  # factory-trimmed, reset value is per chip
    Register("FSC1", 0x08, 0x00),
    Register("FSC2", 0x09, 0x40),
    Register("IDAC0", 0x0A, 0x00, ro_mask=0xF0),  # ID[7:4] read-only
    Register("IDAC1", 0x0B, 0xFF),  # reset value [U]
    Register("GPIOCFG", 0x0C, 0x00),
    Register("GPIODIR", 0x0D, 0xFF),  # reset value [U]
    Register("GPIODAT", 0x0E, 0x00),
)
#: name -> Register. Addresses 0x00-0x0E; RREG wraps past 0x0E.
REGISTERS: Mapping[str, Register] = MappingProxyType({r.name: r for r in _REGS})
N_REGISTERS = len(_REGS)
#: Registers whose write restarts the digital filter (first result after first_after_write_s).
FILTER_RESTART_REGISTERS = frozenset({0x00, 0x01, 0x02, 0x03})


@dataclass(frozen=True)
class Field:
    register: str
    shift: int
    width: int

    @property
    def mask(self) -> int:
        return ((1 << self.width) - 1) << self.shift


FIELDS: Mapping[str, Field] = MappingProxyType({
    "BCS": Field("MUX0", 6, 2), "MUX_SP": Field("MUX0", 3, 3), "MUX_SN": Field("MUX0", 0, 3),
    "CLKSTAT": Field("MUX1", 7, 1), "VREFCON": Field("MUX1", 5, 2), "REFSELT": Field("MUX1", 3, 2),
    "MUXCAL": Field("MUX1", 0, 3),
    "SYS0_RSVD": Field("SYS0", 7, 1), "PGA": Field("SYS0", 4, 3), "DR": Field("SYS0", 0, 4),
    "ID": Field("IDAC0", 4, 4), "DRDY_MODE": Field("IDAC0", 3, 1), "IMAG": Field("IDAC0", 0, 3),
    "I1DIR": Field("IDAC1", 4, 4), "I2DIR": Field("IDAC1", 0, 4),
})


@dataclass(frozen=True)
class DataRate:
    """One DR code row of TI-DS Table 16 (f_OSC = 4.096 MHz); times in seconds."""

    code: int
    sps: float  # exact output data rate
    first_after_reset_s: float  # after RESET, START high, WAKEUP, SYNC
    first_after_write_s: float  # after a VBIAS/MUX0/MUX1/SYS0 write
    period_s: float  # every later result


#: nominal SPS -> DataRate [F:TI-DS p.35 Table 16]. Codes above 1001 are rejected.
DATA_RATES: Mapping[int, DataRate] = MappingProxyType({
    5: DataRate(0b0000, 5.019, 199.258e-3, 200.26e-3, 199.250e-3),
    10: DataRate(0b0001, 10.038, 99.633e-3, 100.635e-3, 99.625e-3),
    20: DataRate(0b0010, 20.075, 49.820e-3, 50.822e-3, 49.812e-3),
    40: DataRate(0b0011, 40.151, 24.92e-3, 25.172e-3, 24.906e-3),
    80: DataRate(0b0100, 80.301, 12.467e-3, 12.719e-3, 12.453e-3),
    160: DataRate(0b0101, 160.602, 6.240e-3, 6.492e-3, 6.226e-3),
    320: DataRate(0b0110, 321.608, 3.124e-3, 3.25e-3, 3.109e-3),
    640: DataRate(0b0111, 643.216, 1.569e-3, 1.695e-3, 1.554e-3),
    1000: DataRate(0b1000, 1000.0, 1.014e-3, 1.141e-3, 1.0e-3),
    2000: DataRate(0b1001, 2000.0, 0.514e-3, 0.578e-3, 0.5e-3),
})
DATA_RATE_BY_CODE: Mapping[int, DataRate] = MappingProxyType({d.code: d for d in DATA_RATES.values()})

#: PGA gain -> SYS0.PGA code.
PGA_CODES: Mapping[int, int] = MappingProxyType({1: 0, 2: 1, 4: 2, 8: 3, 16: 4, 32: 5, 64: 6, 128: 7})
#: MUX1.VREFCON: internal reference off / always on / on only while converting.
VREFCON_CODES: Mapping[str, int] = MappingProxyType({"off": 0b00, "on": 0b01, "converting": 0b10})
#: MUX1.REFSELT: which reference the ADC uses.
REFSELT_CODES: Mapping[str, int] = MappingProxyType(
    {"REF0": 0b00, "REF1": 0b01, "internal": 0b10, "internal_ref0": 0b11})
#: MUX1.MUXCAL system monitors (override MUX_SP/MUX_SN/VBIAS).
MUXCAL_CODES: Mapping[str, int] = MappingProxyType({
    "normal": 0b000, "offset": 0b001, "gain": 0b010, "temperature": 0b011,
    "ref1_monitor": 0b100, "ref0_monitor": 0b101, "avdd_monitor": 0b110, "dvdd_monitor": 0b111})
#: MUX0.BCS burn-out current source, uA -> code.
BCS_CODES: Mapping[float, int] = MappingProxyType({0: 0b00, 0.5: 0b01, 2: 0b10, 10: 0b11})
#: IDAC0.IMAG excitation current, uA -> code.
IMAG_CODES: Mapping[int, int] = MappingProxyType(
    {0: 0, 50: 1, 100: 2, 250: 3, 500: 4, 750: 5, 1000: 6, 1500: 7})


def lookup(table: Mapping, key, what: str):
    """Exact-match lookup; unknown keys raise ConfigurationError naming the valid values."""
    try:
        return table[key]
    except (KeyError, TypeError):
        valid = ", ".join(str(k) for k in table)
        raise ConfigurationError(f"invalid {what} {key!r}; valid: {valid}") from None


def _finite(v) -> bool:
    """True for a real number that is neither NaN nor infinite."""
    try:
        return math.isfinite(v)
    except TypeError:
        return False


def code_to_volts(code: int, vref_V: float, pga: int) -> float:
    """24-bit signed code -> differential input volts: code * (Vref/PGA) / (2**23 - 1)."""
    return code * (vref_V / pga) / FS_DIVISOR


def signed24(raw: bytes) -> int:
    """Three bytes MSB first, two's complement -> int."""
    if len(raw) != 3:
        raise ValueError(f"need 3 bytes, got {len(raw)}")
    value = (raw[0] << 16) | (raw[1] << 8) | raw[2]
    return value - (1 << 24) if value & 0x800000 else value


def diode_temp_c(volts: float, v_at_25c_V: float = TEMP_DIODE_V_AT_25C,
                 V_per_c: float = TEMP_DIODE_V_PER_C) -> float:
    """Internal temperature diode volts -> degC. Defaults: the forum coefficients [F2]; pass a
    per-board calibration once measured."""
    return 25.0 + (volts - v_at_25c_V) / V_per_c


@dataclass(frozen=True)
class ChannelConfig:
    """What MUX0, VBIAS, MUX1 and SYS0 hold for one conversion.

    ``pos``/``neg`` are AIN numbers 0-7; ``muxcal`` selects a system monitor instead
    (e.g. ``"temperature"``); ``reference`` names REFSELT; ``vrefcon`` the internal
    reference power mode; ``burnout_uA`` the BCS current; ``vbias_mask`` the VBIAS bits.
    """

    pos: int = 0
    neg: int = 1
    pga: int = 1
    data_rate_sps: int = 20
    reference: str = "internal"
    vrefcon: str = "on"
    muxcal: str = "normal"
    burnout_uA: float = 0
    vbias_mask: int = 0

    def register_bytes(self) -> bytes:
        """Encode to the four bytes written to MUX0..SYS0 (ConfigurationError on bad values)."""
        for pin, label in ((self.pos, "positive input"), (self.neg, "negative input")):
            if not isinstance(pin, int) or not 0 <= pin <= 7:
                raise ConfigurationError(f"invalid {label} AIN{pin!r}; valid: 0..7")
        if self.pos == self.neg and self.muxcal == "normal":
            raise ConfigurationError(f"positive and negative input are both AIN{self.pos}")
        if not isinstance(self.vbias_mask, int) or not 0 <= self.vbias_mask <= 0xFF:
            raise ConfigurationError(f"invalid VBIAS mask {self.vbias_mask!r}; valid: 0..255")
        if self.reference.startswith("internal") and self.vrefcon == "off":
            raise ConfigurationError("internal reference selected but VREFCON is 'off'")
        mux0 = (lookup(BCS_CODES, self.burnout_uA, "burn-out current (uA)") << 6) | (self.pos << 3) | self.neg
        mux1 = ((lookup(VREFCON_CODES, self.vrefcon, "VREFCON") << 5)
                | (lookup(REFSELT_CODES, self.reference, "reference") << 3)
                | lookup(MUXCAL_CODES, self.muxcal, "MUXCAL"))
        sys0 = (lookup(PGA_CODES, self.pga, "PGA gain") << 4) | lookup(
            DATA_RATES, self.data_rate_sps, "data rate (SPS)").code
        return bytes((mux0, self.vbias_mask, mux1, sys0))

    @property
    def rate(self) -> DataRate:
        return lookup(DATA_RATES, self.data_rate_sps, "data rate (SPS)")


@dataclass(frozen=True)
class Conversion:
    """One ADC result with its own timing (clock monotonic seconds).

    ``t_start_s`` = filter restart (register write), ``t_ready_s`` = DRDY seen low,
    ``t_s`` = midpoint of that window: the centre of the symmetric filter's weighting.
    ``clipped`` is True at the full-scale codes 0x7FFFFF / 0x800000.
    """

    code: int
    volts: float
    t_start_s: float
    t_ready_s: float
    channel: ChannelConfig

    @property
    def t_s(self) -> float:
        return 0.5 * (self.t_start_s + self.t_ready_s)

    @property
    def clipped(self) -> bool:
        return self.code >= CODE_POS_FS or self.code <= CODE_NEG_FS


# --------------------------------------------------------------------------- driver


class ADS1248:
    """Command/register driver. Lines: ``start`` (output), ``reset`` (output or None: RESET
    command is used), ``drdy`` (input, low = result ready). ``ref0_V``/``ref1_V`` are the
    external reference voltages if REF0/REF1 are used.

    ``drdy_poll_s`` is the DRDY polling step after the tabled conversion time has elapsed;
    ``timeout_factor`` x the tabled time (+ ``timeout_margin_s``) bounds every wait.
    """

    def __init__(self, spi: SpiBus, clock: Clock, *, start: OutputLine, drdy: InputLine,
                 reset: OutputLine | None = None, ref0_V: float | None = None, ref1_V: float | None = None,
                 drdy_poll_s: float = 100e-6, timeout_factor: float = 2.0, timeout_margin_s: float = 10e-3,
                 name: str = "ads1248") -> None:
        if spi.mode != SPI_MODE:
            raise ConfigurationError(f"ADS1248 needs SPI mode {SPI_MODE}, bus is in mode {spi.mode}")
        if not (_finite(drdy_poll_s) and drdy_poll_s > 0 and _finite(timeout_factor) and timeout_factor >= 1
                and _finite(timeout_margin_s) and timeout_margin_s >= 0):
            raise ConfigurationError("drdy_poll_s must be finite and > 0, timeout_factor finite and >= 1, "
                                     f"timeout_margin_s finite and >= 0; got {drdy_poll_s!r}, {timeout_factor!r}, "
                                     f"{timeout_margin_s!r}")
        for label, v in (("ref0_V", ref0_V), ("ref1_V", ref1_V)):
            if v is not None and not (_finite(v) and v > 0):
                raise ConfigurationError(f"{label} must be None (not wired) or a finite voltage > 0, got {v!r}")
        self.spi = spi
        self.clock = clock
        self.start_line = start
        self.reset_line = reset
        self.drdy_line = drdy
        self.ref_V = {"internal": INTERNAL_REF_V, "internal_ref0": INTERNAL_REF_V, "REF0": ref0_V, "REF1": ref1_V}
        self.drdy_poll_s = drdy_poll_s
        self.timeout_factor = timeout_factor
        self.timeout_margin_s = timeout_margin_s
        self.name = name
        self.channel: ChannelConfig | None = None  # what MUX0..SYS0 hold now (None: unknown)
        self._rate: DataRate = DATA_RATES[5]  # power-on DR = 0000
        self.conversions = 0
        self.t_reset_s: float | None = None  # clock time of the last reset()

    # -- low level -------------------------------------------------------------------------------
    def _xfer(self, tx: bytes, op: str) -> bytes:
        try:
            return self.spi.transfer(tx)
        except BusError:
            raise
        except OSError as exc:
            raise BusError(f"SPI transfer failed: {exc}", address=self.name, operation=op) from exc

    def command(self, cmd: int) -> None:
        """Send a one-byte command (SYNC is sent twice as the datasheet requires)."""
        tx = bytes((cmd, cmd)) if cmd == Command.SYNC else bytes((cmd,))
        self._xfer(tx, f"command {cmd:#04x}")

    def read_registers(self, address: int, count: int) -> bytes:
        """RREG ``count`` registers from ``address`` (the chip wraps past 0x0E)."""
        if not 0 <= address < N_REGISTERS or not 1 <= count <= 16:
            raise ConfigurationError(f"bad RREG address {address:#04x} / count {count}")
        rx = self._xfer(bytes((Command.RREG | address, count - 1)) + bytes([Command.NOP] * count), "RREG")
        return bytes(rx[2:])

    def write_registers(self, address: int, values: bytes, *, verify: bool = True) -> None:
        """WREG ``values`` from ``address``; read back and compare (RO bits masked)."""
        values = bytes(values)
        if not 0 <= address or address + len(values) > N_REGISTERS or not values:
            raise ConfigurationError(f"bad WREG address {address:#04x} / length {len(values)}")
        self._xfer(bytes((Command.WREG | address, len(values) - 1)) + values, "WREG")
        if verify:
            self._verify(address, values)

    def _verify(self, address: int, values: bytes) -> None:
        back = self.read_registers(address, len(values))
        for i, (w, r) in enumerate(zip(values, back, strict=True)):
            reg = _REGS[address + i]
            if (w & ~reg.ro_mask) != (r & ~reg.ro_mask):
                raise ReadbackMismatch(f"{self.name}: {reg.name} ({reg.address:#04x}) wrote {w:#04x}, "
                                       f"read back {r:#04x}")

    def read_register(self, name: str) -> int:
        return self.read_registers(lookup(REGISTERS, name, "register").address, 1)[0]

    def write_field(self, field: str, value: int) -> None:
        """Masked read-modify-write of one named field, read back and checked."""
        f = lookup(FIELDS, field, "field")
        if not 0 <= value < (1 << f.width):
            raise ConfigurationError(f"value {value} does not fit field {field} ({f.width} bits)")
        reg = REGISTERS[f.register]
        if f.mask & reg.ro_mask:
            raise ConfigurationError(f"field {field} is read-only")
        old = self.read_register(reg.name)
        self.write_registers(reg.address, bytes(((old & ~f.mask) | (value << f.shift),)))
        if reg.address in FILTER_RESTART_REGISTERS:
            self.channel = None  # MUX0..SYS0 no longer match a ChannelConfig

    # -- bring-up -----------------------------------------------------------------------------------
    def reset(self) -> None:
        """Hardware (or command) reset, wait, start continuous conversion, leave RDATAC.

        After reset the chip is in RDATAC mode; SDATAC takes effect at the next DRDY, so we
        wait for one result (5 SPS after reset) before any register access.
        """
        self.start_line.set(False)
        if self.reset_line is not None:
            self.reset_line.set(False)
            self.clock.sleep_s(10e-6)
            self.reset_line.set(True)
        else:
            self.command(Command.RESET)
        t_reset = self.clock.monotonic_s()
        self.clock.sleep_s(RESET_RECOVERY_S)
        self.channel = None
        self._rate = DATA_RATES[5]
        self.start_line.set(True)
        t_start = self.clock.monotonic_s()
        self.command(Command.SDATAC)
        # SDATAC is effective at this DRDY; the power-on result itself (AIN0/AIN1 on REF0) is
        # not read: the next configure() restarts the filter and releases DRDY
        self.wait_drdy(t_start, self._rate.first_after_reset_s)
        self.t_reset_s = t_reset

    def configure(self, channel: ChannelConfig) -> float:
        """Write MUX0..SYS0 for ``channel`` (restarts the filter), verify; return the write time."""
        regs = channel.register_bytes()
        vref = self.ref_V[channel.reference]
        if vref is None or not vref > 0:
            raise ConfigurationError(f"reference {channel.reference} selected but its voltage is not given")
        self._xfer(bytes((Command.WREG | 0x00, 3)) + regs, "WREG")
        t_write = self.clock.monotonic_s()
        self._verify(0x00, regs)
        self.channel = channel
        self._rate = channel.rate
        return t_write

    # -- conversions ----------------------------------------------------------------------------------
    def data_ready(self) -> bool:
        return not self.drdy_line.get()

    def wait_drdy(self, t_from_s: float, expected_s: float, timeout_s: float | None = None) -> float:
        """Sleep until ``t_from_s + expected_s``, then poll DRDY; return the time it was seen low.

        Raises BusTimeout after ``timeout_s`` (default ``timeout_factor * expected_s +
        timeout_margin_s``) from ``t_from_s``; in virtual time this never hangs.
        """
        if timeout_s is None:
            timeout_s = self.timeout_factor * expected_s + self.timeout_margin_s
        deadline = t_from_s + timeout_s
        now = self.clock.monotonic_s()
        due = t_from_s + expected_s
        if now < due:
            self.clock.sleep_s(due - now)
        while True:
            if not self.drdy_line.get():
                return self.clock.monotonic_s()
            now = self.clock.monotonic_s()
            if now >= deadline:
                raise BusTimeout(f"{self.name}: DRDY did not assert within {deadline - t_from_s:.4f} s",
                                 address=getattr(self.spi, "name", self.name), operation="wait DRDY")
            self.clock.sleep_s(min(self.drdy_poll_s, deadline - now))

    def read_data(self) -> int:
        """RDATA: the latest result as a signed 24-bit code (call only after DRDY)."""
        rx = self._xfer(bytes((Command.RDATA, Command.NOP, Command.NOP, Command.NOP)), "RDATA")
        return signed24(bytes(rx[1:4]))

    def convert(self, channel: ChannelConfig) -> Conversion:
        """Select ``channel`` (restarting the filter), wait for its first settled result, read it."""
        t_start = self.configure(channel)
        t_ready = self.wait_drdy(t_start, channel.rate.first_after_write_s)
        code = self.read_data()
        self.conversions += 1
        return Conversion(code, self.volts(code, channel), t_start, t_ready, channel)

    def volts(self, code: int, channel: ChannelConfig) -> float:
        vref = self.ref_V[channel.reference]
        return code_to_volts(code, vref, channel.pga)

    # -- calibration commands --------------------------------------------------------------------
    def _calibrate(self, cmd: int, channel: ChannelConfig, max_conversions: float) -> int:
        self.configure(channel)
        self.command(cmd)
        t0 = self.clock.monotonic_s()
        first = channel.rate.first_after_reset_s
        self.wait_drdy(t0, first, timeout_s=max_conversions * first + self.timeout_margin_s)
        self.read_data()
        self.channel = None
        ofc = self.read_registers(REGISTERS["OFC0"].address, 3)
        return signed24(bytes((ofc[2], ofc[1], ofc[0])))

    def self_offset_calibration(self, channel: ChannelConfig, *,
                                max_conversions: float = CALIBRATION_TIMEOUT_PERIODS) -> int:
        """SELFOCAL; wait for DRDY (bounded by ``max_conversions`` first-conversion times + margin; the
        measured duration is :data:`CALIBRATION_PERIODS`); return the new OFC value (counts)."""
        return self._calibrate(Command.SELFOCAL, channel, max_conversions)

    def system_offset_calibration(self, channel: ChannelConfig, *,
                                  max_conversions: float = CALIBRATION_TIMEOUT_PERIODS) -> int:
        """SYSOCAL with the inputs externally shorted; return the new OFC value (counts)."""
        return self._calibrate(Command.SYSOCAL, channel, max_conversions)
