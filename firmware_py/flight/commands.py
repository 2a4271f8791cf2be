"""Commands to the flight application, applied at cycle boundaries.

Transport: a **command directory** (spool). A client writes one JSON object per file and renames
it to ``*.json`` when complete (rename is atomic, so a half-written command is never read); the
executive polls the directory at its rate-group boundaries, moves each file to ``done/`` and writes
``done/<name>.result.json`` with the outcome. Why a directory and not a socket: it needs no
thread or open port on the flight computer, it works identically in virtual time (tests and
simulation are deterministic), it survives a restart (unprocessed commands wait), and it is what an
uplink file transfer delivers anyway. ``magstack`` tools or ``mv`` are the only client needed.

Commands (``"cmd"`` key), each naming its ``"channel"`` where it applies:

* ``load_table {channel, path}`` - parse, check device id, validate and stage a table (not active);
* ``validate_table {channel, path}`` - report whether a table file would be accepted, stage nothing;
* ``activate_table {channel}`` - swap the staged table in at the channel's next cycle boundary;
* ``set_rate_group {channel, group}`` - move a channel to another rate group at the next boundary;
* ``dump_counters {}`` - write every channel's health counters, group statistics and event counts;
* ``start_refit {channel, files}`` - start the on-orbit batch refit (:mod:`magstack.firmware.calibration.refit`)
  of the channel's calibration over recorded telemetry (``files``: a glob, relative to the config file,
  of telemetry session files carrying position and attitude columns) in a background worker; the
  candidate table (written only if valid and better than the active table on held-out rows) and a
  result file go to ``<telemetry_dir>/refit/``; events ``REFIT_STARTED`` / ``REFIT_FINISHED`` /
  ``REFIT_FAILED``. The candidate is not activated: ``load_table`` + ``activate_table`` take it from there;
* ``stop_refit {channel}`` - cancel a running refit (it stops at its next block).

A command for a channel is queued to the rate group that runs the channel and executed by that
group between two of its cycles, never while a read is under way.
"""
from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from magstack.data.dictionary import COMMANDS as COMMAND_DEFS
from magstack.firmware.flight.events import EventId, EventLog

#: Command name -> its argument names, from the flight dictionary (:data:`magstack.data.dictionary.COMMANDS`).
COMMANDS = {c.name: {a.name for a in c.args} for c in COMMAND_DEFS}
MAX_COMMAND_BYTES = 64 * 1024


@dataclass(frozen=True)
class Command:
    name: str
    args: dict[str, Any]
    source: str                 # file name, for results and events

    @property
    def channel(self) -> str | None:
        return self.args.get("channel")


class CommandRejected(ValueError):
    """A command that cannot be parsed or executed (reported, never raised out of the executive)."""


def parse_command(raw: bytes, source: str) -> Command:
    if len(raw) > MAX_COMMAND_BYTES:
        raise CommandRejected(f"command file larger than {MAX_COMMAND_BYTES} bytes")
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise CommandRejected(f"not a JSON command: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("cmd"), str):
        raise CommandRejected('a command is a JSON object with a "cmd" string')
    name = doc["cmd"]
    if name not in COMMANDS:
        raise CommandRejected(f"unknown command {name!r}; valid: {', '.join(COMMANDS)}")
    args = {k: v for k, v in doc.items() if k not in ("cmd", "id")}
    need = COMMANDS[name]
    missing, unknown = sorted(need - args.keys()), sorted(args.keys() - need)
    if missing or unknown:
        raise CommandRejected(f"{name}: missing {missing}, unknown {unknown}" if missing and unknown else
                              f"{name}: missing argument(s) {missing}" if missing else
                              f"{name}: unknown argument(s) {unknown}")
    for k, v in args.items():
        if not isinstance(v, str) or not v:
            raise CommandRejected(f"{name}: {k} must be a non-empty string")
    return Command(name, args, source)


@dataclass
class CommandSpool:
    """Polls ``directory`` for ``*.json`` commands; hands each to ``dispatch``; files results in ``done/``."""

    directory: Path
    events: EventLog
    dispatch: Callable[[Command], None]
    epoch_now: Callable[[], float]
    accepted: int = 0
    rejected: int = 0
    _seen: set[str] = field(default_factory=set)

    def __post_init__(self) -> None:
        self.directory = Path(self.directory)
        (self.directory / "done").mkdir(parents=True, exist_ok=True)

    def poll(self, _now_s: float = 0.0) -> int:
        """Pick up every complete command file (sorted by name); returns how many were taken."""
        try:
            names = sorted(p.name for p in self.directory.iterdir() if p.suffix == ".json" and p.is_file())
        except OSError:
            return 0
        for name in names:
            path = self.directory / name
            try:
                raw = path.read_bytes()
            except OSError:
                continue   # vanished or unreadable now; try at the next boundary
            try:
                cmd = parse_command(raw, name)
            except CommandRejected as exc:
                self.finish(name, ok=False, message=str(exc))
                continue
            self.accepted += 1
            self.events.emit(self.epoch_now(), EventId.CMD_ACCEPTED, name, cmd.name)
            self._move_to_done(name)
            self.dispatch(cmd)
        return len(names)

    def _move_to_done(self, name: str) -> None:
        try:
            os.replace(self.directory / name, self.directory / "done" / name)
        except OSError:
            pass

    def finish(self, name: str, *, ok: bool, message: str, payload: dict | None = None) -> None:
        """Record a command's outcome: event, ``done/<name>`` and ``done/<name>.result.json``."""
        if not ok:
            self.rejected += 1
        self.events.emit(self.epoch_now(), EventId.CMD_COMPLETED if ok else EventId.CMD_REJECTED, name,
                         message[:200])
        if (self.directory / name).exists():
            self._move_to_done(name)
        result = {"command": name, "ok": ok, "message": message, **({"result": payload} if payload else {})}
        tmp = self.directory / "done" / f".{name}.result.tmp"
        try:
            tmp.write_text(json.dumps(result, indent=1, sort_keys=True, default=str) + "\n", encoding="utf-8")
            os.replace(tmp, self.directory / "done" / f"{name}.result.json")
        except OSError:
            pass
