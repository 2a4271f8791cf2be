"""Benchmarks for issue 15: on-orbit refit with the IGRF-14 reference (time, peak memory).

Run: ``python benchmarks/bench_refit.py [--workdir DIR]``. Simulates one day of 1 Hz telemetry
(86,400 rows, ``orbit_tumbling``, hmc1053 preset, every effect) with ``magstack simulate``, then
measures in this process (perf_counter, tracemalloc peak of Python/numpy allocations):

* IGRF-14 with one ppigrf call per sample (the naive baseline, on ``--naive`` samples);
* the reference field alone over the file (read + IGRF-14 + ITRS->GCRS + attitude + eclipse);
* IGRF-14 alone on the same positions (ppigrf through geomag.igrf_ecef_nT);
* the full refit (1 OLS + 4 robust passes, fit rows cached) and without the cache (every pass
  re-reads and re-evaluates: pure streaming);
* "30 days streamed": the refit over 1, 10 and 30 links to the one-day file (same rows, separate
  paths), plain least squares without cache (memory should not grow) and with the default cache.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from magstack.cli.main import main as cli
from magstack.data.telemetry import iter_telemetry
from magstack.firmware.calibration.refit import RefitOptions, reference_block, refit
from magstack.firmware.reference import geomag

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import measure  # noqa: E402  (sibling module; scripts run from benchmarks/)


def _reference_only(path):
    n = 0
    for blk in iter_telemetry(path):
        b, _, _ = reference_block(blk)
        n += b.shape[0]
    return n


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--days", type=int, nargs="*", default=[1, 10, 30], help="plain streaming runs")
    ap.add_argument("--naive", type=int, default=100, help="samples for the one-call-per-sample baseline")
    ap.add_argument("--naive-only", action="store_true")
    ap.add_argument("--default-days", type=int, nargs="*", default=[1, 10], help="default (robust, cache) runs")
    args = ap.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-refit-"))
    day = work / "day.csv"
    if not day.exists():
        t0 = time.perf_counter()
        assert cli(["simulate", "--program", "orbit_tumbling", "--seconds", "86399", "--rate-hz", "1",
                    "--sessions", "1", "--t0", "1780272000", "--out", str(day)]) == 0
        print(f"simulate 1 day at 1 Hz: {time.perf_counter() - t0:.1f} s, {day.stat().st_size / 2**20:.1f} MiB")
    pos = np.vstack([b.pos_ecef_km for b in iter_telemetry(day)])
    t = np.concatenate([b.t_s for b in iter_telemetry(day)])
    n = t.size
    print(f"rows {n}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs", flush=True)
    k = args.naive
    _, dt_naive, _ = measure(lambda: [geomag.igrf_ecef_nT(t[j:j + 1], pos[j:j + 1]) for j in range(k)])
    _, dt_batch_k, _ = measure(lambda: geomag.igrf_ecef_nT(t[:k], pos[:k]))
    print(f"one ppigrf call per sample ({k} samples): {dt_naive / k * 1e3:.1f} ms/sample "
          f"-> {dt_naive / k * n:.0f} s projected for {n} rows; the batched path on the same {k}: "
          f"{dt_batch_k * 1e3:.0f} ms", flush=True)
    if args.naive_only:
        return
    _, dt_igrf, pk_igrf = measure(lambda: geomag.igrf_ecef_nT(t, pos))
    _, dt_ref, pk_ref = measure(lambda: _reference_only(day))
    res, dt_fit, pk_fit = measure(lambda: refit([day]))
    res0, dt_fit0, pk_fit0 = measure(lambda: refit([day], options=RefitOptions(cache_mb=0)))
    print(f"IGRF-14 alone (ppigrf, in-memory positions): {dt_igrf:.2f} s, peak {pk_igrf:.1f} MiB")
    print(f"reference field over the file (read + IGRF + frames + attitude + eclipse): {dt_ref:.2f} s, "
          f"peak {pk_ref:.1f} MiB")
    print(f"refit, 5 passes, fit rows cached: {dt_fit:.2f} s ({dt_fit / dt_ref:.2f}x the reference alone), "
          f"peak {pk_fit:.1f} MiB; held-out {np.linalg.norm(res.holdout_candidate_uT) * 1e3:.1f} nT vs identity "
          f"{np.linalg.norm(res.holdout_active_uT) * 1e3:.1f} nT, proposed {res.proposed}")
    print(f"refit, 5 passes, no cache (streaming): {dt_fit0:.2f} s ({dt_fit0 / dt_ref:.2f}x), peak {pk_fit0:.1f} MiB; "
          f"same candidate: {np.allclose(res0.fit.theta, res.fit.theta, rtol=1e-7, atol=1e-10)}")
    for d in sorted(set(args.days) | set(args.default_days)):
        links = []
        for k in range(d):
            link = work / f"day{k:02d}.csv"
            if not link.exists():
                os.symlink(day, link)
            links.append(link)
        if d in args.days:
            r1, dt1, pk1 = measure(lambda links=links: refit(links, options=RefitOptions(robust=False, cache_mb=0)))
            print(f"{d:3d} day(s), {r1.rows} rows: OLS streaming (1 pass, no cache) {dt1:.1f} s, "
                  f"{dt1 / d:.1f} s/day, peak {pk1:.1f} MiB", flush=True)
        if d in args.default_days:
            r2, dt2, pk2 = measure(lambda links=links: refit(links))
            print(f"{d:3d} day(s), {r2.rows} rows: default (OLS + 4 robust passes, fit-row cache) {dt2:.1f} s, "
                  f"{dt2 / d:.1f} s/day, peak {pk2:.1f} MiB", flush=True)


if __name__ == "__main__":
    main()
