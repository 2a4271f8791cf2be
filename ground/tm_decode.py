"""``magstack tm decode``: a CCSDS packet stream -> session files, events and housekeeping.

The stream is a concatenation of TM packets (what the flight application writes to
``packets-<run>.bin``), read in blocks (memory does not grow with the file; a file that is not a regular
file, or is larger than ``MAX_STREAM_BYTES``, is refused before a byte is read). Each packet is checked
against its length field and its PUS packet error control, then decoded by the dictionary
(:mod:`magstack.data.packets`). Nothing in the stream can stop the decoder: a bad packet is counted by kind
and skipped; after a packet whose length cannot be trusted the decoder resynchronises on the next offset
that holds a whole valid packet (the skipped bytes count as one bad packet). Per APID the 14-bit sequence
count shows lost packets (``seq_missing``) and repeated or out-of-order ones (``seq_repeated``).

**Attribution.** A channel packet carries its APID and its run id; the run's ``apid_map`` packets (the
first packets of every run, repeated every ``hk_period_s``) name the channel, device id and chip behind
each APID of that run. Rows are attributed to (run id, channel, device, chip), never to an APID alone, so
two concatenated runs never mix, whatever order their sensors are in. Per (run id, APID), in stream order:

* a row whose sequence count continues the previous one (1..``MAX_GAP`` ahead) belongs to the current
  identification;
* after a break in the counts (a repeat, a step back, a jump of more than ``MAX_GAP``: another run with
  the same run id may start there), and before any identification at all, rows wait for the next
  identification of that APID: one that confirms the current one takes them; the first one takes the rows
  since the last break; rows it cannot vouch for (before an earlier break, or held when a *different*
  identification arrives: the point where the other run began is unknown) are refused and counted
  (``unattributed``), as are rows still waiting at the end of the stream;
* a different identification for the same (run id, APID) starts a new output (counted in
  ``identity_conflicts``): the two are split, never merged.

Output, per (run, channel, device), one session file ``<channel>-<run>-<k>.csv`` (k = 1, or 2, 3 ... when
one run id names the channel twice) with the columns ``magstack run`` writes (raw field as ``dut_*_uT``,
``temp_c``, ``session`` = run id, ``cal_*_uT``, ``table_crc32``, ``error_count``, ``flag``), so ``fit``,
``diagnose`` and ``refit`` read it; ``events.jsonl`` and ``housekeeping.jsonl`` (rate groups, telecommand
counters, in stream order) beside them; ``decode-report.json``.

**Output directory.** Every output is written into a fresh hidden stage beside ``out`` (no temporary file
name can be planted: nothing is opened by a name an attacker can predict) and moved into ``out`` whole at
the end (:func:`magstack.data.io.staged_directory`); nothing is written when decoding fails. ``out`` may
not be the directory of an input packet file, nor hold the flight application's own files
(``packets-*``, ``events-*``, ``summary-*``, ``.part`` files); an existing file of the same name is replaced
only if an earlier ``tm decode`` wrote it (it is listed in that directory's ``decode-report.json``).
"""
from __future__ import annotations

import json
import math
import os
import re
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from magstack.data.dictionary import CHANNEL_FIELDS, EVENTS, FLIGHT, Severity, flag_legend
from magstack.data.errors import SessionFileError
from magstack.data.io import open_bounded, read_json_bounded, staged_directory
from magstack.data.packets import MAX_PACKET_BYTES, SEQ_MODULO, PacketError, TmPacket, decode_tm, tm_header
from magstack.data.session import SessionWriter
from magstack.drivers.errors import ConfigurationError

#: Session extra columns the decoder writes (the same as the flight telemetry files).
EXTRA_COLUMNS = ("cal_x_uT", "cal_y_uT", "cal_z_uT", "table_crc32", "error_count")
_EVENT_NAME = {e.id: e.name for e in EVENTS}
#: Largest packet file decoded (a day of the example board's packets is about 60 MB).
MAX_STREAM_BYTES = 4 << 30
#: Bytes read per block.
BLOCK_BYTES = 4 << 20
#: A count more than this far ahead of the previous one on the same APID is a break (see the module doc).
MAX_GAP = 64
#: Rows held per (run id, APID) while waiting for an identification, and in all: older ones beyond are
#: refused (counted), so a stream without identifications cannot fill memory.
MAX_PENDING_ROWS = 200_000
MAX_PENDING_TOTAL = 1_000_000
#: Rows per block written to a session file.
WRITE_ROWS = 8192
#: Names in an output directory that belong to the flight application, never replaced by a decode.
FLIGHT_FILE = re.compile(r"^(?:packets-\d{4,}\.bin|events-\d{4,}\.jsonl|summary-\d{4,}\.json|.*\.part)$")
REPORT_NAME = "decode-report.json"
_LOOKAHEAD = 2 * MAX_PACKET_BYTES + 8         # bytes a decision at one offset may look at beyond it
_CANDIDATE = re.compile(rb"[\x08\x09]")       # first octet of a TM packet with a secondary header and one of our APIDs


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
    unattributed: int = 0        # channel rows no identification can vouch for: refused, not written
    identity_conflicts: int = 0  # one (run id, APID) named twice differently: the outputs are split
    runs: list[int] = field(default_factory=list)
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


# ------------------------------------------------------------------------------------------- packets
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
    """First offset in [start, stop) where a whole valid packet starts, else ``stop`` (only offsets holding a
    possible first octet are tried: runs of zeros or garbage are skipped at C speed)."""
    j = start
    while j < stop:
        m = _CANDIDATE.search(data, j, stop)
        if m is None:
            return stop
        j = m.start()
        if _whole_packet_at(data, j):
            return j
        j += 1
    return stop


class PacketScanner:
    """Incremental form of :func:`iter_packets`: :meth:`feed` blocks of a stream in order, then
    :meth:`finish`; each yields the good packets and counts the bad ones in ``report``."""

    def __init__(self, report: DecodeReport) -> None:
        self.report = report
        self._buf = b""
        self._base = 0                      # stream offset of _buf[0]
        self._last_seq: dict[int, int] = {}
        self._skip: tuple[int, int | None] | None = None   # a skipped run under way: (start, end its header claims)

    def feed(self, block: bytes) -> Iterator[TmPacket]:
        self.report.bytes += len(block)
        yield from self._scan(self._buf + block, final=False)

    def finish(self) -> Iterator[TmPacket]:
        yield from self._scan(self._buf, final=True)

    def _end_skip(self, at: int, eof: bool) -> None:
        start, claimed_end = self._skip
        self._skip = None
        r = self.report
        if eof and claimed_end is not None and claimed_end > at:
            r.truncated += 1
        else:
            r.bad_length += 1
        r.skipped_bytes += at - start

    def _scan(self, data: bytes, final: bool) -> Iterator[TmPacket]:
        r = self.report
        n = len(data)
        limit = n if final else max(0, n - _LOOKAHEAD)
        i = 0
        while i < limit:
            if self._skip is not None:          # a skipped run goes on until the next whole packet
                j = _next_whole(data, i, limit)
                if j >= limit and not final:
                    i = limit
                    break
                self._end_skip(self._base + j, eof=final and j >= n)
                i = j
                continue
            h = tm_header(data, i)
            if h is not None and i + h[2] <= n:
                try:
                    p = decode_tm(data[i:i + h[2]])
                except PacketError as exc:
                    nxt = i + h[2]
                    if exc.kind in ("unknown", "malformed"):       # CRC right: the length is right too
                        setattr(r, exc.kind, getattr(r, exc.kind) + 1)
                        i = nxt
                        continue
                    # a CRC error: trust the length only if no whole packet starts inside it and one follows it
                    if _next_whole(data, i + 1, nxt) == nxt and ((final and nxt == n) or _whole_packet_at(data, nxt)):
                        r.bad_crc += 1
                        i = nxt
                        continue
                else:
                    self._sequence(p)
                    r.packets_ok += 1
                    r.by_packet[p.packet.name] += 1
                    i += h[2]
                    yield p
                    continue
            # the length cannot be trusted (or the stream ends inside the packet): skip to the next whole packet
            self._skip = (self._base + i, None if h is None else self._base + i + h[2])
            i += 1
        if final and self._skip is not None:
            self._end_skip(self._base + n, eof=True)
        self._base += i
        self._buf = data[i:] if not final else b""

    def _sequence(self, p: TmPacket) -> None:
        r = self.report
        prev = self._last_seq.get(p.apid)
        if prev is not None:
            d = (p.seq_count - prev) % SEQ_MODULO
            if d == 0 or d >= SEQ_MODULO // 2:
                r.seq_repeated += 1
            else:
                r.seq_missing += d - 1
        if prev is None or 0 < (p.seq_count - prev) % SEQ_MODULO < SEQ_MODULO // 2:
            self._last_seq[p.apid] = p.seq_count


def iter_packets(data: bytes, report: DecodeReport) -> Iterator[TmPacket]:
    """Yield every good packet of ``data`` (a whole stream in memory); count every bad one in ``report``.
    Never raises."""
    sc = PacketScanner(report)
    report.bytes += len(data)
    sc._buf = data
    yield from sc.finish()


def iter_stream(path: str | os.PathLike, report: DecodeReport, block_bytes: int = BLOCK_BYTES) -> Iterator[TmPacket]:
    """The packets of a packet file, read in blocks (a regular file of at most ``MAX_STREAM_BYTES``;
    :class:`~magstack.errors.InputDataError` otherwise, before a byte is read)."""
    sc = PacketScanner(report)
    with open_bounded(path, MAX_STREAM_BYTES, "packet file") as fh:
        total = 0
        while block := fh.read(block_bytes):
            total += len(block)
            if total > MAX_STREAM_BYTES:
                raise SessionFileError(f"{path}: grew beyond {MAX_STREAM_BYTES} bytes while read")
            yield from sc.feed(block)
    yield from sc.finish()


# ------------------------------------------------------------------------------------------- attribution
@dataclass(frozen=True)
class Identity:
    """What an ``apid_map`` packet says about one channel APID of one run."""

    run_id: int
    name: str
    device_id: str
    chip: str


@dataclass
class _ApidState:
    current: Identity | None = None
    last_seq: int | None = None
    suspect: bool = False                                   # a break since the last identification
    pending: list[list[tuple]] = field(default_factory=list)  # segments of held rows (a break starts one)
    held: int = 0


class _Output:
    """One session file of attributed rows (written in blocks into the stage)."""

    def __init__(self, path: Path, ident: Identity, apid: int, sources: Sequence[str]) -> None:
        self.path = path
        self.rows: list[tuple] = []
        self.written = 0
        self.writer = SessionWriter(path, {
            "device_id": ident.device_id or "unknown", "dut_chip": ident.chip or "unknown",
            "telemetry_channel": ident.name, "run_id": str(ident.run_id), "apid": f"0x{apid:03x}",
            "dut_field": "raw", "flag_bits": flag_legend(FLIGHT), "source": "magstack tm decode",
            "packet_files": " ".join(sources)}, with_flag=True, extra_names=EXTRA_COLUMNS, block_rows=WRITE_ROWS)

    def add(self, rows: list[tuple]) -> None:
        self.rows.extend(rows)
        if len(self.rows) >= WRITE_ROWS:
            self.flush()

    def flush(self) -> None:
        if self.rows:
            self.writer.write_block(_channel_table(self.rows))
            self.written += len(self.rows)
            self.rows = []

    def close(self) -> None:
        self.flush()
        self.writer.close()


def _channel_table(rows: list[tuple]) -> np.ndarray:
    raw = np.array(rows, dtype=float)
    cols = {}
    for k, f in enumerate(CHANNEL_FIELDS, start=1):
        v = raw[:, k] * f.lsb
        cols[f.name] = np.where(raw[:, k] == f.absent, math.nan, v) if f.absent is not None else v
    nan = np.full(len(raw), math.nan)
    return np.column_stack([raw[:, 0], nan, nan, nan, cols["raw_x"], cols["raw_y"], cols["raw_z"], cols["temp"],
                            cols["run_id"], cols["cal_x"], cols["cal_y"], cols["cal_z"], cols["table_crc32"],
                            cols["error_count"], cols["flag"]])


class Attributor:
    """Channel rows -> outputs by (run id, channel, device, chip), as the module doc says."""

    def __init__(self, out_dir: Path, report: DecodeReport, sources: Sequence[str]) -> None:
        self.out_dir, self.report, self.sources = out_dir, report, list(sources)
        self.state: dict[tuple[int, int], _ApidState] = {}
        self.outputs: dict[tuple[Identity, int], _Output] = {}
        self._names: Counter = Counter()
        self._held = 0                        # rows held over all (run id, APID)

    def _commit(self, ident: Identity, apid: int, rows: list[tuple]) -> None:
        if not rows:
            return
        key = (ident, apid)
        out = self.outputs.get(key)
        if out is None:
            stem = ident.name if ident.name and all(c.isalnum() or c in "_-" for c in ident.name) else f"apid{apid:03x}"
            self._names[(stem, ident.run_id)] += 1
            path = self.out_dir / f"{stem}-{ident.run_id:04d}-{self._names[(stem, ident.run_id)]:04d}.csv"
            out = self.outputs[key] = _Output(path, ident, apid, self.sources)
        out.add(rows)

    def _refuse(self, segments: list[list[tuple]]) -> None:
        self.report.unattributed += sum(len(s) for s in segments)

    def _drop_oldest(self, st: _ApidState) -> None:
        st.held -= 1
        self._held -= 1
        self.report.unattributed += 1
        st.pending[0].pop(0)
        if not st.pending[0]:
            st.pending.pop(0)

    def identify(self, apid: int, ident: Identity) -> None:
        st = self.state.setdefault((ident.run_id, apid), _ApidState())
        segs, st.pending = st.pending, []
        self._held -= st.held
        st.held = 0
        if st.current is None:
            self._refuse(segs[:-1])
            if segs:
                self._commit(ident, apid, segs[-1])
        elif ident == st.current:
            for s in segs:
                self._commit(ident, apid, s)
        else:
            self.report.identity_conflicts += 1
            self._refuse(segs)
        st.current, st.suspect = ident, False

    def row(self, apid: int, run_id: int, seq: int, row: tuple) -> None:
        st = self.state.setdefault((run_id, apid), _ApidState())
        brk = st.last_seq is not None and not 1 <= (seq - st.last_seq) % SEQ_MODULO <= MAX_GAP
        st.last_seq = seq
        if st.current is not None and not brk and not st.suspect:
            self._commit(st.current, apid, [row])
            return
        if st.current is not None:
            st.suspect = True
        if brk or not st.pending:
            st.pending.append([])
        st.pending[-1].append(row)
        st.held += 1
        self._held += 1
        while st.held > MAX_PENDING_ROWS:
            self._drop_oldest(st)
        if self._held > MAX_PENDING_TOTAL:
            biggest = max(self.state.values(), key=lambda x: x.held)
            while self._held > MAX_PENDING_TOTAL:
                self._drop_oldest(biggest)

    def finish(self) -> list[Path]:
        for st in self.state.values():
            self._refuse(st.pending)
            st.pending, st.held = [], 0
        self._held = 0
        for out in self.outputs.values():
            out.close()
        self.report.runs = sorted({k[0].run_id for k in self.outputs})
        return [o.path for o in self.outputs.values()]


# ------------------------------------------------------------------------------------------- output
def check_out_dir(out: Path, inputs: Sequence[str | os.PathLike]) -> None:
    """The output-path rule of ``tm decode`` before anything is read (ConfigurationError, exit 2)."""
    real = os.path.realpath(out)
    for p in inputs:
        if os.path.realpath(Path(p).parent) == real:
            raise ConfigurationError(f"--out {out} is the directory of the input {p}: decode into another directory "
                                     "(the flight application's own files are never replaced)")
    if out.is_dir():
        own = sorted(n for n in os.listdir(out) if FLIGHT_FILE.match(n))
        if own:
            raise ConfigurationError(f"--out {out} holds the flight application's files ({', '.join(own[:3])}"
                                     f"{' ...' if len(own) > 3 else ''}): decode into another directory")


def _replaceable(out: Path) -> set[str]:
    """Names in ``out`` an earlier ``tm decode`` wrote (listed in its decode-report.json)."""
    rep = out / REPORT_NAME
    if not rep.is_file():
        return set()
    try:
        doc = read_json_bounded(rep, what="decode report")
    except ValueError:
        return set()
    files = doc.get("files", []) if isinstance(doc, dict) else []
    return {Path(f).name for f in files if isinstance(f, str)} | {REPORT_NAME}


def decode_files(paths: Sequence[str | os.PathLike], out_dir: str | os.PathLike, *,
                 strict: bool = False) -> DecodeReport:
    """Decode packet files (in order) into ``out_dir``; returns the counts (also in decode-report.json).

    ``strict``: a bad packet or an unattributed row is an error (SessionFileError) and nothing is written.
    A stream without a valid packet is SessionFileError too (nothing written)."""
    out = Path(out_dir)
    check_out_dir(out, paths)
    report = DecodeReport()
    sources = [str(p) for p in paths]
    out.parent.mkdir(parents=True, exist_ok=True)
    with staged_directory(out) as stage:
        attr = Attributor(stage, report, sources)
        with open(stage / "events.jsonl", "w", encoding="utf-8") as ev_fh, \
                open(stage / "housekeeping.jsonl", "w", encoding="utf-8") as hk_fh:
            for p in paths:
                for pkt in iter_stream(p, report):
                    _route(pkt, attr, ev_fh, hk_fh)
            written = attr.finish()
        if report.packets_ok == 0:
            raise SessionFileError(f"{', '.join(sources)}: no valid packet in {report.bytes} bytes "
                                   f"({report.bad_packets} bad)")
        if strict and (report.bad_packets or report.unattributed):
            raise SessionFileError(f"{', '.join(sources)}: {report.bad_packets} bad packets, {report.unattributed} "
                                   "unattributed channel rows (--strict: nothing written)")
        report.files = [str(out / f.name) for f in written] + [str(out / "events.jsonl"),
                                                               str(out / "housekeeping.jsonl")]
        (stage / REPORT_NAME).write_text(json.dumps(report.to_dict(), indent=1, sort_keys=True) + "\n",
                                         encoding="utf-8")
        report.files.append(str(out / REPORT_NAME))
        if out.is_dir():
            ok = _replaceable(out)
            clash = sorted(f.name for f in stage.iterdir() if (out / f.name).exists() or (out / f.name).is_symlink())
            clash = [n for n in clash if n not in ok or (out / n).is_symlink()]
            if clash:
                raise ConfigurationError(f"--out {out}: {', '.join(clash[:3])} exist{'s' if len(clash) == 1 else ''} "
                                         "and no earlier tm decode wrote them: decode into another directory")
    return report


def _route(pkt: TmPacket, attr: Attributor, ev_fh, hk_fh) -> None:
    r = pkt.raw
    name = pkt.packet.name
    if name == "channel":
        attr.row(pkt.apid, int(r["run_id"]), pkt.seq_count, (pkt.t_s, *(r[f.name] for f in CHANNEL_FIELDS)))
    elif name == "apid_map":
        if int(r["kind"]) == 1:
            attr.identify(int(r["apid"]), Identity(int(r["run_id"]), str(r["name"]), str(r["device_id"]),
                                                   str(r["chip"])))
    elif name == "event":
        sev = int(r["severity"])
        ev_fh.write(json.dumps({"t_s": pkt.t_s, "id": int(r["event_id"]),
                                "name": _EVENT_NAME.get(int(r["event_id"]), "UNKNOWN"),
                                "severity": Severity(sev).name if sev <= max(Severity) else str(sev),
                                "source": r["source"], "message": r["message"]}, sort_keys=True) + "\n")
    else:
        hk_fh.write(json.dumps({"t_s": pkt.t_s, "apid": pkt.apid, "packet": name, "seq_count": pkt.seq_count, **r},
                               sort_keys=True) + "\n")
