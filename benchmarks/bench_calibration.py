"""Benchmarks of the calibration: speed/memory of the fits and appliers; accuracy on real and simulated benches.

Run: ``python benchmarks/bench_calibration.py [--n 1000000] [--part speed|applier|accuracy|all]``. Peak memory is
measured with tracemalloc (numpy allocations included), time with perf_counter; ratios are against
baselines measured in the same process.

``accuracy``: AV-MagEval tests 3-7 (tests/data/av-mageval, the authors' pairing, transition
samples excluded) held out by 60 s time blocks per axis and norm for gain+offset, eq3, eq3 with mount
rotations (and with session offsets), leave-one-session-out for the sessions the others cover, each
session's own linear map (upper bound); the degeneracy rule on simulated thermal runs; a simulated
bench with known remounts.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from magstack.firmware.cal_table import table_from_fit, validate
from magstack.firmware.calibration import FitData, FitOptions, fit
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.firmware.calibration.streaming import StreamingFit
from magstack.firmware.fixed_point import FixedPointTable, to_fixed_inputs
from magstack.firmware.float_applier import apply_float
from magstack.sim.synthetic_calibration import make_data, random_theta

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import measure  # noqa: E402  (sibling module; scripts run from benchmarks/)
from baselines import fixed_point_before  # noqa: E402

CURRENTS = ("solar", "heater")
TERMS = resolve_terms("eq3", currents=CURRENTS)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--block", type=int, default=50_000)
    ap.add_argument("--part", choices=("speed", "applier", "accuracy", "all"), default="all")
    args = ap.parse_args()
    if args.part in ("accuracy", "all"):
        accuracy()
    if args.part == "accuracy":
        return
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
    res, dt_batch, peak_batch = measure(lambda: fit(data, "eq3", currents=CURRENTS, options=opts))
    print(f"batch fit: {dt_batch:.2f} s, peak extra memory {peak_batch:.0f} MiB "
          f"({peak_batch * 2 ** 20 / n:.0f} B/sample), rmse {res.rmse_norm_uT * 1e3:.1f} nT (noise 52 nT), "
          f"held {len(res.held)}, max |theta - truth| {np.abs(res.theta - theta).max():.2e}")

    if args.part != "applier":
        streaming(model, theta, n, args.block, dt_batch, peak_batch)
    appliers(res, data, n)


def streaming(model, theta, n, block, dt_batch, peak_batch) -> None:
    print(f"== streaming fit, blocks of {block} rows generated on the fly (memory flat in N?)")
    for n_s in (n // 10, n // 2, n):
        def run(n_s=n_s):
            sf = StreamingFit(model)
            r = np.random.default_rng(1)
            for k in range(0, n_s, block):
                d = make_data(model, theta, min(block, n_s - k), r, noise_uT=0.03, t0_s=k * 0.25)
                sf.add(d.b_meas_uT, d.b_ref_uT, d.temp_c, d.currents_A, d.session, d.t_s)
                del d
            return sf.solve(), sf.state_bytes
        (rs, state), dt, peak = measure(run)
        print(f"streaming N={n_s:>8d}: {dt:.2f} s, peak {peak:.1f} MiB (state {state} B), "
              f"max |theta - truth| {np.abs(rs.theta - theta).max():.2e}")
    print(f"streaming vs batch time at N={n}: {dt / dt_batch:.2f}x, peak memory {peak / peak_batch:.3f}x")


def appliers(res, data, n) -> None:
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
    S, K, O, KO = (np.asarray(x) for x in (table.S, table.K_S, table.O, table.K_O))
    D = np.array([d for _, d in table.D])
    cur_m = np.column_stack([cur_A[k] for k, _ in table.D])

    def bare():   # the arithmetic alone: no validity, missing-input or saturation flags
        dT = (t_c - table.t0_c)[:, None]
        return b_uT @ S.T + dT * (b_uT @ K.T) + O + dT * KO + cur_m @ D

    t0 = time.perf_counter()
    for _ in range(reps):
        bare()
    dt_bare = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    for _ in range(reps):
        q, _ = fx.apply_block(bi, ti, ci)
    dt_v = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    for _ in range(reps):
        q_before, _ = fixed_point_before.apply_block(fx, bi, ti, ci)
    dt_b = (time.perf_counter() - t0) / reps
    k = 20_000
    rows = [(tuple(int(x) for x in bi[i]), int(ti[i]), tuple(int(x) for x in ci[i])) for i in range(k)]
    t0 = time.perf_counter()
    for b, t, c in rows:
        fx.apply_sample(b, t, c)
    dt_s = (time.perf_counter() - t0) / k
    err = np.abs(q / 256 - ref * 1e3).max()
    f_rate, v_rate, s_rate = m / dt_f, m / dt_v, 1 / dt_s
    print(f"float64 numpy (baseline): {f_rate:,.0f} samples/s")
    print(f"float64 numpy arithmetic alone (no flags): {m / dt_bare:,.0f} samples/s; fixed-point vectorised "
          f"{v_rate * dt_bare / m:.3f}x of it; max |bare - apply_float| {np.abs(bare() - ref).max():.1e} uT")
    print(f"fixed-point vectorised  : {v_rate:,.0f} samples/s  ({v_rate / f_rate:.3f}x baseline)")
    print(f"fixed-point vectorised, plain baseline (baselines/fixed_point_before.py): {m / dt_b:,.0f} samples/s "
          f"({m / dt_b / f_rate:.3f}x baseline); identical output: {np.array_equal(q, q_before)}")
    print(f"fixed-point per sample  : {s_rate:,.0f} samples/s  ({s_rate / f_rate:.5f}x baseline), "
          f"{dt_s * 1e6:.1f} us/sample in CPython")
    print(f"max |fixed - float| over {m} samples: {err:.4f} nT")


# ---------------------------------------------------------------------------------------- accuracy
REAL = Path(__file__).resolve().parent.parent / "tests" / "data" / "av-mageval"
PAIRS = {3: ("data2.csv", "ref3.csv"), 4: ("data3.csv", "ref4.csv"), 5: ("data5.csv", "ref5.csv"),
         6: ("data6.csv", "ref6.csv"), 7: ("data7.csv", "ref7.csv")}


def _nt(v) -> str:
    if v is None:
        return "n/a"
    v = np.asarray(v) * 1e3
    return " / ".join(f"{x:6.1f}" for x in v) + f"  | {np.linalg.norm(v):6.1f}"


def accuracy() -> None:
    from scipy.spatial.transform import Rotation

    from magstack.data.session import Session
    from magstack.ground import mageval_import as mi
    from magstack.sim.calibration_benches import remount_bench, sweep_sessions_bench, thermal_bench

    parts = [mi.import_mageval(REAL / d, REAL / r, session_id=k, onto=0.25, clock_offset_s=mi.AUTHORS_OFFSET_S)
             for k, (d, r) in PAIRS.items()]
    data = FitData.from_session(Session.concatenate(parts))
    o = FitOptions(exclude_ref_steps_uT=0.1)
    print("== AV-MagEval tests 3-7, steps excluded (0.1 uT); nT x / y / z | norm")
    base_dt = None
    for label, model, terms in (("gain_offset", "gain_offset", []), ("eq3", "eq3", []),
                                ("eq3 + mount_rotation", "eq3", ["mount_rotation"]),
                                ("eq3 + session_offset", "eq3", ["session_offset"]),
                                ("eq3 + session_offset + mount_rotation", "eq3", ["session_offset", "mount_rotation"])):
        t0 = time.perf_counter()
        r = fit(data, model, terms, options=o)
        dt = time.perf_counter() - t0
        base_dt = base_dt or dt
        print(f"{label}: rows {r.n_used}, fit+hold-out {dt:.1f} s ({dt / base_dt:.2f}x gain_offset)")
        print(f"   in-sample            {_nt(r.rmse_uT)}")
        print(f"   held-out time blocks {_nt(r.holdout_blocks_uT)}")
        for k in (3, 4):
            print(f"   session {k} left out  {_nt(r.holdout_per_session_uT.get(k))}")
        print(f"   noise floor          {_nt(r.noise_floor_uT)}")
        if r.mount is not None:
            n_free = sum(int(np.isfinite(v).sum()) for k, v in r.mount.se_rad.items() if k != r.mount.frame)
            print(f"   mount angles determined: {n_free} of {3 * (len(PAIRS) - 1)}; verdict "
                  f"{r.comparison.get('rotation_explains')}; general map held-out "
                  f"{_nt(r.comparison.get('holdout_session_map_uT'))}")
    sq, sqi, n = np.zeros(3), np.zeros(3), 0
    for k in PAIRS:
        r = fit(data.select(data.session == k), "gain_offset", options=o)
        sq += r.holdout_blocks_uT ** 2 * r.n_used
        sqi += r.rmse_uT ** 2 * r.n_used
        n += r.n_used
    print(f"each session's own gain_offset map (upper bound): in-sample {_nt(np.sqrt(sqi / n))}, "
          f"held-out {_nt(np.sqrt(sq / n))}")

    print("== degeneracy rule on simulated thermal runs (sweeps at 25 degC + heat-and-cool at fixed fields)")
    for levels in ([(50.0, 0.0, 0.0)], [(50.0, 0.0, 0.0), (0.0, 0.0, 0.0)],
                   [(50.0, 0.0, 0.0), (0.0, 50.0, 0.0), (0.0, 0.0, 50.0), (0.0, 0.0, 0.0)]):
        m, th, d = thermal_bench(levels, np.random.default_rng(1))
        r = fit(d, "eq3", options=FitOptions(holdout=False))
        forced = fit(d, "eq3", options=FitOptions(holdout=False, max_vif=1e12))
        plain = fit(d, "gain_offset", options=FitOptions(holdout=False))
        deg = sorted(h.name for h in r.held if "degenerate" in h.reason)
        held = {(h.axis, h.column) for h in r.held}
        z = [abs(r.theta[i, c] - th[i, c]) / r.se[i, c] for i in range(3) for c in range(m.n_columns)
             if (i, c) not in held]
        print(f"levels {levels}: degenerate held {deg or 'none'}; fitted {len(z)} of 24, max |error|/se "
              f"{max(z):.2f}")
        for lev in ((0.0, 0.0, 0.0), (-30.0, 0.0, 0.0)):
            other = thermal_bench([lev], np.random.default_rng(7), with_sweeps=False)[2]

            def out(res, other=other):
                X = res.model.design(other.b_meas_uT, other.temp_c)
                return np.sqrt(np.mean((other.b_ref_uT - res.model.predict(res.theta, X)) ** 2, axis=0))
            print(f"   heat-and-cool at {lev} uT (not in the fit): rule {_nt(out(r))}; all 24 forced "
                  f"{_nt(out(forced))}; gain_offset {_nt(out(plain))}")

    print("== simulated bench, 4 sessions x 600 s tumbling field, known remounts (session 0 = frame)")
    rot = {1: (2e-3, -4e-3, 3e-3), 2: (-5e-3, 1e-3, 6e-3), 3: (1e-3, 3e-3, -2e-3)}
    d = remount_bench(rot)
    t0 = time.perf_counter()
    r = fit(d, "gain_offset", ["mount_rotation"], options=FitOptions())
    dt_m = time.perf_counter() - t0
    t0 = time.perf_counter()
    ign = fit(d, "gain_offset", options=FitOptions())
    dt_p = time.perf_counter() - t0
    still = fit(remount_bench({}), "gain_offset", options=FitOptions(holdout=False))
    for k, v in rot.items():
        e = (r.mount.rotvec_rad[k] - np.asarray(v)) / r.mount.se_rad[k]
        print(f"   session {k}: true {np.asarray(v) * 1e3} mrad, fitted {np.round(r.mount.rotvec_rad[k] * 1e3, 3)} "
              f"+- {np.round(r.mount.se_rad[k] * 1e3, 3)}, error/se {np.round(e, 2)}")
    zs = np.abs(r.theta - still.theta) / np.hypot(r.se, still.se)
    zi = np.abs(ign.theta - still.theta) / still.se
    print(f"   sensor parameters vs the same bench without remounts: max |diff|/se {np.nanmax(zs):.2f} with mount "
          f"rotations, {np.nanmax(zi):.0f} without")
    print(f"   in-sample {_nt(r.rmse_uT)} with, {_nt(ign.rmse_uT)} without; held-out blocks "
          f"{_nt(r.holdout_blocks_uT)} with, {_nt(ign.holdout_blocks_uT)} without")
    print(f"   verdict {r.comparison['rotation_explains']}, F p = {r.comparison.get('F_p_value', float('nan')):.3g}; "
          f"fit+hold-out {dt_m:.1f} s ({dt_m / dt_p:.2f}x without mount rotations)")

    print("== simulated AV-MagEval-like bench: one axis per session, X and Y swept twice, known remounts")
    rot = {1: (0.0, 0.0, 0.0), 2: (2e-3, 0.0, 3e-3), 3: (-1e-3, 2e-3, 0.0), 4: (3e-3, -4e-3, 5e-3),
           5: (-2e-3, 3e-3, -4e-3)}
    d = sweep_sessions_bench(["", "x", "y", "z", "x", "y"], rot, seed=1)
    r = fit(d, "gain_offset", ["mount_rotation"], options=FitOptions())
    ign = fit(d, "gain_offset", options=FitOptions())
    print(f"   held-out blocks {_nt(r.holdout_blocks_uT)} with mount rotations, {_nt(ign.holdout_blocks_uT)} without")
    for a_, b_ in ((1, 4), (2, 5)):
        want = (Rotation.from_rotvec(rot[a_]).inv() * Rotation.from_rotvec(rot[b_])).as_rotvec()
        got = (Rotation.from_rotvec(r.mount.rotvec_rad[a_]).inv() * Rotation.from_rotvec(r.mount.rotvec_rad[b_])
               ).as_rotvec()
        se = np.nan_to_num(r.mount.se_rad[a_]) + np.nan_to_num(r.mount.se_rad[b_])
        print(f"   session {b_} relative to {a_}: true {np.round(want * 1e3, 3)} mrad, fitted {np.round(got * 1e3, 3)}"
              f" (+- {np.round(se * 1e3, 3)}, 0 = not observable/held)")
    c = r.comparison
    print(f"   determined angles {sum(int(np.isfinite(v).sum()) for k, v in r.mount.se_rad.items() if k != 0)} of 15; "
          f"verdict {c['rotation_explains']}; F p = {c.get('F_p_value', float('nan')):.3g} (F assumes white "
          f"residuals; the preset's 1/f noise inflates it), held-out map {_nt(c.get('holdout_session_map_uT'))}")


if __name__ == "__main__":
    main()
