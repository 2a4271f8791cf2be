"""Run the refit's map (file -> sufficient statistics) and reduce on Dask.

``dask_mapper(address)`` returns a mapper for :func:`magstack.firmware.calibration.refit.refit`:
one ``dask.delayed`` task per telemetry file (:func:`refit.file_pass`), merged pairwise in a tree
(:meth:`refit.PassStats.merge`: stacked R factors re-factorised, counts added). Without an
address the local threaded scheduler runs it; with one (``tcp://host:8786``) a
``dask.distributed`` cluster does, and every worker must have magstack installed and read the
files at the same paths (shared storage). Dask is an optional extra (``pip install
magstack[dask]``, ``magstack[distributed]`` for clusters); nothing here schedules on its own.

On the local scheduler the tasks run in this process's threads, one per core, so BLAS is held to
one thread while they run (:func:`magstack.firmware.blas.single_thread`): the per-block QR
factorisations are small, and threaded BLAS under threaded tasks only oversubscribes the cores.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

from magstack.drivers.errors import ConfigurationError
from magstack.firmware import blas


def _merge(a, b):
    return a.merge(b)


def dask_mapper(address: str | None = None) -> Callable:
    try:
        import dask
    except ImportError:
        raise ConfigurationError("--engine dask needs the optional dask extra: pip install 'magstack[dask]'") \
            from None

    def mapper(paths: Sequence[str], fn: Callable):
        parts = [dask.delayed(fn, pure=False)(p) for p in paths]
        while len(parts) > 1:   # pairwise tree reduce
            parts = [dask.delayed(_merge)(parts[k], parts[k + 1]) if k + 1 < len(parts) else parts[k]
                     for k in range(0, len(parts), 2)]
        if address is None:
            with blas.single_thread():
                return dask.compute(parts[0], scheduler="threads")[0]
        try:
            from dask.distributed import Client
        except ImportError:
            raise ConfigurationError("--scheduler needs dask.distributed: pip install 'magstack[distributed]'") \
                from None
        with Client(address) as client:
            return client.compute(parts[0]).result()

    mapper.in_process = address is None      # threaded local scheduler: refit shares its fit-row cache
    return mapper
