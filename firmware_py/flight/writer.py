"""The write-behind queue: the flight application's file output off the rate groups' critical path.

A rate group only *offers* work to one bounded FIFO: a telemetry record for a channel's session files,
a packed TM packet, an event line. The work itself (formatting, ``write``, ``fsync``, rotation, rename)
runs elsewhere, in offer order:

* on hardware in the writer thread (:meth:`WriteBehind.start`, thread ``flight-writer``);
* in virtual time in the executive's idle slot (:meth:`WriteBehind.drain` after every slot, on the
  simulation's own thread), so a simulated run is deterministic and writes the bytes the synchronous
  path wrote (the same items in the same order).

A full queue never blocks the caller: the item is dropped and counted per source (``dropped``); each
outage (drops since the last accepted offer) is one ``TLM_QUEUE_FULL`` event, emitted by
:meth:`WriteBehind.report_overflow` at the next rate-group boundary, never inside :meth:`offer` (offers
come under the event log's and the packet stream's locks). A job that raises is counted (``errors``) and
handed to ``on_error``. :meth:`stop` drains the queue and ends the thread; what is offered after it waits
for the next :meth:`drain` (the application's close drains before closing each file).
"""
from __future__ import annotations

import threading
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

from magstack.firmware.flight.events import EventId, EventLog

#: Items the queue holds by default: at 20 Hz x 3 channels (a record and a packet each) 34 s of output,
#: i.e. a stalled SD card may take about that long before anything is dropped.
DEFAULT_CAPACITY = 4096

Job = tuple[Callable[[Any], None], Any, str]


class WriteBehind:
    """A bounded FIFO of ``(function, item, source)`` jobs, run by one consumer (thread or :meth:`drain`)."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY,
                 on_error: Callable[[str, Exception], None] | None = None) -> None:
        if int(capacity) < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity!r}")
        self.capacity = int(capacity)
        self.on_error = on_error
        self._queue: deque[Job] = deque()
        self._cv = threading.Condition(threading.Lock())
        self._thread: threading.Thread | None = None
        self._stopping = False
        self.offered = 0                    # jobs accepted
        self.written = 0                    # jobs run (successfully or not)
        self.errors = 0                     # jobs that raised
        self.dropped: Counter = Counter()   # source -> jobs refused because the queue was full
        self.outages = 0                    # runs of drops without an accepted offer in between
        self.max_depth = 0                  # most jobs waiting at once
        self._dropping = False
        self._reported = 0

    # ------------------------------------------------------------------ the producers' side (rate groups)
    def offer(self, fn: Callable[[Any], None], item: Any, source: str) -> bool:
        """Queue ``fn(item)``; False (counted, nothing else) when the queue is full. Never blocks on I/O."""
        with self._cv:
            if len(self._queue) >= self.capacity:
                self.dropped[source] += 1
                if not self._dropping:
                    self._dropping = True
                    self.outages += 1
                return False
            self._queue.append((fn, item, source))
            self._dropping = False
            self.offered += 1
            self.max_depth = max(self.max_depth, len(self._queue))
            self._cv.notify()
        return True

    def sink(self, fn: Callable[[Any], None], source: str) -> Callable[[Any], None]:
        """A sink that queues ``fn(item)`` (a channel's telemetry sink, the event log's sink)."""
        def queued(item: Any) -> None:
            self.offer(fn, item, source)
        return queued

    def report_overflow(self, events: EventLog, t_s: float) -> None:
        """Emit ``TLM_QUEUE_FULL`` once per outage not yet reported (called at rate-group boundaries)."""
        with self._cv:
            if self.outages == self._reported:
                return
            self._reported = self.outages
            counts = ", ".join(f"{s} {n}" for s, n in sorted(self.dropped.items()))
        events.emit(t_s, EventId.TLM_QUEUE_FULL, "writer",
                    f"write queue of {self.capacity} full; dropped so far: {counts}"[:200])

    # ------------------------------------------------------------------ the consumer's side
    def _run(self, job: Job) -> None:
        fn, item, source = job
        try:
            fn(item)
        except Exception as exc:  # noqa: BLE001 - a failing write is counted; the queue goes on
            self.errors += 1
            if self.on_error is not None:
                self.on_error(source, exc)
        self.written += 1

    def _next(self, wait: bool) -> Job | None:
        with self._cv:
            while wait and not self._queue and not self._stopping:
                self._cv.wait()
            return self._queue.popleft() if self._queue else None

    def drain(self) -> int:
        """Run every queued job on the calling thread (the idle slot in virtual time); the number run.
        Nothing while the writer thread runs: it is the only consumer then (jobs keep their order)."""
        if self._thread is not None:
            return 0
        n = 0
        while (job := self._next(False)) is not None:
            self._run(job)
            n += 1
        return n

    def start(self) -> None:
        """Start the writer thread (idempotent)."""
        if self._thread is None:
            with self._cv:
                self._stopping = False
            self._thread = threading.Thread(target=self._loop, name="flight-writer", daemon=True)
            self._thread.start()

    def _loop(self) -> None:
        while (job := self._next(True)) is not None:
            self._run(job)

    def stop(self) -> None:
        """Drain the queue (the thread finishes it, or the caller does) and end the thread."""
        th = self._thread
        if th is not None:
            with self._cv:
                self._stopping = True
                self._cv.notify_all()
            th.join()
            self._thread = None
        self.drain()

    @property
    def depth(self) -> int:
        return len(self._queue)

    def stats(self) -> dict:
        with self._cv:
            return {"capacity": self.capacity, "offered": self.offered, "written": self.written,
                    "errors": self.errors, "dropped": dict(sorted(self.dropped.items())),
                    "outages": self.outages, "max_depth": self.max_depth, "waiting": len(self._queue)}
