"""Telemetry cost of the CCSDS packet stream at the example board's rates.

    python benchmarks/bench_packets.py [RECORDS]

1. CPU per record, best of 3, in this process: the session-CSV writer (``ChannelTelemetry``, the
   baseline) vs the packet stream (``PacketStream.record``) to a file and to a UDP loopback socket,
   and the ground decoder (``iter_packets``) per packet. RECORDS (default 20,000) realistic records.
2. Packets per second and bytes per second of the shipped example configuration (hmc1053 at 1 Hz,
   lis3mdl at 10 Hz, housekeeping every 10 s) from a 10-minute simulated ``magstack run``, and the
   downlink volume per 95-minute orbit (and per day) at those rates.
"""
from __future__ import annotations

import math
import socket
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from magstack.data.packets import ApidMap  # noqa: E402
from magstack.firmware.flight.ccsds import PacketStream  # noqa: E402
from magstack.firmware.flight.channel import TelemetryRecord  # noqa: E402
from magstack.firmware.flight.telemetry import ChannelTelemetry  # noqa: E402
from magstack.ground.tm_decode import DecodeReport, iter_packets  # noqa: E402

ORBIT_S = 95 * 60


def _records(n: int) -> list[TelemetryRecord]:
    rng = np.random.default_rng(0)
    b = rng.normal(0, 30, (n, 3))
    return [TelemetryRecord("lis3mdl", 1.7e9 + 0.1 * i, tuple(b[i]), tuple(b[i] * 1.01 + 0.2), 20.0 + 0.01 * i % 5,
                            0x1234ABCD, 0, 0) for i in range(n)]


def _cpu_per_item(fn, items) -> float:
    best = math.inf
    for _ in range(3):
        t0 = time.process_time()
        for it in items:
            fn(it)
        best = min(best, time.process_time() - t0)
    return best / len(items)


def main(argv: list[str]) -> int:
    n = int(argv[1]) if len(argv) > 1 else 20_000
    recs = _records(n)
    apids = ApidMap(("lis3mdl",), ("fast",))
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        cpu = {}
        best = math.inf
        for rep_i in range(3):          # a fresh writer (file) per repetition; close() inside the timing
            tlm = ChannelTelemetry(d, f"csv{rep_i}", run_id=1, metadata={}, block_rows=50)
            t0 = time.process_time()
            for r in recs:
                tlm(r)
            tlm.close()
            best = min(best, time.process_time() - t0)
        cpu["csv"] = best / n
        stream = PacketStream(apids, path=d / "p.bin", udp=None)
        cpu["packets file"] = _cpu_per_item(stream.record, recs)
        stream.close()
        rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        rx.bind(("127.0.0.1", 0))
        udp = PacketStream(apids, path=None, udp=rx.getsockname())
        cpu["packets UDP"] = _cpu_per_item(udp.record, recs)
        udp.close()
        rx.close()
        data = (d / "p.bin").read_bytes()
        t0 = time.process_time()
        rep = DecodeReport()
        npk = sum(1 for _ in iter_packets(data, rep))
        cpu["decode/packet"] = (time.process_time() - t0) / npk

        from magstack.cli.main import main as cli
        from magstack.firmware.flight.config import example_config_text

        cfg = d / "flight.toml"
        cfg.write_text(example_config_text().replace("spi0.0,start=6,reset=13,drdy=19,sr=5", "sim")
                       .replace('bus = "1"', 'bus = "sim"').replace('table = "tables/hmc1053.json"', ""))
        duration = 600
        assert cli(["run", "--config", str(cfg), "--duration", str(duration), "--out", str(d / "tlm"), "-q"]) == 0
        pk = (d / "tlm" / "packets-0001.bin").read_bytes()
        rep = DecodeReport()
        count = sum(1 for _ in iter_packets(pk, rep))
        csv_bytes = sum(p.stat().st_size for p in (d / "tlm").glob("*.csv"))
    print(f"CPU per record ({n} records, best of 3, process time):")
    for name, v in cpu.items():
        print(f"  {name:13s} {v * 1e6:7.1f} us   ratio to csv {v / cpu['csv']:.2f}")
    pps, bps = count / duration, len(pk) / duration
    print(f"example board, {duration} s simulated: {count} packets ({dict(rep.by_packet)}), {len(pk)} bytes")
    print(f"  {pps:.2f} packets/s, {bps:.0f} B/s; session CSVs for comparison {csv_bytes / duration:.0f} B/s")
    print(f"  CPU for packets at these rates: {pps * cpu['packets file'] * 1e3:.3f} ms/s "
          f"({pps * cpu['packets file'] * 100:.3f} % of one core)")
    print(f"  downlink per 95-min orbit: {bps * ORBIT_S / 1e6:.2f} MB ({count / duration * ORBIT_S:.0f} packets); "
          f"per day {bps * 86400 / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
