"""GPIO lines as two tiny protocols, injected into drivers (START, RESET, DRDY, set/reset strap).

On the Pi, :class:`LgpioOutputLine` / :class:`LgpioInputLine` wrap ``lgpio``; the
simulator provides lines wired to its chip models.
"""
from __future__ import annotations

import os
import tempfile
from typing import Protocol, runtime_checkable

from magstack.drivers.errors import BusError


@runtime_checkable
class OutputLine(Protocol):
    def set(self, level: bool) -> None:
        """Drive the line high (True) or low (False)."""


@runtime_checkable
class InputLine(Protocol):
    def get(self) -> bool:
        """Current logic level of the line."""


def lgpio_work_dir() -> str | None:
    """Where lgpio may create its notification pipe (``.lgd-nfyN``): lgpio uses ``$LG_WD``, else the current
    directory, and its import fails with FileNotFoundError where that is not writable (a service started in
    ``/``). Returns the directory to put in ``LG_WD`` (the runtime or temporary directory), or None when the
    current one is writable or ``LG_WD`` is already set."""
    if os.environ.get("LG_WD") or os.access(os.getcwd(), os.W_OK):
        return None
    return os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()


def _lgpio_module(chip: int):
    """The ``lgpio`` module, or a BusError (exit 4, one line) when it is not installed or cannot start."""
    wd = lgpio_work_dir()
    if wd is not None:
        os.environ["LG_WD"] = wd
    try:
        import lgpio  # Pi only ([pi] extra)
    except ImportError as exc:
        raise BusError("lgpio is not installed: on the Raspberry Pi install the pi extra (pip install -e '.[pi]'; "
                       "README, 'On a Raspberry Pi')", address=f"gpiochip{chip}", operation="open") from exc
    except OSError as exc:      # its notification pipe could not be created
        raise BusError(f"lgpio cannot start: {exc} (set LG_WD to a writable directory)", address=f"gpiochip{chip}",
                       operation="open") from exc
    return lgpio


def _gpio_call(lgpio, what: str, chip: int, fn, *args):
    """``fn(*args)``; lgpio's own ``lgpio.error`` (not an OSError) or an OSError becomes a BusError naming
    ``/dev/gpiochipN`` and what was attempted."""
    failures = tuple(e for e in (getattr(lgpio, "error", None), OSError) if isinstance(e, type))
    try:
        return fn(*args)
    except failures as exc:
        raise BusError(f"/dev/gpiochip{chip}: {what} failed: {exc}", address=f"gpiochip{chip}",
                       operation=what) from exc


class _Lgpio:
    _handles: dict[int, int] = {}

    @classmethod
    def chip(cls, chip: int) -> int:
        lgpio = _lgpio_module(chip)
        if chip not in cls._handles:
            cls._handles[chip] = _gpio_call(lgpio, "open", chip, lgpio.gpiochip_open, chip)
        return cls._handles[chip]


class LgpioOutputLine:
    def __init__(self, pin: int, *, chip: int = 0, initial: bool = False) -> None:
        lgpio = _lgpio_module(chip)
        self._lg = lgpio
        self._h = _Lgpio.chip(chip)
        self._pin = pin
        _gpio_call(lgpio, f"claim output {pin}", chip, lgpio.gpio_claim_output, self._h, pin, int(initial))

    def set(self, level: bool) -> None:
        self._lg.gpio_write(self._h, self._pin, int(level))


class LgpioInputLine:
    def __init__(self, pin: int, *, chip: int = 0) -> None:
        lgpio = _lgpio_module(chip)
        self._lg = lgpio
        self._h = _Lgpio.chip(chip)
        self._pin = pin
        _gpio_call(lgpio, f"claim input {pin}", chip, lgpio.gpio_claim_input, self._h, pin)

    def get(self) -> bool:
        return bool(self._lg.gpio_read(self._h, self._pin))
