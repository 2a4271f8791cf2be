"""Telecommands: ECSS PUS-C TC packets received over UDP or as packet files, checked, then executed.

Accepted services (docs/ccsds.md): 17,1 ping (answered with 17,2) and 8,1 perform function, whose
function id is the command's opcode in :data:`magstack.data.dictionary.COMMANDS`, followed by its
arguments as length-prefixed UTF-8 strings. Every packet is checked in this order, and a packet that
fails a check is counted under that check, reported (event ``TC_REJECTED`` and, when its header
could be read, a 1,2 acceptance-failure report) and never executed:

0. a packet file of ``tc_dir`` is taken at most once (renamed into ``done/`` before it is read) and read
   under the application's one intake rule (:mod:`.intake`: regular file, no symlink, at most
   ``MAX_TC_BYTES`` checked before reading, owned by the application's user, writable by nobody else);
   a file refused there counts as malformed (type, size) or unauthorised (owner, mode);
1. unauthorised: the UDP source host is not in ``tc_hosts`` (checked first, before any parsing);
2. malformed: shorter than a TC, not a version-1 TC with a secondary header, or the length field
   disagrees with the datagram/file size;
3. bad CRC: the PUS packet error control (CRC-16/CCITT-FALSE) is wrong;
4. wrong APID: not addressed to this application (``APP_APID``);
5. unauthorised: the PUS source id is not in ``tc_source_ids``;
6. invalid: unknown service or function id, wrong number of arguments, an argument the dictionary refuses
   (:func:`magstack.data.dictionary.arg_problem`, the check ``magstack tm command`` applies too);
7. sequence count, per source id, against the count the receiver expects next, V(R) (the sliding windows
   of COP-1's FARM, CCSDS 232.1-B): within ``POSITIVE_WINDOW`` ahead (telecommands lost on the way are
   allowed for: nothing is retransmitted here) it is accepted and V(R) moves past it; within
   ``NEGATIVE_WINDOW`` behind it is a **replay**; anything else is **out of the window**, refused without
   moving V(R) (so one stray count far ahead locks nobody out). The first packet of a source the
   receiver has no state for sets V(R). ``resync_tc {source_id, seq}`` sets V(R) (from the command
   directory, or as a telecommand of that same source: like COP-1's "Set V(R)" directive it is exempt from
   the window check; every other check applies).

V(R) of every source is saved atomically (0600, fsynced) in ``state_path`` before an accepted command is
handed on, and read back at start: a packet of an earlier run is a replay after a restart too.

An accepted command gets a 1,1 report and goes to the application's dispatcher (the same path as the
command directory: executed at a cycle boundary); its CMD_COMPLETED / CMD_REJECTED event becomes the
1,7 / 1,8 report. What authenticates a command here is the configured source address plus the
CRC and the source id; a flight system adds CCSDS SDLS (authenticated encryption with anti-replay).
"""
from __future__ import annotations

import json
import os
import socket
import struct
from dataclasses import asdict, dataclass
from pathlib import Path

from spacepackets.ecss.tc import PusTc

from magstack.data.dictionary import APP_APID, COMMAND_BY_OPCODE, TC_FUNCTION, TC_PING, TcFailure, arg_problem
from magstack.data.io import atomic_write_text
from magstack.data.packets import CRC_BYTES, PRIMARY_HEADER_BYTES, SEQ_MODULO, TC_SECONDARY_BYTES, pec_ok
from magstack.firmware.flight.commands import Command
from magstack.firmware.flight.events import EventId, console
from magstack.firmware.flight.intake import UnsafeInput, check_private_dir, read_bounded

MAX_TC_BYTES = 2048
MAX_PER_POLL = 64            # datagrams / files handled per boundary (the rest wait: bounded work per cycle)
#: Sequence-count windows (counts ahead accepted / behind refused as replays), COP-1 FARM style.
POSITIVE_WINDOW = 64
NEGATIVE_WINDOW = 64
#: The receiver's saved state (V(R) per source id), in the command directory.
STATE_NAME = "tc-receiver.state"
STATE_FORMAT = "magstack-tc-receiver"
MAX_STATE_BYTES = 1 << 16
#: Hosts that mean "every interface": listening there is warned about.
ANY_HOST = ("0.0.0.0", "", "::")


@dataclass
class TcCounters:
    accepted: int = 0
    malformed: int = 0
    bad_crc: int = 0
    wrong_apid: int = 0
    replayed: int = 0
    out_of_window: int = 0
    unauthorised: int = 0
    invalid: int = 0

    @property
    def rejected(self) -> int:
        return (self.malformed + self.bad_crc + self.wrong_apid + self.replayed + self.out_of_window
                + self.unauthorised + self.invalid)

    def to_dict(self) -> dict[str, int]:
        return {f"tc_{k}": v for k, v in asdict(self).items()} | {"tc_rejected": self.rejected}


class _Reject(Exception):
    def __init__(self, code: TcFailure, message: str, header: tuple[int, int] | None = None) -> None:
        super().__init__(message)
        self.code, self.header = code, header


_COUNTER = {TcFailure.MALFORMED: "malformed", TcFailure.BAD_CRC: "bad_crc", TcFailure.WRONG_APID: "wrong_apid",
            TcFailure.REPLAYED: "replayed", TcFailure.OUT_OF_WINDOW: "out_of_window",
            TcFailure.UNAUTHORISED: "unauthorised", TcFailure.UNKNOWN_COMMAND: "invalid",
            TcFailure.BAD_ARGUMENT: "invalid"}


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
        if n == 0 or len(b) != n:
            raise ValueError(f"{cmd.name}: argument {a.name!r} empty or cut")
        try:
            args[a.name] = b.decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"{cmd.name}: argument {a.name!r} is not UTF-8") from None
        why = arg_problem(a, args[a.name])
        if why:
            raise ValueError(f"{cmd.name}: {why}")
        i += 1 + n
    if i != len(app_data):
        raise ValueError(f"{cmd.name}: {len(app_data) - i} byte(s) after the last argument")
    return cmd.name, args


def window_check(expected: int | None, seq: int) -> TcFailure | None:
    """None when ``seq`` may be accepted with ``expected`` = V(R) (None: no state yet), else why not."""
    if expected is None or (seq - expected) % SEQ_MODULO < POSITIVE_WINDOW:
        return None
    if 0 < (expected - seq) % SEQ_MODULO <= NEGATIVE_WINDOW:
        return TcFailure.REPLAYED
    return TcFailure.OUT_OF_WINDOW


class TelecommandReceiver:
    """Checks and dispatches telecommand packets; ``poll`` at a boundary, ``receive`` per packet.

    Raises :class:`~magstack.firmware.flight.intake.UnsafeInput` at construction when ``tc_dir`` or the
    saved state is not private to the application (the application then refuses to start)."""

    def __init__(self, cfg, events, stream, dispatch, epoch_now, state_path: Path | None = None) -> None:
        self.cfg, self.events, self.stream, self.dispatch, self.epoch_now = cfg, events, stream, dispatch, epoch_now
        self.counters = TcCounters()
        self.state_path = Path(state_path) if state_path is not None else None
        self.state_errors = 0
        self._expected: dict[int, int] = {}                 # source id -> V(R), the count expected next
        self._pending: dict[str, tuple[int, int]] = {}      # command source -> request id
        self._refused: set = set()                          # (name, inode, mtime) of packet files not takeable
        self._n = 0
        self.sock = None
        self.directory = Path(cfg.tc_dir) if cfg.tc_dir is not None else None
        if self.directory is not None:
            for d in (self.directory, self.directory / "done"):
                why = check_private_dir(d)
                if why:
                    raise UnsafeInput(f"telecommand directory refused: {why}", "owner")
        self._load_state()
        if cfg.tc_udp is not None:
            if cfg.tc_udp[0] in ANY_HOST:
                console.warning("tc_udp %s:%d listens on every network interface: telecommands are accepted "
                                "only from tc_hosts %s, but the port is reachable from every network; bind a "
                                "local address instead", cfg.tc_udp[0], cfg.tc_udp[1], ", ".join(cfg.tc_hosts))
            try:
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s.setblocking(False)
                s.bind(cfg.tc_udp)
                self.sock = s
            except OSError as exc:
                self.events.emit(self.epoch_now(), EventId.TC_REJECTED, "tc_udp",
                                 f"cannot listen on {cfg.tc_udp[0]}:{cfg.tc_udp[1]}: {exc}"[:200])

    # ------------------------------------------------------------------ state (V(R) per source)
    def _load_state(self) -> None:
        if self.state_path is None or not os.path.lexists(self.state_path):
            return
        raw = read_bounded(self.state_path, MAX_STATE_BYTES)      # UnsafeInput: refuse to start
        try:
            doc = json.loads(raw.decode("utf-8"))
            if not isinstance(doc, dict) or doc.get("format") != STATE_FORMAT or doc.get("version") != 1:
                raise ValueError("not a receiver state document of version 1")
            exp = {int(k): int(v) for k, v in doc["expected"].items()}
            if not all(0 <= k < 65536 and 0 <= v < SEQ_MODULO for k, v in exp.items()):
                raise ValueError("a source id or count out of range")
        except (ValueError, TypeError, KeyError, AttributeError, RecursionError) as exc:
            self.state_errors += 1
            self.events.emit(self.epoch_now(), EventId.TC_STATE_ERROR, "tc_state",
                             f"{self.state_path}: unreadable ({type(exc).__name__}: {exc}); the next telecommand "
                             f"of each source sets its count"[:200])
            return
        self._expected = exp

    def _save_state(self) -> None:
        if self.state_path is None:
            return
        doc = {"format": STATE_FORMAT, "version": 1,
               "expected": {str(k): v for k, v in sorted(self._expected.items())}}
        try:
            atomic_write_text(self.state_path, json.dumps(doc, sort_keys=True) + "\n", perm=0o600)
        except OSError as exc:
            self.state_errors += 1
            self.events.emit(self.epoch_now(), EventId.TC_STATE_ERROR, "tc_state",
                             f"cannot save the sequence counts ({exc}): a restart may accept a replay"[:200])

    def expected(self) -> dict[int, int]:
        """V(R): the sequence count expected next, per source id with state."""
        return dict(self._expected)

    def resync(self, source_id: int, seq: int) -> str:
        """Set V(R) of ``source_id`` to ``seq`` (the ``resync_tc`` command); saved at once."""
        if not 0 <= source_id < 65536 or not 0 <= seq < SEQ_MODULO:
            raise ValueError(f"source id {source_id} or count {seq} out of range")
        if source_id not in self.cfg.tc_source_ids:
            raise ValueError(f"source id {source_id} is not in tc_source_ids {list(self.cfg.tc_source_ids)}")
        old = self._expected.get(source_id)
        self._expected[source_id] = seq
        self._save_state()
        msg = f"source {source_id}: expected count {'none' if old is None else old} -> {seq}"
        self.events.emit(self.epoch_now(), EventId.TC_RESYNC, f"source-{source_id}", msg)
        return msg

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
            n += self._poll_files(MAX_PER_POLL - n)
        return n

    def _poll_files(self, budget: int) -> int:
        try:
            with os.scandir(self.directory) as it:
                names = sorted(e.name for e in it if e.name.endswith(".tc") and not e.name.startswith("."))
        except OSError:
            return 0
        n = 0
        for attempt, name in enumerate(names):
            if n >= budget or attempt >= 4 * MAX_PER_POLL:      # unclaimable files cost little, too
                break
            taken = self.directory / "done" / name
            try:
                os.rename(self.directory / name, taken)         # at most once: taken before it is read
            except OSError as exc:
                self._unclaimable(name, exc)
                continue
            n += 1
            try:
                data = read_bounded(taken, MAX_TC_BYTES)
            except UnsafeInput as exc:
                code = TcFailure.UNAUTHORISED if exc.kind == "owner" else TcFailure.MALFORMED
                self._count(code, "tc_dir", f"packet file {name}: {exc}")
                continue
            self.receive(data, origin=None)
        return n

    def _unclaimable(self, name: str, exc: OSError) -> None:
        try:
            st = os.lstat(self.directory / name)
        except OSError:
            return                                            # gone meanwhile
        key = (name, st.st_ino, st.st_mtime_ns)
        if key in self._refused:
            return
        if len(self._refused) > 10_000:
            self._refused.clear()
        self._refused.add(key)
        self._count(TcFailure.MALFORMED, "tc_dir", f"packet file {name}: cannot take it ({exc.strerror or exc}): "
                                                   "not executed")

    def _count(self, code: TcFailure, origin: str, message: str) -> None:
        setattr(self.counters, _COUNTER[code], getattr(self.counters, _COUNTER[code]) + 1)
        self.events.emit(self.epoch_now(), EventId.TC_REJECTED, origin, f"{code.name}: {message}"[:200])

    def receive(self, data: bytes, origin: str | None = None) -> bool:
        """Check one packet; True if it was accepted (and dispatched). Never raises."""
        try:
            kind, req, source_id, seq = self._check(bytes(data), origin)
        except _Reject as r:
            self._count(r.code, origin or "tc_dir", str(r))
            if r.header is not None:
                self._report("accept_fail", r.header, r.code)
            return False
        if not (kind is not None and kind[0] == "resync_tc"):
            self._expected[source_id] = (seq + 1) % SEQ_MODULO
            self._save_state()                                 # before the command runs: at most once
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
        if kind is not None and kind[0] == "resync_tc":
            if int(kind[1]["source_id"]) != tc.source_id:
                raise _Reject(TcFailure.UNAUTHORISED, f"resync_tc of source {kind[1]['source_id']} sent by source "
                                                      f"{tc.source_id}: a source resynchronises only itself", header)
        else:
            expected = self._expected.get(tc.source_id)
            why = window_check(expected, tc.seq_count)
            if why is not None:
                hint = "; resync_tc sets it" if why is TcFailure.OUT_OF_WINDOW else ""
                raise _Reject(why, f"sequence count {tc.seq_count}, expected {expected} "
                                   f"(window -{NEGATIVE_WINDOW}..+{POSITIVE_WINDOW - 1}){hint}", header)
        return kind, header, tc.source_id, tc.seq_count

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
