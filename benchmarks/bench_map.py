"""What the MAP estimator costs inside ``fit`` and ``refit``, measured in the same process.

``python benchmarks/bench_map.py [--rows 1000000] [--refit-hours 24]``

* ``fit`` on N synthetic Eq. 3 rows (no held-out folds, the 1e6-row case of the issue): total process
  CPU time of the fit, and the CPU time spent inside ``estimator.map_solve`` (every call: sigma iteration,
  the tempco re-centring, the autocorrelation pass) -> the share the MAP solve adds. The baseline is the
  rest of the same fit (design matrix, QR accumulation, residuals, noise floor): the work the previous
  least-squares solve needed too.
* ``refit`` on one simulated day of orbit telemetry at 1 Hz (``magstack simulate --program
  orbit_tumbling``): the same split for the whole refit (reading, IGRF, frames, passes).

CPU times come from ``time.process_time`` (both cores count); BLAS threading as the machine has it.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from magstack.firmware.calibration import FitOptions, estimator, fit
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.sim.synthetic_calibration import make_data, random_theta


class _Timed:
    """Wraps ``estimator.map_solve`` (and the names that imported it) to add up its CPU time."""

    def __init__(self) -> None:
        self.cpu_s = 0.0
        self.calls = 0
        self._orig = estimator.map_solve

    def __call__(self, *a, **k):
        t0 = time.process_time()
        try:
            return self._orig(*a, **k)
        finally:
            self.cpu_s += time.process_time() - t0
            self.calls += 1

    def __enter__(self):
        import importlib
        self._mods = [estimator, importlib.import_module("magstack.firmware.calibration.fit")]
        for m in self._mods:
            m.map_solve = self
        return self

    def __exit__(self, *exc):
        for m in self._mods:
            m.map_solve = self._orig


def bench_fit(rows: int) -> None:
    rng = np.random.default_rng(0)
    m = CalModel(resolve_terms("eq3"), t_ref_s=1.6e9)
    th = random_theta(m, rng)
    d = make_data(m, th, rows, rng, noise_uT=0.02)
    with _Timed() as t:
        c0 = time.process_time()
        w0 = time.perf_counter()
        fit(d, options=FitOptions(holdout=False, chip="hmc1053"))
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    rest = cpu - t.cpu_s
    print(f"fit, {rows} rows eq3 (no held-out): {cpu:.2f} s CPU ({wall:.2f} s wall); map_solve {t.calls} calls "
          f"{t.cpu_s:.3f} s CPU = {100 * t.cpu_s / rest:.1f} % of the rest of the fit ({rest:.2f} s)")


def bench_refit(hours: float) -> None:
    from magstack.cli.main import main
    from magstack.firmware.calibration.refit import refit
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "day.csv"
        seconds = int(hours * 3600)
        rc = main(["simulate", "-q", "--program", "orbit_tumbling", "--seconds", str(seconds), "--rate-hz", "1",
                   "--seed", "3", "--t0", "1780272000", "--out", str(path), "--effects",
                   "interference,misalignment,gain,temperature_gain,offset,temperature_offset,noise"])
        assert rc == 0
        with _Timed() as t:
            c0 = time.process_time()
            w0 = time.perf_counter()
            r = refit([path])
            cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        rest = cpu - t.cpu_s
        print(f"refit, {seconds} s of 1 Hz telemetry ({r.rows} rows, {r.passes} passes): {cpu:.2f} s CPU "
              f"({wall:.2f} s wall); map_solve {t.calls} calls {t.cpu_s:.3f} s CPU = "
              f"{100 * t.cpu_s / rest:.1f} % of the rest of the refit ({rest:.2f} s)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--refit-hours", type=float, default=24.0)
    a = ap.parse_args()
    bench_fit(a.rows)
    bench_refit(a.refit_hours)


if __name__ == "__main__":
    main()
