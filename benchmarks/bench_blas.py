"""Benchmark: small solves with BLAS on its default threads and on one thread.

Run: ``python benchmarks/bench_blas.py [--repeat 30]``. Same matrices, same process, alternating:
numpy's QR (R only) of a 16,384 x 14 block (the refit's per-block factorisation) and scipy's Cholesky
factor and solve of a 30 x 30 normal matrix (a bench fit's parameter count). Wall time per call
(median of ``--repeat``, perf_counter; on a loaded machine the waiting BLAS threads cost wall time,
which is what the flight loop and the refit see) and CPU time per call (process_time, all threads).
"""
from __future__ import annotations

import argparse
import contextlib
import os
import time

import numpy as np
import scipy.linalg

from magstack.firmware import blas


def _time(fn, repeat):
    walls, cpus = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return float(np.median(walls)), float(np.median(cpus))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=30)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    a = rng.normal(size=(16_384, 14))
    m = rng.normal(size=(200, 30))
    g = m.T @ m + 30 * np.eye(30)
    y = rng.normal(size=30)
    cases = {"QR 16384 x 14 (R only)": lambda: np.linalg.qr(a, mode="r"),
             "Cholesky 30 x 30 + solve": lambda: scipy.linalg.cho_solve(scipy.linalg.cho_factor(g), y)}
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; BLAS threads by default "
          f"{blas.blas_threads()}; OPENBLAS_CORETYPE={os.environ.get('OPENBLAS_CORETYPE', '-')}")
    for name, fn in cases.items():
        res = {}
        for _ in range(2):           # alternate to spread the machine's load over both
            for label, ctx in (("default", contextlib.nullcontext), ("1 thread", blas.single_thread)):
                with ctx():
                    fn()
                    res.setdefault(label, []).append(_time(fn, args.repeat))
        (wd, cd), (w1, c1) = (min(res[k]) for k in ("default", "1 thread"))
        print(f"{name}: default threads {wd * 1e3:.3f} ms wall / {cd * 1e3:.3f} ms CPU | one thread "
              f"{w1 * 1e3:.3f} ms wall / {c1 * 1e3:.3f} ms CPU | default / one thread: wall {wd / w1:.1f}x, "
              f"CPU {cd / c1:.1f}x")


if __name__ == "__main__":
    main()
