"""Progress display of the ``magstack`` command (tqdm on stderr).

A bar is shown only when stderr is a terminal and neither ``--json`` nor ``--quiet`` was given
(:func:`progress_enabled`); otherwise the same calls are no-ops, so commands never branch on it.

* :func:`bar` - a tqdm bar for a known total (seconds of a session, rows, folds);
* :func:`stages` - a bar over named stages of a command that calls one long library function
  per stage (``with stages("fit", ["read", "fit + hold-out folds", "write"]) as st: st.next()``);
* :func:`fraction_bar` - a bar fed by a library's ``progress(stage, fraction)`` callback
  (``align_streams``, ``import_mageval``).

Library functions do not import this: they take a plain callback (``progress(done)``), and the
command connects it to a bar.
"""
from __future__ import annotations

import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from tqdm import tqdm

__all__ = ["progress_enabled", "set_progress_policy", "bar", "stages", "Stages", "fraction_bar"]

_policy = {"off": False}


def set_progress_policy(json_mode: bool, quiet: bool) -> None:
    """Called by main with the common flags."""
    _policy["off"] = bool(json_mode or quiet)


def progress_enabled(stream=None) -> bool:
    """True when a bar should be drawn: stderr (or ``stream``) is a TTY and no --json/--quiet."""
    s = sys.stderr if stream is None else stream
    try:
        tty = bool(s.isatty())
    except (AttributeError, ValueError):
        tty = False
    return tty and not _policy["off"]


def bar(total: float | None, desc: str, unit: str = "it", *, enabled: bool = True, **kw) -> tqdm:
    """A tqdm bar on stderr, disabled per :func:`progress_enabled` (or ``enabled=False``, e.g. a
    command's own ``--no-progress``). Use as a context manager."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=not (enabled and progress_enabled()),
                dynamic_ncols=True, leave=False, **kw)


class Stages:
    """A bar over named stages; :meth:`next` marks the previous stage done and names the next."""

    def __init__(self, pbar: tqdm, names: Sequence[str], desc: str) -> None:
        self._bar = pbar
        self._names = list(names)
        self._desc = desc
        self._i = -1

    def next(self, name: str | None = None) -> None:
        if self._i >= 0:
            self._bar.update(1)
        self._i += 1
        label = name or (self._names[self._i] if self._i < len(self._names) else "")
        self._bar.set_description(f"{self._desc} ({label})" if label else self._desc, refresh=True)


@contextmanager
def stages(desc: str, names: Sequence[str]) -> Iterator[Stages]:
    """Context manager yielding a :class:`Stages` bar (total = number of stages)."""
    # tqdm appends ": " to descriptions set later (set_description), not to the initial one
    with bar(len(names), f"{desc}: ", unit="step", bar_format="{desc}{n_fmt}/{total_fmt} {bar} [{elapsed}]") as pbar:
        st = Stages(pbar, names, desc)
        yield st
        pbar.update(pbar.total - pbar.n)


@contextmanager
def fraction_bar(desc: str) -> Iterator[object]:
    """A bar driven by a library ``progress(stage, fraction)`` callback (0..1 per stage); yields the callback."""
    with bar(100, f"{desc}: ", unit="%", bar_format="{desc}{bar} {n:.0f}% [{elapsed}]") as pbar:
        state = {"stage": None}

        def progress(stage: str, fraction: float) -> None:
            if stage != state["stage"]:
                state["stage"] = stage
                pbar.set_description(f"{desc} ({stage})", refresh=False)
            pbar.n = 100.0 * min(max(float(fraction), 0.0), 1.0)
            pbar.refresh()

        yield progress
