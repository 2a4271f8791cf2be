"""Run a command as a child process and take its own CPU clock (``os.wait4``: user + system seconds of the
child, robust against other load) and its wall time."""
from __future__ import annotations

import os
import subprocess
import time


def run_child(argv: list[str], cwd: str | None = None) -> tuple[float, float]:
    """(CPU s of the child, wall s) of one run of ``argv``; SystemExit when it fails."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        raise SystemExit(f"{' '.join(argv)} exited {code}: {proc.stderr.read().decode()[-500:]}")
    proc.stderr.close()
    return usage.ru_utime + usage.ru_stime, wall
