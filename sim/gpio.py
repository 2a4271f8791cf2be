"""Simulated GPIO lines wired to chip models by callbacks."""
from __future__ import annotations

from collections.abc import Callable


class SimOutputLine:
    """A driver-driven line (START, RESET, strap pulse). Calls ``on_change(level)`` on edges."""

    def __init__(self, name: str, on_change: Callable[[bool], None] | None = None, initial: bool = False) -> None:
        self.name = name
        self.level = initial
        self._on_change = on_change
        self.edges = 0

    def connect(self, on_change: Callable[[bool], None]) -> None:
        self._on_change = on_change

    def set(self, level: bool) -> None:
        level = bool(level)
        if level != self.level:
            self.level = level
            self.edges += 1
            if self._on_change is not None:
                self._on_change(level)


class SimInputLine:
    """A chip-driven line (DRDY) read by the driver; ``source()`` gives its level."""

    def __init__(self, name: str, source: Callable[[], bool]) -> None:
        self.name = name
        self._source = source

    def get(self) -> bool:
        return bool(self._source())
