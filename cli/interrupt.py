"""Graceful stop of long-running commands on SIGTERM / SIGINT / SIGHUP.

``with graceful_stop() as stop:`` installs handlers that set ``stop`` (a ``threading.Event``)
and remember which signal arrived (``stop.signal_name``); the command passes ``stop`` to the
library function (``run_bench(..., stop=stop)``), which ends its loop at the next sample and
closes its output. SIGHUP (the terminal or SSH session went away) is handled like SIGTERM.
A second SIGINT raises KeyboardInterrupt as usual (the default handler is
back after the first). Outside the main thread (tests running commands in threads) nothing is
installed and ``stop`` is simply never set.
"""
from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["StopEvent", "graceful_stop", "EXIT_FOR_SIGNAL"]

#: Exit status after a graceful stop: 128 + signal number (shell convention).
EXIT_FOR_SIGNAL = {"SIGHUP": 129, "SIGINT": 130, "SIGTERM": 143}


class StopEvent(threading.Event):
    """An Event that also records the name of the signal that set it."""

    signal_name: str | None = None


@contextmanager
def graceful_stop(signals=(signal.SIGTERM, signal.SIGINT, signal.SIGHUP)) -> Iterator[StopEvent]:
    stop = StopEvent()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = {}

    def handler(signum, _frame) -> None:
        stop.signal_name = signal.Signals(signum).name
        stop.set()
        if signum == signal.SIGINT:  # a second Ctrl-C interrupts at once
            signal.signal(signal.SIGINT, previous.get(signal.SIGINT, signal.default_int_handler))

    for s in signals:
        previous[s] = signal.signal(s, handler)
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
