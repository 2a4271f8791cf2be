"""BLAS threads for small solves: :func:`single_thread` limits the BLAS pool to one thread.

OpenBLAS (numpy's and scipy's default BLAS) starts one thread per core for every BLAS call and
spins them; for the small dense problems here (a 16k x 14 QR, a 30 x 30 Cholesky, a (4 x 208) x
(208 x 1024) product) the hand-off costs more than the arithmetic, and on a loaded machine (the
flight loop competes for a Pi's four cores; the development host has two) the waiting threads
make such a call 5-10x slower than on one thread (``benchmarks/bench_blas.py`` measures both).
The limit is process-wide while the context is open (threadpoolctl), so concurrent callers in
other threads see it too: it changes speed, never results.
"""
from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator


@functools.cache
def _controller():
    """threadpoolctl's view of the BLAS libraries (built once: scanning the process takes ~1 ms).
    scipy.linalg is imported first so that its own BLAS build, if it has one, is loaded and seen."""
    import scipy.linalg  # noqa: F401
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@contextlib.contextmanager
def single_thread() -> Iterator[None]:
    """Run the block with every loaded BLAS library limited to one thread (restored on exit)."""
    with _controller().limit(limits=1, user_api="blas"):
        yield


def blas_threads() -> list[int]:
    """Current thread counts of the loaded BLAS libraries (for benchmarks and reports)."""
    return [lib.num_threads for lib in _controller().select(user_api="blas").lib_controllers]
