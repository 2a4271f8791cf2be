"""Software in the loop: CPU and wall time of ``magstack run --sim --duration D`` of the example board, as a child
process (its own CPU clock from ``os.wait4``, robust against other load on the machine).

The board is the one ``magstack run --init DIR`` writes (HMC1053 on the ADS1248 at 1 Hz with its bench-fit table,
LIS3MDL at 10 Hz, ``[ccsds]`` packets and telecommands, session files, events), simulated in virtual time along
``--program`` (default ``rotation``; ``orbit_nadir`` etc. fly IGRF along an orbit). Baseline in the same run: the
same command for ``--short`` s of virtual time (default 600), so the per-simulated-second cost of the long run can be
compared with the short one (start-up included in both). Prints CPU s, wall s and the real-time factor
(virtual s / CPU s).

Run: ``python benchmarks/bench_flight_day.py [--duration 86400] [--program rotation] [--short 600]``.
"""
from __future__ import annotations

import argparse
import re
import socket
import sys
import tempfile
from pathlib import Path

from _child import run_child


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=86400.0, help="virtual seconds of the measured run")
    ap.add_argument("--program", default="rotation", help="--sim-program of the run")
    ap.add_argument("--short", type=float, default=600.0, help="virtual seconds of the baseline run")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        run_child([sys.executable, "-m", "magstack", "run", "--init", d])
        cfg = Path(d) / "flight.toml"
        cfg.write_text(re.sub(r'tc_udp = "127\.0\.0\.1:\d+"', f'tc_udp = "127.0.0.1:{_free_port()}"', cfg.read_text()))
        rows = {}
        for name, dur in (("baseline", a.short), ("measured", a.duration)):
            rows[name] = (dur, *run_child([sys.executable, "-m", "magstack", "run", "--config", str(cfg), "--sim",
                                           "--sim-program", a.program, "--duration", f"{dur:g}",
                                           "--out", str(Path(d) / name), "-q"], cwd=d))
    print(f"magstack run --sim --sim-program {a.program} (example board of run --init)")
    print(f"{'run':<9} {'virtual s':>10} {'CPU s':>9} {'wall s':>9} {'x real time (CPU)':>18} "
          f"{'CPU ms per virtual s':>21}")
    for name, (dur, cpu, wall) in rows.items():
        print(f"{name:<9} {dur:>10g} {cpu:>9.1f} {wall:>9.1f} {dur / cpu:>18.0f} {1e3 * cpu / dur:>21.2f}")
    (db, cb, _), (dm, cm, _) = rows["baseline"], rows["measured"]
    print(f"CPU per virtual s, measured / baseline: {(cm / dm) / (cb / db):.2f}")


if __name__ == "__main__":
    main()
