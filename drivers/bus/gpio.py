"""GPIO lines as two tiny protocols, injected into drivers (START, RESET, DRDY, set/reset strap).

On the Pi, :class:`LgpioOutputLine` / :class:`LgpioInputLine` wrap ``lgpio``; the
simulator provides lines wired to its chip models.
"""
from __future__ import annotations

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


class _Lgpio:
    _handles: dict[int, int] = {}

    @classmethod
    def chip(cls, chip: int) -> int:
        try:
            import lgpio  # Pi only ([pi] extra)
        except ImportError as exc:  # pragma: no cover - depends on host
            raise BusError("lgpio is not installed; install magstack[pi] on the Raspberry Pi",
                           address=f"gpiochip{chip}", operation="open") from exc
        if chip not in cls._handles:
            cls._handles[chip] = lgpio.gpiochip_open(chip)
        return cls._handles[chip]


class LgpioOutputLine:  # pragma: no cover - hardware only
    def __init__(self, pin: int, *, chip: int = 0, initial: bool = False) -> None:
        import lgpio

        self._lg = lgpio
        self._h = _Lgpio.chip(chip)
        self._pin = pin
        lgpio.gpio_claim_output(self._h, pin, int(initial))

    def set(self, level: bool) -> None:
        self._lg.gpio_write(self._h, self._pin, int(level))


class LgpioInputLine:  # pragma: no cover - hardware only
    def __init__(self, pin: int, *, chip: int = 0) -> None:
        import lgpio

        self._lg = lgpio
        self._h = _Lgpio.chip(chip)
        self._pin = pin
        lgpio.gpio_claim_input(self._h, pin)

    def get(self) -> bool:
        return bool(self._lg.gpio_read(self._h, self._pin))
