"""Telecommands: ECSS PUS-C TC packets received over UDP or as packet files, checked, then executed.

Accepted services (docs/ccsds.md): 17,1 ping (answered with 17,2) and 8,1 perform function, whose
function id is the command's opcode in :data:`magstack.data.dictionary.COMMANDS`, followed by its
arguments as length-prefixed UTF-8 strings. Every packet is checked in this order, and a packet that
fails a check is counted under that check, reported (event ``TC_REJECTED`` and, when its header
could be read, a 1,2 acceptance-failure report) and never executed:

1. unauthorised: the UDP source host is not in ``tc_hosts`` (checked first, before any parsing);
2. malformed: shorter than a TC, not a version-1 TC with a secondary header, or the length field
   disagrees with the datagram/file size;
3. bad CRC: the PUS packet error control (CRC-16/CCITT-FALSE) is wrong;
4. wrong APID: not addressed to this application (``APP_APID``);
5. unauthorised: the PUS source id is not in ``tc_source_ids``;
6. replayed: the sequence count is not newer (mod 2**14, within half the range) than the last one
   accepted from that source id;
7. invalid: unknown service or function id, wrong number of arguments, an argument too long.

An accepted command gets a 1,1 report and goes to the application's dispatcher (the same path as the
command directory: executed at a cycle boundary); its CMD_COMPLETED / CMD_REJECTED event becomes the
1,7 / 1,8 report. What authenticates a command here is the configured source address plus the
CRC and the source id; a flight system adds CCSDS SDLS (authenticated encryption with anti-replay).
"""
from __future__ import annotations

import socket
import struct
from dataclasses import asdict, dataclass
from pathlib import Path

from spacepackets.ecss.tc import PusTc

from magstack.data.dictionary import APP_APID, COMMAND_BY_OPCODE, TC_FUNCTION, TC_PING, TcFailure
from magstack.data.packets import CRC_BYTES, PRIMARY_HEADER_BYTES, SEQ_MODULO, TC_SECONDARY_BYTES, pec_ok
from magstack.firmware.flight.commands import Command
from magstack.firmware.flight.events import EventId

MAX_TC_BYTES = 2048
MAX_PER_POLL = 64            # datagrams / files handled per boundary (the rest wait: bounded work per cycle)


@dataclass
class TcCounters:
    accepted: int = 0
    malformed: int = 0
    bad_crc: int = 0
    wrong_apid: int = 0
    replayed: int = 0
    unauthorised: int = 0
    invalid: int = 0

    @property
    def rejected(self) -> int:
        return self.malformed + self.bad_crc + self.wrong_apid + self.replayed + self.unauthorised + self.invalid

    def to_dict(self) -> dict[str, int]:
        return {f"tc_{k}": v for k, v in asdict(self).items()} | {"tc_rejected": self.rejected}


class _Reject(Exception):
    def __init__(self, code: TcFailure, message: str, header: tuple[int, int] | None = None) -> None:
        super().__init__(message)
        self.code, self.header = code, header


_COUNTER = {TcFailure.MALFORMED: "malformed", TcFailure.BAD_CRC: "bad_crc", TcFailure.WRONG_APID: "wrong_apid",
            TcFailure.REPLAYED: "replayed", TcFailure.UNAUTHORISED: "unauthorised",
            TcFailure.UNKNOWN_COMMAND: "invalid", TcFailure.BAD_ARGUMENT: "invalid"}


def parse_function(app_data: bytes) -> tuple[str, dict[str, str]]:
    """8,1 application data -> (command name, arguments); ValueError when it does not fit the dictionary."""
    if len(app_data) < 2:
        raise ValueError("8,1 without a function id")
    op = struct.unpack(">H", app_data[:2])[0]
    cmd = COMMAND_BY_OPCODE.get(op)
    if cmd is None:
        raise LookupError(f"unknown function id 0x{op:04x}")
    args, i = {}, 2
    for a in cmd.args:
        if i >= len(app_data):
            raise ValueError(f"{cmd.name}: argument {a.name!r} missing")
        n = app_data[i]
        b = app_data[i + 1:i + 1 + n]
        if n == 0 or len(b) != n or n > a.max_len:
            raise ValueError(f"{cmd.name}: argument {a.name!r} empty, cut or longer than {a.max_len} bytes")
        try:
            args[a.name] = b.decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"{cmd.name}: argument {a.name!r} is not UTF-8") from None
        i += 1 + n
    if i != len(app_data):
        raise ValueError(f"{cmd.name}: {len(app_data) - i} byte(s) after the last argument")
    return cmd.name, args


class TelecommandReceiver:
    """Checks and dispatches telecommand packets; ``poll`` at a boundary, ``receive`` per packet."""

    def __init__(self, cfg, events, stream, dispatch, epoch_now) -> None:
        self.cfg, self.events, self.stream, self.dispatch, self.epoch_now = cfg, events, stream, dispatch, epoch_now
        self.counters = TcCounters()
        self._last_seq: dict[int, int] = {}
        self._pending: dict[str, tuple[int, int]] = {}      # command source -> request id
        self._n = 0
        self.sock = None
        if cfg.tc_udp is not None:
            try:
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s.setblocking(False)
                s.bind(cfg.tc_udp)
                self.sock = s
            except OSError as exc:
                self.events.emit(self.epoch_now(), EventId.TC_REJECTED, "tc_udp",
                                 f"cannot listen on {cfg.tc_udp[0]}:{cfg.tc_udp[1]}: {exc}"[:200])
        self.directory = Path(cfg.tc_dir) if cfg.tc_dir is not None else None
        if self.directory is not None:
            (self.directory / "done").mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ input
    def poll(self, _now_s: float = 0.0) -> int:
        n = 0
        while self.sock is not None and n < MAX_PER_POLL:
            try:
                data, addr = self.sock.recvfrom(MAX_TC_BYTES + 1)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            self.receive(data, origin=addr[0])
            n += 1
        if self.directory is not None:
            try:
                names = sorted(p.name for p in self.directory.iterdir() if p.suffix == ".tc" and p.is_file())
            except OSError:
                names = []
            for name in names[:max(0, MAX_PER_POLL - n)]:
                try:
                    data = (self.directory / name).read_bytes()[:MAX_TC_BYTES + 1]
                    (self.directory / name).replace(self.directory / "done" / name)
                except OSError:
                    continue
                self.receive(data, origin=None)
                n += 1
        return n

    def receive(self, data: bytes, origin: str | None = None) -> bool:
        """Check one packet; True if it was accepted (and dispatched). Never raises."""
        try:
            kind, req = self._check(bytes(data), origin)
        except _Reject as r:
            setattr(self.counters, _COUNTER[r.code], getattr(self.counters, _COUNTER[r.code]) + 1)
            self.events.emit(self.epoch_now(), EventId.TC_REJECTED, origin or "tc_dir", f"{r.code.name}: {r}"[:200])
            if r.header is not None:
                self._report("accept_fail", r.header, r.code)
            return False
        self.counters.accepted += 1
        self._report("accept_ok", req)
        if kind is None:                               # ping
            self.stream.emit("ping_reply", APP_APID, self.epoch_now(), {})
            self._report("complete_ok", req)
            return True
        name, args = kind
        self._n += 1
        source = f"tc-{req[1] & 0x3FFF:05d}-{self._n}"
        self._pending[source] = req
        self.events.emit(self.epoch_now(), EventId.CMD_ACCEPTED, source, name)
        self.dispatch(Command(name, args, source))
        return True

    def _check(self, data: bytes, origin: str | None):
        if origin is not None and origin not in self.cfg.tc_hosts:
            raise _Reject(TcFailure.UNAUTHORISED, f"source host {origin} not in tc_hosts")
        if not PRIMARY_HEADER_BYTES + TC_SECONDARY_BYTES + CRC_BYTES <= len(data) <= MAX_TC_BYTES:
            raise _Reject(TcFailure.MALFORMED, f"{len(data)} bytes: not a PUS TC size")
        w0, w1, length = struct.unpack(">HHH", data[:6])
        if w0 >> 13 != 0 or not (w0 >> 12) & 1 or not (w0 >> 11) & 1:
            raise _Reject(TcFailure.MALFORMED, "not a version-1 telecommand with a secondary header")
        header = (w0, w1)
        if length + 7 != len(data):
            raise _Reject(TcFailure.MALFORMED, f"length field says {length + 7} bytes, got {len(data)}", header)
        if not pec_ok(data):
            raise _Reject(TcFailure.BAD_CRC, "packet error control (CRC-16) wrong", header)
        try:
            tc = PusTc.unpack(data)
        except Exception as exc:  # noqa: BLE001 - spacepackets raises ValueError subclasses for a bad header
            raise _Reject(TcFailure.MALFORMED, f"{type(exc).__name__}: {exc}"[:120], header) from None
        if tc.apid != APP_APID:
            raise _Reject(TcFailure.WRONG_APID, f"APID 0x{tc.apid:03x}, this application is 0x{APP_APID:03x}", header)
        if tc.source_id not in self.cfg.tc_source_ids:
            raise _Reject(TcFailure.UNAUTHORISED, f"source id {tc.source_id} not in tc_source_ids", header)
        last = self._last_seq.get(tc.source_id)
        if last is not None and not 0 < (tc.seq_count - last) % SEQ_MODULO < SEQ_MODULO // 2:
            raise _Reject(TcFailure.REPLAYED, f"sequence count {tc.seq_count} not newer than {last}", header)
        st = (tc.service, tc.message_subtype)
        if st == TC_PING:
            kind = None
        elif st == TC_FUNCTION:
            try:
                kind = parse_function(bytes(tc.app_data))
            except LookupError as exc:
                raise _Reject(TcFailure.UNKNOWN_COMMAND, str(exc), header) from None
            except ValueError as exc:
                raise _Reject(TcFailure.BAD_ARGUMENT, str(exc), header) from None
        else:
            raise _Reject(TcFailure.UNKNOWN_COMMAND, f"service {st[0]},{st[1]} not provided", header)
        self._last_seq[tc.source_id] = tc.seq_count
        return kind, header

    # ------------------------------------------------------------------ reports
    def _report(self, name: str, req: tuple[int, int], code: TcFailure | None = None, report: bool = True) -> None:
        values = {"tc_packet_id": req[0], "tc_seq_ctrl": req[1]}
        if code is not None:
            values["failure_code"] = int(code)
        self.stream.emit(name, APP_APID, self.epoch_now(), values, report=report)

    def on_event(self, ev) -> None:
        """Event-log sink: a command's completion event becomes its 1,7 / 1,8 report."""
        if ev.id not in (EventId.CMD_COMPLETED, EventId.CMD_REJECTED):
            return
        req = self._pending.pop(ev.source, None)
        if req is not None:
            ok = ev.id == EventId.CMD_COMPLETED
            # under the event log's lock: the stream must not emit an event (report=False)
            self._report("complete_ok" if ok else "complete_fail", req, None if ok else TcFailure.EXECUTION_FAILED,
                         report=False)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
