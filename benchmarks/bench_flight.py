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

``--part loop`` (issue 25, "the Pi projection"): the rate groups of a typical board run cycle by cycle
on their virtual clocks for ``--seconds`` of flight time, telemetry written to ``--telemetry-dir``
(default a temporary directory on the working disk; fsync every 50 rows as in flight). Per group,
per cycle: CPU time of the cycle (``thread_time``), wall time (``perf_counter``: CPU plus I/O waits,
i.e. the fsync), and blocking time (virtual time the drivers waited: the HMC1053's conversions; on
hardware that is real time with the CPU free). Reported: median, p99 and worst cycle, the cycles
that wrote a telemetry block (fsync) apart, and a projection to a Pi: CPU figures times
``--pi-factor`` (an assumption, not a measurement) plus the blocking time (a property of the
converters, the same on any computer); the fsync cost of an SD card is not measured here.
"""
from __future__ import annotations

import argparse
import os
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


#: Rate groups of the loop measurement: (name, rate Hz, chips) - the example board's slow group and a
#: fast group with the three I2C chips (their drivers' options as in CASES).
GROUPS = (("slow", 1.0, ("hmc1053",)), ("fast", 20.0, ("lis3mdl", "hmc5983", "lsm303dlhc")))


def _pct(x, q):
    return float(np.percentile(x, q)) if len(x) else float("nan")


def loop(seconds: float, pi_factor: float, telemetry_dir: str | None) -> None:
    """Per-group cycle statistics of the flight loop (see the module docstring, ``--part loop``)."""
    opts = {c[0]: c[1] for c in CASES}
    with tempfile.TemporaryDirectory(dir=telemetry_dir or os.getcwd(), prefix="bench-flight-") as tmp:
        table = ct.CalTable(device_id="d", terms=("gain_matrix", "temperature_gain", "offset", "temperature_offset"),
                            S=np.eye(3) * 1.02, K_S=np.full((3, 3), 1e-4), O=[0.3, -0.1, 0.2], K_O=[0.01, 0, 0],
                            validity_temp_c=(-20.0, 60.0), validity_field_uT=100.0)
        store = ct.CalTableStore("d")
        store.load_and_activate(ct.save_table(table, Path(tmp) / "cal.json"))
        print(f"telemetry in {tmp} (fsync every 50 rows); {seconds:g} s of flight time per group; "
              f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
        print(f"{'group':<6} {'Hz':>4} {'cycles':>6} | {'CPU us p50/p99/max':>22} | {'wall us p50/p99/max':>22} | "
              f"{'fsync cycles wall us p50/max':>29} | {'blocking ms (% period)':>22} | "
              f"{'Pi: CPU p99 x F + blocking, % period':>36}")
        for name, hz, chips in GROUPS:
            clock = VirtualClock()
            chans, sinks = [], []
            for chip in chips:
                tlm = ChannelTelemetry(tmp, chip, run_id=1, metadata={}, block_rows=50)
                chans.append(MagChannel(chip, _open(chip, opts[chip], clock), TableCorrector(store), EventLog(),
                                        sink=tlm))
                sinks.append(tlm)
            n = int(seconds * hz)
            cpu, wall, block, fsync = (np.empty(n) for _ in range(4))
            for k in range(n):
                rows_before = [t.rows for t in sinks]
                v0, c0, w0 = clock.monotonic_s(), time.thread_time(), time.perf_counter()
                for ch in chans:
                    ch.run(clock.monotonic_s())
                cpu[k], wall[k] = time.thread_time() - c0, time.perf_counter() - w0
                block[k] = clock.monotonic_s() - v0
                fsync[k] = any(t.rows // 50 != r // 50 for t, r in zip(sinks, rows_before, strict=True))
                clock.sleep_s(max(0.0, (k + 1) / hz - clock.monotonic_s()))    # to the next slot
            for t in sinks:
                t.close()
            fs = fsync.astype(bool)
            period = 1.0 / hz
            pi = (_pct(cpu, 99) * pi_factor + _pct(block, 99)) / period * 100
            print(f"{name:<6} {hz:4g} {n:6d} | {_pct(cpu, 50) * 1e6:6.0f} {_pct(cpu, 99) * 1e6:7.0f} "
                  f"{cpu.max() * 1e6:7.0f} | {_pct(wall, 50) * 1e6:6.0f} {_pct(wall, 99) * 1e6:7.0f} "
                  f"{wall.max() * 1e6:7.0f} | {fs.sum():5d} x {_pct(wall[fs], 50) * 1e6:7.0f} "
                  f"{wall[fs].max(initial=0) * 1e6:8.0f} | {block.mean() * 1e3:8.1f} "
                  f"({block.mean() / period * 100:4.1f} %) | {pi:8.2f} % (F = {pi_factor:g})")
        fd = os.open(Path(tmp) / "fsync-probe", os.O_WRONLY | os.O_CREAT)
        costs = []
        for _ in range(50):
            os.write(fd, b"x" * 8000)          # one 50-row block is about 8 kB
            c0 = time.perf_counter()
            os.fsync(fd)
            costs.append(time.perf_counter() - c0)
        os.close(fd)
        print(f"fsync of an 8 kB append in {tmp}: median {_pct(costs, 50) * 1e3:.2f} ms, "
              f"p99 {_pct(costs, 99) * 1e3:.2f} ms, worst {max(costs) * 1e3:.2f} ms")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=400, help="cycles per measurement (default 400)")
    ap.add_argument("--pi-factor", type=float, default=5.0, help="assumed Pi / this-host CPU-time ratio")
    ap.add_argument("--part", choices=("channels", "loop"), default="channels")
    ap.add_argument("--seconds", type=float, default=300.0, help="--part loop: flight time per group (s)")
    ap.add_argument("--telemetry-dir", default=None, help="--part loop: where telemetry is written (default: cwd)")
    args = ap.parse_args(argv)
    if args.part == "loop":
        loop(args.seconds, args.pi_factor, args.telemetry_dir)
        return 0
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
