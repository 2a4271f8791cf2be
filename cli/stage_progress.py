"""Progress of long library stages on stderr: ``stage  NN%`` on one rewritten line.

Library code (``magstack.ground.alignment``: ``progress(stage, fraction)``) reports; this prints only
when stderr is a terminal and the command is not writing ``--json``, at most every 0.2 s, and ends the
line when done. (A tqdm-based convention for every command may replace it; the callback stays.)
"""
from __future__ import annotations

import sys
import time
from collections.abc import Callable


def stage_progress(enabled: bool = True, stream=None) -> Callable[[str, float], None] | None:
    """A ``progress(stage, fraction)`` callback, or None when it would print nothing."""
    out = stream if stream is not None else sys.stderr
    if not enabled or not getattr(out, "isatty", lambda: False)():
        return None
    state = {"t": 0.0, "stage": ""}

    def progress(stage: str, fraction: float) -> None:
        now = time.monotonic()
        new = stage != state["stage"]
        if not (new or fraction >= 1.0 or now - state["t"] >= 0.2):
            return
        if new and state["stage"]:
            out.write("\n")
        state["t"], state["stage"] = now, stage
        out.write(f"\r{stage} {100 * min(max(fraction, 0.0), 1.0):3.0f}%")
        out.flush()

    return progress
