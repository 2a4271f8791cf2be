"""Footprint of the flight application: import time and resident memory of ``magstack run``.

Runs ``python -X importtime -m magstack.cli.main run --config CONFIG --sim --duration S --out DIR -q`` in a
fresh interpreter ``--runs`` times (each into a new telemetry directory) and reports the medians of

* import time: the sum of the cumulative times of the top-level imports ``-X importtime`` logs (every module
  the run loads, also those imported on first use), s;
* the process's CPU (user + system) and wall time, s;
* its peak resident set (``ru_maxrss`` from ``os.wait4``), MiB;

beside the same figures of a bare interpreter (``python -c pass``) and of ``python -c "import numpy"``, measured
the same way in the same run (ratios say what magstack adds). Under qemu user-mode emulation (the emulated Pi of
hil/pi-emulated-check.sh) the resident set is the emulator's process and includes its translated-code cache.

Run: ``python benchmarks/bench_flight_footprint.py --config flight.toml [--duration 60] [--runs 3] [--json]``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_IMPORT_LINE = re.compile(r"^import time:\s+(\d+)\s+\|\s+(\d+)\s+\|( *)(\S+)")


def import_seconds(stderr: str) -> tuple[float, int]:
    """(Sum of the top-level imports' cumulative times in s, modules imported) from ``-X importtime`` output."""
    total_us, modules = 0, 0
    for line in stderr.splitlines():
        m = _IMPORT_LINE.match(line)
        if m:
            modules += 1
            if len(m.group(3)) == 1:      # one space before the name: a top-level import
                total_us += int(m.group(2))
    return total_us / 1e6, modules


def one_run(args: list[str]) -> dict:
    """CPU, wall, peak RSS and import time of one ``python -X importtime ARGS`` run."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-X", "importtime", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    if code not in (0, 1):              # 1: a simulated run that ended degraded (no table) still ran whole
        raise SystemExit(f"python {' '.join(args)} exited {code}: {err.strip().splitlines()[-1:]}")
    imp, modules = import_seconds(err)
    return {"import_s": imp, "modules": modules, "cpu_s": usage.ru_utime + usage.ru_stime, "wall_s": wall,
            "max_rss_MiB": usage.ru_maxrss / 1024.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True, help="flight configuration (magstack run --example-config)")
    ap.add_argument("--duration", type=float, default=60.0, help="virtual seconds of the simulated run")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json", action="store_true", help="one JSON object on stdout instead of the table")
    a = ap.parse_args()
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        cases = {
            "python -c pass (baseline)": lambda i: ["-c", "pass"],
            "python -c 'import numpy'": lambda i: ["-c", "import numpy"],
            f"magstack run --sim --duration {a.duration:g}": lambda i: [
                "-m", "magstack.cli.main", "run", "--config", str(Path(a.config).resolve()), "--sim",
                "--duration", f"{a.duration:g}", "--out", str(Path(tmp) / f"tlm{i}"), "-q"],
        }
        for name, args in cases.items():
            runs = [one_run(args(i)) for i in range(a.runs)]
            results[name] = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    info = {"machine": platform.machine(), "python": platform.python_version(), "runs": a.runs, "cases": results}
    if a.json:
        print(json.dumps(info))
        return
    print(f"{info['machine']}, Python {info['python']}, median of {a.runs} runs")
    print(f"{'case':<34} {'import s':>9} {'modules':>8} {'CPU s':>8} {'wall s':>8} {'peak RSS MiB':>13}")
    for name, r in results.items():
        print(f"{name:<34} {r['import_s']:>9.3f} {r['modules']:>8.0f} {r['cpu_s']:>8.3f} {r['wall_s']:>8.3f} "
              f"{r['max_rss_MiB']:>13.1f}")


if __name__ == "__main__":
    main()
