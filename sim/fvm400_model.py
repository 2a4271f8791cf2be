"""Simulated MEDA FVM400 fluxgate: the byte-level serial protocol of drivers/fvm400.py.

The model reads the true field from a :class:`magstack.sim.truth_source.TruthSource` at the injected
clock's time, answers the command set of ``magstack.drivers.fvm400.COMMANDS`` (facts and gaps:
hardware-facts section 6) and can inject faults: garbled records, partial records, dropped
replies, over-range values and records in the wrong units (decimal tesla, as a front-panel
unit change would produce). It is reached three ways:

* ``open_serial("fvm400sim://?seed=1&garble=0.05")`` builds a private model (pyserial URL
  handler :mod:`magstack.sim.serial_protocols.protocol_fvm400sim`);
* ``register_instrument("bench", model)`` then ``open_serial("fvm400sim://bench")`` wires a
  named model to a bench truth source and clock;
* :class:`PtyInstrument` serves a model behind a real pseudo-terminal (``os.openpty``), so a
  driver opens the slave path like ``/dev/ttyUSB0``.

Simulator assumptions where the real protocol is undocumented (marked [U] in the facts):
commands are sent without terminator; an unknown command is answered ``N`` EOT and recorded in
:attr:`FVM400Model.protocol_errors`; ``GM``/``GX`` answer ``A`` + digit + EOT; polar records are
``|B| nT, inclination, declination`` (centidegrees). The model never clips: an over-range
field is reported as the number it is, and the driver decides. Two unsettled points are switches
so the driver can be tested against both readings: ``absolute_mode_digit`` (what GM answers in
absolute mode: 0 assumed, 1 per the public driver's header) and ``eot_after_reply`` (whether set and
get replies end in EOT).
"""
from __future__ import annotations

import math
import os
import select
import threading
import tty
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from magstack.drivers.clock import Clock, SystemClock
from magstack.drivers.errors import ConfigurationError
from magstack.drivers.fvm400 import ACK, COMMANDS, DATA_TRAILER, EOT, NAK, RECORD_END, SERIAL_SETTINGS
from magstack.sim.truth_source import StaticTruth, TruthSource


@dataclass
class FVM400Faults:
    """Per-query fault probabilities (0..1)."""

    garble: float = 0.0       # 1-3 record bytes replaced with non-numeric characters
    partial: float = 0.0      # record cut short, no trailer (reader times out mid-record)
    dropout: float = 0.0      # no reply at all
    over_range: float = 0.0   # one component reported as +-9_999_999 nT
    wrong_units: float = 0.0  # record in decimal tesla (front panel set to other units)

    def __post_init__(self) -> None:
        for k, v in self.__dict__.items():
            if not (0.0 <= float(v) <= 1.0):
                raise ConfigurationError(f"fault probability {k} must be in [0, 1], got {v}")


class FVM400Model:
    """Byte-in, byte-out FVM400 instrument.

    ``probe_from_truth`` (3x3) maps the truth frame into the probe frame (default identity);
    ``noise_uT`` is white noise per component (1 sigma); output is integer nT.
    """

    baudrate = SERIAL_SETTINGS["baudrate"]

    def __init__(self, truth: TruthSource | None = None, clock: Clock | None = None, *,
                 probe_from_truth=None, noise_uT: float = 0.0, seed: int = 0,
                 faults: FVM400Faults | None = None, absolute_mode_digit: int = 0,
                 eot_after_reply: bool = True) -> None:
        if absolute_mode_digit not in (0, 1):
            raise ConfigurationError(f"absolute_mode_digit must be 0 or 1, got {absolute_mode_digit!r}")
        self.absolute_mode_digit = absolute_mode_digit
        self.eot_after_reply = bool(eot_after_reply)
        self.truth = truth if truth is not None else StaticTruth()
        self.clock = clock if clock is not None else SystemClock()
        self.probe_from_truth = np.eye(3) if probe_from_truth is None else np.asarray(probe_from_truth, float)
        if self.probe_from_truth.shape != (3, 3) or not np.isfinite(self.probe_from_truth).all():
            raise ConfigurationError(f"probe_from_truth must be a finite 3x3 matrix, got {probe_from_truth!r}")
        if not (noise_uT >= 0 and math.isfinite(noise_uT)):
            raise ConfigurationError(f"noise_uT must be >= 0, got {noise_uT}")
        self.noise_uT = float(noise_uT)
        self.faults = faults or FVM400Faults()
        self.rng = np.random.default_rng(seed)
        self.mode = 0            # 0 absolute, 1 relative
        self.representation = 0  # 0 rectangular, 1 polar
        self.channel = 0
        self.zero_nT = np.zeros(3)
        self._rx = bytearray()
        self._tx = bytearray()
        self._lock = threading.Lock()
        self.protocol_errors: list[str] = []
        self.queries = 0
        self.injected: dict[str, int] = {k: 0 for k in FVM400Faults().__dict__}
        self._dispatch: dict[bytes, Callable[[], bytes]] = {
            COMMANDS["query"].send: self._query,
            COMMANDS["defaults"].send: self._defaults,
            COMMANDS["get_mode"].send: lambda: self._reply(str(self.mode ^ self.absolute_mode_digit).encode()),
            COMMANDS["get_representation"].send: lambda: self._reply(str(self.representation).encode()),
            COMMANDS["set_absolute"].send: lambda: self._set("mode", 0),
            COMMANDS["set_relative"].send: lambda: self._set("mode", 1),
            COMMANDS["set_rectangular"].send: lambda: self._set("representation", 0),
            COMMANDS["set_polar"].send: lambda: self._set("representation", 1),
            COMMANDS["channel_x"].send: lambda: self._set("channel", 0),
            COMMANDS["channel_y"].send: lambda: self._set("channel", 1),
            COMMANDS["channel_z"].send: lambda: self._set("channel", 2),
        }
        self._prefixes = {c[:k] for c in self._dispatch for k in range(1, len(c))}

    # ---------------------------------------------------------------- state changes
    def _reply(self, payload: bytes = b"") -> bytes:
        return ACK + payload + (EOT if self.eot_after_reply else b"")

    def _set(self, attr: str, value: int) -> bytes:
        setattr(self, attr, value)
        if attr == "mode" and value == 1:  # relative: zero the selected channel at the present field
            self.zero_nT[self.channel] = self._field_nT()[self.channel]
        if attr == "mode" and value == 0:
            self.zero_nT[:] = 0.0
        return self._reply()

    def _defaults(self) -> bytes:
        self.mode, self.representation, self.channel = 0, 0, 0
        self.zero_nT[:] = 0.0
        return self._reply()

    def _field_nT(self) -> np.ndarray:
        t = self.clock.monotonic_s()
        b = self.probe_from_truth @ np.asarray(self.truth.field_uT(t), float).reshape(3)
        if self.noise_uT:
            b = b + self.rng.normal(0.0, self.noise_uT, 3)
        return b * 1000.0

    # ---------------------------------------------------------------- query + faults
    def _roll(self, name: str) -> bool:
        p = getattr(self.faults, name)
        hit = p > 0 and self.rng.random() < p
        if hit:
            self.injected[name] += 1
        return hit

    def _query(self) -> bytes:
        self.queries += 1
        if self._roll("dropout"):
            return b""
        b_nT = self._field_nT() - self.zero_nT
        vals = np.rint(b_nT).astype(np.int64)
        if self._roll("over_range"):
            vals[int(self.rng.integers(3))] = 9_999_999 * (1 if self.rng.random() < 0.5 else -1)
        if self.representation == 1:
            mag = float(np.linalg.norm(b_nT))
            inc = math.degrees(math.atan2(b_nT[2], math.hypot(b_nT[0], b_nT[1]))) if mag else 0.0
            dec = math.degrees(math.atan2(b_nT[1], b_nT[0])) if mag else 0.0
            record = f" {round(mag)},{round(inc * 100)},{round(dec * 100)}"
        elif self._roll("wrong_units"):
            record = " " + ",".join(f"{v * 1e-9:.6f}" for v in vals)
        else:
            record = " " + ",".join(str(int(v)) for v in vals)
        rec = bytearray(record.encode("ascii"))
        if self._roll("garble"):
            for _ in range(int(self.rng.integers(1, 4))):
                rec[int(self.rng.integers(len(rec)))] = int(self.rng.choice(list(b"#x?~/;")))
        if self._roll("partial"):
            return ACK + EOT + bytes(rec[: int(self.rng.integers(1, len(rec)))])
        return ACK + EOT + bytes(rec) + RECORD_END + DATA_TRAILER + EOT

    # ---------------------------------------------------------------- byte interface
    def receive(self, data: bytes) -> None:
        """Bytes from the host. Complete commands are answered into the output buffer."""
        with self._lock:
            for byte in bytes(data):
                if byte in (0x0D, 0x0A) and not self._rx:
                    continue
                self._rx.append(byte)
                cmd = bytes(self._rx)
                if cmd in self._dispatch:
                    self._rx.clear()
                    self._tx += self._dispatch[cmd]()
                elif cmd not in self._prefixes:
                    self._rx.clear()
                    self.protocol_errors.append(f"unknown command {cmd!r}")
                    self._tx += NAK + EOT

    def pending(self) -> int:
        with self._lock:
            return len(self._tx)

    def take(self, n: int) -> bytes:
        """Remove and return up to ``n`` output bytes."""
        with self._lock:
            out = bytes(self._tx[:n])
            del self._tx[:n]
            return out

    def clear_output(self) -> None:
        with self._lock:
            self._tx.clear()

    def clear_input(self) -> None:
        with self._lock:
            self._rx.clear()


# -------------------------------------------------------------------- named instruments
_REGISTRY: dict[str, FVM400Model] = {}


def register_instrument(name: str, model: FVM400Model) -> None:
    """Make ``fvm400sim://<name>`` open ``model`` (replaces an earlier one of that name)."""
    if not name or not name.replace("_", "").replace("-", "").isalnum():
        raise ConfigurationError(f"instrument name must be alphanumeric/_/-: {name!r}")
    _REGISTRY[name] = model


def unregister_instrument(name: str) -> None:
    _REGISTRY.pop(name, None)


def get_instrument(name: str) -> FVM400Model:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"no simulated FVM400 named {name!r}; registered: {sorted(_REGISTRY) or 'none'}") from None


# -------------------------------------------------------------------- pseudo-terminal
class PtyInstrument:
    """Serve a model behind ``os.openpty``: open :attr:`port` with pyserial like a USB adapter.

    Use as a context manager; a daemon thread moves bytes between the pty master and the model.
    """

    def __init__(self, model: FVM400Model) -> None:
        self.model = model
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="fvm400-pty", daemon=True)

    def _serve(self) -> None:
        while not self._stop.is_set():
            r, _, _ = select.select([self._master], [], [], 0.02)
            if r:
                try:
                    data = os.read(self._master, 256)
                except OSError:
                    return
                self.model.receive(data)
            n = self.model.pending()
            if n:
                try:
                    os.write(self._master, self.model.take(n))
                except OSError:
                    return

    def __enter__(self) -> PtyInstrument:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __exit__(self, *exc) -> None:
        self.close()
