"""Benchmark: error-model single-sample ``sense()`` and ``sense_series`` now vs before the stage refactor.

Run from the repository root: ``python benchmarks/bench_error_model.py [--n 20000] [--n-loop 2000]``.

"before" is the pre-refactor implementation frozen verbatim in
``benchmarks/baselines/error_model_before.py``; both are timed in this process,
interleaved, best of ``--repeat``, so the printed ratios (now / before, < 1 = faster now) do not
depend on the machine. Columns:

* ``static``: ``sense()`` per call with a :class:`~magstack.sim.truth_source.StaticTruth` (what the
  register-level chip simulators use by default), i.e. the error model's own per-sample cost;
* ``program``: ``sense()`` per call with the ``full`` coil program as truth (its own sampling costs
  ~60-100 us per call);
* ``series``: ``sense_series`` throughput.

It also checks that both give the same samples (max |now - before|, uT) and times one
measurement-level run (what ``magstack simulate`` does before writing).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from baselines import error_model_before as before  # sibling folder (scripts run from benchmarks/)

from magstack.sim.coil_programs import program
from magstack.sim.error_model import ErrorModel
from magstack.sim.measurement_sim import simulate_measurement
from magstack.sim.presets import PRESET_NAMES, preset, preset_info
from magstack.sim.truth_source import StaticTruth


def _best_pair(fn_now, fn_before, repeat: int) -> tuple[float, float]:
    """Best-of-``repeat`` wall times (s) of two functions, run alternately (order swapped every round)."""
    best = [float("inf"), float("inf")]
    for r in range(repeat):
        for i in ((0, 1) if r % 2 == 0 else (1, 0)):
            fn = (fn_now, fn_before)[i]
            t0 = time.perf_counter()
            fn()
            best[i] = min(best[i], time.perf_counter() - t0)
    return best[0], best[1]


def _loop(cls, params, t, truth):
    def run():
        m = cls(params, seed=0)
        for x in t:
            m.sense(x, truth)
    return run


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000, help="samples for the sense_series runs")
    ap.add_argument("--n-loop", type=int, default=2000, help="samples for the sense() loops")
    ap.add_argument("--repeat", type=int, default=5, help="best of this many alternating runs")
    args = ap.parse_args()
    truth = program("full", 3600.0)
    static = StaticTruth()
    print(f"{'preset':<11} | {'static now':>10} {'before':>8} {'ratio':>6} | {'program now':>11} {'before':>8} "
          f"{'ratio':>6} | {'series now':>11} {'before':>11} {'ratio':>6} | {'max |now-before| uT':>20}")
    ratios = []
    for name in PRESET_NAMES:
        p = preset(name)
        p_before = before.ErrorParams.from_dict(p.to_dict())
        rate = preset_info(name).rate_hz
        t_loop = np.arange(args.n_loop) / rate
        t_vec = np.arange(args.n) / rate
        s_now, s_before = _best_pair(_loop(ErrorModel, p, t_loop, static),
                                     _loop(before.ErrorModel, p_before, t_loop, static), args.repeat)
        p_now, p_bef = _best_pair(_loop(ErrorModel, p, t_loop, truth),
                                  _loop(before.ErrorModel, p_before, t_loop, truth), args.repeat)
        v_now, v_before = _best_pair(lambda p=p, t=t_vec: ErrorModel(p, seed=0).sense_series(t, truth),
                                     lambda p=p_before, t=t_vec: before.ErrorModel(p, seed=0).sense_series(t, truth),
                                     args.repeat)
        m_now, m_before = ErrorModel(p, seed=0), before.ErrorModel(p_before, seed=0)
        diff = max(float(np.abs(m_now.sense(x, truth) - m_before.sense(x, truth)).max()) for x in t_loop[:500])
        diff = max(diff, float(np.abs(ErrorModel(p, seed=0).sense_series(t_vec, truth)
                                      - before.ErrorModel(p_before, seed=0).sense_series(t_vec, truth)).max()))
        us = 1e6 / args.n_loop
        ratios.append(s_now / s_before)
        print(f"{name:<11} | {s_now * us:>7.2f} us {s_before * us:>5.2f} us {s_now / s_before:>5.2f}x | "
              f"{p_now * us:>8.1f} us {p_bef * us:>5.1f} us {p_now / p_bef:>5.2f}x | "
              f"{args.n / v_now:>9.0f}/s {args.n / v_before:>9.0f}/s {v_now / v_before:>5.2f}x | {diff:>20.3g}")
    print(f"single-sample sense() (static truth), now / before: worst {max(ratios):.2f}x (limit 1.5x)")
    # whole measurement-level run (what `magstack simulate` does before writing)
    p = preset("lis3mdl")
    tr = program("full", 600.0)
    t0 = time.perf_counter()
    simulate_measurement(p, tr, duration_s=600.0, rate_hz=80.0, seed=0)
    dt = time.perf_counter() - t0
    print(f"simulate_measurement lis3mdl 'full' 600 s at 80 Hz (48001 rows): {dt:.2f} s ({48001 / dt:.0f} rows/s)")


if __name__ == "__main__":
    main()
