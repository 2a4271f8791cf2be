"""MEDA FVM400 fluxgate (bench reference) over a serial line.

The transport is any pyserial object: ``open_serial("/dev/ttyUSB0")`` on the bench,
``open_serial("fvm400sim://bench")`` in simulation (see :mod:`magstack.sim.fvm400_model`). Protocol facts
come from public driver code, not the (unread) manual; see hardware-facts section 6 and the
framing table below. A polled query returns::

    'A' EOT                  acknowledge frame
    ' -8989,-108638,-107863' CR 'D' EOT     data frame: three signed integers, nT

Robust reading: each query's reply is checked and, if bad, counted under a reason in
:attr:`FVM400.skipped` and retried (up to ``max_attempts``): ``no_ack``, ``nak``, ``garbled``,
``partial`` (reply cut short), ``wrong_units`` (decimal values: the front panel is not set to
nT), ``polar`` (not three rectangular components), ``out_of_range`` (a component beyond
``max_abs_nT``). A query with no reply raises :class:`BusTimeout`; too many bad replies in a row
raise :class:`ProtocolError`. Each sample is host-timestamped through the injected clock.
"""
from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass
from types import MappingProxyType

from magstack.drivers.bus.serial_port import open_serial
from magstack.drivers.clock import Clock, SystemClock
from magstack.drivers.errors import BusError, BusTimeout, ConfigurationError, ProtocolError, ReadbackMismatch
from magstack.drivers.magnetometer import MagSample

# ------------------------------------------------------------------------- framing table
EOT = b"\x04"
ACK = b"A"
NAK = b"N"            # simulator's answer to an unknown command [U: not documented]
RECORD_END = b"\r"
DATA_TRAILER = b"D"

#: Serial line settings (C++ driver: 9600 baud via wiringSerial, 8N1; Python rig: 8N1, 2 s timeout).
SERIAL_SETTINGS = MappingProxyType({"baudrate": 9600, "bytesize": 8, "parity": "N", "stopbits": 1,
                                    "timeout_s": 2.0})


@dataclass(frozen=True)
class Command:
    """One protocol command. ``reply``: ``ack`` (A EOT), ``digit`` (A d EOT), ``record`` (A EOT rec CR D EOT)."""

    name: str
    send: bytes
    reply: str
    doc: str


COMMANDS = MappingProxyType({c.name: c for c in (
    Command("query", b"?", "record", "request one vector"),
    Command("defaults", b"*", "ack", "restore defaults: rectangular, absolute"),
    Command("get_mode", b"GM", "digit", "0 absolute, 1 relative"),
    Command("get_representation", b"GX", "digit", "0 rectangular, 1 polar"),
    Command("set_absolute", b"SM0", "ack", "absolute mode"),
    Command("set_relative", b"SM1", "ack", "relative mode (zero the selected channel)"),
    Command("set_rectangular", b"SX0", "ack", "rectangular X,Y,Z"),
    Command("set_polar", b"SX1", "ack", "polar representation"),
    Command("channel_x", b"SC0", "ack", "select channel X"),
    Command("channel_y", b"SC1", "ack", "select channel Y"),
    Command("channel_z", b"SC2", "ack", "select channel Z"),
)})

#: Nominal measuring range per component (nT), [U: not confirmed from the manual]. Calibration
#: treats reference rows at or beyond it as possibly saturated (magstack.firmware.calibration.reference).
NOMINAL_RANGE_NT = 100_000

#: Magnitude above which a component is rejected as out of range (nT). The nominal range is
#: +-100 000 nT [U]; real files hold 107 240 nT and a rig comment shows 108 638, so the default
#: accepts up to 2x nominal and rejects only values that cannot be a field reading.
DEFAULT_MAX_ABS_NT = 200_000

_INT_RE = re.compile(r"^[+-]?\d+$")
_DEC_RE = re.compile(r"^[+-]?(\d+\.\d*|\.\d+)([eE][+-]?\d+)?$")


class RecordError(ValueError):
    """A reply that cannot be used; ``reason`` is one of the skip reasons."""

    def __init__(self, reason: str, detail: str) -> None:
        self.reason = reason
        super().__init__(f"{reason}: {detail}")


def parse_record(text: str, *, max_abs_nT: float = DEFAULT_MAX_ABS_NT) -> tuple[int, int, int]:
    """Parse a data record (without CR/'D'/EOT) into three integer nT values or raise RecordError."""
    body = text.strip()
    if not body:
        raise RecordError("partial", "empty record")
    if not all(32 <= ord(c) < 127 for c in body):
        raise RecordError("garbled", f"non-printable bytes in {body!r}")
    cells = [c.strip() for c in body.split(",")]
    if any(_DEC_RE.match(c) for c in cells) and all(_INT_RE.match(c) or _DEC_RE.match(c) for c in cells):
        raise RecordError("wrong_units", f"decimal values {body!r}: instrument not set to integer nT")
    if not all(_INT_RE.match(c) for c in cells):
        raise RecordError("garbled", f"not integers: {body!r}")
    if len(cells) != 3:
        raise RecordError("partial" if len(cells) < 3 else "garbled", f"{len(cells)} fields in {body!r}")
    vals = tuple(int(c) for c in cells)
    if any(abs(v) > max_abs_nT for v in vals):
        raise RecordError("out_of_range", f"{vals} beyond +-{max_abs_nT:g} nT")
    return vals  # type: ignore[return-value]


class FVM400:
    """Polled FVM400 reference magnetometer; implements :class:`magstack.drivers.magnetometer.Magnetometer`.

    ``port``: an open pyserial object (8N1, 9600 baud, read timeout set). ``b_uT`` is in the probe
    frame (+X cable-to-tip, +Z down through the base). ``configure=True`` selects rectangular,
    absolute output and reads both settings back; every ``verify_every`` samples (0: never) the
    settings are read again, because a polar or relative record is syntactically a valid vector.
    """

    name = "fvm400"

    def __init__(self, port, clock: Clock | None = None, *, max_abs_nT: float = DEFAULT_MAX_ABS_NT,
                 max_attempts: int = 3, configure: bool = True, verify_every: int = 50) -> None:
        if max_attempts < 1:
            raise ConfigurationError(f"max_attempts must be >= 1, got {max_attempts}")
        if not (max_abs_nT > 0):
            raise ConfigurationError(f"max_abs_nT must be > 0, got {max_abs_nT}")
        self.port = port
        self.clock = clock if clock is not None else SystemClock()
        self.max_abs_nT = float(max_abs_nT)
        self.max_attempts = int(max_attempts)
        self.verify_every = int(verify_every)
        self.skipped: Counter[str] = Counter()
        self.last_skip: str = ""
        self.samples = 0
        self.port_name = str(getattr(port, "port", None) or getattr(port, "name", "serial"))
        if configure:
            self.configure()

    @classmethod
    def open(cls, url: str = "/dev/ttyUSB0", clock: Clock | None = None, *,
             timeout_s: float = SERIAL_SETTINGS["timeout_s"], **kwargs) -> FVM400:
        """Open ``url`` (device path or ``fvm400sim://...``) with the table's line settings."""
        port = open_serial(url, baudrate=SERIAL_SETTINGS["baudrate"], timeout_s=timeout_s)
        try:
            return cls(port, clock, **kwargs)
        except Exception:
            port.close()
            raise

    # ------------------------------------------------------------------ low level
    def _write(self, data: bytes) -> None:
        try:
            self.port.write(data)
            self.port.flush()
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise BusError(f"FVM400 write failed: {exc}", address=self.port_name, operation="write") from exc

    def _read_frame(self, what: str) -> bytes:
        """Bytes up to and including EOT; b'' on timeout without data; partial bytes on timeout."""
        try:
            return bytes(self.port.read_until(EOT))
        except (OSError, ValueError) as exc:
            raise BusError(f"FVM400 read failed ({what}): {exc}", address=self.port_name,
                           operation="read") from exc

    def _discard_input(self) -> None:
        try:
            self.port.reset_input_buffer()
        except (OSError, ValueError) as exc:
            raise BusError(f"FVM400 flush failed: {exc}", address=self.port_name, operation="flush") from exc

    def command(self, name: str) -> int | None:
        """Send a non-query command from :data:`COMMANDS`; returns the digit for ``digit`` replies."""
        try:
            cmd = COMMANDS[name]
        except KeyError:
            raise ConfigurationError(f"unknown FVM400 command {name!r}; valid: {', '.join(COMMANDS)}") from None
        if cmd.reply == "record":
            raise ConfigurationError("use read() for the query command")
        self._discard_input()
        self._write(cmd.send)
        frame = self._read_frame(name)
        if not frame:
            raise BusTimeout(f"FVM400 did not answer {cmd.send!r}", address=self.port_name, operation=name)
        if not frame.endswith(EOT) or not frame.startswith(ACK):
            raise ProtocolError(f"FVM400 {name}: unexpected reply {frame!r}")
        payload = frame[len(ACK):-len(EOT)].strip()
        if cmd.reply == "digit":
            if len(payload) != 1 or not payload.isdigit():
                raise ProtocolError(f"FVM400 {name}: expected one digit, got {frame!r}")
            return int(payload)
        if payload:
            raise ProtocolError(f"FVM400 {name}: unexpected payload {frame!r}")
        return None

    def configure(self) -> None:
        """Rectangular, absolute output, verified by read-back (ReadbackMismatch otherwise)."""
        self.command("set_rectangular")
        self.command("set_absolute")
        self.verify_settings()

    # ------------------------------------------------------------------ sampling
    def _query_once(self) -> tuple[tuple[int, int, int], float, str]:
        self._discard_input()
        t0 = self.clock.monotonic_s()
        self._write(COMMANDS["query"].send)
        ack = self._read_frame("ack")
        if not ack:
            raise BusTimeout("FVM400 did not answer a query", address=self.port_name, operation="query")
        if not ack.endswith(EOT):
            raise RecordError("partial", f"acknowledge cut short: {ack!r}")
        if ack.strip() == NAK + EOT:
            raise RecordError("nak", "instrument refused the query")
        if ack[-2:-1] != ACK:
            raise RecordError("no_ack", f"reply does not start with an acknowledge: {ack!r}")
        data = self._read_frame("record")
        t1 = self.clock.monotonic_s()
        if not data.endswith(DATA_TRAILER + EOT):
            raise RecordError("partial", f"record cut short: {data!r}")
        try:
            text = data[: -len(DATA_TRAILER + EOT)].decode("ascii")
        except UnicodeDecodeError:
            raise RecordError("garbled", f"non-ASCII record {data!r}") from None
        text = text.rstrip("\r\n")
        return parse_record(text, max_abs_nT=self.max_abs_nT), 0.5 * (t0 + t1), text

    def verify_settings(self) -> None:
        """Raise ReadbackMismatch unless the instrument is in rectangular, absolute mode."""
        for getter in ("get_representation", "get_mode"):
            got = self.command(getter)
            if got != 0:
                raise ReadbackMismatch(f"FVM400 settings changed (front panel?): {getter} = {got}, expected 0")

    def read(self) -> MagSample:
        """Query one vector. Bad replies are counted in :attr:`skipped` and re-queried."""
        if self.verify_every and self.samples and self.samples % self.verify_every == 0:
            self.verify_settings()
        reasons = []
        for _ in range(self.max_attempts):
            try:
                vals, t_s, text = self._query_once()
            except RecordError as exc:
                self.skipped[exc.reason] += 1
                self.last_skip = str(exc)
                reasons.append(exc.reason)
                continue
            except BusTimeout:
                self.skipped["timeout"] += 1
                self.last_skip = "timeout"
                raise
            self.samples += 1
            epoch = self.clock.epoch_s() - (self.clock.monotonic_s() - t_s)
            b_uT = tuple(v / 1000.0 for v in vals)
            return MagSample(t_s, b_uT, None, None, (), {"epoch_s": epoch, "raw": text})  # type: ignore[arg-type]
        raise ProtocolError(f"FVM400: {self.max_attempts} bad replies in a row ({', '.join(reasons)}); "
                            f"last: {self.last_skip}")

    def data_ready(self) -> bool:
        """A polled instrument converts on request, so a fresh sample is always available."""
        return True

    def close(self) -> None:
        try:
            self.port.close()
        except (OSError, ValueError):
            pass

    def __enter__(self) -> FVM400:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

