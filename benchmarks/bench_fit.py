"""Benchmark: ``fit`` with its held-out figures against plain numpy lstsq of the same design.

Run: ``python benchmarks/bench_fit.py [--n 1000000] [--refit] [--nan-fraction 0.01]``. Data as
``bench_calibration.py`` (Eq. 3 + two currents, 30 parameters, one session, 0.25 s rows, so 5 interleaved 60 s
time-block folds; ``--nan-fraction``: that share of rows with a NaN DUT reading, excluded by the fit). CPU seconds by
``process_time`` (best of ``--repeat``), peak memory by tracemalloc in a separate run (the input arrays are built
before tracing starts: the peak is the fit's own memory), also at ``--n-small`` rows (default N / 2) for the
growth per added row; the baseline (design matrix + ``np.linalg.lstsq``) runs in the same process, with BLAS on
one thread and on its default threads.
``--refit`` also times the refit path (every fold refits its rows, the plain mechanism) and prints
how far the cross-fit's parameters and held-out figures are from it.
"""
from __future__ import annotations

import argparse
import functools
import os
import sys
import tracemalloc

import numpy as np

from magstack.firmware.blas import blas_threads, single_thread
from magstack.firmware.calibration import FitOptions, crossfit, fit
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.sim.synthetic_calibration import make_data, random_theta

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import best_cpu  # noqa: E402  (sibling module; scripts run from benchmarks/)

CURRENTS = ("solar", "heater")


def peak_mib(fn) -> float:
    """Peak traced memory (MiB) of one ``fn()`` call."""
    import gc
    gc.collect()
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2 ** 20


def refit_path(data, opts):
    """The same fit with every held-out fold refitting its rows (the plain path)."""
    keep = crossfit.applies
    crossfit.applies = lambda model, options: False
    try:
        return fit(data, "eq3", currents=CURRENTS, options=opts)
    finally:
        crossfit.applies = keep


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--n-small", type=int, default=None, help="second size for the memory growth (default N / 2)")
    ap.add_argument("--refit", action="store_true")
    ap.add_argument("--nan-fraction", type=float, default=0.0,
                    help="fraction of rows with a NaN DUT reading (excluded by the fit: rows not copied)")
    args = ap.parse_args()
    model = CalModel(resolve_terms("eq3", currents=CURRENTS), CURRENTS, (), 25.0, 0.0)

    def bench_data(n):
        rng = np.random.default_rng(0)
        d = make_data(model, random_theta(model, rng), n, rng, noise_uT=0.03, t0_s=0.0)
        d.b_meas_uT[rng.random(n) < args.nan_fraction, 1] = np.nan
        return d

    data = bench_data(args.n)
    in_mib = sum(a.nbytes for a in (data.b_meas_uT, data.b_ref_uT, data.temp_c, data.t_s, data.session,
                                    *data.currents_A.values())) / 2 ** 20
    opts = FitOptions()

    ok = np.all(np.isfinite(data.b_meas_uT), axis=1)

    def lstsq():
        X = model.design(data.b_meas_uT, data.temp_c, data.currents_A, data.session, data.t_s)
        if ok.all():
            return np.linalg.lstsq(X, data.b_ref_uT, rcond=None)[0]
        return np.linalg.lstsq(X[ok], data.b_ref_uT[ok], rcond=None)[0]     # the usable rows, as fit uses

    def lstsq_1():
        with single_thread():
            return lstsq()

    def run():
        return fit(data, "eq3", currents=CURRENTS, options=opts)

    print(f"== fit with held-out figures, N = {args.n} ({np.count_nonzero(~ok)} with a NaN reading), "
          f"{int(model.axis_mask().sum())} parameters, input arrays {in_mib:.0f} MiB; BLAS default threads "
          f"{blas_threads()}")
    _, base1 = best_cpu(lstsq_1, args.repeat)
    _, base_d = best_cpu(lstsq, args.repeat)
    res, cpu = best_cpu(run, args.repeat)
    pk_fit, pk_base = peak_mib(run), peak_mib(lstsq_1)
    print(f"numpy lstsq (design + lstsq): {base1:.3f} s CPU BLAS 1 thread, {base_d:.3f} s default threads; "
          f"peak {pk_base:.0f} MiB")
    n_small = args.n_small or max(args.n // 2, 1000)
    pk_small = peak_mib(functools.partial(fit, bench_data(n_small), "eq3", currents=CURRENTS, options=opts))
    print(f"fit (cross-fit): {cpu:.3f} s CPU = {cpu / base1:.2f}x lstsq (1 thread), {cpu / base_d:.2f}x (default); "
          f"peak {pk_fit:.1f} MiB at {args.n} rows, {pk_small:.1f} MiB at {n_small}: "
          f"{(pk_fit - pk_small) * 2 ** 20 / (args.n - n_small):.1f} B per added row")
    print(f"   held-out time blocks {np.round(res.holdout_blocks_uT * 1e3, 3)} nT; in-sample "
          f"{np.round(res.rmse_uT * 1e3, 3)} nT")
    if args.refit:
        old, cpu_old = best_cpu(lambda: refit_path(data, opts), 1)
        pk_old = peak_mib(lambda: refit_path(data, opts))
        rel = np.max(np.abs(res.theta - old.theta) / np.maximum(np.abs(old.theta), 1e-300))
        rel_h = np.max(np.abs(res.holdout_blocks_uT - old.holdout_blocks_uT) / old.holdout_blocks_uT)
        print(f"refit path (every fold refits its rows): {cpu_old:.3f} s CPU = {cpu_old / base1:.2f}x lstsq "
              f"(1 thread), {cpu_old / base_d:.2f}x (default); peak {pk_old:.0f} MiB; cross-fit vs refit: "
              f"parameters {rel:.1e}, held-out {rel_h:.1e} max relative difference")


if __name__ == "__main__":
    main()
