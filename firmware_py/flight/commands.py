"""Commands to the flight application, applied at cycle boundaries.

Transport: a **command directory** (spool). A client writes one JSON object per file and renames
it to ``*.json`` when complete (rename is atomic, so a half-written command is never read). The
spool runs in its own slow rate group (never on a fast group's critical path) and takes at most
``per_poll`` files per cycle, in name order. Each file is first **claimed**: renamed into
``processing/`` (a command that cannot be claimed is never executed, and reported once); only then is it
read (:func:`~magstack.firmware.flight.intake.read_bounded`: regular file, at most 64 KiB, owned by the
application's user and writable by nobody else, no symlink, a FIFO never blocks), parsed and handed on;
its outcome goes to ``done/<name>.result.json`` and the file to ``done/``. So every command runs at most
once, also across a crash: a file still in ``processing/`` at start-up is reported as interrupted and
not run again. Every rejection is counted and evented. The directory is created 0700 and refused when
another user owns it or others may write it. Why a directory and not a socket: it needs no
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
* ``stop_refit {channel}`` - cancel a running refit (it stops at its next block);
* ``resync_tc {source_id, seq}`` - set the telecommand receiver's expected sequence count of a PUS source
  (:mod:`.telecommands`).

A command for a channel is queued to the rate group that runs the channel and executed by that
group between two of its cycles, never while a read is under way.
"""
from __future__ import annotations

import json
import os
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from magstack.data.dictionary import COMMAND as COMMAND_BY_NAME
from magstack.data.dictionary import COMMANDS as COMMAND_DEFS
from magstack.data.dictionary import arg_problem
from magstack.firmware.flight.events import EventId, EventLog
from magstack.firmware.flight.intake import UnsafeInput, check_private_dir, read_bounded

#: Command name -> its argument names, from the flight dictionary (:data:`magstack.data.dictionary.COMMANDS`).
COMMANDS = {c.name: {a.name for a in c.args} for c in COMMAND_DEFS}
MAX_COMMAND_BYTES = 64 * 1024


@dataclass(frozen=True)
class Command:
    name: str
    args: dict[str, Any]
    source: str                 # file name (or packet id), for results and events
    #: ``reply(source, ok=, message=, payload=)`` records the outcome; None: the command directory's results.
    #: A packet command source (telecommands) passes its own, so its acceptance/completion reports go back to it.
    reply: Callable[..., None] | None = field(default=None, compare=False)

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
    for a in COMMAND_BY_NAME[name].args:
        why = arg_problem(a, args[a.name])
        if why:
            raise CommandRejected(f"{name}: {why}")
    return Command(name, args, source)


@dataclass
class CommandSpool:
    """Polls ``directory`` for ``*.json`` commands; claims, reads, parses and hands each to ``dispatch``."""

    directory: Path
    events: EventLog
    dispatch: Callable[[Command], bool]            # False: cannot be queued now, offer it again later
    epoch_now: Callable[[], float]
    per_poll: int = 8
    accepted: int = 0
    rejected: int = 0
    _refused: set = field(default_factory=set)     # (name, inode, mtime) of files already reported unclaimable
    _waiting: deque = field(default_factory=deque)  # parsed commands their channel could not queue yet

    def __post_init__(self) -> None:
        self.directory = Path(self.directory)
        for d in (self.directory, self.directory / "processing", self.directory / "done"):
            why = check_private_dir(d)
            if why:
                raise UnsafeInput(f"command directory refused: {why}")

    def recover(self) -> int:
        """Report commands left in ``processing/`` by a stop or crash as interrupted (never run again)."""
        n = 0
        for name in sorted(os.listdir(self.directory / "processing")):
            if (self.directory / "done" / f"{name}.result.json").exists():
                self._file_away(name)        # finished; only the move to done/ was lost
                continue
            n += 1
            self.finish(name, ok=False, message="interrupted by a stop or crash while being executed; "
                                                "not executed again (at most once)")
        return n

    def poll(self, _now_s: float = 0.0) -> int:
        """Take up to ``per_poll`` complete command files (sorted by name); returns how many were taken.

        ``dispatch`` returns False when the command's channel cannot queue it now: the command waits here
        (claimed, not executed) and no new file is taken until it is handed on (back-pressure: the files
        stay in the directory while the application is busy)."""
        taken = 0
        while self._waiting and taken < self.per_poll:
            if not self.dispatch(self._waiting[0]):
                return taken
            self._waiting.popleft()
            taken += 1
        if self._waiting:
            return taken
        try:
            with os.scandir(self.directory) as it:
                names = sorted(e.name for e in it if e.name.endswith(".json") and not e.name.startswith("."))
        except OSError:
            return taken
        for attempt, name in enumerate(names):
            if taken >= self.per_poll or attempt >= 4 * self.per_poll:   # unclaimable files cost little, too
                break
            if not self._claim(name):
                continue
            taken += 1
            try:
                cmd = parse_command(read_bounded(self.directory / "processing" / name, MAX_COMMAND_BYTES), name)
            except (CommandRejected, UnsafeInput) as exc:
                self.finish(name, ok=False, message=str(exc))
                continue
            self.accepted += 1
            self.events.emit(self.epoch_now(), EventId.CMD_ACCEPTED, name, cmd.name)
            if not self.dispatch(cmd):
                self._waiting.append(cmd)
                break
        return taken

    def _claim(self, name: str) -> bool:
        """Rename ``name`` into ``processing/`` before anything is read (at most once); False if impossible."""
        src = self.directory / name
        try:
            os.rename(src, self.directory / "processing" / name)
            return True
        except OSError as exc:
            try:
                st = os.lstat(src)
            except OSError:
                return False                 # gone meanwhile (the client took it back)
            key = (name, st.st_ino, st.st_mtime_ns)
            if key not in self._refused:
                if len(self._refused) > 10_000:
                    self._refused.clear()
                self._refused.add(key)
                self.rejected += 1
                self.events.emit(self.epoch_now(), EventId.CMD_REJECTED, name,
                                 f"cannot claim the command file ({exc.strerror or exc}): not executed")
            return False

    def _file_away(self, name: str) -> None:
        try:
            os.replace(self.directory / "processing" / name, self.directory / "done" / name)
        except OSError:
            pass                             # stays in processing/: never taken again, reported at restart

    def finish(self, name: str, *, ok: bool, message: str, payload: dict | None = None) -> None:
        """Record a command's outcome: event, ``done/<name>`` and ``done/<name>.result.json``."""
        if not ok:
            self.rejected += 1
        self.events.emit(self.epoch_now(), EventId.CMD_COMPLETED if ok else EventId.CMD_REJECTED, name,
                         message[:200])
        self._file_away(name)
        result = {"command": name, "ok": ok, "message": message, **({"result": payload} if payload else {})}
        tmp = self.directory / "done" / f".{name}.result.tmp"
        try:
            tmp.write_text(json.dumps(result, indent=1, sort_keys=True, default=str) + "\n", encoding="utf-8")
            os.replace(tmp, self.directory / "done" / f"{name}.result.json")
        except (OSError, ValueError):
            pass
