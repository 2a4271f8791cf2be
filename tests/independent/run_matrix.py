"""Confusion matrix of ``magstack diagnose`` on independent sessions (docs/diagnosis-independent.md).

    python tests/independent/run_matrix.py --seeds 1 2 3 --strengths 1 0.5 --clean-seeds 10 --out matrix.json

Runs whatever ``magstack`` the interpreter imports. Prints one line per case and the matrix.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from generator import EFFECTS  # noqa: E402
from harness import case  # noqa: E402


def _code_state() -> str:
    """Where the imported magstack lives and, for a git work tree, its HEAD and a hash of its diff."""
    import hashlib
    import subprocess

    import magstack.ground
    root = Path(magstack.ground.__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
        diff = subprocess.run(["git", "-C", str(root), "diff", "HEAD"], capture_output=True, check=True).stdout
        dirty = f", uncommitted diff sha1 {hashlib.sha1(diff).hexdigest()[:12]}" if diff else ", clean tree"
    except (OSError, subprocess.CalledProcessError):
        return str(root)
    return f"{root} at {head[:12]}{dirty}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--effects", nargs="*", default=list(EFFECTS))
    ap.add_argument("--seeds", nargs="*", type=int, default=[1])
    ap.add_argument("--strengths", nargs="*", type=float, default=[1.0])
    ap.add_argument("--clean-seeds", type=int, default=0, help="clean sessions with seeds 100..100+N-1")
    ap.add_argument("--excursion-times", default="even", choices=["even", "random"])
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    print(f"magstack under test: {_code_state()}", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [(e, s, x) for e in a.effects for x in a.strengths for s in a.seeds]
        jobs += [(None, 100 + k, 1.0) for k in range(a.clean_seeds)]
        for e, s, x in jobs:
            t0 = time.perf_counter()
            o = case(Path(tmp), e, s, x, excursion_times=a.excursion_times)
            r = o.row()
            r["seconds"] = round(time.perf_counter() - t0, 2)
            rows.append(r)
            print(f"{r['effect']:20s} seed {s:3d} x{x:<4g} -> {r['verdict']:20s} {r['outcome']:11s} "
                  f"base {r['baseline_rmse_nT']:7.1f} after {r['after_rmse_nT']:7.1f} noise {r['noise_floor_nT']:6.1f} "
                  f"after/noise {r['after_over_noise']:.2f} excess {r['excess_nT']:.1f} runner-up {r['runner_up']} "
                  f"distinguishable {r['distinguishable']} ({r['seconds']} s)", flush=True)
    for x in a.strengths:
        print(f"\nconfusion (strength x{x:g}): true effect -> verdicts")
        for e in a.effects:
            c = Counter(r["verdict"] for r in rows if r["effect"] == e and r["strength"] == x)
            print(f"  {e:20s} {dict(c)}")
    clean = [r for r in rows if r["effect"] == "none"]
    if clean:
        fa = sum(r["outcome"] == "false_alarm" for r in clean)
        print(f"\nclean sessions: {fa}/{len(clean)} false alarms "
              f"({dict(Counter(r['verdict'] for r in clean))})")
    if a.out:
        Path(a.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
