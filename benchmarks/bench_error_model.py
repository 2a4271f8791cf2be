"""Benchmark for issue 7: error-model throughput, vectorised vs per-sample, and a full simulate run.

Run: ``python benchmarks/bench_error_model.py [--n 20000]``. Times with perf_counter; the baseline
is the per-sample ``sense()`` loop measured in the same process, so the printed ratios are
machine-independent. Prints samples/s and the speed-up of ``sense_series``. The loops use the
``full`` coil program as truth (whose own sampling costs ~60-100 us per call); the ``static``
column repeats the ``sense()`` loop with a :class:`~magstack.sim.truth_source.StaticTruth` (what the
register-level chip simulators use by default), i.e. the error model's own per-sample cost.
"""
from __future__ import annotations

import argparse

import numpy as np
from _timing import best_wall_s  # sibling module (scripts run from benchmarks/)

from magstack.sim.coil_programs import program
from magstack.sim.error_model import ErrorModel
from magstack.sim.measurement_sim import simulate_measurement
from magstack.sim.presets import PRESET_NAMES, preset, preset_info
from magstack.sim.truth_source import StaticTruth


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000, help="samples for the vectorised runs")
    ap.add_argument("--n-loop", type=int, default=2000, help="samples for the per-sample baseline")
    args = ap.parse_args()
    truth = program("full", 3600.0)
    static = StaticTruth()
    print(f"{'preset':<11} {'sense() loop':>14} {'sense_series':>14} {'speed-up':>9} {'sense() static':>15} "
          f"{'us/call':>8}")
    for name in PRESET_NAMES:
        p = preset(name)
        rate = preset_info(name).rate_hz
        t_loop = np.arange(args.n_loop) / rate
        t_vec = np.arange(args.n) / rate

        def loop(t_loop=t_loop, p=p):
            m = ErrorModel(p, seed=0)
            for x in t_loop:
                m.sense(x, truth)

        def vec(t_vec=t_vec, p=p):
            ErrorModel(p, seed=0).sense_series(t_vec, truth)

        def loop_static(t_loop=t_loop, p=p):
            m = ErrorModel(p, seed=0)
            for x in t_loop:
                m.sense(x, static)

        per_loop = best_wall_s(loop, 1) / args.n_loop
        per_vec = best_wall_s(vec) / args.n
        per_static = best_wall_s(loop_static) / args.n_loop
        print(f"{name:<11} {1 / per_loop:>11.0f}/s {1 / per_vec:>11.0f}/s {per_loop / per_vec:>8.1f}x "
              f"{1 / per_static:>13.0f}/s {per_static * 1e6:>8.1f}")
    # whole measurement-level run (what `magstack simulate` does before writing)
    p = preset("lis3mdl")
    tr = program("full", 600.0)
    dt = best_wall_s(lambda: simulate_measurement(p, tr, duration_s=600.0, rate_hz=80.0, seed=0), 1)
    print(f"simulate_measurement lis3mdl 'full' 600 s at 80 Hz (48001 rows): {dt:.2f} s "
          f"({48001 / dt:.0f} rows/s)")


if __name__ == "__main__":
    main()
