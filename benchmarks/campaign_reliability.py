"""Fault and hostile-input campaign over the flight application and the ground tools (bounded, 127.0.0.1 only).

    python benchmarks/campaign_reliability.py [--scale 1.0] [--seed 0] [--json]

Re-runs the categories of a hostile operator and a failing disk, each trial with a known right answer:

* ``udp_tc``: malformed, corrupt, replayed, out-of-window, unauthorised (a receiver that allows only another
  host) and valid telecommands over UDP on 127.0.0.1, each under its counter; then a bounded flood of junk
  datagrams, every one counted;
* ``tc_dir`` / ``command_dir``: symlinks, FIFOs, directories, sparse 6 GiB files, files others may write,
  files of another user (as root), hostile tables and paths dropped where the application takes orders;
* ``config``: hostile numbers and directory clashes in flight.toml;
* ``tc_sequence``: a count far ahead, replays across a restart, resynchronisation;
* ``stream``: bit flips, cuts, duplicates and junk in a recorded packet stream (no crash, no decoded row
  that the run did not record, bad packets counted), and two concatenated runs with their sensors in
  another order (no row in another sensor's file);
* ``decode_out``: ``tm decode --out`` onto the flight's own files and planted symlinks;
* ``tables``: hostile posterior blocks (table validate, and the flight's table store);
* ``readers``: /dev/zero, FIFOs and 6 GiB sparse files given to every ground reader (a child process with a
  3 GiB memory limit and a 60 s timeout: a hang or a memory blow-up shows as such);
* ``merge``: ADCS positions inside the Earth or beyond its orbits, NaN samples, quaternions off unit norm;
* ``full_disk``: ``magstack run`` with a per-file size limit (RLIMIT_FSIZE): the summary must be written and
  every record either in the files or counted as lost;
* ``kill9``: a real-time run killed at a random moment: at most 1 s of packets lost.

Each trial ends as ``refused`` (a clean refusal: one line, the documented exit code or counter) or
``correct``; or as a failure: ``traceback``, ``hang``, ``wrong`` (a bad input accepted or an output wrong
without a word) or ``uncounted`` (records lost without being counted). Exit status 1 when any trial failed.
``--scale`` multiplies the randomised trial counts (fuzzed streams, flood size, kills).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import textwrap
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from magstack.cli.main import main as cli  # noqa: E402
from magstack.data.dictionary import APP_APID, COMMAND  # noqa: E402
from magstack.data.packets import ApidMap, encode_command_args, pack_tc  # noqa: E402
from magstack.data.session import read_session  # noqa: E402

FAILURES = ("traceback", "hang", "wrong", "uncounted")


class Bad(Exception):
    """A failed trial: ``kind`` one of FAILURES."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def expect(cond: bool, message: str, kind: str = "wrong") -> None:
    if not cond:
        raise Bad(kind, message)


class Campaign:
    def __init__(self) -> None:
        self.results: dict[str, Counter] = defaultdict(Counter)
        self.failures: list[tuple[str, str, str, str]] = []

    def trial(self, category: str, name: str, fn: Callable[[], str]) -> None:
        try:
            outcome = fn()
        except Bad as exc:
            outcome = exc.kind
            self.failures.append((category, name, exc.kind, str(exc)[:300]))
        except Exception as exc:  # noqa: BLE001 - an exception escaping the code under test is a traceback
            outcome = "traceback"
            self.failures.append((category, name, "traceback", f"{type(exc).__name__}: {exc}"[:300]))
        self.results[category][outcome] += 1


def run_cli(argv: list[str]) -> tuple[int, str, str]:
    """``magstack argv`` in this process: (exit code, stdout, stderr); an exception out of it is a traceback."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli(argv)
    if "Traceback" in err.getvalue():
        raise Bad("traceback", err.getvalue()[-300:])
    return code, out.getvalue(), err.getvalue()


def refused(argv: list[str], code: int, why: str) -> Callable[[], str]:
    def t() -> str:
        got, _, err = run_cli(argv)
        expect(got == code and why in err and len(err.strip().splitlines()) == 1,
               f"exit {got} (want {code}), stderr {err[-200:]!r}")
        return "refused"
    return t


CHILD = textwrap.dedent("""
    import resource, sys
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
    from magstack.cli.main import main
    sys.exit(main(sys.argv[1:]))
""")


def child_refused(argv: list[str], code: int, why: str, timeout_s: float = 60.0) -> Callable[[], str]:
    def t() -> str:
        try:
            r = subprocess.run([sys.executable, "-c", CHILD, *argv], capture_output=True, text=True,
                               timeout=timeout_s, cwd=ROOT)
        except subprocess.TimeoutExpired:
            raise Bad("hang", f"still running after {timeout_s} s") from None
        if "Traceback" in r.stderr or "MemoryError" in r.stderr:
            raise Bad("traceback", r.stderr[-300:])
        expect(r.returncode == code and why in r.stderr, f"exit {r.returncode} (want {code}): {r.stderr[-200:]!r}")
        return "refused"
    return t


# ------------------------------------------------------------------------------------- fixtures
def sim_config(d: Path, table: bool = False) -> Path:
    from magstack.firmware.flight.config import example_config_text

    d.mkdir(parents=True, exist_ok=True)
    text = (example_config_text().replace("spi0.0,start=6,reset=13,drdy=19,sr=5", "sim")
            .replace('bus = "1"', 'bus = "sim"'))
    if table:
        from magstack.firmware import cal_table as ct

        (d / "tables").mkdir(exist_ok=True)
        ct.save_table(ct.CalTable(device_id="hmc1053:sn1", terms=("gain_matrix", "offset"), S=np.eye(3),
                                  O=np.zeros(3), validity_field_uT=100.0), d / "tables/hmc1053.json")
    else:
        text = text.replace('table = "tables/hmc1053.json"', "")
    p = d / "flight.toml"
    p.write_text(text)
    return p


def tc(name: str, *args: str, seq: int = 1, source: int = 1, apid: int = APP_APID) -> bytes:
    data = struct.pack(">H", COMMAND[name].opcode) + encode_command_args(args) if name != "ping" else b""
    return pack_tc(*((17, 1) if name == "ping" else (8, 1)), data, apid=apid, seq_count=seq, source_id=source)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def receiver(d: Path, **cfg):
    from magstack.firmware.flight.ccsds import CcsdsConfig, PacketStream
    from magstack.firmware.flight.events import EventLog
    from magstack.firmware.flight.telecommands import STATE_NAME, TelecommandReceiver

    stream = PacketStream(ApidMap(("mag",), ("g",)), path=d / "tm.bin", udp=None)
    dispatched: list = []
    rx = TelecommandReceiver(CcsdsConfig(**cfg), EventLog(), stream, dispatched.append, lambda: 0.0,
                             state_path=d / STATE_NAME)
    return rx, stream, dispatched


# ------------------------------------------------------------------------------------- categories
def cat_udp_tc(c: Campaign, d: Path, rng: np.random.Generator, scale: float) -> None:
    port, other = free_port(), free_port()
    rx, stream, dispatched = receiver(d, tc_udp=("127.0.0.1", port))
    (d / "other").mkdir()
    # a receiver whose only allowed host is not this one (TEST-NET-1): everything sent from 127.0.0.1 is foreign
    rx2, stream2, _ = receiver(d / "other", tc_udp=("127.0.0.1", other), tc_hosts=("192.0.2.1",))
    good = tc("activate_table", "mag", seq=5)
    flipped = bytearray(good)
    flipped[-1] ^= 0x40
    cases = [("valid", good, "127.0.0.1", "accepted"), ("bad crc", bytes(flipped), "127.0.0.1", "bad_crc"),
             ("truncated", good[:-3], "127.0.0.1", "malformed"), ("trailing byte", good + b"\0", "127.0.0.1",
                                                                   "malformed"),
             ("wrong apid", tc("activate_table", "mag", seq=6, apid=0x123), "127.0.0.1", "wrong_apid"),
             ("foreign host", tc("activate_table", "mag", seq=7), "foreign", "unauthorised"),
             ("foreign source id", tc("activate_table", "mag", seq=8, source=9), "127.0.0.1", "unauthorised"),
             ("replay", good, "127.0.0.1", "replayed"),
             ("far ahead", tc("dump_counters", seq=9000), "127.0.0.1", "out_of_window"),
             ("next after far ahead", tc("dump_counters", seq=6), "127.0.0.1", "accepted"),
             ("unknown function", pack_tc(8, 1, b"\x00\x63", seq_count=7, source_id=1), "127.0.0.1", "invalid"),
             ("65-byte channel", tc("activate_table", "a" * 65, seq=8), "127.0.0.1", "invalid"),
             ("service not provided", pack_tc(3, 5, b"", seq_count=9, source_id=1), "127.0.0.1", "invalid"),
             ("ping", tc("ping", seq=10), "127.0.0.1", "accepted")]

    def send(data: bytes, to: str) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(data, ("127.0.0.1", other if to == "foreign" else port))

    def take(n_before: int, want: int) -> None:
        for _ in range(400):
            rx.poll()
            if rx.counters.accepted + rx.counters.rejected >= n_before + want:
                return
            time.sleep(0.005)
        raise Bad("uncounted", f"{n_before + want - rx.counters.accepted - rx.counters.rejected} datagrams not counted")

    for name, data, host, counter in cases:
        def t(data=data, host=host, counter=counter) -> str:
            r = rx2 if host == "foreign" else rx
            before = dict(vars(r.counters))
            n = len(dispatched)
            send(data, host)
            for _ in range(400):
                r.poll()
                if sum(vars(r.counters).values()) > sum(before.values()):
                    break
                time.sleep(0.005)
            after = vars(r.counters)
            moved = [k for k in after if after[k] != before[k]]
            expect(moved == [counter], f"counted under {moved}, want {counter}")
            expect((len(dispatched) > n) == (counter == "accepted" and data[7] == 8),
                   "dispatched" if len(dispatched) > n else "not dispatched")
            return "correct" if counter == "accepted" else "refused"
        c.trial("udp_tc", name, t)
    flood = int(2000 * scale)

    def t_flood() -> str:
        n0 = rx.counters.accepted + rx.counters.rejected
        accepted = rx.counters.accepted
        for k in range(flood):
            send(bytes(rng.integers(0, 256, int(rng.integers(1, 80)), dtype=np.uint8)), "127.0.0.1")
            if k % 100 == 99:
                take(n0, k + 1)
        take(n0, flood)
        expect(rx.counters.accepted == accepted, "junk accepted")
        return "refused"
    c.trial("udp_tc", f"flood of {flood} junk datagrams", t_flood)
    for x in (rx, stream, rx2, stream2):
        x.close()


def cat_tc_dir(c: Campaign, d: Path) -> None:
    tcd = d / "tc"
    rx, stream, dispatched = receiver(d, tc_dir=tcd)
    outside = d / "outside.tc"
    outside.write_bytes(tc("dump_counters", seq=2))
    hostile: dict[str, Callable[[Path], None]] = {
        "symlink.tc": lambda p: os.symlink(outside, p),
        "world-writable.tc": lambda p: (p.write_bytes(tc("dump_counters", seq=3)), p.chmod(0o666)),
        "group-writable.tc": lambda p: (p.write_bytes(tc("dump_counters", seq=4)), p.chmod(0o620)),
        "sparse-6GiB.tc": lambda p: open(p, "wb").truncate(6 << 30),
        "fifo.tc": lambda p: os.mkfifo(p),
        "directory.tc": lambda p: p.mkdir(),
        "2049-bytes.tc": lambda p: (p.write_bytes(b"\x18" * 2049), p.chmod(0o600)),
        "empty.tc": lambda p: (p.write_bytes(b""), p.chmod(0o600)),
    }
    if os.geteuid() == 0:
        hostile["foreign.tc"] = lambda p: (p.write_bytes(tc("dump_counters", seq=5)), p.chmod(0o600),
                                           os.chown(p, 12345, 12345))
    for name, make in hostile.items():
        def t(name=name, make=make) -> str:
            make(tcd / name)
            before, n = rx.counters.rejected, len(dispatched)
            rx.poll()
            expect(rx.counters.rejected == before + 1 and len(dispatched) == n, f"{name} not refused")
            expect(not os.path.lexists(tcd / name), f"{name} left to be taken again")
            return "refused"
        c.trial("tc_dir", name, t)

    def t_good() -> str:
        p = tcd / "good.tc"
        p.write_bytes(tc("dump_counters", seq=1))
        p.chmod(0o600)
        rx.poll()
        expect([x.name for x in dispatched] == ["dump_counters"], f"dispatched {dispatched}")
        return "correct"
    c.trial("tc_dir", "valid packet file", t_good)
    rx.close()
    stream.close()


def cat_command_dir(c: Campaign, d: Path) -> None:
    import logging

    from magstack.firmware.flight.app import FlightApp
    from magstack.firmware.flight.config import load_config

    logging.getLogger("magstack.flight").setLevel(logging.ERROR)      # the refusals are expected: no console
    cfg = sim_config(d, table=True)
    cmd = d / "commands"
    cmd.mkdir(mode=0o700)
    good = d / "tables" / "hmc1053.json"
    files = {
        "devzero.json": {"cmd": "load_table", "channel": "hmc1053", "path": "/dev/zero"},
        "outside.json": {"cmd": "load_table", "channel": "hmc1053", "path": "/etc/passwd"},
        "etc-refit.json": {"cmd": "start_refit", "channel": "hmc1053", "files": "/etc/*"},
        "unknown-arg.json": {"cmd": "dump_counters", "x": "1"},
        "long-channel.json": {"cmd": "activate_table", "channel": "a" * 65},
        "bad-resync.json": {"cmd": "resync_tc", "source_id": "1", "seq": "99999"},
    }
    for name, doc in files.items():
        (cmd / name).write_text(json.dumps(doc))
    os.symlink(good, cmd / "symlink.json")
    os.mkfifo(cmd / "fifo.json")
    open(cmd / "sparse.json", "wb").truncate(6 << 30)
    (cmd / "world.json").write_text(json.dumps({"cmd": "dump_counters"}))
    (cmd / "world.json").chmod(0o666)
    (cmd / "zz-good.json").write_text(json.dumps({"cmd": "load_table", "channel": "hmc1053",
                                                  "path": "tables/hmc1053.json"}))
    app = FlightApp(load_config(cfg), virtual=True, simulate=True, telemetry_dir=d / "tlm", run_id=1)
    try:
        app.run(6.0)
    finally:
        app.close()
        logging.getLogger("magstack.flight").setLevel(logging.NOTSET)
    results = {p.name[:-len(".result.json")]: json.loads(p.read_text()) for p in (cmd / "done").glob("*.result.json")}
    for name in [*files, "symlink.json", "fifo.json", "sparse.json", "world.json"]:
        def t(name=name) -> str:
            r = results.get(name)
            expect(r is not None, f"{name}: no result", "uncounted")
            expect(r["ok"] is False, f"{name} executed: {r['message']}")
            return "refused"
        c.trial("command_dir", name, t)
    c.trial("command_dir", "valid load_table", lambda: (expect(results["zz-good.json"]["ok"] is True,
                                                               results["zz-good.json"]["message"]), "correct")[1])


def cat_config(c: Campaign, d: Path) -> None:
    base = sim_config(d / "base").read_text()
    cases = [("rate 1e309", ("rate_hz = 10.0", "rate_hz = 1e309"), "rate_group[1].rate_hz"),
             ("5000-digit integer", ("block_rows = 50", "block_rows = " + "9" * 5000), "flight"),
             ("negative rotation", ("rotate_mb = 16", "rotate_mb = -1"), "flight.rotate_mb"),
             ("string rate", ("rate_hz = 1.0", 'rate_hz = "fast"'), "rate_group[0].rate_hz"),
             ("hk period 0", ("hk_period_s = 10.0", "hk_period_s = 0"), "ccsds.hk_period_s"),
             ("commands in the telemetry", ('command_dir = "commands"', 'command_dir = "telemetry"'),
              "flight.command_dir"),
             ("telecommands in the commands", ('tc_dir = "telecommands"', 'tc_dir = "commands"'), "ccsds.tc_dir"),
             ("port 0", ('tc_udp = "127.0.0.1:50511"', 'tc_udp = "127.0.0.1:0"'), "ccsds.tc_udp")]
    for k, (name, (old, new), key) in enumerate(cases):
        def t(k=k, old=old, new=new, key=key) -> str:
            p = d / f"c{k}" / "flight.toml"
            p.parent.mkdir()
            expect(old in base, f"{old!r} not in the example")
            p.write_text(base.replace(old, new, 1))
            return refused(["run", "--config", str(p), "--duration", "1"], 3, key)()
        c.trial("config", name, t)

    def t_any() -> str:
        p = d / "any" / "flight.toml"
        p.parent.mkdir()
        p.write_text(base.replace('tc_udp = "127.0.0.1:50511"', f'tc_udp = "0.0.0.0:{free_port()}"', 1))
        bind = socket.socket.bind

        def loopback_only(self, addr):      # the campaign never listens beyond 127.0.0.1
            return bind(self, ("127.0.0.1", addr[1]) if addr[0] == "0.0.0.0" else addr)
        socket.socket.bind = loopback_only
        try:
            code, _, err = run_cli(["run", "--config", str(p), "--duration", "1", "--out", str(p.parent / "tlm")])
        finally:
            socket.socket.bind = bind
        expect(code == 0 and "every network interface" in err, f"exit {code}, no warning: {err[-200:]!r}")
        return "correct"
    c.trial("config", "tc_udp on 0.0.0.0 (warned)", t_any)


def cat_tc_sequence(c: Campaign, d: Path) -> None:
    rx, stream, _ = receiver(d)
    steps = [("first contact", tc("dump_counters", seq=100), True), ("far ahead", tc("dump_counters", seq=8100), False),
             ("operator goes on", tc("dump_counters", seq=101), True), ("replay", tc("dump_counters", seq=100), False),
             ("gap within the window", tc("dump_counters", seq=150), True),
             ("behind beyond the window", tc("dump_counters", seq=20), False)]
    for name, data, ok in steps:
        c.trial("tc_sequence", name, lambda data=data, ok=ok: (expect(rx.receive(data) == ok, "wrong decision"),
                                                               "correct" if ok else "refused")[1])
    rx.close()
    stream.close()
    rx2, stream2, _ = receiver(d)                            # a restart: the saved state is read back
    c.trial("tc_sequence", "replay after a restart",
            lambda: (expect(not rx2.receive(tc("dump_counters", seq=150)), "replay accepted"), "refused")[1])
    rx2.resync(1, 5000)
    c.trial("tc_sequence", "after resync",
            lambda: (expect(rx2.receive(tc("dump_counters", seq=5000)), "refused after resync"), "correct")[1])
    rx2.close()
    stream2.close()


def _two_runs(d: Path) -> tuple[Path, Path]:
    a = sim_config(d / "a", table=True)
    code, _, _ = run_cli(["run", "--config", str(a), "--duration", "20", "--out", str(d / "a" / "tlm"), "-q"])
    expect(code == 0, "run a failed")
    b = sim_config(d / "b", table=True)
    text = b.read_text()
    head, rest = text.split("[[sensor]]", 1)
    first, second = rest.split("[[sensor]]", 1)
    second, tail = second.split("# CCSDS", 1)
    b.write_text(head + "[[sensor]]" + second + "[[sensor]]" + first + "# CCSDS" + tail)
    code, _, _ = run_cli(["run", "--config", str(b), "--duration", "20", "--out", str(d / "b" / "tlm"), "-q"])
    expect(code == 0, "run b failed")
    return d / "a" / "tlm", d / "b" / "tlm"


def cat_stream(c: Campaign, d: Path, rng: np.random.Generator, scale: float, runs: tuple[Path, Path]) -> None:
    from magstack.ground.tm_decode import decode_files

    a, b = runs
    data = (a / "packets-0001.bin").read_bytes()
    truth = {ch: read_session(a / f"{ch}-0001-0001.csv") for ch in ("hmc1053", "lis3mdl")}

    def rows_ok(out: Path, truth: dict) -> int:
        n = 0
        for p in out.glob("*.csv"):
            s = read_session(p)
            ref = truth[s.metadata["telemetry_channel"]]
            for t, row in zip(s.t_s, s.dut_uT, strict=True):
                k = int(np.argmin(np.abs(ref.t_s - t)))
                expect(abs(ref.t_s[k] - t) < 1e-4 and np.allclose(ref.dut_uT[k], row, atol=2e-4, equal_nan=True),
                       f"{p.name}: a row at {t} the run did not record")
                n += 1
        return n

    for k in range(int(55 * scale)):
        def t(k=k) -> str:
            b_ = bytearray(data)
            ops = []
            for _ in range(int(rng.integers(1, 6))):
                op, at = rng.choice(["flip", "cut", "dup", "junk"]), int(rng.integers(0, len(b_)))
                ops.append(op)
                if op == "flip":
                    b_[at] ^= 1 << int(rng.integers(0, 8))
                elif op == "cut":
                    del b_[at:at + int(rng.integers(1, 200))]
                elif op == "dup":
                    b_[at:at] = b_[at:at + int(rng.integers(1, 200))]
                else:
                    b_[at:at] = bytes(rng.integers(0, 256, int(rng.integers(1, 100)), dtype=np.uint8))
            src = d / f"s{k}.bin"
            src.write_bytes(bytes(b_))
            try:
                rep = decode_files([src], d / f"s{k}")
            except ValueError as exc:               # no valid packet left: a clean refusal
                expect("no valid packet" in str(exc), str(exc))
                return "refused"
            n = rows_ok(d / f"s{k}", truth)
            expect(n + rep.unattributed <= sum(len(s) for s in truth.values()) + rep.seq_repeated,
                   "more rows than recorded")
            expect(bytes(b_) == data or rep.bad_packets + rep.seq_repeated + rep.seq_missing > 0,
                   f"damage ({ops}) not counted")
            shutil.rmtree(d / f"s{k}", ignore_errors=True)
            return "correct"
        c.trial("stream", f"fuzzed stream {k}", t)

    def t_concat() -> str:
        both = d / "both.bin"
        both.write_bytes(data + (b / "packets-0001.bin").read_bytes())
        rep = decode_files([both], d / "both")
        expect(rep.unattributed == 0 and rep.identity_conflicts == 2, f"{rep.to_dict()}")
        for run in (a, b):
            tr = {ch: read_session(run / f"{ch}-0001-0001.csv") for ch in ("hmc1053", "lis3mdl")}
            for p in (d / "both").glob("*.csv"):
                s = read_session(p)
                ref = tr[s.metadata["telemetry_channel"]]
                expect(len(s) == len(ref), f"{p.name}: {len(s)} rows, a run recorded {len(ref)}")
        return "correct"
    c.trial("stream", "two runs, sensors in another order", t_concat)


def cat_decode_out(c: Campaign, d: Path, runs: tuple[Path, Path]) -> None:
    tlm = d / "tlm"
    shutil.copytree(runs[0], tlm)
    before = {p.name: p.read_bytes() for p in tlm.iterdir()}

    def t_own() -> str:
        r = refused(["tm", "decode", str(tlm / "packets-0001.bin"), "--out", str(tlm)], 2, "another directory")()
        expect({p.name: p.read_bytes() for p in tlm.iterdir()} == before, "flight files changed")
        return r
    c.trial("decode_out", "--out = the telemetry directory", t_own)

    def t_planted() -> str:
        victim = d / "victim"
        victim.write_text("keep\n")
        out = d / "dec"
        out.mkdir()
        for n in (".events.jsonl.tmp", ".housekeeping.jsonl.tmp", ".decode-report.json.tmp"):
            os.symlink(victim, out / n)
        code, _, _ = run_cli(["tm", "decode", str(tlm / "packets-0001.bin"), "--out", str(out), "-q"])
        expect(code == 0 and victim.read_text() == "keep\n", f"exit {code}, victim {victim.read_text()!r}")
        return "correct"
    c.trial("decode_out", "planted temporary-file symlinks", t_planted)

    def t_taken() -> str:
        out = d / "mine"
        out.mkdir()
        (out / "events.jsonl").write_text("mine\n")
        r = refused(["tm", "decode", str(tlm / "packets-0001.bin"), "--out", str(out)], 2, "no earlier tm decode")()
        expect((out / "events.jsonl").read_text() == "mine\n", "replaced")
        return r
    c.trial("decode_out", "a name taken by another file", t_taken)


def cat_tables(c: Campaign, d: Path) -> None:
    from magstack.firmware import cal_table as ct
    from magstack.firmware.errors import CalTableInvalid
    from magstack.firmware.flight.tables import FlightTableStore

    def table(name: str, cov_x, **extra) -> Path:
        names = {a: [f"S[{a},{j}]" for j in "xyz"] + [f"O[{a}]"] for a in "xyz"}
        post = {a: {"names": names[a], "cov": (np.eye(4) * 1e-6).tolist()} for a in "xyz"}
        post["x"]["cov"] = cov_x
        post.update(extra)
        p = d / f"{name}.json"
        ct.save_table(ct.CalTable(device_id="m:1", terms=("gain_matrix", "offset"), S=np.eye(3), O=np.zeros(3),
                                  validity_field_uT=100.0, posterior=post), p)
        return p

    def cov(**kv) -> list:
        m = np.eye(4) * 1e-6
        for key, v in kv.items():
            m[int(key[1]), int(key[2])] = v
        return m.tolist()
    cases = {"negative variance by a 1e300 entry": (cov(e00=1e300, e11=-1.0), {}),
             "negative variance by a 1e10 entry": (cov(e00=1e10, e11=-1.0), {}),
             "asymmetry by a 1e10 entry": (cov(e00=1e10, e23=5e-7), {}),
             "all 1e308": (np.full((4, 4), 1e308).tolist(), {}),
             "correlation above 1": (cov(e12=5e-6, e21=5e-6), {}),
             "negative sigma": (cov(), {"sigma_uT": [0.1, -1.0, 0.1]}),
             "negative bound": (cov(), {"bound_uT": -0.1}),
             "zero bound": (cov(), {"bound_uT": 0.0}),
             "negative noise floor": (cov(), {"noise_floor_uT": [0.0, -1e-3, 0.0]})}
    for name, (cv, extra) in cases.items():
        def t(name=name, cv=cv, extra=extra) -> str:
            p = table(name.replace(" ", "_"), cv, **extra)
            code, _, err = run_cli(["table", "validate", str(p)])
            expect(code == 1 and len(err.strip().splitlines()) == 1 and "posterior" in err, f"exit {code}: {err!r}")
            store = FlightTableStore("m:1", "m", (d,), d)
            try:
                store.load(p)
            except CalTableInvalid:
                return "refused"
            raise Bad("wrong", "the flight's table store staged it")
        c.trial("tables", name, t)


def cat_readers(c: Campaign, d: Path, inputs: dict[str, Path]) -> None:
    fifo = d / "fifo.csv"
    os.mkfifo(fifo)
    sparse = d / "sparse.csv"
    open(sparse, "wb").truncate(6 << 30)
    tbl, mag, adcs = str(inputs["table"]), str(inputs["mag"]), str(inputs["adcs"])
    out = str(d / "out")
    cases = {"merge --adcs /dev/zero": ["merge", mag, "--adcs", "/dev/zero", "--out", out + "1.csv"],
             "merge --adcs FIFO": ["merge", mag, "--adcs", str(fifo), "--out", out + "2.csv"],
             "merge --adcs 6 GiB": ["merge", mag, "--adcs", str(sparse), "--out", out + "3.csv"],
             "merge /dev/zero": ["merge", "/dev/zero", "--adcs", adcs, "--out", out + "4.csv"],
             "fit /dev/zero": ["fit", "/dev/zero", "--out", out + "5.json"],
             "fit FIFO": ["fit", str(fifo), "--out", out + "6.json"],
             "fit 6 GiB": ["fit", str(sparse), "--out", out + "7.json"],
             "apply /dev/zero": ["apply", tbl, "/dev/zero", "--out", out + "8.csv"],
             "align FIFO": ["align", str(fifo)],
             "tm decode /dev/zero": ["tm", "decode", "/dev/zero", "--out", out + "9"],
             "tm decode FIFO": ["tm", "decode", str(fifo), "--out", out + "10"],
             "tm decode 6 GiB": ["tm", "decode", str(sparse), "--out", out + "11"],
             "refit FIFO": ["refit", str(fifo), "--out", out + "12.json"],
             "diagnose FIFO": ["diagnose", str(fifo)],
             "table validate FIFO": ["table", "validate", str(fifo)]}
    for name, argv in cases.items():
        c.trial("readers", name, child_refused(argv, 3, "more than the" if "6 GiB" in name else "regular file"))


def cat_merge(c: Campaign, d: Path, inputs: dict[str, Path]) -> None:
    lines = inputs["adcs"].read_text().splitlines()

    def variant(name: str, row: int, cells: dict[int, str]) -> Path:
        ls = list(lines)
        x = ls[row].split(",")
        for i, v in cells.items():
            x[i] = v
        ls[row] = ",".join(x)
        p = d / f"{name}.csv"
        p.write_text("\n".join(ls) + "\n")
        return p
    cases = {"position 1e308 km": ({1: "1e308"}, "beyond any Earth orbit"),
             "the Earth's centre": ({1: "0", 2: "0", 3: "0"}, "inside the Earth"),
             "500 km from the centre": ({1: "500", 2: "0", 3: "0"}, "inside the Earth"),
             "quaternion norm 1.01": ({4: "1.01", 5: "0", 6: "0", 7: "0"}, "quaternion norm")}
    for k, (name, (cells, why)) in enumerate(cases.items()):
        p = variant(f"m{k}", 5, cells)
        c.trial("merge", name, refused(["merge", str(inputs["mag"]), "--adcs", str(p), "--out",
                                        str(d / f"o{k}.csv")], 3, why))

    def t_nan() -> str:
        p = variant("nan", 4, {2: "nan"})
        code, out, err = run_cli(["merge", str(inputs["mag"]), "--adcs", str(p), "--out", str(d / "n.csv"),
                                  "--json"])
        rep = json.loads(out)
        expect(code == 0 and rep["adcs_rows_skipped"] == 1 and "1 ADCS samples" in err, f"{code} {err!r}")
        return "correct"
    c.trial("merge", "a NaN sample (counted and said)", t_nan)

    def t_norm() -> str:
        ls = [lines[0]] + [",".join(x if i < 4 else f"{float(x) * 1.0009:.12f}" for i, x in enumerate(r.split(",")))
                           for r in lines[1:]]
        p = d / "norm.csv"
        p.write_text("\n".join(ls) + "\n")
        code, _, _ = run_cli(["merge", str(inputs["mag"]), "--adcs", str(p), "--out", str(d / "q.csv"), "--method",
                              "nearest", "-q"])
        s = read_session(d / "q.csv")
        q = np.column_stack([s.extra[k] for k in ("q_body_eci_w", "q_body_eci_x", "q_body_eci_y", "q_body_eci_z")])
        ok = np.all(np.isfinite(q), axis=1)
        expect(code == 0 and np.allclose(np.linalg.norm(q[ok], axis=1), 1, atol=1e-9), "not normalised")
        return "correct"
    c.trial("merge", "quaternions of norm 1.0009 (normalised)", t_norm)


FSIZE = textwrap.dedent("""
    import resource, sys
    resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), resource.RLIM_INFINITY))
    from magstack.cli.main import main
    sys.exit(main(sys.argv[2:]))
""")


def cat_full_disk(c: Campaign, d: Path) -> None:
    from magstack.ground.tm_decode import DecodeReport, iter_packets

    for limit in (9_000, 16_000, 24_000):          # the run's largest file reaches 29 kB in 40 s
        def t(limit=limit) -> str:
            root = d / f"fs{limit}"
            cfg = sim_config(root, table=True)
            tlm = root / "tlm"
            try:
                r = subprocess.run([sys.executable, "-c", FSIZE, str(limit), "run", "--config", str(cfg), "--duration",
                                    "40", "--out", str(tlm)], capture_output=True, text=True, timeout=300, cwd=ROOT)
            except subprocess.TimeoutExpired:
                raise Bad("hang", "run under a full disk did not end") from None
            if "Traceback" in r.stderr:
                raise Bad("traceback", r.stderr[-300:])
            expect(r.returncode == 1 and "DEGRADED" in r.stdout, f"exit {r.returncode}: {r.stderr[-200:]!r}")
            summary = json.loads((tlm / "summary-0001.json").read_text())
            for ch, x in summary["channels"].items():
                expect(x["telemetry"]["rows"] + x["telemetry"]["rows_lost"] == x["cycles"],
                       f"{ch}: rows not counted", "uncounted")
            rep = DecodeReport()
            pk = list(iter_packets((tlm / "packets-0001.bin").read_bytes(), rep))
            p = summary["packets"]
            expect(len(pk) == p["written"] and rep.bad_packets == 0, "packet file disagrees with the count")
            chan = sum(1 for x in pk if x.packet.name == "channel")
            dropped = summary["write_queue"]["dropped"].get("packets", 0)
            cycles = sum(x["cycles"] for x in summary["channels"].values())
            expect(chan + p["send_errors"] + dropped >= cycles, "channel packets lost without a count", "uncounted")
            return "correct"
        c.trial("full_disk", f"file size limit {limit} B", t)


def cat_kill9(c: Campaign, d: Path, rng: np.random.Generator, scale: float) -> None:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_kill import one_kill

    for k in range(max(1, int(5 * scale))):
        def t(k=k) -> str:
            (d / f"k{k}").mkdir()
            r = one_kill(d / f"k{k}", float(rng.uniform(0.5, 3.0)))
            expect(r["loss_s"] is not None and r["loss_s"] <= 1.0 and r["bad_packets"] == 0,
                   f"{r}", "uncounted")
            return "correct"
        c.trial("kill9", f"kill {k}", t)


def _inputs(d: Path) -> dict[str, Path]:
    """A table, a magnetometer session and its ADCS file for the reader and merge trials."""
    from magstack.data.session import Session, write_session
    from magstack.data.telemetry import POS_COLUMNS, QUAT_COLUMNS

    code, _, _ = run_cli(["simulate", "--program", "orbit_tumbling", "--seconds", "120", "--rate-hz", "1", "--t0",
                          "1780272000", "--out", str(d / "orbit.csv"), "-q"])
    expect(code == 0, "simulate failed")
    s = read_session(d / "orbit.csv")
    write_session(d / "mag.csv", Session(s.t_s, s.ref_uT, s.dut_uT, s.temp_c, s.session))
    rows = ["t_s," + ",".join(POS_COLUMNS + QUAT_COLUMNS)]
    rows += [",".join(f"{v:.9f}" for v in (s.t_s[k], *(s.extra[c][k] for c in POS_COLUMNS + QUAT_COLUMNS)))
             for k in range(len(s))]
    (d / "adcs.csv").write_text("\n".join(rows) + "\n")
    # two minutes of a tumble pin no table to a useful region: a wide --validity-sd (a table is all the trials need)
    code, _, _ = run_cli(["fit", str(d / "orbit.csv"), "--no-holdout", "--validity-sd", "5000", "--out",
                          str(d / "t.json"), "-q"])
    expect(code == 0, "fit failed")
    return {"table": d / "t.json", "mag": d / "mag.csv", "adcs": d / "adcs.csv"}


def run(scale: float, seed: int, only: set[str] | None = None) -> Campaign:
    c = Campaign()
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)

        def want(name: str) -> bool:
            return only is None or name in only

        for name, fn in (("udp_tc", lambda p: cat_udp_tc(c, p, rng, scale)), ("tc_dir", lambda p: cat_tc_dir(c, p)),
                         ("command_dir", lambda p: cat_command_dir(c, p)), ("config", lambda p: cat_config(c, p)),
                         ("tc_sequence", lambda p: cat_tc_sequence(c, p)), ("tables", lambda p: cat_tables(c, p))):
            if want(name):
                (t / name).mkdir()
                fn(t / name)
        if want("stream") or want("decode_out"):
            runs = _two_runs(t / "runs")
            if want("stream"):
                (t / "stream").mkdir()
                cat_stream(c, t / "stream", rng, scale, runs)
            if want("decode_out"):
                (t / "decode_out").mkdir()
                cat_decode_out(c, t / "decode_out", runs)
        if want("readers") or want("merge"):
            (t / "inputs").mkdir()
            inputs = _inputs(t / "inputs")
            if want("readers"):
                (t / "readers").mkdir()
                cat_readers(c, t / "readers", inputs)
            if want("merge"):
                (t / "merge").mkdir()
                cat_merge(c, t / "merge", inputs)
        if want("full_disk"):
            (t / "full_disk").mkdir()
            cat_full_disk(c, t / "full_disk")
        if want("kill9"):
            (t / "kill9").mkdir()
            cat_kill9(c, t / "kill9", rng, scale)
    return c


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", type=float, default=1.0, help="multiplies the randomised trial counts")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="", help="comma-separated categories (default: all)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    c = run(args.scale, args.seed, {x for x in args.only.split(",") if x} or None)
    total = Counter()
    for cnt in c.results.values():
        total.update(cnt)
    res = {"trials": sum(total.values()), "seconds": round(time.monotonic() - t0, 1),
           "totals": {k: total.get(k, 0) for k in ("refused", "correct", *FAILURES)},
           "categories": {k: dict(v) for k, v in c.results.items()},
           "failures": [{"category": a, "trial": b, "kind": k, "message": m} for a, b, k, m in c.failures]}
    if args.json:
        print(json.dumps(res))
    else:
        print(f"{'category':<12} " + " ".join(f"{k:>9}" for k in ("refused", "correct", *FAILURES)))
        for cat, cnt in c.results.items():
            print(f"{cat:<12} " + " ".join(f"{cnt.get(k, 0):>9}" for k in ("refused", "correct", *FAILURES)))
        print(f"{'total':<12} " + " ".join(f"{res['totals'][k]:>9}" for k in ("refused", "correct", *FAILURES)))
        print(f"{res['trials']} trials in {res['seconds']} s")
        for f in res["failures"]:
            print(f"FAILED {f['category']}/{f['trial']}: {f['kind']}: {f['message']}")
    return 1 if any(res["totals"][k] for k in FAILURES) else 0


if __name__ == "__main__":
    sys.exit(main())
