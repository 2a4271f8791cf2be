"""Wall and CPU time of ``magstack demo`` (the default run: 1200 s + 600 s simulated sessions, eight steps and
the HTML report), as a child process in an empty directory.

Baseline in the same run: ``magstack --help`` (the interpreter and the command's start-up), so ``ratio`` says how
many start-ups the demo costs. Run: ``python benchmarks/bench_demo.py [--runs N] [--seconds S]``.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile

from _child import run_child


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=None, help="the demo's --seconds (default: its default)")
    a = ap.parse_args()
    base = [run_child([sys.executable, "-m", "magstack", "--help"])[0] for _ in range(3)]
    rows = []
    for _ in range(a.runs):
        with tempfile.TemporaryDirectory() as d:
            extra = [] if a.seconds is None else ["--seconds", str(a.seconds)]
            rows.append(run_child([sys.executable, "-m", "magstack", "demo", "--out", d, "-q", *extra], cwd=d))
    cpu, wall = zip(*rows, strict=True)
    print(f"magstack demo{'' if a.seconds is None else f' --seconds {a.seconds:g}'}: {a.runs} run(s)")
    print(f"  wall s  {' '.join(f'{w:.1f}' for w in wall)}  (median {statistics.median(wall):.1f})")
    print(f"  CPU s   {' '.join(f'{c:.1f}' for c in cpu)}  (median {statistics.median(cpu):.1f})")
    b = statistics.median(base)
    print(f"  baseline magstack --help: {b:.2f} s CPU; demo / baseline {statistics.median(cpu) / b:.0f}x")


if __name__ == "__main__":
    main()
