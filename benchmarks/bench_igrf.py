"""Benchmark: IGRF-14 field at 86,400 positions (one day at 1 Hz).

Run: ``python benchmarks/bench_igrf.py [--n 86400] [--repeat 3]``. Same positions (a 97.4 deg, 500 km
circular orbit), same times (one day from 2026-06-01, 1 s apart), same process:

* ``geomag.igrf_ecef_nT`` (the vectorised evaluation magstack uses);
* baseline 1: the plain vectorised numpy evaluation in ``baselines/igrf_numpy.py`` (one loop over
  (n, m) on full-length arrays, same coefficients);
* baseline 2: ppigrf's ``igrf_gc`` as magstack called it before (the two epoch dates of the segment,
  8192 positions per call, blended linearly in time).

Times are CPU seconds (``process_time``, best of ``--repeat``), with BLAS limited to one thread and
with the library default, and the largest difference between the three results.
"""
from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import os
import sys

import numpy as np

from magstack.firmware import blas
from magstack.firmware.reference import geomag

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import best_cpu  # noqa: E402  (sibling modules; scripts run from benchmarks/)
from baselines import igrf_numpy  # noqa: E402


def _orbit(n: int):
    t = dt.datetime(2026, 6, 1, tzinfo=dt.UTC).timestamp() + np.arange(n, dtype=float)
    w = 2 * np.pi / 5677.0 * np.arange(n)
    inc = np.radians(97.4)
    spin = 2 * np.pi / 86164.0 * np.arange(n)     # Earth rotation under the orbit
    x, y, z = np.cos(w), np.sin(w) * np.cos(inc), np.sin(w) * np.sin(inc)
    p = 6878.137 * np.column_stack([x * np.cos(spin) + y * np.sin(spin), -x * np.sin(spin) + y * np.cos(spin), z])
    return t, p


def _ppigrf_batched(t, p, chunk=8192):
    import ppigrf

    ep = geomag.igrf_epochs_s()
    r = np.linalg.norm(p, axis=1)
    th = np.arccos(p[:, 2] / r)
    ph = np.arctan2(p[:, 1], p[:, 0])
    s = int(np.searchsorted(ep, t[0], side="right") - 1)
    assert t[-1] < ep[s + 1]
    w = (t - ep[s]) / (ep[s + 1] - ep[s])
    dates = [dt.datetime.fromtimestamp(e, dt.UTC).replace(tzinfo=None) for e in ep[s:s + 2]]
    out = np.empty((t.size, 3))
    for k in range(0, t.size, chunk):
        j = slice(k, k + chunk)
        br, bt, bp = ppigrf.igrf_gc(r[j], np.degrees(th[j]), np.degrees(ph[j]), dates)
        comb = [(1 - w[j]) * c[0] + w[j] * c[1] for c in (br, bt, bp)]
        out[j] = geomag.spherical_to_ecef(th[j], ph[j], *comb)
    return out


def _numpy_baseline(t, p):
    ep = geomag.igrf_epochs_s()
    r = np.linalg.norm(p, axis=1)
    th = np.arccos(p[:, 2] / r)
    ph = np.arctan2(p[:, 1], p[:, 0])
    s = int(np.searchsorted(ep, t[0], side="right") - 1)
    w = (t - ep[s]) / (ep[s + 1] - ep[s])
    return geomag.spherical_to_ecef(th, ph, *igrf_numpy.igrf_spherical_nT(r, th, ph, s, w))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=86_400)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    t, p = _orbit(args.n)
    geomag.igrf_ecef_nT(t[:2], p[:2])
    print(f"{args.n} positions; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; "
          f"BLAS threads by default {blas.blas_threads()}")
    for label, limit in (("BLAS 1 thread", True), ("BLAS default threads", False)):
        ctx = blas.single_thread() if limit else contextlib.nullcontext()
        with ctx:
            ours, c_ours = best_cpu(lambda: geomag.igrf_ecef_nT(t, p), args.repeat)
            base, c_base = best_cpu(lambda: _numpy_baseline(t, p), args.repeat)
            pp, c_pp = best_cpu(lambda: _ppigrf_batched(t, p), 1)
        us = 1e6 / args.n
        print(f"[{label}] geomag {c_ours:.3f} s ({c_ours * us:.2f} us/sample) | plain numpy baseline "
              f"{c_base:.3f} s ({c_base * us:.2f} us/sample) -> ratio {c_ours / c_base:.2f}x | ppigrf batched "
              f"{c_pp:.2f} s ({c_pp * us:.1f} us/sample) -> {c_pp / c_ours:.1f}x slower than geomag")
        print(f"    max |geomag - ppigrf| {np.abs(ours - pp).max():.2e} nT, "
              f"max |geomag - numpy baseline| {np.abs(ours - base).max():.2e} nT", flush=True)


if __name__ == "__main__":
    main()
