"""Benchmarks for issue 6: batch fit and streaming fit (time, peak memory), applier throughput.

Run: ``python benchmarks/bench_calibration.py [--n 1000000]``. Peak memory is measured with
tracemalloc (numpy allocations included), time with perf_counter; ratios are against
baselines measured in the same process.
"""
from __future__ import annotations

import argparse
import gc
import time
import tracemalloc

import numpy as np

from magstack.firmware.cal_table import table_from_fit, validate
from magstack.firmware.calibration import FitOptions, fit
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.firmware.calibration.streaming import StreamingFit
from magstack.firmware.fixed_point import FixedPointTable, to_fixed_inputs
from magstack.firmware.float_applier import apply_float
from magstack.sim.synthetic_calibration import make_data, random_theta

CURRENTS = ("solar", "heater")
TERMS = resolve_terms("eq3", currents=CURRENTS)


def _measure(fn):
    gc.collect()
    tracemalloc.start()
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, dt, peak / 2 ** 20


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--block", type=int, default=50_000)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    model = CalModel(TERMS, CURRENTS, (), 25.0, 0.0)
    theta = random_theta(model, rng)
    n = args.n
    data = make_data(model, theta, n, rng, noise_uT=0.03, t0_s=0.0)
    in_bytes = sum(a.nbytes for a in (data.b_meas_uT, data.b_ref_uT, data.temp_c, data.t_s, data.session,
                                      *data.currents_A.values()))
    print(f"== batch fit: N = {n}, {int(model.axis_mask().sum())} parameters (Eq. 3 + 2 currents), "
          f"input arrays {in_bytes / 2 ** 20:.0f} MiB")
    opts = FitOptions(holdout=False)
    res, dt_batch, peak_batch = _measure(lambda: fit(data, "eq3", currents=CURRENTS, options=opts))
    print(f"batch fit: {dt_batch:.2f} s, peak extra memory {peak_batch:.0f} MiB "
          f"({peak_batch * 2 ** 20 / n:.0f} B/sample), rmse {res.rmse_norm_uT * 1e3:.1f} nT (noise 52 nT), "
          f"held {len(res.held)}, max |theta - truth| {np.abs(res.theta - theta).max():.2e}")

    print(f"== streaming fit, blocks of {args.block} rows generated on the fly (memory flat in N?)")
    for n_s in (n // 10, n // 2, n):
        def run(n_s=n_s):
            sf = StreamingFit(model)
            r = np.random.default_rng(1)
            for k in range(0, n_s, args.block):
                d = make_data(model, theta, min(args.block, n_s - k), r, noise_uT=0.03, t0_s=k * 0.25)
                sf.add(d.b_meas_uT, d.b_ref_uT, d.temp_c, d.currents_A, d.session, d.t_s)
                del d
            return sf.solve(), sf.state_bytes
        (rs, state), dt, peak = _measure(run)
        print(f"streaming N={n_s:>8d}: {dt:.2f} s, peak {peak:.1f} MiB (state {state} B), "
              f"max |theta - truth| {np.abs(rs.theta - theta).max():.2e}")
    print(f"streaming vs batch time at N={n}: {dt / dt_batch:.2f}x, peak memory {peak / peak_batch:.3f}x")

    print("== appliers (same table, same inputs)")
    table = table_from_fit(res, "bench", validity_temp_c=(-40.0, 85.0), validity_field_uT=100.0,
                           validity_currents_A={"solar": (-5.0, 5.0), "heater": (-5.0, 5.0)})
    assert validate(table).ok, validate(table).problems
    fx = FixedPointTable.from_table(table)
    m = min(n, 1_000_000)
    cur = np.column_stack([data.currents_A[k][:m] for k in CURRENTS])
    bi, ti, ci, _ = to_fixed_inputs(data.b_meas_uT[:m], data.temp_c[:m], cur)
    b_uT, t_c, cur_A = bi / 1e3, ti / 100, {k: ci[:, j] / 1e3 for j, k in enumerate(CURRENTS)}
    reps = 3
    t0 = time.perf_counter()
    for _ in range(reps):
        ref, _ = apply_float(table, b_uT, t_c, cur_A)
    dt_f = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    for _ in range(reps):
        q, _ = fx.apply_block(bi, ti, ci)
    dt_v = (time.perf_counter() - t0) / reps
    k = 20_000
    rows = [(tuple(int(x) for x in bi[i]), int(ti[i]), tuple(int(x) for x in ci[i])) for i in range(k)]
    t0 = time.perf_counter()
    for b, t, c in rows:
        fx.apply_sample(b, t, c)
    dt_s = (time.perf_counter() - t0) / k
    err = np.abs(q / 256 - ref * 1e3).max()
    f_rate, v_rate, s_rate = m / dt_f, m / dt_v, 1 / dt_s
    print(f"float64 numpy (baseline): {f_rate:,.0f} samples/s")
    print(f"fixed-point vectorised  : {v_rate:,.0f} samples/s  ({v_rate / f_rate:.3f}x baseline)")
    print(f"fixed-point per sample  : {s_rate:,.0f} samples/s  ({s_rate / f_rate:.5f}x baseline), "
          f"{dt_s * 1e6:.1f} us/sample in CPython")
    print(f"max |fixed - float| over {m} samples: {err:.4f} nT")


if __name__ == "__main__":
    main()
