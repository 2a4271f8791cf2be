"""``fvm400sim://`` pyserial URL handler: a simulated FVM400 on a serial port object.

URL forms::

    fvm400sim://bench                        the model registered as "bench"
    fvm400sim://?seed=1&noise_uT=0.02&garble=0.05&partial=0&dropout=0&over_range=0&wrong_units=0

The second form builds a private :class:`magstack.sim.fvm400_model.FVM400Model` (static truth field,
virtual clock). Reads never block in real time: when fewer bytes are available than asked, the
read returns them and, if the model's clock is virtual (has ``advance_s``), advances it by the
port timeout, as a real timed-out read would take. Each byte read also advances a virtual clock
by its transmission time (10 bits / baud). Opening at anything other than 9600 8N1 fails.
"""
from __future__ import annotations

import urllib.parse

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from magstack.drivers.clock import VirtualClock
from magstack.sim.fvm400_model import FVM400Faults, FVM400Model, get_instrument

_FAULT_KEYS = set(FVM400Faults().__dict__)


def model_from_url(url: str) -> FVM400Model:
    """Parse an ``fvm400sim://`` URL into a (registered or new) model; ValueError when malformed."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme != "fvm400sim":
        raise ValueError(f"expected fvm400sim://..., got {url!r}")
    name = (parts.netloc + parts.path).strip("/")
    query = urllib.parse.parse_qs(parts.query, keep_blank_values=True)
    if name:
        if query:
            raise ValueError(f"a named instrument takes no options: {url!r}")
        try:
            return get_instrument(name)
        except KeyError as exc:
            raise ValueError(str(exc)) from None
    known = _FAULT_KEYS | {"seed", "noise_uT"}
    bad = set(query) - known
    if bad:
        raise ValueError(f"unknown fvm400sim option(s) {sorted(bad)}; valid: {sorted(known)}")
    try:
        opts = {k: v[-1] for k, v in query.items()}
        faults = FVM400Faults(**{k: float(opts[k]) for k in _FAULT_KEYS if k in opts})
        return FVM400Model(None, VirtualClock(), noise_uT=float(opts.get("noise_uT", 0.0)),
                           seed=int(opts.get("seed", 0)), faults=faults)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"bad fvm400sim option in {url!r}: {exc}") from None


class Serial(SerialBase):
    """pyserial port object backed by an :class:`FVM400Model`."""

    model: FVM400Model | None = None

    def open(self) -> None:
        if self.is_open:
            raise SerialException("port already open")
        if self._port is None:
            raise SerialException("port must be configured before it can be used")
        try:
            self.model = model_from_url(str(self._port))
        except ValueError as exc:
            raise SerialException(str(exc)) from None
        self.is_open = True
        try:
            self._reconfigure_port()
        except SerialException:
            self.is_open = False
            raise
        self.model.clear_input()
        self.model.clear_output()

    def _reconfigure_port(self) -> None:
        if not self.is_open or self.model is None:
            return
        want = (self.model.baudrate, 8, "N", 1)
        got = (self._baudrate, self._bytesize, self._parity, self._stopbits)
        if got != want:
            raise SerialException(f"fvm400sim: the instrument talks {want[0]} baud 8N1; port opened with "
                                  f"{got[0]} baud {got[1]}{got[2]}{got[3]}")

    def close(self) -> None:
        self.is_open = False

    def _check(self) -> FVM400Model:
        if not self.is_open or self.model is None:
            raise PortNotOpenError()
        return self.model

    def _advance(self, dt_s: float) -> None:
        adv = getattr(self.model.clock, "advance_s", None) if self.model else None
        if adv is not None and dt_s > 0:
            adv(dt_s)

    @property
    def in_waiting(self) -> int:
        return self._check().pending()

    def read(self, size: int = 1) -> bytes:
        m = self._check()
        data = m.take(size)
        self._advance(len(data) * 10.0 / self._baudrate)
        if len(data) < size and self._timeout:
            self._advance(float(self._timeout))
        return data

    def write(self, data) -> int:
        m = self._check()
        b = bytes(data)
        self._advance(len(b) * 10.0 / self._baudrate)
        m.receive(b)
        return len(b)

    def reset_input_buffer(self) -> None:
        self._check().clear_output()

    def reset_output_buffer(self) -> None:
        self._check()

    def flush(self) -> None:
        self._check()

    @property
    def out_waiting(self) -> int:
        return 0

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    def _update_break_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
