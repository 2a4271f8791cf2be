"""Graceful stop of long-running commands on SIGTERM / SIGINT / SIGHUP.

``with graceful_stop() as stop:`` installs handlers that set ``stop`` (a ``threading.Event``)
and remember which signal arrived (``stop.signal_name``); the command passes ``stop`` to the
library function (``run_bench(..., stop=stop)``), which ends its loop at the next sample and
closes its output. SIGHUP (the terminal or SSH session went away) is handled like SIGTERM.
A second SIGINT raises KeyboardInterrupt as usual (the default handler is
back after the first). Outside the main thread (tests running commands in threads) nothing is
installed and ``stop`` is simply never set.

Outside ``graceful_stop``, :func:`signals_raise` (installed by ``cli/main.py`` around every command) turns
SIGTERM / SIGHUP into :class:`Stopped`, a ``KeyboardInterrupt`` like Ctrl-C's, so that a command stopped by a
service manager or a closed terminal runs its clean-up as on Ctrl-C (temporary files and directories removed,
partial results written) instead of dying where it stands.
"""
from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["StopEvent", "Stopped", "graceful_stop", "signals_raise", "exit_for", "EXIT_FOR_SIGNAL"]

#: Exit status after a graceful stop: 128 + signal number (shell convention).
EXIT_FOR_SIGNAL = {"SIGHUP": 129, "SIGINT": 130, "SIGTERM": 143}


class Stopped(KeyboardInterrupt):
    """SIGTERM or SIGHUP raised as an exception (:func:`signals_raise`); ``signal_name`` names it."""

    def __init__(self, signal_name: str) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name


def exit_for(exc: KeyboardInterrupt) -> tuple[str, int]:
    """``(signal name, exit status)`` of an interrupt: :class:`Stopped` names its signal, else SIGINT."""
    name = getattr(exc, "signal_name", None) or "SIGINT"
    return name, EXIT_FOR_SIGNAL.get(name, 130)


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


@contextmanager
def signals_raise(signals=(signal.SIGTERM, signal.SIGHUP)) -> Iterator[None]:
    """Within: the first of ``signals`` raises :class:`Stopped` in the main thread; later ones are ignored
    so that the clean-up it starts is not cut short. The previous handlers are restored on exit; outside
    the main thread nothing is installed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    raised = []

    def handler(signum, _frame) -> None:
        if not raised:
            raised.append(signum)
            raise Stopped(signal.Signals(signum).name)

    previous = {s: signal.signal(s, handler) for s in signals}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
