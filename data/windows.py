"""Time windows: choose session rows by time (``--window t0:t1`` / ``--drop-window t0:t1``).

Syntax of one window (seconds)::

    30:600        relative: 30 s to 600 s after the start of each session (its first t_s)
    :120          relative, from the start to 120 s
    600:          relative, from 600 s to the end
    @1598371900:@1598372100   absolute: t_s values (Unix epoch s, the session file's clock)

Both ends of one window use the same kind (relative or absolute). Intervals are closed
``[t0, t1]``. Several ``--window`` options keep the union; ``--drop-window`` removes rows
afterwards (applied after the keep windows). "Start of each session" is per integer ``session``
id, so several files fitted together are each windowed from their own start.

:func:`window_arg` is the argparse ``type=`` for these options (shared by ``import-mageval``,
``fit``, ``apply`` and ``diagnose``), :func:`select_rows` the row mask, :func:`describe` the
one-line metadata record of what was chosen.
"""
from __future__ import annotations

import argparse
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

_NUM = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_END = re.compile(rf"^\s*(@?)\s*({_NUM})?\s*$")


@dataclass(frozen=True)
class TimeWindow:
    """Closed interval ``[t0_s, t1_s]``; ``absolute``: on the t_s clock, else seconds after a
    session's first row. ``None`` ends are open."""

    t0_s: float | None
    t1_s: float | None
    absolute: bool = False

    def __str__(self) -> str:
        at = "@" if self.absolute else ""
        a = "" if self.t0_s is None else f"{at}{self.t0_s:.15g}"
        b = "" if self.t1_s is None else f"{at}{self.t1_s:.15g}"
        return f"{a}:{b}"


def parse_window(text: str) -> TimeWindow:
    """Parse ``t0:t1`` (see module docstring); ValueError with the reason."""
    if text.count(":") != 1:
        raise ValueError(f"time window {text!r}: want t0:t1 (seconds; @ for absolute t_s), e.g. 30:600")
    ends = []
    kinds = []
    for part in text.split(":"):
        m = _END.match(part)
        if not m:
            raise ValueError(f"time window {text!r}: {part.strip()!r} is not a number of seconds")
        at, num = m.groups()
        if at and num is None:
            raise ValueError(f"time window {text!r}: '@' needs a time")
        v = None if num is None else float(num)
        if v is not None and not math.isfinite(v):
            raise ValueError(f"time window {text!r}: ends must be finite")
        ends.append(v)
        if num is not None:
            kinds.append(bool(at))
    if ends[0] is None and ends[1] is None:
        raise ValueError(f"time window {text!r}: give at least one end")
    if len(set(kinds)) > 1:
        raise ValueError(f"time window {text!r}: both ends must be relative or both absolute (@)")
    if ends[0] is not None and ends[1] is not None and ends[1] < ends[0]:
        raise ValueError(f"time window {text!r}: end before start")
    return TimeWindow(ends[0], ends[1], bool(kinds and kinds[0]))


def window_arg(text: str) -> TimeWindow:
    """argparse ``type=`` for ``--window`` / ``--drop-window`` (bad text -> usage error, exit 2)."""
    try:
        return parse_window(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_window_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--window`` and ``--drop-window`` (repeatable) to a command's parser."""
    parser.add_argument("--window", action="append", type=window_arg, default=[], metavar="T0:T1",
                        help="keep only rows in this time window, s after each session's start "
                             "(@T for absolute t_s); repeat for several; open ends allowed (30: or :600)")
    parser.add_argument("--drop-window", action="append", type=window_arg, default=[], metavar="T0:T1",
                        help="drop rows in this time window (same syntax; applied after --window)")


def _in_window(w: TimeWindow, t: np.ndarray, start: np.ndarray) -> np.ndarray:
    x = t if w.absolute else t - start
    ok = np.isfinite(x)
    if w.t0_s is not None:
        ok &= x >= w.t0_s
    if w.t1_s is not None:
        ok &= x <= w.t1_s
    return ok


def session_start_s(t_s: np.ndarray, session: np.ndarray | None) -> np.ndarray:
    """(N,) first finite t_s of each row's session (the zero of relative windows)."""
    t = np.asarray(t_s, dtype=float).reshape(-1)
    s = np.zeros(t.size, np.int64) if session is None else np.asarray(session).reshape(-1)
    start = np.full(t.size, np.nan)
    for k in np.unique(s):
        m = s == k
        tk = t[m][np.isfinite(t[m])]
        start[m] = tk.min() if tk.size else np.nan
    return start


def select_rows(t_s, session=None, windows: Sequence[TimeWindow] = (),
                drop_windows: Sequence[TimeWindow] = ()) -> np.ndarray:
    """(N,) bool: rows inside any of ``windows`` (all rows when there are none) and outside
    every one of ``drop_windows``. Rows with a non-finite t_s are kept only without windows."""
    t = np.asarray(t_s, dtype=float).reshape(-1)
    start = session_start_s(t, session)
    if windows:
        keep = np.zeros(t.size, dtype=bool)
        for w in windows:
            keep |= _in_window(w, t, start)
    else:
        keep = np.ones(t.size, dtype=bool)
    for w in drop_windows:
        keep &= ~_in_window(w, t, start)
    return keep


def describe(windows: Sequence[TimeWindow], drop_windows: Sequence[TimeWindow], kept: int, total: int) -> str:
    """One metadata line: the windows and how many rows they kept."""
    parts = []
    if windows:
        parts.append("keep " + " ".join(str(w) for w in windows))
    if drop_windows:
        parts.append("drop " + " ".join(str(w) for w in drop_windows))
    what = "; ".join(parts) if parts else "all rows"
    return f"{what} (s after each session's start; @ = absolute t_s); {kept} of {total} rows"
