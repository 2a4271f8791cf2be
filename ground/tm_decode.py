"""``magstack tm decode``: a CCSDS packet stream -> session files, events and housekeeping.

The stream is a concatenation of TM packets (what the flight application writes to
``packets-<run>.bin``). Each packet is checked against its length field and its PUS packet error
control, then decoded by the dictionary (:mod:`magstack.data.packets`). Nothing in the stream can
stop the decoder: a bad packet is counted by kind and skipped; after a packet whose length cannot be
trusted the decoder resynchronises on the next offset that holds a whole valid packet (the skipped
bytes count as one bad packet). Per APID the 14-bit sequence count shows lost packets (``seq_missing``)
and repeated or out-of-order ones (``seq_repeated``).

Output, per channel, one session file ``<channel>-<run>-0001.csv`` with the columns ``magstack run``
writes (raw field as ``dut_*_uT``, ``temp_c``, ``session`` = run id, ``cal_*_uT``, ``table_crc32``,
``error_count``, ``flag``), so ``fit``, ``diagnose`` and ``refit`` read it; ``events.jsonl`` and
``housekeeping.jsonl`` (rate groups, telecommand counters) beside them; ``decode-report.json``.
"""
from __future__ import annotations

import json
import math
import os
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from magstack.data.dictionary import CHANNEL_FIELDS, EVENTS, FLIGHT, Severity, flag_legend
from magstack.data.packets import SEQ_MODULO, PacketError, TmPacket, decode_tm, from_raw, tm_header
from magstack.data.session import SessionWriter

#: Session extra columns the decoder writes (the same as the flight telemetry files).
EXTRA_COLUMNS = ("cal_x_uT", "cal_y_uT", "cal_z_uT", "table_crc32", "error_count")
_EVENT_NAME = {e.id: e.name for e in EVENTS}


@dataclass
class DecodeReport:
    """Counts of what the stream held; every bad packet is counted under exactly one kind."""

    bytes: int = 0
    packets_ok: int = 0
    bad_crc: int = 0
    bad_length: int = 0          # length field disagrees with the stream (resynchronised)
    truncated: int = 0           # the stream ends inside a packet
    unknown: int = 0             # valid packet, APID or service not in the dictionary
    malformed: int = 0           # valid CRC, payload does not fit the dictionary
    skipped_bytes: int = 0
    seq_missing: int = 0
    seq_repeated: int = 0
    by_packet: Counter = field(default_factory=Counter)
    files: list[str] = field(default_factory=list)

    @property
    def bad_packets(self) -> int:
        return self.bad_crc + self.bad_length + self.truncated + self.unknown + self.malformed

    def to_dict(self) -> dict:
        d = asdict(self)
        d["by_packet"] = dict(self.by_packet)
        d["bad_packets"] = self.bad_packets
        return d


def _whole_packet_at(data: bytes, at: int) -> int:
    """Length of a whole, CRC-valid packet of ours at ``at``, or 0."""
    h = tm_header(data, at)
    if h is None or at + h[2] > len(data):
        return 0
    try:
        decode_tm(data[at:at + h[2]])
    except PacketError as exc:
        return h[2] if exc.kind in ("unknown", "malformed") else 0
    return h[2]


def _next_whole(data: bytes, start: int, stop: int) -> int:
    """First offset in [start, stop) where a whole valid packet starts, else ``stop``."""
    j = start
    while j < stop and not _whole_packet_at(data, j):
        j += 1
    return j


def iter_packets(data: bytes, report: DecodeReport) -> Iterator[TmPacket]:
    """Yield every good packet of ``data``; count every bad one in ``report``. Never raises."""
    report.bytes += len(data)
    i, n = 0, len(data)
    last_seq: dict[int, int] = {}
    while i < n:
        h = tm_header(data, i)
        if h is not None and i + h[2] <= n:
            try:
                p = decode_tm(data[i:i + h[2]])
            except PacketError as exc:
                nxt = i + h[2]
                if exc.kind in ("unknown", "malformed"):       # CRC right: the length is right too
                    setattr(report, exc.kind, getattr(report, exc.kind) + 1)
                    i = nxt
                    continue
                # a CRC error: trust the length only if no whole packet starts inside it and one follows it
                if _next_whole(data, i + 1, nxt) == nxt and (nxt == n or _whole_packet_at(data, nxt)):
                    report.bad_crc += 1
                    i = nxt
                    continue
            else:
                prev = last_seq.get(p.apid)
                if prev is not None:
                    d = (p.seq_count - prev) % SEQ_MODULO
                    if d == 0 or d >= SEQ_MODULO // 2:
                        report.seq_repeated += 1
                    else:
                        report.seq_missing += d - 1
                if prev is None or 0 < (p.seq_count - prev) % SEQ_MODULO < SEQ_MODULO // 2:
                    last_seq[p.apid] = p.seq_count
                report.packets_ok += 1
                report.by_packet[p.packet.name] += 1
                i += h[2]
                yield p
                continue
        # the length cannot be trusted (or the stream ends inside the packet): go to the next whole packet
        j = _next_whole(data, i + 1, n)
        if j >= n and h is not None and i + h[2] > n:
            report.truncated += 1
        else:
            report.bad_length += 1
        report.skipped_bytes += j - i
        i = j


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def decode_files(paths, out_dir: str | os.PathLike) -> DecodeReport:
    """Decode packet files (in order) into ``out_dir``; returns the counts (also in decode-report.json)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = DecodeReport()
    rows: dict[int, list[tuple]] = defaultdict(list)
    names: dict[int, dict] = {}
    events, hk = [], []
    sources = []
    for p in paths:
        sources.append(str(p))
        data = Path(p).read_bytes()
        for pkt in iter_packets(data, report):
            r = pkt.raw
            name = pkt.packet.name
            if name == "channel":
                rows[pkt.apid].append((pkt.t_s, *(r[f.name] for f in CHANNEL_FIELDS)))
            elif name == "apid_map":
                names.setdefault(int(r["apid"]), dict(r))
            elif name == "event":
                sev = int(r["severity"])
                events.append({"t_s": pkt.t_s, "id": int(r["event_id"]),
                               "name": _EVENT_NAME.get(int(r["event_id"]), "UNKNOWN"),
                               "severity": Severity(sev).name if sev <= max(Severity) else str(sev),
                               "source": r["source"], "message": r["message"]})
            else:
                hk.append({"t_s": pkt.t_s, "apid": pkt.apid, "packet": name, "seq_count": pkt.seq_count,
                           **{k: v for k, v in r.items()}})
    for apid, recs in sorted(rows.items()):
        info = names.get(apid, {})
        chan = info.get("name") or f"apid{apid:03x}"
        if not all(ch.isalnum() or ch in "_-" for ch in chan):
            chan = f"apid{apid:03x}"
        run_id = int(info.get("run_id", 0))
        path = out / f"{chan}-{run_id:04d}-0001.csv"
        _write_channel(path, recs, run_id, {
            "device_id": info.get("device_id") or "unknown", "dut_chip": info.get("chip") or "unknown",
            "telemetry_channel": chan, "run_id": str(run_id), "apid": f"0x{apid:03x}", "dut_field": "raw",
            "flag_bits": flag_legend(FLIGHT), "source": "magstack tm decode", "packet_files": " ".join(sources)})
        report.files.append(str(path))
    for fname, items in (("events.jsonl", events), ("housekeeping.jsonl", hk)):
        _atomic_text(out / fname, "".join(json.dumps(e, sort_keys=True) + "\n" for e in items))
        report.files.append(str(out / fname))
    _atomic_text(out / "decode-report.json", json.dumps(report.to_dict(), indent=1, sort_keys=True) + "\n")
    return report


def _write_channel(path: Path, recs: list[tuple], run_id: int, meta: dict) -> None:
    raw = np.array(recs, dtype=float)
    cols = {f.name: np.array([from_raw(f, int(v)) for v in raw[:, k + 1]]) for k, f in enumerate(CHANNEL_FIELDS)}
    nan = np.full(len(raw), math.nan)
    table = np.column_stack([raw[:, 0], nan, nan, nan, cols["raw_x"], cols["raw_y"], cols["raw_z"], cols["temp"],
                             np.full(len(raw), float(run_id)), cols["cal_x"], cols["cal_y"], cols["cal_z"],
                             cols["table_crc32"], cols["error_count"], cols["flag"]])
    if path.exists():
        path.unlink()
    with SessionWriter(path, meta, with_flag=True, extra_names=EXTRA_COLUMNS, block_rows=20000) as w:
        w.write_block(table)
