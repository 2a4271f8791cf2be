"""Flight application: CPU time per cycle per channel, and the share of each rate group's period it uses.

For each channel of the example board (HMC1053 through the ADS1248, LIS3MDL, HMC5983, LSM303DLHC),
on simulated buses in virtual time, CPU time (``time.process_time``) of:

* ``read``      - the driver's ``read()`` alone (driver + simulated bus and chip): the baseline;
* ``channel``   - one full channel cycle: read, checks, fixed-point correction, telemetry row
                  (written to a session file in a temporary directory).

``flight overhead`` = channel - read is what the flight application adds per cycle; it runs unchanged
on the Pi. The simulator's share of ``read`` does not exist on hardware (there the bus transfer is I/O
wait, not CPU), so the on-board CPU per cycle is bounded by the channel figure. Pi projection: the
figures times ``--pi-factor`` (default 5: single-core CPython on a Raspberry Pi 4 at 1.5 GHz runs
pure-Python code about 4-6x slower than this x86 host in pyperformance-style comparisons; run this
script on the Pi to replace the assumption with a measurement).

Run: ``python benchmarks/bench_flight.py [--cycles N] [--pi-factor F]``.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from magstack.drivers.clock import VirtualClock
from magstack.drivers.registry import open_chip
from magstack.firmware import cal_table as ct
from magstack.firmware.corrector import TableCorrector
from magstack.firmware.flight.channel import MagChannel
from magstack.firmware.flight.events import EventLog
from magstack.firmware.flight.telemetry import ChannelTelemetry
from magstack.sim.i2c_bench import default_bench
from magstack.sim.truth_source import StaticTruth

#: (chip, driver options, rate-group rate in Hz as in a typical config, the chip's fastest output rate)
CASES = (("hmc1053", {}, 1.0, 2.81), ("lis3mdl", {"odr_hz": 80.0}, 20.0, 1000.0),
         ("hmc5983", {"odr_hz": 75.0}, 20.0, 220.0), ("lsm303dlhc", {"odr_hz": 75.0}, 20.0, 220.0))


def _open(chip, options, clock):
    truth = StaticTruth((20.0, -5.0, 40.0), 25.0)
    if chip == "hmc1053":
        return open_chip(chip, "sim", clock, truth=truth)
    return open_chip(chip, "sim", clock, bench=default_bench(clock, truth), **options)


def _cpu_per_call(fn, n: int) -> float:
    t0 = time.process_time()
    for _ in range(n):
        fn()
    return (time.process_time() - t0) / n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=400, help="cycles per measurement (default 400)")
    ap.add_argument("--pi-factor", type=float, default=5.0, help="assumed Pi / this-host CPU-time ratio")
    args = ap.parse_args(argv)
    print(f"{'channel':<11} {'read us':>9} {'channel us':>10} {'overhead us':>11} {'ratio':>6} "
          f"{'group Hz':>8} {'% period':>8} {'Pi % period':>11} {'chip max Hz':>11}")
    with tempfile.TemporaryDirectory() as tmp:
        table = ct.CalTable(device_id="d", terms=("gain_matrix", "temperature_gain", "offset", "temperature_offset"),
                            S=np.eye(3) * 1.02, K_S=np.full((3, 3), 1e-4), O=[0.3, -0.1, 0.2], K_O=[0.01, 0, 0],
                            validity_temp_c=(-20.0, 60.0), validity_field_uT=100.0)
        store = ct.CalTableStore("d")
        store.load_and_activate(ct.save_table(table, Path(tmp) / "cal.json"))
        for chip, options, group_hz, chip_max_hz in CASES:
            n = max(20, args.cycles // (20 if chip == "hmc1053" else 1))
            clock = VirtualClock()
            mag = _open(chip, options, clock)
            read_s = _cpu_per_call(mag.read, n)
            tlm = ChannelTelemetry(tmp, chip, run_id=1, metadata={}, block_rows=50)
            ch = MagChannel(chip, mag, TableCorrector(store), EventLog(), sink=tlm)
            chan_s = _cpu_per_call(lambda c=ch, k=clock: c.run(k.monotonic_s()), n)
            tlm.close()
            share = chan_s * group_hz * 100
            print(f"{chip:<11} {read_s * 1e6:9.1f} {chan_s * 1e6:10.1f} {(chan_s - read_s) * 1e6:11.1f} "
                  f"{chan_s / read_s:6.2f} {group_hz:8.1f} {share:8.3f} {share * args.pi_factor:11.3f} "
                  f"{chip_max_hz:11.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
