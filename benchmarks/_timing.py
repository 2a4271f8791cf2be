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


def measure(fn: Callable[[], object]) -> tuple[object, float, float]:
    """(result, wall s, peak traced Python memory MiB) of one ``fn()`` call (tracemalloc)."""
    import gc
    import tracemalloc

    gc.collect()
    tracemalloc.start()
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, dt, peak / 2 ** 20


def best_cpu(fn: Callable[[], object], repeat: int = 3) -> tuple[object, float]:
    """(last result, best-of-``repeat`` CPU seconds of ``fn()``): ``process_time``, every thread of the
    process (BLAS threads that spin count)."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t0)
    return out, best
