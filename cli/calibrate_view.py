"""The terminal view of ``magstack calibrate`` while it records: plain ANSI text, works over SSH.

One frame (:func:`render`) shows the field sphere as 12 bands (z from +1 at the top to -1 at the bottom) by 16
longitude sectors (from the board's +X through +Y), each cell two characters: ``##`` covered, ``..`` empty,
``@@`` where the field points in the board frame now, ``<>`` the cell to turn towards; then the spread of the
corrected magnitude, the next turn in words and whether the coverage is enough. :class:`TerminalView` redraws
in place (cursor home, clear below) at most every ``min_interval_s`` of an injected clock and counts frames.
No curses: only escape sequences every terminal emulator and ``tmux`` understands.
"""
from __future__ import annotations

import math

from magstack.firmware.calibration.live_coverage import N_BANDS, N_SECTORS, CoverageState, turn_hint

HOME_CLEAR = "\x1b[H\x1b[J"
HIDE_CURSOR, SHOW_CURSOR = "\x1b[?25l", "\x1b[?25h"
GREEN, YELLOW, BOLD, RESET = "\x1b[32m", "\x1b[33m", "\x1b[1m", "\x1b[0m"


def sphere_lines(state: CoverageState, color: bool = True) -> list[str]:
    """The cell map, top band (+Z) first."""
    out = []
    for band in range(N_BANDS - 1, -1, -1):
        cells = []
        for sector in range(N_SECTORS):
            k = band * N_SECTORS + sector
            if k == state.current:
                cells.append((BOLD if color else "") + "@@" + (RESET if color else ""))
            elif k == state.target:
                cells.append((YELLOW if color else "") + "<>" + (RESET if color else ""))
            elif state.filled[k]:
                cells.append((GREEN if color else "") + "##" + (RESET if color else ""))
            else:
                cells.append("..")
        label = "+Z " if band == N_BANDS - 1 else "-Z " if band == 0 else "   "
        out.append(f"  {label}|" + "".join(cells) + "|")
    out.append("      +X      +Y      -X      -Y      (longitude of the field in the board frame)")
    return out


def render(state: CoverageState, info: dict, color: bool = True) -> str:
    """One frame. ``info``: title, elapsed_s, samples, rate_hz, gaps, expected_uT (or None)."""
    pct = f"{state.fraction:.0%}"
    spread = "n/a" if not math.isfinite(state.spread_uT) else f"{state.spread_uT:.2f} uT"
    rel = (f" ({100 * state.spread_uT / state.magnitude_uT:.1f} % of {state.magnitude_uT:.1f})"
           if math.isfinite(state.spread_uT) and state.magnitude_uT > 0 else "")
    exp = info.get("expected_uT")
    lines = [f"{info.get('title', 'magstack calibrate')}",
             f"recording {info.get('elapsed_s', 0.0):6.1f} s   {state.samples} samples "
             f"({info.get('rate_hz', float('nan')):.1f} Hz)   gaps {info.get('gaps', 0)}",
             f"field sphere (board frame): {state.cells_filled}/{len(state.filled)} cells ({pct}), "
             f"direction spread {state.min_eig:.2f}/0.33, shape {state.shape}", ""]
    lines += sphere_lines(state, color)
    lines += ["", f"|B| spread {spread}{rel}" + (f"   local field {exp:.2f} uT" if exp else ""),
              f"next: {turn_hint(state.current, state.target)}"]
    if state.enough:
        lines.append((GREEN if color else "") + "coverage ENOUGH: press Ctrl-C to stop and fit (more turns still "
                     "help)" + (RESET if color else ""))
    else:
        lines.append("coverage not yet enough (need 55 % of cells, spread >= 0.18, ellipsoid shape); "
                     "Ctrl-C stops and keeps what was recorded")
    return "\n".join(lines) + "\n"


class TerminalView:
    """Redraws a frame on ``stream`` at most every ``min_interval_s`` (``clock`` injected); ``frames`` counts."""

    def __init__(self, stream, clock, min_interval_s: float = 0.1, color: bool = True) -> None:
        self.stream = stream
        self.clock = clock
        self.min_interval_s = float(min_interval_s)
        self.color = color
        self.frames = 0
        self._last = -math.inf
        self.first_s = math.nan
        self.last_s = math.nan

    def start(self) -> None:
        self.stream.write(HIDE_CURSOR)
        self.stream.flush()

    def maybe_draw(self, state_fn, info: dict, force: bool = False) -> bool:
        now = self.clock.monotonic_s()
        if not force and now - self._last < self.min_interval_s:
            return False
        self._last = now
        self.stream.write(HOME_CLEAR + render(state_fn(), info, self.color))
        self.stream.flush()
        self.frames += 1
        if not math.isfinite(self.first_s):
            self.first_s = now
        self.last_s = now
        return True

    def rate_hz(self) -> float:
        span = self.last_s - self.first_s
        return (self.frames - 1) / span if self.frames > 1 and span > 0 else float("nan")

    def stop(self) -> None:
        self.stream.write(SHOW_CURSOR)
        self.stream.flush()
