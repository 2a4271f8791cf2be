"""Shared timing helper for the benchmark scripts (run as ``python benchmarks/bench_x.py``)."""
from __future__ import annotations

import time
from collections.abc import Callable


def best_wall_s(fn: Callable[[], object], repeat: int = 3) -> float:
    """Best-of-``repeat`` wall time of ``fn()`` in seconds (perf_counter)."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best
