"""How much of the packet stream a kill -9 loses: real-time ``magstack run`` on simulated sensors, killed at a
random moment, the packet file decoded afterwards.

    python benchmarks/bench_kill.py [--kills 20] [--seed 0] [--dir DIR] [--json]

Each kill: a fresh telemetry directory, ``python -m magstack run --config flight.toml --sim`` (the shipped
example on simulated buses: hmc1053 at 1 Hz, lis3mdl at 10 Hz, real time), started, left to run until its
packet file exists plus a random 0.5..3 s, then SIGKILL. The loss is the time between the kill (wall clock,
the same system clock the run stamps its records with) and the last channel packet of the 10 Hz channel
in the file: what was recorded before the kill but is not in the file, plus up to one 0.1 s period
that had no sample yet. Also counted: channel packets in the file, a cut packet at its end (``truncated``).
Prints one line per kill and the median / max loss; ``--json``: one JSON object instead.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from magstack.ground.tm_decode import DecodeReport, iter_packets  # noqa: E402


def _config(d: Path) -> Path:
    from magstack.firmware.flight.config import example_config_text

    text = (example_config_text().replace("spi0.0,start=6,reset=13,drdy=19,sr=5", "sim")
            .replace('bus = "1"', 'bus = "sim"').replace('table = "tables/hmc1053.json"', ""))
    p = d / "flight.toml"
    p.write_text(text)
    return p


def one_kill(d: Path, delay_s: float, timeout_s: float = 60.0) -> dict:
    """Start a run in ``d``, SIGKILL it ``delay_s`` after its packet file appeared; what the file holds."""
    cfg = _config(d)
    tlm = d / "tlm"
    proc = subprocess.Popen([sys.executable, "-m", "magstack", "run", "--config", str(cfg), "--sim", "--out",
                             str(tlm), "-q"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=ROOT)
    pk = tlm / "packets-0001.bin"
    t_end = time.monotonic() + timeout_s
    try:
        while not (pk.exists() and pk.stat().st_size > 0):
            if time.monotonic() > t_end or proc.poll() is not None:
                err = proc.stderr.read().decode()[-500:] if proc.stderr else ""
                raise RuntimeError(f"the run did not start: {err}")
            time.sleep(0.05)
        time.sleep(delay_s)
        t_kill = time.time()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
    rep = DecodeReport()
    last: dict[int, float] = {}
    n = 0
    for p in iter_packets(pk.read_bytes(), rep):
        if p.packet.name == "channel":
            n += 1
            last[p.apid] = max(last.get(p.apid, 0.0), p.t_s)
    fast = last.get(0x101)                   # lis3mdl, the second sensor of the example: 10 Hz
    return {"delay_s": round(delay_s, 3), "channel_packets": n, "truncated": rep.truncated,
            "bad_packets": rep.bad_packets, "loss_s": None if fast is None else round(t_kill - fast, 4)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dir", type=Path, default=None, help="where the runs write (default: a temporary directory)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    runs = []
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for k in range(args.kills):
            d = Path(tmp) / f"kill{k:03d}"
            d.mkdir()
            r = one_kill(d, float(rng.uniform(0.5, 3.0)))
            runs.append(r)
            if not args.json:
                print(f"kill {k + 1:3d}: after {r['delay_s']:.2f} s, {r['channel_packets']} channel packets in the "
                      f"file, last 10 Hz packet {r['loss_s']} s before the kill, truncated {r['truncated']}")
    losses = [r["loss_s"] if r["loss_s"] is not None else float("inf") for r in runs]
    res = {"kills": len(runs), "median_loss_s": statistics.median(losses), "max_loss_s": max(losses),
           "kills_without_channel_packets": sum(r["channel_packets"] == 0 for r in runs),
           "truncated_files": sum(r["truncated"] > 0 for r in runs), "runs": runs}
    if args.json:
        print(json.dumps(res))
    else:
        print(f"{res['kills']} kills: loss median {res['median_loss_s']:.3f} s, max {res['max_loss_s']:.3f} s; "
              f"{res['kills_without_channel_packets']} files without a channel packet, "
              f"{res['truncated_files']} ending in a cut packet")
    return 0


if __name__ == "__main__":
    sys.exit(main())
