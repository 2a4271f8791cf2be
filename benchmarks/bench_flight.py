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

Run: ``python benchmarks/bench_flight.py [--cycles N] [--pi-factor F] [--part channels|loop|writer]``.

``--part loop`` ("the Pi projection"): the rate groups of a typical board run cycle by cycle
on their virtual clocks for ``--seconds`` of flight time, telemetry written to ``--telemetry-dir``
(default a temporary directory on the working disk; fsync every 50 rows as in flight). Per group,
per cycle: CPU time of the cycle (``thread_time``), wall time (``perf_counter``: CPU plus I/O waits,
i.e. the fsync), and blocking time (virtual time the drivers waited: the HMC1053's conversions; on
hardware that is real time with the CPU free). Reported: median, p99 and worst cycle, the cycles
that wrote a telemetry block (fsync) apart, and a projection to a Pi: CPU figures times
``--pi-factor`` (an assumption, not a measurement) plus the blocking time (a property of the
converters, the same on any computer); the fsync cost of an SD card is not measured here.

``--part writer`` (fsync off the critical path): the same groups twice in this process, first
with the telemetry sinks writing inside the cycle (``inline``: the synchronous path, the baseline), then
behind it (``behind``: the sinks only queue into :class:`~magstack.firmware.flight.writer.WriteBehind`, a
writer thread writes and fsyncs, as ``magstack run`` does on hardware). ``os.fsync`` is wrapped to time
each call per thread, so the fsync time inside the rate group's cycles is measured, not inferred.
Reported per group and mode: wall p50/p99/worst, off-CPU time (wall - CPU: fsync, GIL hand-overs,
preemption), cycles that called fsync and their fsync time, overruns, and the ratios behind / inline.
``--fsync-delay-ms D`` makes every fsync D ms longer (an SD card emulated: an assumption, not a card).

``--part simrun``: CPU of ``run --sim`` (example configuration) with write-behind vs writing in the cycle.
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile
import threading
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
from magstack.firmware.flight.writer import WriteBehind
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


def _store(tmp: str) -> ct.CalTableStore:
    table = ct.CalTable(device_id="d", terms=("gain_matrix", "temperature_gain", "offset", "temperature_offset"),
                        S=np.eye(3) * 1.02, K_S=np.full((3, 3), 1e-4), O=[0.3, -0.1, 0.2], K_O=[0.01, 0, 0],
                        validity_temp_c=(-20.0, 60.0), validity_field_uT=100.0)
    store = ct.CalTableStore("d")
    store.load_and_activate(ct.save_table(table, Path(tmp) / "cal.json"))
    return store


class FsyncMeter:
    """Replaces ``os.fsync`` while in use: seconds and calls per thread, optionally ``delay_s`` longer per call
    (a slower card emulated)."""

    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._real = os.fsync
        self._pause = threading.Event()

    def _fsync(self, fd) -> None:
        t0 = time.perf_counter()
        if self.delay_s > 0:
            self._pause.wait(self.delay_s)
        self._real(fd)
        name = threading.current_thread().name
        self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0
        self.calls[name] = self.calls.get(name, 0) + 1

    def here_s(self) -> float:
        """fsync seconds of the calling thread so far."""
        return self.seconds.get(threading.current_thread().name, 0.0)

    def __enter__(self) -> FsyncMeter:
        os.fsync = self._fsync
        return self

    def __exit__(self, *exc) -> None:
        os.fsync = self._real


def _cycles(hz: float, chips, seconds: float, tmp: str, store, tag: str, writer: WriteBehind | None = None,
            meter: FsyncMeter | None = None) -> dict[str, np.ndarray]:
    """Run one group's channels cycle by cycle on a virtual clock, telemetry into ``tmp``: per cycle CPU s
    (``thread_time``), wall s (``perf_counter``), blocking s (virtual time the drivers waited), fsync s on this
    thread (with a ``meter``) and whether it is a cycle in which each channel hands over a full 50-row block.
    With ``writer`` the sinks only queue (write-behind, as in flight)."""
    opts = {c[0]: c[1] for c in CASES}
    clock = VirtualClock()
    chans, sinks = [], []
    for chip in chips:
        tlm = ChannelTelemetry(tmp, f"{chip}-{tag}", run_id=1, metadata={}, block_rows=50)
        sink = tlm if writer is None else writer.sink(tlm, chip)
        chans.append(MagChannel(chip, _open(chip, opts[chip], clock), TableCorrector(store), EventLog(), sink=sink))
        sinks.append(tlm)
    n = int(seconds * hz)
    out = {k: np.zeros(n) for k in ("cpu", "wall", "block", "fsync_wait")}
    here = meter.here_s if meter is not None else (lambda: 0.0)
    for k in range(n):
        v0, f0, c0, w0 = clock.monotonic_s(), here(), time.thread_time(), time.perf_counter()
        for ch in chans:
            ch.run(clock.monotonic_s())
        out["cpu"][k], out["wall"][k] = time.thread_time() - c0, time.perf_counter() - w0
        out["block"][k], out["fsync_wait"][k] = clock.monotonic_s() - v0, here() - f0
        clock.sleep_s(max(0.0, (k + 1) / hz - clock.monotonic_s()))    # to the next slot
    out["fsync_cycle"] = (np.arange(1, n + 1) % 50) == 0    # one row per channel per cycle: the 50th rows
    if writer is not None:
        writer.stop()
    for t in sinks:
        t.close()
    return out


def _fsync_probe(tmp: str) -> list[float]:
    """Seconds per fsync of an 8 kB append (one 50-row block) in ``tmp``, 50 times."""
    fd = os.open(Path(tmp) / "fsync-probe", os.O_WRONLY | os.O_CREAT)
    costs = []
    for _ in range(50):
        os.write(fd, b"x" * 8000)
        c0 = time.perf_counter()
        os.fsync(fd)
        costs.append(time.perf_counter() - c0)
    os.close(fd)
    return costs


def loop(seconds: float, pi_factor: float, telemetry_dir: str | None) -> None:
    """Per-group cycle statistics of the flight loop (see the module docstring, ``--part loop``)."""
    with tempfile.TemporaryDirectory(dir=telemetry_dir or os.getcwd(), prefix="bench-flight-") as tmp:
        store = _store(tmp)
        print(f"telemetry in {tmp} (fsync every 50 rows); {seconds:g} s of flight time per group; "
              f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
        print(f"{'group':<6} {'Hz':>4} {'cycles':>6} | {'CPU us p50/p99/max':>22} | {'wall us p50/p99/max':>22} | "
              f"{'fsync cycles wall us p50/max':>29} | {'blocking ms (% period)':>22} | "
              f"{'Pi: CPU p99 x F + blocking, % period':>36}")
        for name, hz, chips in GROUPS:
            c = _cycles(hz, chips, seconds, tmp, store, name)
            cpu, wall, block, fs = c["cpu"], c["wall"], c["block"], c["fsync_cycle"]
            n, period = len(cpu), 1.0 / hz
            pi = (_pct(cpu, 99) * pi_factor + _pct(block, 99)) / period * 100
            print(f"{name:<6} {hz:4g} {n:6d} | {_pct(cpu, 50) * 1e6:6.0f} {_pct(cpu, 99) * 1e6:7.0f} "
                  f"{cpu.max() * 1e6:7.0f} | {_pct(wall, 50) * 1e6:6.0f} {_pct(wall, 99) * 1e6:7.0f} "
                  f"{wall.max() * 1e6:7.0f} | {fs.sum():5d} x {_pct(wall[fs], 50) * 1e6:7.0f} "
                  f"{wall[fs].max(initial=0) * 1e6:8.0f} | {block.mean() * 1e3:8.1f} "
                  f"({block.mean() / period * 100:4.1f} %) | {pi:8.2f} % (F = {pi_factor:g})")
        costs = _fsync_probe(tmp)
        print(f"fsync of an 8 kB append in {tmp}: median {_pct(costs, 50) * 1e3:.2f} ms, "
              f"p99 {_pct(costs, 99) * 1e3:.2f} ms, worst {max(costs) * 1e3:.2f} ms")


def writer(seconds: float, pi_factor: float, telemetry_dir: str | None, fsync_delay_ms: float) -> None:
    """fsync on the critical path (the sinks write in the cycle: the baseline) vs off it (write-behind: the
    sinks queue, a writer thread writes), both in this process, one after the other per group; ratios."""
    with tempfile.TemporaryDirectory(dir=telemetry_dir or os.getcwd(), prefix="bench-writer-") as tmp, \
            FsyncMeter(fsync_delay_ms / 1e3) as meter:
        store = _store(tmp)
        print(f"telemetry in {tmp}, fsync every 50 rows" + (f" + {fsync_delay_ms:g} ms injected per fsync"
                                                             if fsync_delay_ms > 0 else "")
              + f"; {seconds:g} s of flight time per group and mode; load average {os.getloadavg()[0]:.1f} "
              f"on {os.cpu_count()} CPUs; wall = CPU + off-CPU (fsync, GIL, preemption)")
        print(f"{'group':<6} {'Hz':>3} {'mode':<6} | {'wall us p50/p99/worst':>23} | {'off-CPU us p99/worst':>20} | "
              f"{'fsync in cycle: n, us/cycle worst':>33} | {'overruns':>8} | {'blocking ms':>11} | "
              f"{'Pi: CPU p99 x F + blocking, % period':>36}")
        for name, hz, chips in GROUPS:
            res = {}
            for mode in ("inline", "behind"):
                # the loop runs in virtual time, faster than real time: the queue holds the whole run so that
                # nothing is dropped (the writer competes for the CPU and GIL more densely than in flight)
                w = WriteBehind(capacity=int(seconds * hz) * len(chips) + 16) if mode == "behind" else None
                if w is not None:
                    w.start()
                res[mode] = c = _cycles(hz, chips, seconds, tmp, store, f"{name}-{mode}", w, meter)
                wall, off = c["wall"], np.maximum(c["wall"] - c["cpu"], 0.0)
                period = 1.0 / hz
                pi = (_pct(c["cpu"], 99) * pi_factor + _pct(c["block"], 99)) / period * 100
                print(f"{name:<6} {hz:3g} {mode:<6} | {_pct(wall, 50) * 1e6:5.0f} {_pct(wall, 99) * 1e6:7.0f} "
                      f"{wall.max() * 1e6:9.0f} | {_pct(off, 99) * 1e6:8.0f} {off.max() * 1e6:9.0f} | "
                      f"{int((c['fsync_wait'] > 0).sum()):14d} {c['fsync_wait'].max() * 1e6:18.0f} | "
                      f"{int((wall > period).sum()):8d} | {c['block'].mean() * 1e3:11.1f} | "
                      f"{pi:6.1f} % (F = {pi_factor:g})"
                      + ("" if w is None else f" | queue: max depth {w.max_depth}, dropped {sum(w.dropped.values())}"))
            a, b = res["inline"], res["behind"]
            fa, fb = a["wall"][a["fsync_cycle"]], b["wall"][b["fsync_cycle"]]
            print(f"{name:<6} ratio behind / inline: wall p99 {_pct(b['wall'], 99) / _pct(a['wall'], 99):.2f}, "
                  f"worst {b['wall'].max() / a['wall'].max():.2f}; in the fsync cycles: p50 "
                  f"{_pct(fb, 50) / _pct(fa, 50):.2f}, worst {_pct(fb, 100) / _pct(fa, 100):.2f}")
        print("fsync calls (seconds) per thread: " + ", ".join(f"{t} {n} ({meter.seconds[t]:.2f} s)"
                                                              for t, n in sorted(meter.calls.items())))
        costs = _fsync_probe(tmp)
        print(f"fsync of an 8 kB append in {tmp}" + (" (with the injected delay)" if fsync_delay_ms > 0 else "")
              + f": median {_pct(costs, 50) * 1e3:.2f} ms, p99 {_pct(costs, 99) * 1e3:.2f} ms, "
              f"worst {max(costs) * 1e3:.2f} ms")


def simrun(seconds: float, repeat: int = 3) -> None:
    """CPU of a simulated run (``run --sim`` of the example configuration, [ccsds] included, no table) with
    write-behind (drained in the idle slot) vs writing in the cycle, alternating in this process; best of
    ``repeat`` and the ratio."""
    from magstack.cli.commands.run import _sim_options
    from magstack.firmware.flight.app import FlightApp
    from magstack.firmware.flight.config import example_config_text, load_config

    with tempfile.TemporaryDirectory(dir=os.getcwd(), prefix="bench-simrun-") as tmp:
        cfg = Path(tmp) / "flight.toml"
        cfg.write_text(example_config_text().replace("spi0.0,start=6,reset=13,drdy=19,sr=5", "sim")
                       .replace('bus = "1"', 'bus = "sim"').replace('table = "tables/hmc1053.json"', ""))
        best = {False: math.inf, True: math.inf}
        for i in range(repeat):
            for behind in (False, True):
                c0 = time.process_time()
                app = FlightApp(load_config(cfg), virtual=True, simulate=True, run_id=1, write_behind=behind,
                                telemetry_dir=Path(tmp) / f"t{i}{behind}",
                                chip_options=_sim_options("rotation", seconds, 0))
                try:
                    app.run(seconds)
                finally:
                    app.close()
                best[behind] = min(best[behind], time.process_time() - c0)
        print(f"run --sim, {seconds:g} s of virtual time, best of {repeat} CPU s: in the cycle {best[False]:.2f}, "
              f"write-behind {best[True]:.2f}, ratio {best[True] / best[False]:.2f} "
              f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=400, help="cycles per measurement (default 400)")
    ap.add_argument("--pi-factor", type=float, default=5.0, help="assumed Pi / this-host CPU-time ratio")
    ap.add_argument("--part", choices=("channels", "loop", "writer", "simrun"), default="channels")
    ap.add_argument("--seconds", type=float, default=300.0, help="--part loop: flight time per group (s)")
    ap.add_argument("--telemetry-dir", default=None, help="--part loop: where telemetry is written (default: cwd)")
    ap.add_argument("--fsync-delay-ms", type=float, default=0.0,
                    help="--part writer: extra wait per fsync, emulating a slower card (default 0)")
    args = ap.parse_args(argv)
    if args.part == "loop":
        loop(args.seconds, args.pi_factor, args.telemetry_dir)
        return 0
    if args.part == "simrun":
        simrun(args.seconds)
        return 0
    if args.part == "writer":
        writer(args.seconds, args.pi_factor, args.telemetry_dir, args.fsync_delay_ms)
        return 0
    print(f"{'channel':<11} {'read us':>9} {'channel us':>10} {'overhead us':>11} {'ratio':>6} "
          f"{'group Hz':>8} {'% period':>8} {'Pi % period':>11} {'chip max Hz':>11}")
    with tempfile.TemporaryDirectory() as tmp:
        store = _store(tmp)
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
