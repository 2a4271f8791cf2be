"""BLAS threads around small solves: one thread (threadpoolctl).

OpenBLAS's default threading makes the small solves of the calibration (tens of columns) several
times slower on a loaded 2-core host, and on a Raspberry Pi the flight loop competes for the cores.
``single_threaded_blas()`` limits BLAS to one thread for the block it guards; nested use is cheap
(the limit is applied once, by the outermost block). Without threadpoolctl it does nothing.
"""
from __future__ import annotations

import contextlib
import threading

_local = threading.local()


@contextlib.contextmanager
def single_threaded_blas():
    """Context: BLAS limited to one thread (outermost block only)."""
    if getattr(_local, "depth", 0):
        _local.depth += 1
        try:
            yield
        finally:
            _local.depth -= 1
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:   # pragma: no cover - threadpoolctl is a dependency
        limiter = contextlib.nullcontext()
    else:
        limiter = threadpool_limits(limits=1, user_api="blas")
    _local.depth = 1
    try:
        with limiter:
            yield
    finally:
        _local.depth = 0
