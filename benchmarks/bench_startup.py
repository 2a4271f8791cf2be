"""Start-up time of the ``magstack`` command (target: under 0.5 s for ``--help`` and
``run --example-config``).

Each case runs ``python -m magstack.cli.main ARGS`` in a fresh interpreter ``--runs`` times and
takes the child's own CPU clock (user + system seconds from ``os.wait4``: what the process itself
spent, robust against other load on the machine), alongside its wall time; the figure is the
median. The baseline, measured the same way in the same run, is a bare interpreter
(``python -c pass``): ``ratio`` = case / baseline says how much the command adds to Python's own start.

Run: ``python benchmarks/bench_startup.py [--runs N]``.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

CASES = {
    "python -c pass (baseline)": ["-c", "pass"],
    "magstack --help": ["-m", "magstack.cli.main", "--help"],
    "magstack run --example-config": ["-m", "magstack.cli.main", "run", "--example-config"],
    "magstack fit --help": ["-m", "magstack.cli.main", "fit", "--help"],
    # the cost of a parser built from every command module (what `--help` avoids by loading on demand)
    "every command module (old --help)": ["-c", "from magstack.cli.main import ALL, build_parser; "
                                                "build_parser(ALL).format_help()"],
}


def one_run(args: list[str]) -> tuple[float, float]:
    """(CPU s of the child, wall s) of one ``python ARGS`` run."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"python {' '.join(args)} exited {proc.returncode}")
    return usage.ru_utime + usage.ru_stime, wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=7)
    runs = ap.parse_args().runs
    results = {}
    for name, args in CASES.items():
        one_run(args)   # warm the file cache
        cpu, wall = zip(*(one_run(args) for _ in range(runs)), strict=True)
        results[name] = (statistics.median(cpu), statistics.median(wall))
    base = results["python -c pass (baseline)"][0]
    print(f"{'case':<34} {'CPU s (median)':>15} {'wall s (median)':>16} {'ratio':>7}   ({runs} runs each)")
    for name, (cpu, wall) in results.items():
        print(f"{name:<34} {cpu:>15.3f} {wall:>16.3f} {cpu / base:>7.1f}")


if __name__ == "__main__":
    main()
