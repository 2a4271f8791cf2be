"""Benchmarks of ``diagnose``: time on 4 sessions x 900 samples, and time / peak memory at
large N (default 2.5e5 and 1e6 rows).

Run: ``python benchmarks/bench_diagnose.py [--big 250000,1000000] [--repeat 7]``. Small case: wall time
(perf_counter) and CPU time (process_time), each best of ``--repeat`` after one warm-up run; large cases:
one run's wall and CPU time, peak memory by tracemalloc (numpy allocations included). The
baseline measured in the same process is the calibration fit (gain_offset, held-out time blocks) of
the same data, so the ratio says how much more the diagnosis costs than one held-out calibration.
"""
from __future__ import annotations

import argparse
import gc
import time
import tracemalloc

import numpy as np
from _timing import best_cpu, best_wall_s  # noqa: E402  (run as a script from benchmarks/)

from magstack.data.session import Session
from magstack.firmware.blas import blas_threads
from magstack.firmware.calibration import FitData, FitOptions, fit
from magstack.ground.diagnose import diagnose_model
from magstack.sim.coil_programs import program
from magstack.sim.error_model import ErrorParams
from magstack.sim.measurement_sim import simulate_measurement
from magstack.sim.presets import preset


def small_case() -> Session:
    """4 power cycles x 900 samples of the 'full' bench program, HMC1053 gain/offset/noise + time skew."""
    p = preset("hmc1053")
    params = ErrorParams(gain_matrix=p.gain_matrix, offset_uT=p.offset_uT, noise_white_uT=p.noise_white_uT,
                         axis_delay_s=p.axis_delay_s, lsb_uT=p.lsb_uT)
    truth = program("full", 3600 / 2.5, sessions=4)
    r = simulate_measurement(params, truth, duration_s=3600 / 2.5 - 0.4, rate_hz=2.5, seed=1,
                             effects=["time_skew", "gain", "offset", "noise", "quantization"])
    return Session(r.t_s, r.ref_uT, r.dut_uT, r.temp_c, r.session, r.currents_A)


def big_case(n: int) -> Session:
    """n rows of a tumbling field with thermal cycle, a current, 8 sessions (numpy only, fast to make)."""
    rng = np.random.default_rng(0)
    t = np.arange(n) / 2.5
    w = 2 * np.pi * np.array([1 / 97.0, 1 / 131.0, 1 / 173.0])
    b = np.column_stack([40 * np.sin(w[0] * t), 35 * np.cos(w[1] * t), 30 * np.sin(w[2] * t)])
    temp = 30 + 20 * np.sin(2 * np.pi * t / t[-1])
    cur = {"heater_A": 0.4 * ((t // 45) % 2)}
    dut = b * 1.1 + 0.3 + 0.05 * (temp - 25)[:, None] * np.array([1, 0, 0]) + rng.standard_normal((n, 3)) * 0.02
    return Session(t, b + rng.standard_normal((n, 3)) * 0.001, dut, temp, (np.arange(n) * 8 // n), cur)


def measure(fn):
    gc.collect()
    tracemalloc.start()
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, dt, dc, peak / 2 ** 20


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--big", default="250000,1000000", help="large row counts (comma separated, '' = skip)")
    ap.add_argument("--repeat", type=int, default=7, help="runs of the small case (best of them)")
    args = ap.parse_args()
    s = small_case()
    fd = FitData.from_session(s)
    d = diagnose_model(s, "gain_offset")           # the first run loads the lazily imported modules
    base = best_wall_s(lambda: fit(fd, "gain_offset", options=FitOptions()), args.repeat)
    _, base_c = best_cpu(lambda: fit(fd, "gain_offset", options=FitOptions()), args.repeat)
    t_d = best_wall_s(lambda: diagnose_model(s, "gain_offset"), args.repeat)
    _, c_d = best_cpu(lambda: diagnose_model(s, "gain_offset"), args.repeat)
    print(f"small: {len(s)} rows in {len(np.unique(s.session))} sessions; verdict {d.verdict}; "
          f"BLAS threads {blas_threads()}")
    print(f"  calibration fit with held-out blocks (baseline): {base:.3f} s wall, {base_c:.3f} s CPU")
    print(f"  diagnose: {t_d:.3f} s wall, {c_d:.3f} s CPU (best of {args.repeat} each) = {t_d / base:.1f}x / "
          f"{c_d / base_c:.1f}x baseline; targets < 10 s and <= 0.3 s")
    for n in [int(x) for x in args.big.split(",") if x]:
        sb = big_case(n)
        _, bt, bc, bm = measure(lambda sb=sb: fit(FitData.from_session(sb), "gain_offset", options=FitOptions()))
        d, dt, dc, dm = measure(lambda sb=sb: diagnose_model(sb, "gain_offset"))
        data_mib = sum(a.nbytes for a in (sb.t_s, sb.ref_uT, sb.dut_uT, sb.temp_c, sb.session,
                                          *sb.currents_A.values())) / 2 ** 20
        print(f"big n={n}: session arrays {data_mib:.0f} MiB; verdict {d.verdict}")
        print(f"  fit (baseline): {bt:.1f} s wall, {bc:.1f} s CPU, peak {bm:.0f} MiB")
        print(f"  diagnose: {dt:.1f} s wall, {dc:.1f} s CPU, peak {dm:.0f} MiB "
              f"({dm * 2 ** 20 / n:.0f} B/row, {dm / data_mib:.1f}x the session arrays, {dm / bm:.2f}x the fit)")


if __name__ == "__main__":
    main()
