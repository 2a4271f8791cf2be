"""The flight application's CCSDS packet stream and telecommand input (``[ccsds]`` in flight.toml).

:func:`attach_ccsds` is the one hook the application calls (after building its channels): it wraps
each channel's telemetry sink, the event log's sink and each rate group's boundary so that every
telemetry record, event and housekeeping summary also becomes a PUS-C TM packet (layouts:
:mod:`magstack.data.dictionary`, docs/ccsds.md), written to ``<telemetry_dir>/packets-<run>.bin``
and/or sent as UDP datagrams (by the application's write-behind writer, :mod:`.writer`: the rate groups
only pack); with ``csv = false`` the session CSVs are not written. Telecommands
(:mod:`.telecommands`) are polled at the fastest group's boundary, like the command directory.

A packet that cannot be written or sent is counted (``tm_send_errors``) with a rate-limited
``TLM_WRITE_ERROR`` event; the flight loop never stops for it, and the run's summary and degraded reasons
carry the count. Every channel packet carries its run id, and the run's ``apid_map`` packets (run id,
APID -> channel, device id, chip) are the first packets of the run and are repeated every ``hk_period_s``,
so a decoder can attribute every channel packet to a channel and a run (:mod:`magstack.ground.tm_decode`).
"""
from __future__ import annotations

import math
import os
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from magstack.data.dictionary import APP_APID, EVENT_SUBTYPE, TM_PACKET, Severity
from magstack.data.packets import ApidMap, TmEncoder
from magstack.firmware.errors import FlightConfigError
from magstack.firmware.flight.events import Event, EventId
from magstack.firmware.flight.intake import UnsafeInput
from magstack.firmware.flight.writer import WriteBehind

DEFAULT_TM_PORT, DEFAULT_TC_PORT = 50510, 50511


@dataclass(frozen=True)
class CcsdsConfig:
    """``[ccsds]``: where packets go and where telecommands come from (checked at load)."""

    csv: bool = True                                 # also write the session CSVs
    packets: bool = True                             # write <telemetry_dir>/packets-<run>.bin
    tm_udp: tuple[str, int] | None = None            # send each TM packet as a datagram here
    hk_period_s: float = 10.0                        # housekeeping and APID-map packets every ... s
    tc_udp: tuple[str, int] | None = None            # receive telecommands on this local address
    tc_dir: Path | None = None                       # ... or as packet files (*.tc) dropped here
    tc_hosts: tuple[str, ...] = ("127.0.0.1",)       # UDP source hosts allowed to command
    tc_source_ids: tuple[int, ...] = (1,)            # PUS TC source ids allowed to command


def _address(c, key: str, v: Any) -> tuple[str, int]:
    if not isinstance(v, str) or v.count(":") != 1:
        raise c.err(key, f'must be "host:port", got {v!r}')
    host, port = v.split(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise c.err(key, f'must be "host:port" with a port in 1..65535, got {v!r}')
    return host, int(port)


def parse_ccsds(c, obj: Any, base: Path, has_command_dir: bool = True) -> CcsdsConfig | None:
    """``[ccsds]`` -> CcsdsConfig (``c`` is the config module's error context)."""
    if obj is None:
        return None
    from magstack.firmware.flight.config import _num, _str, _table

    t = _table(c, "ccsds", obj, set(), {"csv", "packets", "tm_udp", "hk_period_s", "tc_udp", "tc_dir", "tc_hosts",
                                        "tc_source_ids"})
    for k in ("csv", "packets"):
        if not isinstance(t.get(k, True), bool):
            raise c.err(f"ccsds.{k}", f"must be true or false, got {t[k]!r}")
    hosts = t.get("tc_hosts", ["127.0.0.1"])
    ids = t.get("tc_source_ids", [1])
    if not isinstance(hosts, list) or not all(isinstance(h, str) and h for h in hosts):
        raise c.err("ccsds.tc_hosts", "must be a list of host addresses")
    if not isinstance(ids, list) or not all(isinstance(i, int) and not isinstance(i, bool) and 0 <= i < 65536
                                            for i in ids):
        raise c.err("ccsds.tc_source_ids", "must be a list of integers in 0..65535")
    cfg = CcsdsConfig(
        csv=t.get("csv", True), packets=t.get("packets", True),
        tm_udp=_address(c, "ccsds.tm_udp", t["tm_udp"]) if "tm_udp" in t else None,
        hk_period_s=float(_num(c, "ccsds.hk_period_s", t.get("hk_period_s", 10.0), 0.01, 86400.0)),
        tc_udp=_address(c, "ccsds.tc_udp", t["tc_udp"]) if "tc_udp" in t else None,
        tc_dir=base / _str(c, "ccsds.tc_dir", t["tc_dir"]) if "tc_dir" in t else None,
        tc_hosts=tuple(hosts), tc_source_ids=tuple(ids))
    if (cfg.tc_udp is not None or cfg.tc_dir is not None) and not has_command_dir:
        raise c.err("ccsds", "telecommands (tc_udp, tc_dir) need flight.command_dir: results are filed there")
    if not (cfg.csv or cfg.packets or cfg.tm_udp):
        raise c.err("ccsds", "csv, packets and tm_udp are all off: the run would record no telemetry")
    return cfg


def apid_map(cfg) -> ApidMap:
    """The APIDs and packets a flight configuration produces (sensors and rate groups in file order)."""
    cc = cfg.ccsds
    return ApidMap(tuple(s.name for s in cfg.sensors), tuple(g.name for g in cfg.rate_groups),
                   telecommands=cc is not None and (cc.tc_udp is not None or cc.tc_dir is not None))


class PacketStream:
    """Encodes and emits TM packets to a file and/or a UDP address; never raises on a write, nor on close.

    The file is written without a user-space buffer: each packet is one ``write`` on an ``O_APPEND``
    descriptor as soon as the writer takes it, so a process killed at any moment loses only the packets
    still waiting in the write-behind queue (:mod:`.writer`), never a buffer of written ones. It is fsynced
    (for a power cut) every ``sync_s`` seconds of ``now`` (the application's clock) and every
    ``sync_every`` packets. A write that fails or is cut short (disk full) is cut back off the file (no
    partial packet stays in it) and counted (``send_errors``); the next packet tries again."""

    def __init__(self, apids: ApidMap, *, path: Path | None, udp: tuple[str, int] | None,
                 on_error: Callable[[str], None] | None = None, sync_every: int = 200,
                 writer: WriteBehind | None = None, now: Callable[[], float] | None = None,
                 sync_s: float = 1.0, run_id: int = 0) -> None:
        self.apids = apids
        self.writer = writer                        # None: written and sent by the caller (synchronous)
        self.encoder = TmEncoder()
        self.path = path
        self.run_id = int(run_id)
        self._fd: int | None = None
        self._size = 0
        if path is not None:
            self._fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
            self._size = os.fstat(self._fd).st_size
        self._udp = udp
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM) if udp is not None else None
        self.on_error = on_error
        self.sync_every = max(1, sync_every)
        self.sync_s = float(sync_s)
        self._now = now
        self._synced_at: float | None = None
        self._unsynced = 0
        self.sent = 0
        self.bytes = 0
        self.send_errors = 0                        # packets that could not be written or sent
        self.sync_errors = 0                        # fsyncs that failed (written data may not be durable)
        self._lock = threading.Lock()

    def _file_write(self, data: bytes) -> None:
        """One packet onto the file, whole or not at all (OSError when not)."""
        if self._fd is None:
            raise ValueError("packet file closed")
        try:
            n = os.write(self._fd, data)
            if n != len(data):
                raise OSError(28, f"short write ({n} of {len(data)} bytes)")
        except OSError:
            try:
                os.ftruncate(self._fd, self._size)      # no partial packet stays in the file
            except OSError:
                pass
            raise
        self._size += len(data)
        self._unsynced += 1
        t = self._now() if self._now is not None else None
        if self._synced_at is None and t is not None:
            self._synced_at = t
        if self._unsynced >= self.sync_every or (t is not None and t - self._synced_at >= self.sync_s):
            self._sync(t)

    def _sync(self, t: float | None) -> None:
        self._unsynced = 0
        self._synced_at = t
        try:
            os.fsync(self._fd)
        except OSError:
            self.sync_errors += 1

    def _write(self, data: bytes) -> str:
        try:
            if self.path is not None:
                self._file_write(data)
            if self._sock is not None:
                self._sock.sendto(data, self._udp)
        except (OSError, ValueError) as exc:     # ValueError: written after close
            self.send_errors += 1
            if self.send_errors & (self.send_errors - 1) == 0:          # an event at the 1st, 2nd, 4th, 8th ...
                return f"packet stream: {type(exc).__name__}: {exc} ({self.send_errors} so far)"[:200]
            return ""
        self.sent += 1
        self.bytes += len(data)
        return ""

    def emit(self, name: str, apid: int, t_s: float, values: dict, subtype: int | None = None,
             report: bool = True) -> None:
        """Pack (sequence count of ``apid``) and send one packet; thread-safe (rate groups run in threads).

        With a ``writer`` the caller only packs: the write, fsync and datagram are queued (under the lock, so
        packets leave in packing order) and a full queue drops the packet (counted by the writer)."""
        with self._lock:
            data = self.encoder.pack(TM_PACKET[name], apid, t_s, values, subtype)
            if self.writer is not None:
                self.writer.offer(self._send, (data, report), "packets")
                return
            err = self._write(data)
        if err and report and self.on_error is not None:
            self.on_error(err)

    def _send(self, job: tuple[bytes, bool]) -> None:
        """The writer's job: write/send one packed packet (the writer is the only caller of ``_write`` then)."""
        data, report = job
        err = self._write(data)
        if err and report and self.on_error is not None:
            self.on_error(err)

    # -------------------------------------------------------------------- what the application produces
    def record(self, rec) -> None:
        """One channel packet from a :class:`~magstack.firmware.flight.channel.TelemetryRecord`."""
        raw = rec.raw_uT or (None, None, None)
        cal = rec.cal_uT or (None, None, None)
        self.emit("channel", self.apids.channel(rec.channel), rec.t_s, {
            "raw_x": raw[0], "raw_y": raw[1], "raw_z": raw[2], "cal_x": cal[0], "cal_y": cal[1], "cal_z": cal[2],
            "temp": rec.temp_c, "flag": rec.flags, "table_crc32": rec.table_crc32, "error_count": rec.error_count,
            "run_id": self.run_id})

    def event(self, ev: Event) -> None:
        sev = Severity(ev.severity)
        self.emit("event", APP_APID, ev.t_s, {"event_id": int(ev.id), "severity": int(sev), "source": ev.source,
                                              "message": ev.message}, subtype=EVENT_SUBTYPE[sev],
                  report=False)    # called under the event log's lock: an error event here would deadlock

    def group_hk(self, group, t_s: float) -> None:
        st = group.stats
        self.emit("group_hk", self.apids.group(group.name), t_s, {
            "runs": st.runs, "overruns": st.overruns, "missed_slots": st.missed_slots,
            "clock_steps_back": st.clock_steps_back, "exec_max": st.exec_max_s})

    def apid_announcements(self, t_s: float, run_id: int, sensors) -> None:
        for s in sensors:
            self.emit("apid_map", APP_APID, t_s, {"apid": self.apids.channel(s.name), "kind": 1, "run_id": run_id,
                                                  "name": s.name, "device_id": s.device_id, "chip": s.chip})
        for g in self.apids.groups:
            self.emit("apid_map", APP_APID, t_s, {"apid": self.apids.group(g), "kind": 2, "run_id": run_id,
                                                  "name": g, "device_id": "", "chip": ""})

    def stats(self) -> dict:
        return {"path": None if self.path is None else str(self.path), "written": self.sent, "bytes": self.bytes,
                "send_errors": self.send_errors, "sync_errors": self.sync_errors}

    def flush(self) -> None:
        """Nothing to hand over: every packet is one unbuffered write, so a reader of the file sees whole
        packets as soon as they are written (kept for the callers that hand a ground step a consistent file)."""

    def close(self) -> None:
        """fsync and close (a failure is counted in ``sync_errors``, never raised); safe to call twice."""
        with self._lock:
            fd, self._fd = self._fd, None
            if fd is not None:
                try:
                    os.fsync(fd)
                except OSError:
                    self.sync_errors += 1
                try:
                    os.close(fd)
                except OSError:
                    self.sync_errors += 1
            if self._sock is not None:
                self._sock.close()


def _tee(*sinks):
    """One sink feeding several; each gets every item even if another raised (the first error is re-raised:
    the channel counts it as a telemetry error)."""
    sinks = tuple(s for s in sinks if s is not None)

    def sink(item) -> None:
        error = None
        for s in sinks:
            try:
                s(item)
            except Exception as exc:  # noqa: BLE001 - re-raised below, after the other sinks had the item
                error = error or exc
        if error is not None:
            raise error
    return sink


class CcsdsLink:
    """What :func:`attach_ccsds` built: the packet stream, the telecommand receiver, the HK schedule."""

    def __init__(self, app, cfg: CcsdsConfig) -> None:
        from magstack.firmware.flight.telecommands import STATE_NAME, TelecommandReceiver

        self.cfg = cfg
        self.app = app
        path = app.telemetry_dir / f"packets-{app.run_id:04d}.bin" if cfg.packets else None
        # fsync by time on the system clock (a power cut loses at most a second of packets); in virtual time
        # every sync_every packets only (a simulated day would otherwise wait for 86,400 fsyncs)
        clk = next(iter(app.clocks.values()))
        now = None if getattr(app, "virtual", False) else clk.monotonic_s
        self.stream = PacketStream(apid_map(app.cfg), path=path, udp=cfg.tm_udp, on_error=self._error,
                                   writer=getattr(app, "writer", None), now=now, run_id=app.run_id)
        self.receiver = None
        if cfg.tc_udp is not None or cfg.tc_dir is not None:
            state = app.cfg.command_dir / STATE_NAME if app.cfg.command_dir is not None else None
            try:
                self.receiver = TelecommandReceiver(cfg, app.events, self.stream, self._submit, self._now,
                                                    state_path=state)
            except UnsafeInput as exc:
                self.stream.close()
                raise FlightConfigError(f"{app.cfg.path}: ccsds.tc_dir: {exc}") from None
        self._next_hk: dict[str, float] = {}

    def _submit(self, cmd) -> None:
        """Hand an accepted telecommand to the application (``FlightApp.submit``); a full channel queue is
        a rejection (its CMD_REJECTED event becomes the 1,8 report)."""
        if not self.app.submit(cmd):
            self.app.events.emit(self._now(), EventId.CMD_REJECTED, cmd.source, "channel command queue full")

    def _now(self) -> float:
        clk = next(iter(self.app.clocks.values()))
        return self.app.epoch_of(clk.monotonic_s())

    def _error(self, msg: str) -> None:
        self.app.events.emit(self._now(), EventId.TLM_WRITE_ERROR, "packets", msg)

    def hk_hook(self, group):
        def hook(now_s: float) -> None:
            due = self._next_hk.get(group.name)
            if due is not None and now_s < due:
                return
            self._next_hk[group.name] = now_s + self.cfg.hk_period_s if due is None else \
                due + self.cfg.hk_period_s * max(1, math.ceil((now_s - due) / self.cfg.hk_period_s))
            t = self.app.epoch_of(now_s)
            if group.name == self.app.cfg.rate_groups[0].name:
                self.stream.apid_announcements(t, self.app.run_id, self.app.cfg.sensors)
                self.stream.emit("app_hk", APP_APID, t, self.tc_counters())
            self.stream.group_hk(group, t)
        return hook

    def tc_counters(self) -> dict[str, int]:
        c = self.receiver.counters.to_dict() if self.receiver is not None else {}
        return {**c, "tm_send_errors": self.stream.send_errors}

    def resync(self, source_id: int, seq: int) -> str:
        """The ``resync_tc`` command (ValueError without a telecommand input)."""
        if self.receiver is None:
            raise ValueError("this configuration takes no telecommands ([ccsds] tc_udp / tc_dir)")
        return self.receiver.resync(source_id, seq)

    def counters(self) -> dict:
        """The packet stream's and the telecommand receiver's counters (the run's summary)."""
        rx = self.receiver
        return {**self.stream.stats(),
                "telecommands": None if rx is None else {**rx.counters.to_dict(), "state_errors": rx.state_errors,
                                                         "expected_seq": {str(k): v for k, v in
                                                                          sorted(rx.expected().items())}}}

    def degraded_reasons(self) -> list[str]:
        out = []
        if self.stream.send_errors:
            out.append(f"{self.stream.send_errors} packets could not be written or sent")
        if self.stream.sync_errors:
            out.append(f"{self.stream.sync_errors} fsyncs of the packet file failed (packets may not be durable)")
        return out

    def close(self) -> None:
        if self.receiver is not None:
            self.receiver.close()
        self.stream.close()


def attach_ccsds(app) -> CcsdsLink | None:
    """Route ``app``'s telemetry records, events and housekeeping into packets; start telecommand input.

    Returns None when the configuration has no ``[ccsds]`` table (the application is unchanged)."""
    cfg = getattr(app.cfg, "ccsds", None)
    if cfg is None:
        return None
    link = CcsdsLink(app, cfg)
    # the run's identification (run id, APID -> channel, device, chip) precedes every other packet of the run
    link.stream.apid_announcements(link._now(), app.run_id, app.cfg.sensors)
    for slot in app.slots.values():
        slot.channel.sink = _tee(slot.channel.sink if cfg.csv else None, link.stream.record)
    for ev in list(app.events.recent):          # events of the start-up (table activation) come first
        link.stream.event(ev)
    app.events.sink = _tee(app.events.sink, link.stream.event,
                           link.receiver.on_event if link.receiver is not None else None)
    configured = {g.name for g in app.cfg.rate_groups}
    groups = [g for g in app.executive.groups if g.name in configured]   # not the command spool's own group
    for g in groups:
        g.boundary.append(link.hk_hook(g))
    if link.receiver is not None:
        # telecommands are taken where the command files are: the spool's own rate group, off the sensors' path
        spool = [g for g in app.executive.groups if g.name not in configured]
        host = spool[0] if spool else max(groups, key=lambda x: x.rate_hz)
        host.boundary.insert(0, link.receiver.poll)
    return link
