"""Benchmark: housekeeping-current interpolation over one day of telemetry.

Run: ``python benchmarks/bench_housekeeping.py TELEMETRY.csv [--repeat 25]`` (a day at 1 Hz from
``magstack simulate --program orbit_tumbling --seconds 86399 --rate-hz 1``; bench_refit.py writes one).
The file is read once into blocks (as refit reads it); then, best of ``--repeat`` in CPU time:

* ``housekeeping.interpolate_currents`` over those blocks, every current column (what refit runs);
* baseline: ``np.interp`` of each current column over the day's rows from its finite samples
  (arrays already concatenated; no session or gap rule).
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from magstack.data.telemetry import iter_telemetry, read_header
from magstack.firmware.calibration.housekeeping import interpolate_currents

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import best_cpu  # noqa: E402  (sibling module; scripts run from benchmarks/)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("telemetry")
    ap.add_argument("--repeat", type=int, default=25)
    args = ap.parse_args()
    blocks = list(iter_telemetry(args.telemetry))
    names = read_header(args.telemetry).currents
    t = np.concatenate([b.t_s for b in blocks])
    cols = {k: np.concatenate([b.currents_A[k] for b in blocks]) for k in names}
    print(f"{t.size} rows in {len(blocks)} blocks, currents {names} (samples: "
          f"{', '.join(f'{k} {int(np.isfinite(v).sum())}' for k, v in cols.items())}); "
          f"load average {os.getloadavg()[0]:.1f}")

    def ours():
        return [b.currents_A for b in interpolate_currents(iter(blocks), names)]

    def baseline():
        out = {}
        for k, x in cols.items():
            ok = np.isfinite(x)
            out[k] = np.interp(t, t[ok], x[ok])
        return out

    (_, c_ours), (_, c_base) = best_cpu(ours, args.repeat), best_cpu(baseline, args.repeat)
    got = {k: np.concatenate([c[k] for c in ours()]) for k in names}
    ref = baseline()
    both = {k: np.isfinite(got[k]) for k in names}
    diff = max(float(np.abs(got[k][both[k]] - ref[k][both[k]]).max(initial=0.0)) for k in names)
    print(f"interpolate_currents {c_ours * 1e3:.1f} ms | np.interp baseline {c_base * 1e3:.1f} ms | "
          f"ratio {c_ours / c_base:.2f}x | max |difference| where both have a value {diff:.2e} A; "
          f"rows without a value: {', '.join(f'{k} {int((~both[k]).sum())}' for k in names)}")


if __name__ == "__main__":
    main()
