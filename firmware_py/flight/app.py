"""Build and run the flight application from a :class:`~magstack.firmware.flight.config.FlightConfig`.

One :class:`FlightApp` = rate groups (each on its own clock: virtual clocks in simulation, the system
clock on hardware), a :class:`~magstack.firmware.flight.channel.MagChannel` per sensor opened through
the chip factory (``magstack.drivers.registry.open_chip``: the same code on the Pi and on simulated
buses), a calibration-table store and fixed-point corrector per channel, telemetry files per channel,
the event log (``events.jsonl``), and the command spool. Telemetry rows, packets and event lines are
written behind the rate groups (:mod:`.writer`): a writer thread on hardware, the idle slot between two
slots in virtual time; ``write_behind=False`` writes them inside the cycle (the synchronous path: the
benchmark's baseline and the tests' reference).
"""
from __future__ import annotations

import json
import math
import os
import re
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from magstack.data.io import atomic_write_text
from magstack.drivers.clock import SystemClock, VirtualClock
from magstack.drivers.registry import open_chip
from magstack.firmware.cal_table import save_table, validate
from magstack.firmware.corrector import TableCorrector
from magstack.firmware.errors import CalTableInvalid, FlightConfigError
from magstack.firmware.flight.ccsds import attach_ccsds
from magstack.firmware.flight.channel import ChannelLimits, MagChannel
from magstack.firmware.flight.commands import Command, CommandSpool
from magstack.firmware.flight.config import FlightConfig, SensorConfig, check_directories
from magstack.firmware.flight.events import EventFileSink, EventId, EventLog
from magstack.firmware.flight.executive import Executive, RateGroup
from magstack.firmware.flight.intake import MAX_REFIT_INPUT_BYTES, UnsafeInput, check_file, inside_roots
from magstack.firmware.flight.tables import FlightTableStore
from magstack.firmware.flight.telemetry import ChannelTelemetry
from magstack.firmware.flight.writer import WriteBehind

#: Name of the command spool's own rate group (not configurable: it is not a sensor timeline).
COMMAND_GROUP = "_commands"
#: Commands waiting for one channel's boundary; more wait in the spool (back-pressure).
CHANNEL_QUEUE = 16
#: Files of the telemetry directory that hold a run id: <channel>-<run>-<index>.csv[.part],
#: events-<run>.jsonl, summary-<run>.json.
_RUN_FILE = re.compile(r"^(?:.+-(\d{4,})-\d{4,}\.csv(?:\.part)?|(?:events|summary)-(\d{4,})\.jsonl?)$")

#: ``chip_options(sensor, clock) -> extra open_chip keyword arguments`` (the simulator's truth source ...).
ChipOptions = Callable[[SensorConfig, Any], dict]


@dataclass
class ChannelSlot:
    """A channel with its table store, corrector, telemetry and current rate group."""

    sensor: SensorConfig
    channel: MagChannel
    store: FlightTableStore
    telemetry: ChannelTelemetry
    group: str
    pending: deque = field(default_factory=deque)      # commands for the next boundaries (thread-safe ends)
    table_rejected: str = ""                           # why the configured table was refused at start


class _Cancelled(Exception):
    pass


class RefitJob:
    """One channel's batch refit in a background worker (it reads files; the rate groups keep running)."""

    def __init__(self, channel: str, files: list[str], active, device_id: str, out_dir: Path, events: EventLog,
                 now: Callable[[], float]) -> None:
        self.channel, self.files, self.active, self.device_id = channel, files, active, device_id
        self.out_dir, self.events, self.now = Path(out_dir), events, now
        self.cancel = threading.Event()
        self.result: dict | None = None
        self.thread = threading.Thread(target=self._run, name=f"refit-{channel}", daemon=True)

    def start(self) -> None:
        self.events.emit(self.now(), EventId.REFIT_STARTED, self.channel, f"{len(self.files)} telemetry file(s)")
        self.thread.start()

    def _progress(self, _rows: int, _label: str) -> None:
        if self.cancel.is_set():
            raise _Cancelled()

    def _run(self) -> None:
        from magstack.firmware.calibration.refit import RefitOptions, refit

        self.out_dir.mkdir(parents=True, exist_ok=True)
        stamp = f"{self.channel}-{int(self.now())}"
        try:
            res = refit(self.files, self.active, RefitOptions(device_id=self.device_id), progress=self._progress)
        except _Cancelled:
            self.result = {"ok": False, "message": "stopped by stop_refit"}
            self.events.emit(self.now(), EventId.REFIT_FAILED, self.channel, "stopped by stop_refit")
        except Exception as exc:  # noqa: BLE001 - a refit failure is an event, never a crash of the executive
            self.result = {"ok": False, "message": f"{type(exc).__name__}: {exc}"}
            self.events.emit(self.now(), EventId.REFIT_FAILED, self.channel, f"{type(exc).__name__}: {exc}"[:200])
        else:
            self.result = {"ok": True, **res.to_dict()}
            if res.proposed and res.candidate is not None:
                path = save_table(res.candidate, self.out_dir / f"{stamp}-candidate.json")
                os.chmod(path, 0o644)        # loadable under the intake rule whatever the umask
                self.result["candidate_path"] = str(path)
                msg = f"candidate {path.name} proposed"
            else:
                msg = "no candidate proposed: " + "; ".join(res.reasons)[:180]
            self.events.emit(self.now(), EventId.REFIT_FINISHED, self.channel, msg)
        try:
            (self.out_dir / f"{stamp}-result.json").write_text(json.dumps(self.result, indent=1, sort_keys=True,
                                                                          default=str) + "\n", encoding="utf-8")
        except OSError:
            pass


class FlightApp:
    """The on-board application. ``virtual=True`` runs every rate group on its own VirtualClock."""

    def __init__(self, cfg: FlightConfig, *, virtual: bool = False, simulate: bool = False,
                 telemetry_dir: str | Path | None = None, run_id: int | None = None,
                 chip_options: ChipOptions | None = None, start_epoch_s: float | None = None,
                 stop: threading.Event | None = None, write_behind: bool = True) -> None:
        self.cfg = cfg
        self.virtual = virtual
        self.simulate = simulate
        self.telemetry_dir = Path(telemetry_dir) if telemetry_dir is not None else cfg.telemetry_dir
        check_directories(cfg, self.telemetry_dir)
        self.telemetry_dir.mkdir(parents=True, exist_ok=True)
        self.run_id = run_id if run_id is not None else self._next_run_id()
        self.writer = WriteBehind(cfg.write_queue, on_error=self._write_failed) if write_behind else None
        self._event_sink = EventFileSink(self.telemetry_dir / f"events-{self.run_id:04d}.jsonl")
        self.events = EventLog(sink=self._behind(self._event_sink, "events"))
        shared = None if virtual else SystemClock()
        self.clocks: dict[str, Any] = {}
        groups = []
        periods = [(g.name, g.period_s) for g in cfg.rate_groups]
        if cfg.command_dir is not None:
            periods.append((COMMAND_GROUP, 1.0 / cfg.command_rate_hz))
        for name, period_s in periods:
            clk = VirtualClock(**({} if start_epoch_s is None else {"start_epoch_s": start_epoch_s})) \
                if virtual else shared
            self.clocks[name] = clk
            groups.append(RateGroup(name, period_s, clk))
        any_clock = next(iter(self.clocks.values()))
        offset = any_clock.epoch_s() - any_clock.monotonic_s()
        self.epoch_of = (lambda t: t + offset) if virtual else (lambda t: t - shared.monotonic_s() + shared.epoch_s())
        self.executive = Executive(groups, self.events, self.epoch_of, stop)
        self.slots: dict[str, ChannelSlot] = {}
        self.refits: dict[str, RefitJob] = {}
        try:
            for s in cfg.sensors:
                self._add_channel(s, chip_options)
        except BaseException:
            self.close()
            raise
        for g in groups:
            g.boundary.append(self._boundary_hook(g))
            if self.writer is not None:
                g.boundary.append(lambda now_s, w=self.writer: w.report_overflow(self.events, self.epoch_of(now_s)))
        self.spool = None
        if cfg.command_dir is not None:
            # its own slow rate group (thread), a bounded number of files per cycle: a burst of commands
            # never lands on a sensor group's critical path
            cmd_clock = self.clocks[COMMAND_GROUP]
            try:
                self.spool = CommandSpool(cfg.command_dir, self.events, self.submit,
                                          lambda: self.epoch_of(cmd_clock.monotonic_s()),
                                          per_poll=cfg.commands_per_cycle)
            except (UnsafeInput, OSError) as exc:
                self.close()
                raise FlightConfigError(f"{cfg.path}: flight.command_dir: {exc}") from None
            self.spool.recover()
            self.executive.group(COMMAND_GROUP).boundary.insert(0, self.spool.poll)
        try:
            self.ccsds = attach_ccsds(self)     # [ccsds]: packet stream + telecommands (None without the table)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ construction
    def _next_run_id(self) -> int:
        """One more than any run id on disk (telemetry files and ``.part`` files, event logs, summaries)."""
        ids = [int(m.group(1) or m.group(2)) for n in os.listdir(self.telemetry_dir) if (m := _RUN_FILE.match(n))]
        return max(ids, default=0) + 1

    def _table_roots(self) -> tuple[Path, ...]:
        return (*self.cfg.table_roots, self.telemetry_dir / "refit")

    def _add_channel(self, s: SensorConfig, chip_options: ChipOptions | None) -> None:
        clock = self.clocks[s.rate_group]
        bus = "sim" if self.simulate else s.bus
        extra = dict(chip_options(s, clock)) if chip_options is not None else {}
        mag = open_chip(s.chip, bus, clock, **{**s.options, **extra})
        store = FlightTableStore(s.device_id, s.name, self._table_roots(), self.cfg.path.parent)
        meta = {"device_id": s.device_id, "dut_chip": s.chip, "bus": bus, "flight_config": self.cfg.name,
                "run_id": str(self.run_id), "rate_group": s.rate_group, "source": "magstack run"}
        tlm = ChannelTelemetry(self.telemetry_dir, s.name, run_id=self.run_id, metadata=meta,
                               rotate_bytes=self.cfg.rotate_bytes, block_rows=self.cfg.block_rows, events=self.events)
        ch = MagChannel(s.name, mag, TableCorrector(store), self.events, sink=self._behind(tlm, f"telemetry/{s.name}"),
                        limits=ChannelLimits(s.max_field_uT, s.max_rate_uT_per_s, s.reinit_after, s.degrade_after,
                                             rate_horizon_s=self.cfg.group(s.rate_group).period_s),
                        epoch_of=self.epoch_of)
        slot = ChannelSlot(s, ch, store, tlm, s.rate_group)
        self.slots[s.name] = slot
        self.executive.group(s.rate_group).components.append(ch)
        if s.table is not None:
            try:
                store.load_and_activate(s.table)
                self.events.emit(self.epoch_of(clock.monotonic_s()), EventId.TABLE_ACTIVATED, s.name,
                                 f"{s.table} crc32 0x{store.active.crc32:08x}")
            except CalTableInvalid as exc:
                slot.table_rejected = str(exc)
                self.events.emit(self.epoch_of(clock.monotonic_s()), EventId.TABLE_REJECTED, s.name, str(exc)[:200])

    def _behind(self, sink, source: str):
        """``sink`` as the rate groups see it: queued to the writer (or itself, without write-behind)."""
        return sink if self.writer is None else self.writer.sink(sink, source)

    def _write_failed(self, source: str, exc: Exception) -> None:
        """A queued write raised (the writers count their own I/O errors; this is anything else)."""
        self.events.emit(self._now(None), EventId.TLM_WRITE_ERROR, source, f"{type(exc).__name__}: {exc}"[:200])

    # ------------------------------------------------------------------ boundaries and commands
    def _boundary_hook(self, group: RateGroup):
        def hook(now_s: float) -> None:
            for slot in self.slots.values():
                if slot.group != group.name:
                    continue
                if slot.pending:                 # one command per boundary: bounded work between two cycles
                    self._execute(slot, slot.pending.popleft())
                if slot.store.cycle_boundary():
                    a = slot.store.active
                    self.events.emit(self.epoch_of(now_s), EventId.TABLE_ACTIVATED, slot.sensor.name,
                                     f"crc32 0x{a.crc32:08x}" if a.crc32 is not None else "unsaved table")
        return hook

    def submit(self, cmd: Command) -> bool:
        """Hand over a parsed command (from the command directory or any other command source): a channel-less
        command runs now, a channel's is queued to its group; False when that queue is full (offer it later).
        The outcome goes to ``cmd.reply`` (default: the command directory's result files)."""
        if cmd.channel is None:
            self._execute(None, cmd)
            return True
        slot = self.slots.get(cmd.channel)
        if slot is None:
            self._finish(cmd, ok=False, message=f"no channel {cmd.channel!r}; have {sorted(self.slots)}")
            return True
        if len(slot.pending) >= CHANNEL_QUEUE:
            return False
        slot.pending.append(cmd)
        return True

    def _execute(self, slot: ChannelSlot | None, cmd: Command) -> None:
        ok, msg, payload = True, "done", None
        try:
            if cmd.name == "dump_counters":
                payload = self.counters()
                msg = "counters dumped"
            elif cmd.name == "load_table":
                res = slot.store.load(cmd.args["path"])
                self.events.emit(self._now(slot),
                                 EventId.TABLE_LOADED, slot.sensor.name, f"{cmd.args['path']} staged")
                msg = f"staged (worst-case output {res.worst_output_uT:.1f} uT); activate with activate_table"
            elif cmd.name == "validate_table":
                v = validate(slot.store.read(cmd.args["path"]))
                ok, msg = v.ok, "valid" if v.ok else "invalid: " + "; ".join(v.problems)
            elif cmd.name == "activate_table":
                slot.store.request_activation()
                msg = "activation requested (takes effect at the next cycle boundary)"
            elif cmd.name == "set_rate_group":
                msg = self._move(slot, cmd.args["group"])
            elif cmd.name == "start_refit":
                msg = self._start_refit(slot, cmd.args["files"])
            elif cmd.name == "resync_tc":
                if self.ccsds is None:
                    raise ValueError("this configuration takes no telecommands (no [ccsds] table)")
                msg = self.ccsds.resync(int(cmd.args["source_id"]), int(cmd.args["seq"]))
            elif cmd.name == "stop_refit":
                job = self.refits.get(slot.sensor.name)
                if job is None or not job.thread.is_alive():
                    raise ValueError("no refit running on this channel")
                job.cancel.set()
                msg = "stop requested (the refit stops at its next block)"
        except CalTableInvalid as exc:
            ok, msg = False, str(exc)
            if cmd.name == "load_table":
                self.events.emit(self._now(slot), EventId.TABLE_REJECTED, slot.sensor.name, msg[:200])
        except Exception as exc:  # noqa: BLE001 - any failure of a command is a counted, evented rejection
            ok, msg = False, f"{type(exc).__name__}: {str(exc)[:300]}"
        self._finish(cmd, ok=ok, message=msg, payload=payload)

    def _finish(self, cmd: Command, *, ok: bool, message: str, payload: dict | None = None) -> None:
        reply = cmd.reply or (self.spool.finish if self.spool is not None else None)
        if reply is None:               # a source without a reply path: the outcome is at least an event
            self.events.emit(self._now(None), EventId.CMD_COMPLETED if ok else EventId.CMD_REJECTED, cmd.source,
                             message[:200])
            return
        reply(cmd.source, ok=ok, message=message, payload=payload)

    def _now(self, slot: ChannelSlot | None) -> float:
        clk = self.clocks[slot.group] if slot is not None else next(iter(self.clocks.values()))
        return self.epoch_of(clk.monotonic_s())

    def _move(self, slot: ChannelSlot, group: str) -> str:
        if group not in self.clocks:
            raise ValueError(f"no rate group {group!r}; have {sorted(self.clocks)}")
        if self.virtual and self.clocks[group] is not self.clocks[slot.group]:
            # in virtual time the driver is bound to its group's clock: only same-timeline moves are exact
            raise ValueError("in virtual time a channel cannot change timelines; restart with the new config")
        if group == COMMAND_GROUP:
            raise ValueError(f"{group!r} is the command spool's group, not a sensor timeline")
        old = self.executive.group(slot.group)
        old.components.remove(slot.channel)
        self.executive.group(group).components.append(slot.channel)
        slot.channel.limits.rate_horizon_s = self.executive.group(group).period_s
        prev, slot.group = slot.group, group
        return f"moved from {prev} to {group}"

    # ------------------------------------------------------------------ refit
    def _start_refit(self, slot: ChannelSlot, pattern: str) -> str:
        import glob

        name = slot.sensor.name
        job = self.refits.get(name)
        if job is not None and job.thread.is_alive():
            raise ValueError("a refit is already running on this channel (stop_refit first)")
        base = self.cfg.path.parent
        roots = (*self.cfg.refit_roots, self.telemetry_dir)
        matches = sorted(glob.glob(pattern if Path(pattern).is_absolute() else str(base / pattern)))
        if not matches:
            raise ValueError(f"no telemetry files match {pattern!r}")
        files = [str(inside_roots(f, roots, base)) for f in matches]      # UnsafeInput: outside the roots
        for f in files:
            check_file(f, MAX_REFIT_INPUT_BYTES)     # the intake rule (type, size, owner, mode): UnsafeInput
        job = RefitJob(name, files, slot.store.active, slot.sensor.device_id, self.telemetry_dir / "refit",
                       self.events, lambda: self._now(slot))
        self.refits[name] = job
        job.start()
        return f"refit started over {len(files)} file(s)"

    # ------------------------------------------------------------------ running
    def run(self, duration_s: float | None = None, pauses=()) -> None:
        """Run for ``duration_s`` (virtual time: required); ``pauses``: ``(t_s, action)`` called with the
        application standing still at ``t_s`` after the start (virtual time only, :meth:`Executive.run_virtual`),
        after everything written so far has reached the files (:meth:`flush_outputs`)."""
        if self.virtual:
            if duration_s is None or not math.isfinite(duration_s):
                raise ValueError("virtual time needs a finite duration")
            drain = None if self.writer is None else (lambda _g: self.writer.drain())
            pauses = [(t, (lambda a=a: (self.flush_outputs(), a()))) for t, a in pauses]
            self.executive.run_virtual(duration_s, on_slot=drain, pauses=pauses)   # writes in the idle slot
            if self.writer is not None:
                self.writer.drain()
        else:
            if self.writer is not None:
                self.writer.start()
            self.executive.run_threads(duration_s)

    def stop(self) -> None:
        self.executive.stop()

    def flush_outputs(self) -> None:
        """Write what is queued and hand the packet file's buffer to the OS (not fsynced), so a reader of the
        telemetry directory sees every packet so far; the session files keep their own blocks."""
        if self.writer is not None:
            self.writer.drain()
        if self.ccsds is not None:
            self.ccsds.stream.flush()

    def counters(self) -> dict:
        sink = getattr(self, "_event_sink", None)
        return {"channels": {n: s.channel.counters() | {"corrector": dict(s.channel.corrector.status),
                                                         "table": s.store.telemetry(),
                                                         "telemetry": s.telemetry.stats()}
                             for n, s in self.slots.items()},
                "rate_groups": {g.name: {"rate_hz": g.rate_hz, **g.stats.to_dict()} for g in self.executive.groups},
                "events": self.events.snapshot(),
                "events_lost": (0 if sink is None else sink.lost) + self.events.sink_errors
                + (0 if self.writer is None else self.writer.dropped["events"]),
                "write_queue": None if self.writer is None else self.writer.stats(),
                "commands": None if self.spool is None else {"accepted": self.spool.accepted,
                                                             "rejected": self.spool.rejected},
                "packets": None if getattr(self, "ccsds", None) is None else self.ccsds.counters(),
                "degraded": self.degraded_reasons()}

    def degraded_reasons(self) -> list[str]:
        """Why the run ended degraded (``magstack run`` exits 1): a channel degraded at the end, a configured
        table refused at start and none active since, telemetry rows or events that could not be written."""
        out = []
        for n, s in self.slots.items():
            if s.channel.degraded:
                out.append(f"channel {n} degraded")
            if s.table_rejected and s.store.active is None:
                out.append(f"channel {n}: configured table rejected, running uncalibrated ({s.table_rejected})")
            if s.telemetry.rows_lost:
                out.append(f"channel {n}: {s.telemetry.rows_lost} telemetry rows could not be written")
        dropped = sum(self.writer.dropped.values()) if self.writer is not None else 0
        if dropped:
            out.append(f"write queue full: {dropped} records, packets or event lines dropped "
                       f"({', '.join(f'{s} {n}' for s, n in sorted(self.writer.dropped.items()))})")
        sink = getattr(self, "_event_sink", None)
        lost = (0 if sink is None else sink.lost) + self.events.sink_errors     # dropped ones: the reason above
        if lost:
            out.append(f"{lost} events could not be written to the event log")
        if getattr(self, "ccsds", None) is not None:
            out += self.ccsds.degraded_reasons()
        return out

    def wait_refits(self, timeout_s: float | None = None) -> None:
        """Wait for running refits (tests, and a clean shutdown)."""
        for job in getattr(self, "refits", {}).values():
            job.thread.join(timeout_s)

    def close(self) -> None:
        """Write everything queued, close every telemetry file (rename to final), the packet stream and the
        event log; safe to call twice."""
        for job in getattr(self, "refits", {}).values():
            job.cancel.set()
        self.wait_refits(30.0)
        writer = getattr(self, "writer", None)
        drain = writer.stop if writer is not None else (lambda: None)   # stop: drain, end the thread
        drain()
        for s in getattr(self, "slots", {}).values():
            s.telemetry.close()
            close = getattr(s.channel.mag, "close", None)
            if close is not None:
                try:
                    close()
                except Exception:  # noqa: BLE001 - closing must not hide the run's result
                    pass
        drain()                                  # events of the closes (a failed rename ...) and their packets
        if getattr(self, "ccsds", None) is not None:
            self.ccsds.close()
        drain()
        sink = getattr(self, "_event_sink", None)
        if sink is not None:
            sink.close()

    def write_summary(self, path: str | Path) -> Path:
        """Write the counters atomically (FileWriteError, an OSError, when the disk is still full)."""
        return atomic_write_text(path, json.dumps(self.counters(), indent=1, sort_keys=True, default=str) + "\n")
