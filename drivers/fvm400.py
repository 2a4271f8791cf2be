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

Bounded everywhere: a reply is read up to :data:`MAX_REPLY_BYTES` and each field is at most
:data:`MAX_FIELD_CHARS` characters before any number conversion (a multi-thousand-digit integer is a
``garbled`` reply, never a plain ValueError); only typed errors (:class:`RecordError` is a
:class:`ProtocolError`) leave the driver.

Unsettled protocol points (the manual body was not read; docs/fvm400.md):

- what ``GM`` answers in absolute mode: the project assumes 0, the only public driver's header implies
  1 (its setter sends ``SM0``). :meth:`FVM400.configure` accepts either digit after ``SM0``, warns
  (:class:`ProtocolAssumptionWarning`, also in :attr:`FVM400.notes`) when it is 1, and from then on
  checks the settings against the digit the instrument gave.
- whether set / get replies end in EOT: after ``A`` (and the digit) the driver waits at most
  ``eot_wait_s`` for an EOT and accepts its absence (noted once); it never waits for a terminator
  that does not come longer than that, and a reply that does not start with ``A`` is a ProtocolError.
"""
from __future__ import annotations

import math
import re
import warnings
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

#: Longest reply accepted for one frame (a record of three 7-digit values is ~30 bytes).
MAX_REPLY_BYTES = 64
#: Longest field of a record (sign + digits, or a decimal); longer is ``garbled`` before conversion.
MAX_FIELD_CHARS = 12
#: Default wait for the optional EOT after a set / get reply, s (about 100 byte times at 9600 baud).
DEFAULT_EOT_WAIT_S = 0.1

_INT_RE = re.compile(r"^[+-]?[0-9]+$")
_DEC_RE = re.compile(r"^[+-]?([0-9]+\.[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?$")


class ProtocolAssumptionWarning(UserWarning):
    """The instrument answered in a way the project's (unverified) protocol assumptions did not expect."""


class RecordError(ProtocolError):
    """A reply that cannot be used; ``reason`` is one of the skip reasons (a typed ProtocolError)."""

    def __init__(self, reason: str, detail: str) -> None:
        self.reason = reason
        super().__init__(f"{reason}: {detail}")


def parse_record(text: str, *, max_abs_nT: float = DEFAULT_MAX_ABS_NT) -> tuple[int, int, int]:
    """Parse a data record (without CR/'D'/EOT) into three integer nT values or raise RecordError."""
    if len(text) > MAX_REPLY_BYTES:
        raise RecordError("garbled", f"record of {len(text)} characters (limit {MAX_REPLY_BYTES})")
    body = text.strip()
    if not body:
        raise RecordError("partial", "empty record")
    if not all(32 <= ord(c) < 127 for c in body):
        raise RecordError("garbled", f"non-printable bytes in {body!r}")
    cells = [c.strip() for c in body.split(",")]
    if any(len(c) > MAX_FIELD_CHARS for c in cells):
        raise RecordError("garbled", f"a field longer than {MAX_FIELD_CHARS} characters in {body[:40]!r}...")
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
                 max_attempts: int = 3, configure: bool = True, verify_every: int = 50,
                 eot_wait_s: float = DEFAULT_EOT_WAIT_S) -> None:
        if max_attempts < 1:
            raise ConfigurationError(f"max_attempts must be >= 1, got {max_attempts}")
        if not (max_abs_nT > 0):
            raise ConfigurationError(f"max_abs_nT must be > 0, got {max_abs_nT}")
        if not (isinstance(eot_wait_s, (int, float)) and math.isfinite(eot_wait_s) and 0 < eot_wait_s <= 2.0):
            raise ConfigurationError(f"eot_wait_s must be in (0, 2] s, got {eot_wait_s!r}")
        timeout = getattr(port, "timeout", 0.0)
        if timeout is None or not math.isfinite(timeout):
            raise ConfigurationError("the FVM400 port needs a finite read timeout (pyserial timeout=None blocks "
                                     "forever on a missing reply); open it with timeout_s")
        self.port = port
        self.clock = clock if clock is not None else SystemClock()
        self.max_abs_nT = float(max_abs_nT)
        self.max_attempts = int(max_attempts)
        self.verify_every = int(verify_every)
        self.eot_wait_s = float(eot_wait_s)
        self.skipped: Counter[str] = Counter()
        self.last_skip: str = ""
        self.samples = 0
        self.notes: list[str] = []             # protocol assumptions the instrument contradicted
        self.absolute_mode_digit: int | None = None   # what GM answered after SM0 (0 assumed)
        self.set_replies_end_with_eot: bool | None = None
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
        """Bytes up to and including EOT, at most :data:`MAX_REPLY_BYTES`; b'' on timeout without data;
        partial bytes on timeout or when the limit was reached without EOT."""
        try:
            return bytes(self.port.read_until(EOT, MAX_REPLY_BYTES))
        except (OSError, ValueError) as exc:
            raise BusError(f"FVM400 read failed ({what}): {exc}", address=self.port_name,
                           operation="read") from exc

    def _read_bytes(self, n: int, what: str, timeout_s: float | None = None) -> bytes:
        """Up to ``n`` bytes within the port timeout (or ``timeout_s``)."""
        old = self.port.timeout
        try:
            if timeout_s is not None:
                self.port.timeout = timeout_s
            return bytes(self.port.read(n))
        except (OSError, ValueError) as exc:
            raise BusError(f"FVM400 read failed ({what}): {exc}", address=self.port_name,
                           operation="read") from exc
        finally:
            if timeout_s is not None:
                self.port.timeout = old

    def _note(self, text: str) -> None:
        if text not in self.notes:
            self.notes.append(text)
            warnings.warn(f"FVM400 on {self.port_name}: {text}", ProtocolAssumptionWarning, stacklevel=3)

    def _discard_input(self) -> None:
        try:
            self.port.reset_input_buffer()
        except (OSError, ValueError) as exc:
            raise BusError(f"FVM400 flush failed: {exc}", address=self.port_name, operation="flush") from exc

    def command(self, name: str) -> int | None:
        """Send a non-query command from :data:`COMMANDS`; returns the digit for ``digit`` replies.

        Reply: ``A`` (+ one digit), then an optional EOT awaited at most ``eot_wait_s``. No answer
        within the port timeout raises BusTimeout; anything else unexpected ProtocolError.
        """
        try:
            cmd = COMMANDS[name]
        except KeyError:
            raise ConfigurationError(f"unknown FVM400 command {name!r}; valid: {', '.join(COMMANDS)}") from None
        if cmd.reply == "record":
            raise ConfigurationError("use read() for the query command")
        self._discard_input()
        self._write(cmd.send)
        head = self._read_bytes(1, name)
        if not head:
            raise BusTimeout(f"FVM400 did not answer {cmd.send!r}", address=self.port_name, operation=name)
        if head != ACK:
            rest = self._read_bytes(MAX_REPLY_BYTES, name, timeout_s=self.eot_wait_s)
            raise ProtocolError(f"FVM400 {name}: unexpected reply {(head + rest)[:MAX_REPLY_BYTES]!r}")
        digit = None
        if cmd.reply == "digit":
            d = self._read_bytes(1, name)
            if len(d) != 1 or not d.isdigit():
                raise ProtocolError(f"FVM400 {name}: expected one digit after 'A', got {d!r}")
            digit = int(d)
        tail = self._read_bytes(1, name, timeout_s=self.eot_wait_s)
        if tail == EOT:
            self.set_replies_end_with_eot = True
        elif not tail:
            if self.set_replies_end_with_eot is not False:
                self._note(f"no EOT after the reply to {cmd.send!r} within {self.eot_wait_s:g} s; accepted "
                           "(the EOT after set/get replies is an unverified assumption)")
            self.set_replies_end_with_eot = False
        else:
            got = head + (str(digit).encode() if digit is not None else b"")
            raise ProtocolError(f"FVM400 {name}: unexpected byte {tail!r} after {got!r}")
        return digit

    def configure(self) -> None:
        """Rectangular, absolute output, verified by read-back (ReadbackMismatch otherwise).

        ``GM`` after ``SM0`` may answer 0 (project assumption) or 1 (the public driver's header): either
        is accepted, 1 with a :class:`ProtocolAssumptionWarning`, and becomes the expected value."""
        self.command("set_rectangular")
        self.command("set_absolute")
        got = self.command("get_mode")
        if got not in (0, 1):
            raise ReadbackMismatch(f"FVM400 get_mode = {got} after SM0, expected 0 or 1")
        if got == 1:
            self._note("GM answers 1 after SM0 (absolute); the project assumed 0 - accepting 1 as 'absolute' "
                       "(the public C++ driver's header defines ABSOLUTE = 1)")
        self.absolute_mode_digit = got
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
        if len(data) >= MAX_REPLY_BYTES and not data.endswith(EOT):
            raise RecordError("garbled", f"record longer than {MAX_REPLY_BYTES} bytes: {data[:40]!r}...")
        if not data.endswith(DATA_TRAILER + EOT):
            raise RecordError("partial", f"record cut short: {data!r}")
        try:
            text = data[: -len(DATA_TRAILER + EOT)].decode("ascii")
        except UnicodeDecodeError:
            raise RecordError("garbled", f"non-ASCII record {data!r}") from None
        text = text.rstrip("\r\n")
        return parse_record(text, max_abs_nT=self.max_abs_nT), 0.5 * (t0 + t1), text

    def verify_settings(self) -> None:
        """Raise ReadbackMismatch unless the instrument is in rectangular, absolute mode (the absolute-mode
        digit is the one GM gave after SM0 in :meth:`configure`, 0 if never configured)."""
        expected = {"get_representation": 0,
                    "get_mode": 0 if self.absolute_mode_digit is None else self.absolute_mode_digit}
        for getter, want in expected.items():
            got = self.command(getter)
            if got != want:
                raise ReadbackMismatch(f"FVM400 settings changed (front panel?): {getter} = {got}, expected {want}")

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

