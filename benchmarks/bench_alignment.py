"""Alignment on real bench data: time per file, estimated offsets, linear-fit RMSE vs. the authors.

    python benchmarks/bench_alignment.py [DIR]
    python benchmarks/bench_alignment.py --memory [ROWS]
    python benchmarks/bench_alignment.py --mageval-memory [DUT_ROWS]

With ``--memory`` it writes a synthetic raw bench session of ROWS rows (default 2,000,000) and
runs ``magstack align SESSION --json`` on it in a fresh process, printing wall time and peak RSS
(``resource.getrusage``, which covers numpy's buffers) next to a process that only reads the file.
With ``--mageval-memory`` it writes an AV-MagEval-shaped pair (DUT_ROWS rows at 0.47 s, default
1,000,000; reference at 4 Hz, 4 h - 0.3 s behind) and runs ``magstack import-mageval`` and
``magstack align DATA REF --json`` on it, printing exit code, wall time and peak RSS.

DIR holds dataN.csv/refN.csv (default: tests/data/av-mageval, the shipped subset; a full
copy of MIT-STARLab/AV-MagEval-Data with testN/ sub-folders is also accepted). For each of
tests 5, 6, 7 it prints:

* wall time of :func:`magstack.ground.alignment.align_streams` (offset + skew + axis map + RMSE), best of
  5, and its ratio to a baseline run in the same process (one interpolation + one 12-parameter
  linear fit at the authors' offset);
* the estimated clock offset +- 1 sigma vs. the authors' 4 h - 0.5 s;
* the vector RMSE of the linear fit ``ref ~ A dut + b`` after our alignment and after the
  authors' correction, on the same rows, for the reference interpolated onto the DUT timestamps
  and for the authors' uniform 0.25 s grid; and after also correcting the per-axis skew.

(The real files' temperature spans 0.1-0.3 degC, so ``align_streams`` keeps the plain model there;
the temperature is passed as ``magstack align`` does.)

Then a simulated thermally cycled session (HMC1053 error model, -20..60 degC, 600 s, known
clock offset, several seeds): offset error and sigma of the plain model (no temperature terms),
of the belsten Eq. 3 temperature terms and of Eq. 3 + dT^2 terms (the default), and the time of
``align_streams`` with each relative to the plain model.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _timing import best_wall_s  # noqa: E402  (sibling module; scripts run from benchmarks/)

from magstack.ground.alignment import align_streams, interp_no_extrapolation, linear_fit_rmse_uT  # noqa: E402
from magstack.ground.mageval_import import (  # noqa: E402
    AUTHORS_AXIS_MAP,
    AUTHORS_OFFSET_S,
    KELVIN_OFFSET,
    apply_axis_map,
    import_mageval,
    read_mageval_data,
    read_mageval_ref,
)

PAIRS = {5: ("data5.csv", "ref5.csv"), 6: ("data6.csv", "ref6.csv"), 7: ("data7.csv", "ref7.csv")}


def _find(root: Path, name: str, test: int) -> Path:
    for p in (root / name, root / f"test{test}" / name):
        if p.exists():
            return p
    raise FileNotFoundError(f"{name} not in {root}")




MEMORY_CHILD = """
import resource, sys, time
from magstack.data.session import read_session
t0 = time.perf_counter()
if sys.argv[2] == "read":
    read_session(sys.argv[1])
else:
    from magstack.cli.main import main
    import contextlib, io
    with contextlib.redirect_stdout(io.StringIO()) as out:
        rc = main(["align", sys.argv[1], "--json"])
    assert rc == 0, out.getvalue()
print(time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
"""


def synthetic_raw_session(path: Path, rows: int, offset_s: float = 0.137, rate_hz: float = 80.0) -> None:
    """A raw bench session of ``rows`` interleaved DUT/reference rows at ``rate_hz`` each: a field of
    slow random sinusoids (0.005-0.3 Hz, 30 uT), DUT = gain/offset/axis-mixed field read ``offset_s``
    later on its own clock plus 20 nT noise, reference = field plus 1 nT noise, 25 degC."""
    from magstack.data.session import SessionWriter

    rng = np.random.default_rng(7)
    freqs, phases = rng.uniform(0.005, 0.3, (3, 12)), rng.uniform(0, 2 * np.pi, (3, 12))
    A = np.array([[1.02, 0.01, -0.02], [0.015, 0.97, 0.01], [-0.01, 0.02, 1.05]])

    def field(t: np.ndarray) -> np.ndarray:
        return np.stack([np.sin(2 * np.pi * freqs[i] * t[:, None] + phases[i]).sum(axis=1) for i in range(3)],
                        axis=1) * (30.0 / np.sqrt(12))

    n_each = rows // 2
    with SessionWriter(path, {"dut_chip": "synthetic", "reference": "synthetic"}, block_rows=20000) as w:
        for start in range(0, n_each, 100000):
            k = np.arange(start, min(n_each, start + 100000))
            t = 1.7e9 + k / rate_hz
            t_rel = k / rate_hz
            ref = field(t_rel) + rng.normal(0, 0.001, (k.size, 3))
            dut = (field(t_rel - offset_s) @ A.T + [0.5, -0.3, 0.2]) + rng.normal(0, 0.02, (k.size, 3))
            table = np.full((2 * k.size, 9), np.nan)
            table[0::2, 0], table[1::2, 0] = t, t + 0.5 / rate_hz
            table[0::2, 4:7], table[1::2, 1:4] = dut, ref
            table[:, 7], table[:, 8] = 25.0, 0
            w.write_block(table)


MAGEVAL_CHILD = """
import resource, sys, time, contextlib, io
from magstack.cli.main import main
t0 = time.perf_counter()
with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.redirect_stderr(io.StringIO()) as err:
    rc = main(sys.argv[1:])
print(rc, time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
print(out.getvalue().strip()[:300].replace(chr(10), " | "))
print(err.getvalue().strip()[:300])
"""


def synthetic_mageval(data_csv: Path, ref_csv: Path, dut_rows: int, offset_s: float = 4 * 3600 - 0.3) -> None:
    """AV-MagEval-shaped files: DUT logger at ~2.13 Hz (0.47 s), FVM400 reference at 4 Hz on a clock
    ``offset_s`` behind; a field of slow random sinusoids (0.002-0.1 Hz); temperatures in kelvin."""
    rng = np.random.default_rng(11)
    freqs, phases = rng.uniform(0.002, 0.1, (3, 12)), rng.uniform(0, 2 * np.pi, (3, 12))

    def field(t: np.ndarray) -> np.ndarray:
        return np.stack([np.sin(2 * np.pi * freqs[i] * t[:, None] + phases[i]).sum(axis=1) for i in range(3)],
                        axis=1) * (30.0 / np.sqrt(12))

    t0 = 1.598e9
    with open(data_csv, "w") as fh:
        fh.write("time,x_test,y_test,z_test,x_U7,y_U7,z_U7,x_U9,y_U9,z_U9,temp_mag,temp_pi\n")
        for start in range(0, dut_rows, 200000):
            k = np.arange(start, min(dut_rows, start + 200000))
            t = k * 0.47
            b = field(t)
            dut = np.column_stack([b[:, 1], b[:, 0], -b[:, 2]]) + rng.normal(0, 0.02, (k.size, 3))
            table = np.column_stack([t0 + t, dut, dut * 0.9, dut * 1.1, np.full(k.size, 298.9),
                                     297.1 + 0.05 * np.sin(t / 600)])
            np.savetxt(fh, table, fmt=["%.3f"] + ["%.3f"] * 9 + ["%.3f", "%.3f"], delimiter=",")
    with open(ref_csv, "w") as fh:
        n_ref = int(dut_rows * 0.47 * 4)
        for start in range(0, n_ref, 400000):
            k = np.arange(start, min(n_ref, start + 400000))
            t = k * 0.25
            np.savetxt(fh, np.column_stack([t0 + t - offset_s, field(t) + rng.normal(0, 0.001, (k.size, 3))]),
                       fmt="%.3f", delimiter=",")


def mageval_memory(dut_rows: int) -> int:
    """Time and peak memory of ``import-mageval`` and ``align DATA REF`` on large AV-MagEval-shaped files."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory(prefix="bench-mageval-mem-") as tmp:
        d, r = Path(tmp) / "data1.csv", Path(tmp) / "ref1.csv"
        synthetic_mageval(d, r, dut_rows)
        sizes = d.stat().st_size, r.stat().st_size
        print(f"synthetic AV-MagEval pair: {dut_rows:,} DUT rows ({sizes[0] / 1e6:.1f} MB), "
              f"{int(dut_rows * 0.47 * 4):,} reference rows ({sizes[1] / 1e6:.1f} MB); true offset 4 h - 0.3 s")
        for args in (["import-mageval", str(d), str(r), "--out", str(Path(tmp) / "s.csv")],
                     ["align", "--json", str(d), str(r)]):
            out = subprocess.run([sys.executable, "-c", MAGEVAL_CHILD, *args], capture_output=True, text=True,
                                 check=True).stdout.splitlines()
            rc, t, rss = out[0].split()
            print(f"  magstack {args[0]}: exit {rc}, {float(t):.1f} s, peak RSS {int(rss) / 1e6:.0f} MB = "
                  f"{int(rss) / sum(sizes):.1f}x the input size")
            print(f"    {out[1][:200] if len(out) > 1 else ''} {out[2][:200] if len(out) > 2 else ''}")
    return 0


def memory(rows: int) -> int:
    """Peak memory (max RSS) of ``magstack align SESSION --json`` on a synthetic raw session."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory(prefix="bench-align-mem-") as tmp:
        path = Path(tmp) / "raw.csv"
        synthetic_raw_session(path, rows)
        size = path.stat().st_size
        res = {}
        for what in ("read", "align"):
            out = subprocess.run([sys.executable, "-c", MEMORY_CHILD, str(path), what], capture_output=True,
                                 text=True, check=True).stdout.split()
            res[what] = (float(out[0]), int(out[1]))
    print(f"synthetic raw session: {rows:,} rows ({rows // 2:,} DUT + {rows // 2:,} reference at 80 Hz), "
          f"{size / 1e6:.1f} MB")
    for what, label in (("read", "read_session only (baseline)"), ("align", "magstack align --json")):
        t, rss = res[what]
        print(f"  {label}: {t:.1f} s, peak RSS {rss / 1e6:.0f} MB = {rss / size:.1f}x the file size")
    return 0


def main(argv: list[str]) -> int:
    if len(argv) > 1 and argv[1] == "--memory":
        return memory(int(argv[2]) if len(argv) > 2 else 2_000_000)
    if len(argv) > 1 and argv[1] == "--mageval-memory":
        return mageval_memory(int(argv[2]) if len(argv) > 2 else 1_000_000)
    root = Path(argv[1]) if len(argv) > 1 else ROOT / "tests" / "data" / "av-mageval"
    print(f"data: {root}")
    print(f"{'test':>4} {'align s':>8} {'x base':>7} {'offset - authors (s)':>22} {'RMSE nT ours/authors':>22} "
          f"{'0.25 s grid':>14} {'+skew':>7}")
    for test, (dn, rn) in PAIRS.items():
        d, r = _find(root, dn, test), _find(root, rn, test)
        cols, _ = read_mageval_data(d)
        t_ref, ref_raw, _ = read_mageval_ref(r)
        t_dut = cols["time"]
        dut = np.column_stack([cols["x_test"], cols["y_test"], cols["z_test"]])
        ref = apply_axis_map(ref_raw, AUTHORS_AXIS_MAP)
        temp_c = cols["temp_pi"] - KELVIN_OFFSET

        def baseline(t_dut=t_dut, dut=dut, t_ref=t_ref, ref=ref):
            y, ok = interp_no_extrapolation(t_ref + AUTHORS_OFFSET_S, ref, t_dut)
            return linear_fit_rmse_uT(y[ok], dut[ok])

        def ours_full(t_dut=t_dut, dut=dut, t_ref=t_ref, ref=ref, temp_c=temp_c):
            return align_streams(t_dut, dut, t_ref, ref, temp_c=temp_c)

        t_base = best_wall_s(baseline, 5)
        t_align = best_wall_s(ours_full, 5)
        rep = ours_full()
        off = rep.offset.offset_s
        ours, ok1 = interp_no_extrapolation(t_ref + off, ref, t_dut)
        auth, ok2 = interp_no_extrapolation(t_ref + AUTHORS_OFFSET_S, ref, t_dut)
        ok = ok1 & ok2
        r_ours = linear_fit_rmse_uT(ours[ok], dut[ok])["vector"] * 1e3
        r_auth = linear_fit_rmse_uT(auth[ok], dut[ok])["vector"] * 1e3
        g_ours = import_mageval(d, r, clock_offset_s=off, onto=0.25, gaps="drop")
        g_auth = import_mageval(d, r, clock_offset_s=AUTHORS_OFFSET_S, onto=0.25, gaps="drop")
        n = min(len(g_ours), len(g_auth))
        rg_o = linear_fit_rmse_uT(g_ours.ref_uT[:n], g_ours.dut_uT[:n])["vector"] * 1e3
        rg_a = linear_fit_rmse_uT(g_auth.ref_uT[:n], g_auth.dut_uT[:n])["vector"] * 1e3
        # per-axis skew: DUT axis i read the field at t + skew_i -> its value at t is dut_i(t - skew_i)
        shift = [e.value if e.determined else 0.0 for e in rep.skew_s]
        dcorr = np.column_stack([interp_no_extrapolation(t_dut, dut[:, i], t_dut - shift[i])[0] for i in range(3)])
        ok3 = ok1 & np.all(np.isfinite(dcorr), axis=1)
        r_skew = linear_fit_rmse_uT(ours[ok3], dcorr[ok3])["vector"] * 1e3
        print(f"{test:>4} {t_align:8.3f} {t_align / t_base:7.0f} {off - AUTHORS_OFFSET_S:+10.3f} "
              f"+- {rep.offset.sigma_s:.3f}      {r_ours:7.1f} / {r_auth:7.1f}   {rg_o:5.1f}/{rg_a:5.1f} {r_skew:7.1f}")
        print("     skew (s, rel. to offset): " + ", ".join(
            f"{ax} {e.value:+.3f}+-{e.sigma:.3f}{'' if e.determined else ' (undetermined)'}"
            for ax, e in zip("xyz", rep.skew_s, strict=True)) + f"; map: {rep.axis_map.describe()}")
        print(f"     model: {rep.model}")
    thermal_cycling()
    return 0


def thermal_cycling(seeds: int = 5, duration_s: float = 600.0) -> None:
    """Plain vs temperature model on simulated -20..60 degC cycling with a known clock offset."""
    from magstack.ground.errors import AlignmentError
    from magstack.sim.coil_programs import program
    from magstack.sim.error_model import without
    from magstack.sim.measurement_sim import simulate_measurement
    from magstack.sim.presets import preset

    truth = program("temp_cycling", duration_s, sessions=1)
    variants = {"plain (old)": {"temp_model": "off"}, "Eq. 3": {"temp_order": 1}, "Eq. 3 + dT^2": {"temp_order": 2}}
    print(f"\nsimulated temp_cycling, HMC1053 error model without per-axis delays, {duration_s:.0f} s, DUT 2.5 Hz, "
          f"reference 4 Hz; offset error / sigma (s) per seed")
    times: dict[str, list[float]] = {k: [] for k in variants}
    for seed in range(seeds):
        true_off = 1.234 + 0.1 * seed
        dut = simulate_measurement(preset("hmc1053"), truth, duration_s=duration_s, rate_hz=2.5, seed=seed,
                                   effects=without("time_skew"))
        ref = simulate_measurement(preset("hmc1053"), truth, duration_s=duration_s - 1.0, rate_hz=4.0,
                                   seed=seed + 100, t_start_s=0.137)
        temp = np.round(dut.temp_c + np.random.default_rng(seed).normal(0.0, 0.05, dut.t_s.size), 2)
        cells = []
        for name, kw in variants.items():
            def run(kw=kw, dut=dut, ref=ref, temp=temp, true_off=true_off):
                return align_streams(dut.t_s, dut.dut_uT, ref.t_s - true_off, ref.ref_uT, prior_s=0.0,
                                     search_halfwidth_s=10.0, temp_c=temp, **kw)
            def timed(run=run):
                try:
                    run()
                except AlignmentError:
                    pass

            times[name].append(best_wall_s(timed, 3))
            try:
                o = run().offset
                cells.append(f"{name}: {o.offset_s - true_off:+.4f} +- {o.sigma_s:.4f}")
            except AlignmentError as exc:
                cells.append(f"{name}: refused ({str(exc).split(': ')[-1]})")
        print(f"  seed {seed}: " + "; ".join(cells))
    base = float(np.median(times["plain (old)"])) if times["plain (old)"] else float("nan")
    print("  align_streams time (median over seeds): " + ", ".join(
        f"{k} {np.median(v):.3f} s ({np.median(v) / base:.2f}x plain)" for k, v in times.items() if v))


if __name__ == "__main__":
    sys.exit(main(sys.argv))
