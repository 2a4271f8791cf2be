"""Driver read path on the simulated I2C bench: reads per second (wall clock) per chip.

Baseline, measured in the same process: one raw 6-byte register-block transfer on the same
simulated bus (``SimI2CBus.transfer``). Each driver read is a full ``Magnetometer.read()``:
data-ready polling, data block, overflow check (LIS3MDL: INT_SRC), temperature, decoding,
in virtual time. Two sensed-value sources: ``ideal`` (truth passed through: the cost of driver,
bus and register model alone) and ``preset-model`` (``ErrorModel(preset(chip))`` from
:mod:`magstack.sim.error_model`, one ``sense()`` per conversion).

Run: ``python benchmarks/bench_i2c_read.py [--seconds S]``.
"""
from __future__ import annotations

import argparse
import time

from magstack.drivers.bus.i2c import I2CRead, I2CWrite
from magstack.drivers.registry import open_chip
from magstack.sim.i2c_bench import CHIPS, default_bench
from magstack.sim.i2c_register_model import IdealSensor

CASES = (("lis3mdl", {"odr_hz": 1000.0}), ("lis3mdl", {"odr_hz": 80.0}),
         ("hmc5983", {"odr_hz": 220.0}), ("lsm303dlhc", {"odr_hz": 220.0}))


def _rate(fn, seconds: float) -> tuple[float, int]:
    n = 0
    t0 = time.perf_counter()
    while True:
        for _ in range(50):
            fn()
        n += 50
        dt = time.perf_counter() - t0
        if dt >= seconds:
            return n / dt, n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=1.0, help="measuring time per case (s)")
    args = ap.parse_args(argv)

    bench = default_bench()
    bus = bench.bus_for("lis3mdl")
    addr = bench.address("lis3mdl")
    msgs = [I2CWrite(bytes([0x28 | 0x80])), I2CRead(6)]
    base, _ = _rate(lambda: bus.transfer(addr, msgs), args.seconds)
    print(f"baseline raw 6-byte transfer on SimI2CBus: {base:12.0f} transfers/s")
    print(f"{'chip':<11} {'odr_hz':>7} {'sensor':<13} {'reads/s':>9} {'x odr':>7} {'/ baseline':>10} "
          f"{'transfers/read':>15}")
    for chip, cfg in CASES:
        for label, sensors in (("ideal", {c: IdealSensor() for c in CHIPS}), ("preset-model", None)):
            b = default_bench(sensors=sensors)
            # a noise-free static field repeats bit-identical samples: stuck-data check off there
            stuck = {"stuck_limit": None} if label == "ideal" else {}
            mag = open_chip(chip, "sim", b.clock, bench=b, **cfg, **stuck)
            cbus = b.bus_for(chip)
            for _ in range(200):          # warm-up (lazy imports, first conversions)
                mag.read()
            n0 = cbus.transfer_count
            rate, n = _rate(mag.read, args.seconds)
            per_read = (cbus.transfer_count - n0) / n
            print(f"{chip:<11} {cfg['odr_hz']:7g} {label:<13} {rate:9.0f} {rate / cfg['odr_hz']:7.1f} "
                  f"{rate / base:10.3f} {per_read:15.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
