"""The flight application's CCSDS packet stream and telecommand input (``[ccsds]`` in flight.toml).

:func:`attach_ccsds` is the one hook the application calls (after building its channels): it wraps
each channel's telemetry sink, the event log's sink and each rate group's boundary so that every
telemetry record, event and housekeeping summary also becomes a PUS-C TM packet (layouts:
:mod:`magstack.data.dictionary`, docs/ccsds.md), written to ``<telemetry_dir>/packets-<run>.bin``
and/or sent as UDP datagrams (by the application's write-behind writer, :mod:`.writer`: the rate groups
only pack); with ``csv = false`` the session CSVs are not written. Telecommands
(:mod:`.telecommands`) are polled at the fastest group's boundary, like the command directory.

A packet that cannot be written or sent is counted (``tm_send_errors``) with a rate-limited
``TLM_WRITE_ERROR`` event; the flight loop never stops for it.
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
from magstack.firmware.flight.events import Event, EventId
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
    """Encodes and emits TM packets to a file and/or a UDP address; never raises on a write."""

    def __init__(self, apids: ApidMap, *, path: Path | None, udp: tuple[str, int] | None,
                 on_error: Callable[[str], None] | None = None, sync_every: int = 200,
                 writer: WriteBehind | None = None) -> None:
        self.apids = apids
        self.writer = writer                        # None: written and sent by the caller (synchronous)
        self.encoder = TmEncoder()
        self.path = path
        self._fh = open(path, "ab") if path is not None else None
        self._udp = udp
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM) if udp is not None else None
        self.on_error = on_error
        self.sync_every = max(1, sync_every)
        self.sent = 0
        self.bytes = 0
        self.send_errors = 0
        self._lock = threading.Lock()

    def _write(self, data: bytes) -> str:
        try:
            if self._fh is not None:
                self._fh.write(data)
                if (self.sent + 1) % self.sync_every == 0:
                    self._fh.flush()
                    os.fsync(self._fh.fileno())
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
            "temp": rec.temp_c, "flag": rec.flags, "table_crc32": rec.table_crc32, "error_count": rec.error_count})

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

    def flush(self) -> None:
        """Hand the file's buffered packets to the OS (no fsync): a reader of the file sees whole packets."""
        with self._lock:
            if self._fh is not None and not self._fh.closed:
                self._fh.flush()

    def close(self) -> None:
        with self._lock:
            if self._fh is not None and not self._fh.closed:
                try:
                    self._fh.flush()
                    os.fsync(self._fh.fileno())
                except OSError:
                    self.send_errors += 1
                self._fh.close()
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
        from magstack.firmware.flight.telecommands import TelecommandReceiver

        self.cfg = cfg
        self.app = app
        path = app.telemetry_dir / f"packets-{app.run_id:04d}.bin" if cfg.packets else None
        self.stream = PacketStream(apid_map(app.cfg), path=path, udp=cfg.tm_udp, on_error=self._error,
                                   writer=getattr(app, "writer", None))
        self.receiver = None
        if cfg.tc_udp is not None or cfg.tc_dir is not None:
            self.receiver = TelecommandReceiver(cfg, app.events, self.stream, self._submit, self._now)
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
