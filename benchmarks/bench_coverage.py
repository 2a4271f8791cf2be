"""Coverage of the calibration's accuracy figures on independent benches (docs/calibration-coverage.md).

    python benchmarks/bench_coverage.py [--per-shape 8] [--seed 0] [--shapes wide_sweeps,room,...]
                                        [--out coverage.json] [--keep DIR]

For each bench shape of ``tests/coverage/bench_generator.py`` (default: all seven, 8 benches each) it
writes the bench and its held-out data as session files, runs ``magstack fit`` (defaults) and
``magstack apply --extrapolate`` in-process with the ``magstack`` this interpreter imports, prints one line
per bench and the per-shape table (markdown), and writes every bench's figures and the summary to
``--out`` (JSON). ``--keep DIR`` keeps the session files and tables there.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "coverage"))

import bench_generator as gen  # noqa: E402
import harness  # noqa: E402

from magstack.data.io import to_json  # noqa: E402


def _code_state() -> dict:
    """Where the imported magstack lives and, in a git work tree, its commit and whether it has changes."""
    import magstack
    src = Path(magstack.__file__).resolve().parent
    state = {"magstack": str(src), "version": getattr(magstack, "__version__", None)}
    try:
        git = ["git", "-C", str(src)]
        state["commit"] = subprocess.run(git + ["rev-parse", "HEAD"], capture_output=True, text=True,
                                         check=True).stdout.strip()
        state["dirty"] = bool(subprocess.run(git + ["status", "--porcelain"], capture_output=True, text=True,
                                             check=True).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        pass
    return state


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-shape", type=int, default=8, help="benches per shape (default 8)")
    ap.add_argument("--seed", type=int, default=0, help="base seed (default 0)")
    ap.add_argument("--shapes", default=",".join(gen.SHAPES), help="comma-separated shapes (default: all)")
    ap.add_argument("--out", default="coverage.json", help="JSON report (default coverage.json)")
    ap.add_argument("--keep", default=None, help="keep the session files and tables in this directory")
    a = ap.parse_args(argv)
    shapes = [s for s in a.shapes.split(",") if s]
    unknown = sorted(set(shapes) - set(gen.SHAPES))
    if unknown:
        ap.error(f"unknown shape(s) {unknown}; known: {', '.join(gen.SHAPES)}")
    results = []
    t_all = time.perf_counter()
    for shape in shapes:
        for k in range(a.per_shape):
            t0 = time.perf_counter()
            r = harness.run_bench(shape, k, a.seed, None if a.keep is None else Path(a.keep) / f"{shape}-{k}")
            r["wall_s"] = round(time.perf_counter() - t0, 2)
            results.append(r)
            box = harness._get(r, "in_box", "axis") or [None, None]
            rng = harness._get(r, "in_range", "axis") or [None, None]
            print(f"{shape:15s} {k:2d} fit exit {r['fit_exit']} mode {r.get('mode', '-'):5s} "
                  f"in range {harness._f(rng[0])}/{harness._f(rng[1])} in box {harness._f(box[0])}/"
                  f"{harness._f(box[1])} above bound {harness._f(r.get('box_above_bound_noisy'))} "
                  f"box {r.get('box_temp_c')} degC {r.get('box_field_uT')} uT  {r['wall_s']:.1f} s", flush=True)
    summary = harness.summarise(results)
    modes = {m for s in summary.values() for m in s["modes"]}
    print()
    if "param" in modes:
        print("sd = param: apply wrote no per-axis predictive sd (cal_sigma_{x,y,z}_nT); the sd is the table's "
              "parameter posterior (cal_uncertainty.predictive_sd_uT), compared with the error of the noise-free "
              "sample.")
    if "total" in modes:
        print("sd = total: apply's per-axis predictive sd cal_sigma_{x,y,z}_nT, compared with the error of the "
              "noisy sample.")
    print(f"honest: per axis {harness.HONEST_AXIS[0]:.2f} / {harness.HONEST_AXIS[1]:.2f}; vector (chi-square(3)) "
          f"{harness.HONEST_VECTOR[0]:.2f} / {harness.HONEST_VECTOR[1]:.3f}; in-range and in-box figures are means "
          "over the shape's benches")
    print(harness.table_text(summary))
    doc = {"code": _code_state(), "seed": a.seed, "per_shape": a.per_shape, "shapes": shapes,
           "wall_s": round(time.perf_counter() - t_all, 1), "honest_axis": harness.HONEST_AXIS,
           "honest_vector": harness.HONEST_VECTOR, "summary": summary, "benches": results}
    Path(a.out).write_text(to_json(doc, indent=1) + "\n")
    print(f"\nwrote {a.out} ({len(results)} benches, {doc['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
