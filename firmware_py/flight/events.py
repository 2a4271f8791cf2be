"""Events with stable numeric ids and severities (F' / cFE style), counted and logged.

Ids, severities and texts are declared once in the flight dictionary
(:data:`magstack.data.dictionary.EVENTS`); ids never change meaning once released: ground tools and
tests key on them. Severities follow F' (DIAGNOSTIC .. FATAL).

Events of severity WARNING_HI and worse also go to the ``magstack.flight`` logger (the console of
``magstack run``), rate-limited per (id, source): the 1st, 2nd, 3rd, 10th, 100th, ... occurrence, each
line saying how many there were so far. Neither the log nor a failing event file stops the application:
an event that cannot be written is counted (``EventFileSink.lost``) and writing resumes by itself.
"""
from __future__ import annotations

import json
import logging
import os
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

from magstack.data.dictionary import EVENTS, Severity

#: Event ids, derived from the flight dictionary (:data:`magstack.data.dictionary.EVENTS`).
EventId = IntEnum("EventId", {e.name: e.id for e in EVENTS}, module=__name__)
#: Severity of each event id (the event definition, like an F' .fppi entry).
SEVERITY: dict[EventId, Severity] = {EventId(e.id): e.severity for e in EVENTS}

#: The console of the flight application (``magstack run`` shows WARNING and worse on stderr).
console = logging.getLogger("magstack.flight")


def _worth_logging(n: int) -> bool:
    """Rate limit of the console: the 1st, 2nd, 3rd, then every power of ten (10th, 100th, ...)."""
    if n <= 3:
        return n >= 1
    while n % 10 == 0:
        n //= 10
    return n == 1


@dataclass(frozen=True)
class Event:
    t_s: float
    id: EventId
    source: str
    message: str

    @property
    def severity(self) -> Severity:
        return SEVERITY[self.id]

    def to_dict(self) -> dict:
        return {"t_s": self.t_s, "id": int(self.id), "name": self.id.name, "severity": self.severity.name,
                "source": self.source, "message": self.message}


@dataclass
class EventLog:
    """Counts every event by id and source; keeps the last ``keep`` in memory; ``sink`` gets each."""

    keep: int = 10_000
    sink: Callable[[Event], None] | None = None
    counts: Counter = field(default_factory=Counter)           # (id, source) -> n
    recent: list[Event] = field(default_factory=list)
    sink_errors: int = 0                                        # events the sink raised on (not written)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def emit(self, t_s: float, eid: EventId, source: str, message: str = "") -> Event:
        """Count and record one event (thread-safe: rate-group threads and the refit worker share the log)."""
        ev = Event(float(t_s), EventId(eid), source, message)
        with self._lock:
            self.counts[(ev.id, source)] += 1
            n = self.counts[(ev.id, source)]
            self.recent.append(ev)
            if len(self.recent) > self.keep:
                del self.recent[: len(self.recent) - self.keep]
            if self.sink is not None:
                try:
                    self.sink(ev)
                except Exception:  # noqa: BLE001 - logging an event must never stop the application
                    self.sink_errors += 1
        if ev.severity >= Severity.WARNING_HI and _worth_logging(n):
            level = logging.ERROR if ev.severity >= Severity.FATAL else logging.WARNING
            console.log(level, "%s %s: %s%s", ev.id.name, source, message, f" ({n} so far)" if n > 1 else "")
        return ev

    def count(self, eid: EventId, source: str | None = None) -> int:
        return sum(n for (i, s), n in self.counts.items() if i == eid and (source is None or s == source))

    def snapshot(self) -> dict[str, int]:
        """``{"CHAN_TIMEOUT/lis3mdl": 3, ...}`` for telemetry and `dump_counters`."""
        with self._lock:
            items = sorted(self.counts.items())
        return {f"{i.name}/{s}": n for (i, s), n in items}


class EventFileSink:
    """Append events as JSON lines to ``path`` (one ``write`` per line on an ``O_APPEND`` descriptor),
    fsynced every ``sync_every``. A line that cannot be written whole (disk full) is cut back off the
    file and counted in ``lost``; the next event tries again, so writing resumes when space returns."""

    def __init__(self, path: str | os.PathLike, sync_every: int = 20) -> None:
        self.path = Path(path)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_CLOEXEC", 0),
                                       0o644)
        self.sync_every = max(1, int(sync_every))
        self._n = 0
        self.lost = 0

    def __call__(self, ev: Event) -> None:
        if self._fd is None:
            self.lost += 1
            return
        data = (json.dumps(ev.to_dict(), allow_nan=False) + "\n").encode("utf-8")
        size = None
        try:
            size = os.fstat(self._fd).st_size
            if os.write(self._fd, data) != len(data):
                raise OSError(28, "short write")
            self._n += 1
            if self._n % self.sync_every == 0:
                os.fsync(self._fd)
        except OSError:
            self.lost += 1
            if size is not None:
                try:
                    os.ftruncate(self._fd, size)     # no partial line stays in the file
                except OSError:
                    pass

    def close(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            try:
                os.fsync(fd)
            except OSError:
                pass
            os.close(fd)
