"""Benchmarks of the on-orbit refit with the IGRF-14 reference (time, peak memory).

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

``--part plain``: the refit against the plain pipeline of ``baselines/refit_plain.py``, CPU
seconds best of ``--repeat`` in this process, with BLAS on its default threads and held to one thread
(``firmware/blas.single_thread`` around the whole call), then the whole process (``magstack refit`` as
a child process; its CPU time from the OS). ``--part profile``: cProfile of one refit, shares of the
total per function (the hot spots). ``--part dask``: ``--dask-files`` files of ``--dask-hours`` each,
refit in process against ``--engine dask`` on the local scheduler.
"""
from __future__ import annotations

import argparse
import contextlib
import cProfile
import os
import pstats
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from magstack.cli.main import main as cli
from magstack.data.telemetry import iter_telemetry
from magstack.firmware import blas
from magstack.firmware.calibration.refit import RefitOptions, reference_block, refit
from magstack.firmware.reference import geomag

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import best_cpu, measure  # noqa: E402  (sibling module; scripts run from benchmarks/)
from baselines.refit_plain import plain_refit  # noqa: E402


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
    ap.add_argument("--part", choices=("all", "plain", "profile", "dask"), default="all")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dask-files", type=int, default=4)
    ap.add_argument("--dask-hours", type=float, default=6.0)
    args = ap.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-refit-"))
    day = work / "day.csv"
    if not day.exists():
        _simulate(day, 86399, 1780272000)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; BLAS threads by default "
          f"{blas.blas_threads()}", flush=True)
    if args.part == "plain":
        return plain(day, work, args.repeat)
    if args.part == "profile":
        return profile(day)
    if args.part == "dask":
        return dask_vs_local(work, args.dask_files, args.dask_hours, args.repeat)
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


def _simulate(path: Path, seconds: float, t0: int) -> None:
    c0 = time.perf_counter()
    assert cli(["simulate", "--program", "orbit_tumbling", "--seconds", f"{seconds:g}", "--rate-hz", "1",
                "--sessions", "1", "--t0", str(t0), "--out", str(path)]) == 0
    print(f"simulate {seconds:g} s at 1 Hz: {time.perf_counter() - c0:.1f} s, {path.stat().st_size / 2**20:.1f} MiB")


def _child_cpu(cmd: list[str], env: dict | None = None) -> float:
    """CPU seconds (user + system) of a child process run to completion."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def plain(day: Path, work: Path, repeat: int) -> None:
    for label, ctx in (("BLAS default threads", contextlib.nullcontext), ("BLAS 1 thread", blas.single_thread)):
        with ctx():
            coef, c_plain = best_cpu(lambda: plain_refit(str(day)), repeat)
            res, c_refit = best_cpu(lambda: refit([day]), repeat)
        s_plain, s_refit = coef[:, :3], np.asarray(res.candidate.S)
        print(f"[{label}] refit in process {c_refit:.2f} s CPU | plain pipeline {c_plain:.2f} s CPU | ratio "
              f"{c_refit / c_plain:.2f}x | gain matrices differ by {np.abs(s_plain - s_refit).max():.1e} "
              f"(plain has no holds or coverage rules)", flush=True)
    py = sys.executable
    bench_dir = os.path.dirname(os.path.abspath(__file__))
    plain_cmd = [py, "-c", f"import sys; sys.path.insert(0, {bench_dir!r}); "
                           f"from baselines.refit_plain import plain_refit; plain_refit({str(day)!r})"]
    refit_cmd = [os.path.join(os.path.dirname(py), "magstack"), "refit", str(day), "--out", str(work / "cand.json"),
                 "-q"]
    for label, env in (("BLAS default threads", None), ("OPENBLAS_NUM_THREADS=1", {**os.environ,
                                                                                   "OPENBLAS_NUM_THREADS": "1"})):
        best_plain = min(_child_cpu(plain_cmd, env) for _ in range(repeat))
        best_refit = min(_child_cpu(refit_cmd, env) for _ in range(repeat))
        print(f"whole process (imports included, {label}): magstack refit {best_refit:.2f} s CPU | "
              f"plain pipeline {best_plain:.2f} s CPU | ratio {best_refit / best_plain:.2f}x", flush=True)


def profile(day: Path) -> None:
    refit([day])
    for label, ctx in (("BLAS default threads", contextlib.nullcontext), ("BLAS 1 thread", blas.single_thread)):
        prof = cProfile.Profile(time.process_time)     # CPU of the process (BLAS threads included)
        with ctx():
            c0 = time.process_time()
            prof.enable()
            refit([day])
            prof.disable()
            total = time.process_time() - c0
        rows = [(ct, tt, f"{os.path.basename(file)}:{line}:{fn}")
                for (file, line, fn), (_, _, tt, ct, _) in pstats.Stats(prof).stats.items()
                if "magstack" in file or "wt-" in file or "_py/" in file]
        print(f"[{label}] refit {total:.2f} s CPU (profiled); share of that CPU per function, cumulative / own:")
        for ct, tt, name in sorted(rows, reverse=True)[:22]:
            print(f"  {ct / total * 100:5.1f} % / {tt / total * 100:5.1f} %  {name}", flush=True)


def dask_vs_local(work: Path, n_files: int, hours: float, repeat: int) -> None:
    from magstack.ground.refit_dask import dask_mapper

    paths = []
    for k in range(n_files):
        p = work / f"part{k}-{hours:g}h.csv"
        if not p.exists():
            _simulate(p, hours * 3600 - 1, 1780272000 + int(k * hours * 3600))
        paths.append(p)
    rows = sum(len(b) for p in paths for b in iter_telemetry(p))

    def timed(fn, ctx=contextlib.nullcontext):
        best = (float("inf"), float("inf"), None)
        for _ in range(repeat):
            with ctx():
                w, c = time.perf_counter(), time.process_time()
                out = fn()
                best = min(best, (time.process_time() - c, time.perf_counter() - w, out), key=lambda x: x[0])
        return best

    c_loc, w_loc, local = timed(lambda: refit(paths))
    c_one, w_one, _ = timed(lambda: refit(paths), blas.single_thread)
    c_dsk, w_dsk, dsk = timed(lambda: refit(paths, mapper=dask_mapper(None)))
    print(f"{n_files} files x {hours:g} h ({rows} rows), 5 passes, CPU s / wall s: in process, BLAS default threads "
          f"{c_loc:.2f} / {w_loc:.2f}; in process, BLAS 1 thread {c_one:.2f} / {w_one:.2f}; dask local scheduler "
          f"(BLAS 1 thread) {c_dsk:.2f} / {w_dsk:.2f} -> dask / in-process (1 thread): CPU {c_dsk / c_one:.2f}x, "
          f"wall {w_dsk / w_one:.2f}x; same candidate: "
          f"{np.allclose(dsk.fit.theta, local.fit.theta, rtol=1e-9, atol=1e-12)}")


if __name__ == "__main__":
    main()
