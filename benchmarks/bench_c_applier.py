"""The C applier (firmware_c/): equality at full count, speed against the Python fixed-point applier, sizes.

Run: ``python benchmarks/bench_c_applier.py [--part equality|speed|size|all]`` (needs gcc; the ARM figures
need Debian's gcc-arm-linux-gnueabihf and qemu-user, the Cortex-M4 size gcc-arm-none-eabi).

* ``equality``: ``--tables`` hypothesis-generated tables (half physical calibrations, half any int32 coefficient
  with every limit) with ``--samples`` rows each (edges from hypothesis, the rest inside, on and beyond the
  table's validity box, temperatures in runs and near t0, exact rounding halves), and ``--kernel-tables`` more with
  32 whole chunks of 32 samples each for the block path's kernels (``c_applier_build.kernel_cases``). Compared bit
  for bit with the Python applier (``apply_block`` on every row, ``apply_sample`` on every row unless
  ``--no-per-sample``): the host library through ctypes (``magstack_cal_apply_block`` and ``magstack_cal_apply``
  on every row, and the block again with terms precomputed for all or part of the temperatures), and the harness
  cross-compiled for 32-bit ARM run by qemu-arm (``magstack_cal_apply`` on every row, and the block path checked
  against it inside the harness), without and with precomputed terms.
* ``speed``: CPU time per sample of ``magstack_cal_apply_block`` (ctypes, one call per block; the builds of
  ``HOST_BUILDS``, with and without terms precomputed for the streams' -40..85 degC by ``magstack_cal_precompute``)
  against ``FixedPointTable.apply_block`` (numpy) on the same block, in this process, best of ``--repeat``; four
  temperature patterns (``PATTERNS``); the table has per-axis and magnitude limits; a summary of the ratios per
  pattern at the end. ns per sample on emulated ARM from the harness's own clock under qemu-arm (wall time, so it
  includes the host's load).
* ``size``: the library's code size (``size`` of the object file) for the host, 32-bit ARM Linux and Cortex-M4,
  and the table image's size.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "c_applier"))

import c_applier_build as cb  # noqa: E402  (the tests' build helper)

from magstack.firmware import cal_image  # noqa: E402
from magstack.firmware import fixed_point as fp  # noqa: E402


def collect_cases(n_tables: int, n_samples: int, n_kernel: int = 0, n_chunks: int = 32) -> list:
    """``n_tables`` cases of ``cb.cases`` and ``n_kernel`` of ``cb.kernel_cases`` (whole chunks for the block path's
    kernels) drawn by hypothesis (generation only, derandomised: the same cases every run)."""
    from hypothesis import HealthCheck, Phase, given, settings

    out = []
    for strategy, count in ((cb.cases(n_random=n_samples), n_tables), (cb.kernel_cases(n_chunks=n_chunks), n_kernel)):
        if count == 0:
            continue

        @settings(max_examples=count, database=None, deadline=None, phases=[Phase.generate], derandomize=True,
                  suppress_health_check=list(HealthCheck))
        @given(strategy)
        def draw(case):
            out.append(case)

        draw()
    return out


def _kernel_chunks(cases) -> tuple[int, int]:
    """(chunks whose inputs are all inside the kernel bounds, all chunks) of the cases' blocks."""
    inside = total = 0
    for _fx, _names, b, t, c in cases:
        for s in range(0, b.shape[0], cb.CHUNK):
            bb, tt, cc = b[s:s + cb.CHUNK], t[s:s + cb.CHUNK], c[s:s + cb.CHUNK]
            total += 1
            inside += bool((bb >= -cb.KERNEL_B).all() and (bb < cb.KERNEL_B).all() and (tt >= -cb.KERNEL_T).all()
                           and (tt < cb.KERNEL_T).all() and (cc >= -cb.KERNEL_I).all() and (cc < cb.KERNEL_I).all())
    return inside, total


def equality(args, build: Path) -> None:
    t0 = time.perf_counter()
    cases = collect_cases(args.tables, args.samples, args.kernel_tables)
    n_rows = sum(c[2].shape[0] for c in cases)
    inside, chunks = _kernel_chunks(cases)
    print(f"{len(cases)} tables ({args.kernel_tables} of them with whole chunks for the kernels; "
          f"{sum(1 for c in cases if c[0].D)} with currents, {sum(1 for c in cases if any(c[0].K_S2))} with K_S2), "
          f"{n_rows} samples drawn in {time.perf_counter() - t0:.1f} s; {inside} of {chunks} chunks of {cb.CHUNK} "
          f"samples inside the kernel bounds")
    lib = cb.CApplier(cb.build_shared(build))
    refs = []
    t0 = time.perf_counter()
    for fx, _names, b, t, c in cases:
        refs.append(cb.python_reference(fx, b, t, c, per_sample=not args.no_per_sample))
    print(f"Python reference: {time.perf_counter() - t0:.1f} s "
          f"({'apply_block and apply_sample' if not args.no_per_sample else 'apply_block'} on every row)")
    print("field limits: " + _limit_counts(cases, refs))
    flags: dict[int, int] = {}
    bad_host = bad_pre = 0
    rng = np.random.default_rng(11)
    t0 = time.perf_counter()
    for (fx, names, b, t, c), (q, s) in zip(cases, refs, strict=True):
        rc, table = lib.load(cb.image_of(fx, names))
        assert rc == 0
        out, st = lib.apply_block(table, b, t, c)
        bad_host += int(np.count_nonzero((out != q).any(axis=1) | (st != s)))
        for r in range(b.shape[0]):
            o, s1 = lib.apply(table, b[r], int(t[r]), c[r])
            bad_host += int(o != tuple(int(x) for x in q[r]) or s1 != s[r])
        rc, storage = lib.precompute(table, *cb.precomputed_range(rng, t))
        assert rc == 0
        out, st = lib.apply_block(table, b, t, c)
        bad_pre += int(np.count_nonzero((out != q).any(axis=1) | (st != s)))
        del storage
        for v, k in zip(*np.unique(s, return_counts=True), strict=True):
            flags[int(v)] = flags.get(int(v), 0) + int(k)
    print(f"host (gcc -O2, ctypes): {n_rows} samples, {bad_host} differ (block and per-sample calls), {bad_pre} differ "
          f"with precomputed terms (block) [{time.perf_counter() - t0:.1f} s]")
    print("status bits over all samples: " + ", ".join(f"{k}: {v}" for k, v in sorted(flags.items())))
    if cb.tool(cb.ARM_CC) is None or cb.tool(cb.QEMU_ARM) is None:
        print("ARM: skipped (gcc-arm-linux-gnueabihf or qemu-user not installed)")
        return
    exe = cb.build_harness(build, "harness_arm", cc=cb.ARM_CC, extra=("-static",))
    t0 = time.perf_counter()
    for mode in (("check",), ("check", "pre")):
        bad_arm = bad_block = 0
        for i in range(0, len(cases), 32):
            part = cases[i:i + 32]
            recs = [cb.Record(cb.image_of(fx, names), b, t, c) for fx, names, b, t, c in part]
            for (rc, out, st, differ), (q, s) in zip(cb.run_harness([cb.QEMU_ARM, str(exe)], recs, mode=mode),
                                                     refs[i:i + 32], strict=True):
                assert rc == 0
                bad_arm += int(np.count_nonzero((out != q).any(axis=1) | (st != s)))
                bad_block += differ
        print(f"32-bit ARM (arm-linux-gnueabihf-gcc -O2, qemu-arm{', precomputed terms' if len(mode) > 1 else ''}): "
              f"{n_rows} samples, {bad_arm} differ from Python, {bad_block} block-path samples differ from the "
              f"per-sample path [{time.perf_counter() - t0:.1f} s]")


def _limit_counts(cases, refs) -> str:
    """How the cases meet their field limits: tables with per-axis and magnitude limits, samples whose whole-nT
    output is on its axis' limit or 1 nT past it (and of those, outputs on a half nT), whose magnitude is on its
    limit or past it by less than 1 nT, and saturated outputs."""
    k = dict.fromkeys(("axes", "norm", "on", "past", "half", "norm_on", "norm_past", "saturated"), 0)
    for (fx, *_), (q, _s) in zip(cases, refs, strict=True):
        nt, lim = cb.whole_nT(q), np.array(fx.axis_limits_nT, np.int64)
        k["axes"] += fx.field_limits_nT is not None
        on, past = nt == lim, nt == lim + 1
        k["on"] += int(np.count_nonzero(on.any(axis=1)))
        k["past"] += int(np.count_nonzero(past.any(axis=1)))
        k["half"] += int(np.count_nonzero(((on | past) & (np.abs(q) % 256 == 128)).any(axis=1)))
        k["saturated"] += int(np.count_nonzero(((q == fp.INT32_MAX) | (q == fp.INT32_MIN)).any(axis=1)))
        if fx.field_norm_nT is not None:
            k["norm"] += 1
            ss, n2 = (nt ** 2).sum(axis=1), fx.field_norm_nT ** 2
            k["norm_on"] += int(np.count_nonzero(ss == n2))
            k["norm_past"] += int(np.count_nonzero((ss > n2) & (ss < (fx.field_norm_nT + 1) ** 2)))
    return (f"{k['axes']} tables with per-axis limits, {k['norm']} with a magnitude limit; samples with an output on "
            f"its axis limit {k['on']}, 1 nT past it {k['past']} ({k['half']} of these on a half nT); magnitude on "
            f"its limit {k['norm_on']}, past it by less than 1 nT {k['norm_past']}; saturated outputs "
            f"{k['saturated']}")


#: Temperature patterns of the speed part: (label, how the temperature of sample r is drawn).
PATTERNS = ("steady: a +-15 degC swing over the block (a new value every ~170 samples)",
            "slow: a random walk of 0.01 degC steps, one every 4 samples (a flight thermistor)",
            "noisy: the +-15 degC swing with +-0.02 degC noise on every sample",
            "random: a new temperature every sample, -40..85 degC (worst case)")


def _stream(n: int, pattern: int, rng: np.random.Generator):
    """A sensor stream: |B| <= 100 uT, one current, the temperature by ``pattern`` (index into PATTERNS); the table
    has per-axis and magnitude limits (as a table fitted with a posterior has)."""
    fx, names = cb.random_fixed(rng, realistic=True)
    while len(fx.D) != 1:
        fx, names = cb.random_fixed(rng, realistic=True)
    f = fx.field_limit_nT
    fx = dataclasses.replace(fx, field_limits_nT=tuple(int(x) for x in np.round(f * rng.uniform(0.7, 1.0, 3))),
                             field_norm_nT=int(1.3 * f))
    b = rng.integers(-100_000, 100_001, (n, 3)).astype(np.int32)
    swing = np.round(fx.t0_cdeg + 1500 * np.sin(2 * np.pi * np.arange(n) / n)).astype(np.int64)
    if pattern == 0:
        t = swing
    elif pattern == 1:
        t = fx.t0_cdeg + np.cumsum(np.where(np.arange(n) % 4 == 0, rng.choice([-1, 1], n), 0))
    elif pattern == 2:
        t = swing + rng.integers(-2, 3, n)
    else:
        t = rng.integers(-4000, 8501, n)
    c = rng.integers(-2000, 2001, (n, 1)).astype(np.int32)
    return fx, names, b, np.clip(t, -4000, 8500).astype(np.int32), c


def _best_cpu(repeat: int, fn, *a) -> float:
    """Best-of-``repeat`` CPU seconds (``time.process_time``) of ``fn(*a)``."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.process_time()
        fn(*a)
        best = min(best, time.process_time() - t0)
    return best


#: The host builds timed: flags, what they are, and whether the table gets precomputed terms for PRECOMPUTED_CDEG.
HOST_BUILDS = (("-O2 -DMAGSTACK_CAL_COMPACT", "gcc -O2 -DMAGSTACK_CAL_COMPACT", False),
               ("-O2", "gcc -O2 (generic x86-64)", False),
               ("-O2", "gcc -O2 (generic x86-64), terms precomputed", True),
               ("-O3 -march=native", "gcc -O3 -march=native", False),
               ("-O3 -march=native", "gcc -O3 -march=native, terms precomputed", True),
               ("-O3 -march=native -DMAGSTACK_CAL_VECTOR", "gcc -O3 -march=native -DMAGSTACK_CAL_VECTOR", False))
#: The temperatures (centi-degC) given precomputed terms (``magstack_cal_precompute``): the streams' -40..85 degC.
PRECOMPUTED_CDEG = (-4000, 8500)


def speed(args, build: Path) -> None:
    """CPU time (``time.process_time``, best of ``--repeat``) of each applier on the same block in this process."""
    libs, built = [], {}
    for flags, label, pre in HOST_BUILDS:
        if flags not in built:
            sub = build / flags.replace(" ", "").replace("=", "").replace("-", "_")
            sub.mkdir(exist_ok=True)
            built[flags] = cb.CApplier(cb.compile_c("gcc", [*flags.split(), "-fPIC", "-shared", str(cb.SOURCE)],
                                                    sub / "libmagstack_cal.so"))
        libs.append((label, built[flags], pre))
    rng = np.random.default_rng(7)
    n = args.block
    print(f"load average {os.getloadavg()[0]:.1f}; block {n} samples; CPU time, best of {args.repeat}; precomputed "
          f"terms: {PRECOMPUTED_CDEG[0] / 100:g}..{PRECOMPUTED_CDEG[1] / 100:g} degC "
          f"({(PRECOMPUTED_CDEG[1] - PRECOMPUTED_CDEG[0] + 1) * cb.TERMS_BYTES / 1e6:.1f} MB)")
    arm = None
    if cb.tool(cb.ARM_CC) and cb.tool(cb.QEMU_ARM):
        arm = cb.build_harness(build, "harness_arm_bench", cc=cb.ARM_CC, extra=("-static",))
    summary = []
    for p, label in enumerate(PATTERNS):
        fx, names, b, t, c = _stream(n, p, rng)
        raw = cb.image_of(fx, names)
        b64, t64, c64 = b.astype(np.int64), t.astype(np.int64), c.astype(np.int64)
        q, s = fx.apply_block(b64, t64, c64)
        out, st = np.empty((n, 3), np.int32), np.empty(n, np.uint8)

        py = _best_cpu(args.repeat, fx.apply_block, b64, t64, c64)
        print(f"{label} ({len(np.unique(t))} distinct temperatures): Python apply_block {py / n * 1e9:.1f} ns per "
              f"sample ({n / py / 1e6:.1f} M samples/s)")
        ratios = []
        for name, lib, pre in libs:
            rc, table = lib.load(raw)
            assert rc == 0
            storage = None
            if pre:
                rc, storage = lib.precompute(table, *PRECOMPUTED_CDEG)
                assert rc == 0
            lib.apply_block_into(table, b, t, c, out, st)
            assert np.array_equal(out, q) and np.array_equal(st, s)
            ct = _best_cpu(args.repeat, lib.apply_block_into, table, b, t, c, out, st)
            del storage
            print(f"  C {name}: {ct / n * 1e9:.2f} ns per sample ({n / ct / 1e6:.0f} M samples/s), "
                  f"{py / ct:.1f}x Python")
            ratios.append(py / ct)
        summary.append((label.split(":")[0], ratios))
        if arm is not None:
            m = min(n, 200_000)
            rec = cb.Record(raw, b[:m], t[:m], np.pad(c[:m], ((0, 0), (0, 3))))
            ns = min(cb.run_harness([cb.QEMU_ARM, str(arm)], [rec], mode=("bench", "3"))[0][1]
                     for _ in range(args.repeat))
            print(f"  C on 32-bit ARM (arm-linux-gnueabihf-gcc -O2) emulated by qemu-arm on this host: "
                  f"{ns / (3 * m):.1f} ns per sample")
    print("ratio to Python per pattern (" + "; ".join(label for label, _, _ in libs) + "):")
    for pattern, ratios in summary:
        print(f"  {pattern}: " + ", ".join(f"{r:.1f}x" for r in ratios))


def size(args, build: Path) -> None:
    print(f"table image: {cal_image.SIZE} bytes (format version {cal_image.VERSION})")
    rows = [("host x86-64, gcc -O2", "gcc", "size", ["-O2"]),
            ("host x86-64, gcc -O2 -DMAGSTACK_CAL_COMPACT", "gcc", "size", ["-O2", "-DMAGSTACK_CAL_COMPACT"]),
            ("32-bit ARM Linux, arm-linux-gnueabihf-gcc -O2", cb.ARM_CC, "arm-linux-gnueabihf-size", ["-O2"]),
            ("Cortex-M4, arm-none-eabi-gcc -Os -mthumb", cb.M4_CC, "arm-none-eabi-size",
             ["-Os", "-mcpu=cortex-m4", "-mthumb"]),
            ("Cortex-M4, arm-none-eabi-gcc -O2 -mthumb", cb.M4_CC, "arm-none-eabi-size",
             ["-O2", "-mcpu=cortex-m4", "-mthumb"]),
            ("Cortex-M4, arm-none-eabi-gcc -Os -mthumb -DMAGSTACK_CAL_COMPACT", cb.M4_CC, "arm-none-eabi-size",
             ["-Os", "-mcpu=cortex-m4", "-mthumb", "-DMAGSTACK_CAL_COMPACT"])]
    for label, cc, sz, flags in rows:
        if cb.tool(cc) is None or cb.tool(sz) is None:
            print(f"{label}: skipped ({cc} not installed)")
            continue
        obj = cb.compile_c(cc, [*flags, "-c", str(cb.SOURCE)], build / f"{cc}{''.join(flags).replace('=', '')}.o")
        text, data, bss = subprocess.run([sz, str(obj)], capture_output=True, text=True,
                                         check=True).stdout.splitlines()[1].split()[:3]
        undef = subprocess.run([sz.replace("size", "nm"), "-u", str(obj)], capture_output=True, text=True,
                               check=True).stdout.split()
        print(f"{label}: text {text} B, data {data} B, bss {bss} B; external symbols: "
              f"{', '.join(u for u in undef if u != 'U') or 'none'}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--part", choices=("equality", "speed", "size", "all"), default="all")
    ap.add_argument("--tables", type=int, default=256)
    ap.add_argument("--samples", type=int, default=4096, help="random rows per table (plus up to 12 edge rows)")
    ap.add_argument("--kernel-tables", type=int, default=128,
                    help="further tables with 32 whole chunks of 32 samples for the block path's kernels")
    ap.add_argument("--no-per-sample", action="store_true", help="Python reference by apply_block only")
    ap.add_argument("--block", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    if cb.tool("gcc") is None:
        sys.exit("gcc is needed")
    gcc = subprocess.run(["gcc", "-dumpfullversion"], capture_output=True, text=True).stdout.strip()
    print(f"gcc {gcc}; MAX_CURRENTS {fp.MAX_CURRENTS}")
    with tempfile.TemporaryDirectory(prefix="magstack-c-") as tmp:
        build = Path(tmp)
        for part in ("equality", "speed", "size"):
            if args.part in (part, "all"):
                print(f"== {part}")
                globals()[part](args, build)


if __name__ == "__main__":
    main()
