"""Events with stable numeric ids and severities (F' / cFE style), counted and logged.

Ids, severities and texts are declared once in the flight dictionary
(:data:`magstack.data.dictionary.EVENTS`); ids never change meaning once released: ground tools and
tests key on them. Severities follow F' (DIAGNOSTIC .. FATAL).
"""
from __future__ import annotations

import json
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
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def emit(self, t_s: float, eid: EventId, source: str, message: str = "") -> Event:
        """Count and record one event (thread-safe: rate-group threads and the refit worker share the log)."""
        ev = Event(float(t_s), EventId(eid), source, message)
        with self._lock:
            self.counts[(ev.id, source)] += 1
            self.recent.append(ev)
            if len(self.recent) > self.keep:
                del self.recent[: len(self.recent) - self.keep]
            if self.sink is not None:
                self.sink(ev)
        return ev

    def count(self, eid: EventId, source: str | None = None) -> int:
        return sum(n for (i, s), n in self.counts.items() if i == eid and (source is None or s == source))

    def snapshot(self) -> dict[str, int]:
        """``{"CHAN_TIMEOUT/lis3mdl": 3, ...}`` for telemetry and `dump_counters`."""
        return {f"{i.name}/{s}": n for (i, s), n in sorted(self.counts.items())}


class EventFileSink:
    """Append events as JSON lines to ``path``; flushed per event, fsynced every ``sync_every``."""

    def __init__(self, path: str | os.PathLike, sync_every: int = 20) -> None:
        self.path = Path(path)
        self._fh = open(self.path, "a", encoding="utf-8")
        self.sync_every = max(1, int(sync_every))
        self._n = 0

    def __call__(self, ev: Event) -> None:
        self._fh.write(json.dumps(ev.to_dict(), allow_nan=False) + "\n")
        self._fh.flush()
        self._n += 1
        if self._n % self.sync_every == 0:
            os.fsync(self._fh.fileno())

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.flush()
            os.fsync(self._fh.fileno())
            self._fh.close()
