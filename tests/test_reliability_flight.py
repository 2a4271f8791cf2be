"""The flight application under a hostile operator and a failing disk: the telecommand directory under the one
intake rule, a full disk at the end of a run, telecommand sequence windows across restarts, the configuration
checks, and kill -9 against the packet file."""
from __future__ import annotations

import json
import os
import re
import socket
import stat
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from magstack.cli.main import main
from magstack.data.dictionary import APP_APID, COMMAND
from magstack.data.packets import ApidMap, encode_command_args, pack_tc
from magstack.firmware.errors import FlightConfigError
from magstack.firmware.flight.ccsds import CcsdsConfig, PacketStream
from magstack.firmware.flight.events import EventId, EventLog
from magstack.firmware.flight.intake import UnsafeInput
from magstack.firmware.flight.telecommands import TelecommandReceiver
from magstack.ground.tm_decode import DecodeReport, iter_packets
from tests.test_ccsds_packets import sim_config

ROOT = Path(__file__).resolve().parents[1]
STATE_NAME = "tc-receiver.state"             # the receiver's saved state, in the command directory


def _function(name: str, *args: str, seq: int = 1, source: int = 1) -> bytes:
    app = struct.pack(">H", COMMAND[name].opcode) + encode_command_args(args)
    return pack_tc(8, 1, app, apid=APP_APID, seq_count=seq, source_id=source)


class _Rig:
    """A telecommand receiver with a packet file, a telecommand directory and a state file in ``root``."""

    def __init__(self, root: Path, **cfg) -> None:
        self.root = root
        self.stream = PacketStream(ApidMap(("mag",), ("g",)), path=root / "tm.bin", udp=None)
        self.events = EventLog()
        self.dispatched = []
        self.rx = TelecommandReceiver(CcsdsConfig(**cfg), self.events, self.stream, self.dispatched.append,
                                      lambda: 100.0, state_path=root / STATE_NAME)

    def close(self) -> None:
        self.rx.close()
        self.stream.close()


# ------------------------------------------------------------------------------------- tc_dir: the intake rule
def test_telecommand_directory_is_private_and_hostile_packet_files_are_refused(tmp_path):
    old = os.umask(0)
    try:
        rig = _Rig(tmp_path, tc_dir=tmp_path / "tc")
    finally:
        os.umask(old)
    tc = tmp_path / "tc"
    assert stat.S_IMODE(os.stat(tc).st_mode) == 0o700 and stat.S_IMODE(os.stat(tc / "done").st_mode) == 0o700
    good = _function("dump_counters", seq=1)
    outside = tmp_path / "outside.tc"
    outside.write_bytes(_function("dump_counters", seq=2))
    os.symlink(outside, tc / "01-symlink.tc")
    (tc / "02-world-writable.tc").write_bytes(_function("dump_counters", seq=3))
    (tc / "02-world-writable.tc").chmod(0o666)
    with open(tc / "03-sparse.tc", "wb") as fh:               # 6 GiB, sparse: refused before a byte is read
        fh.truncate(6 << 30)
    os.mkfifo(tc / "04-fifo.tc")
    (tc / "05-dir.tc").mkdir()
    (tc / "06-good.tc").write_bytes(good)
    (tc / "06-good.tc").chmod(0o600)
    expect = {"01-symlink.tc": "is a symbolic link", "02-world-writable.tc": "writable by group or others",
              "03-sparse.tc": "more than the limit of 2048", "04-fifo.tc": "not a regular file",
              "05-dir.tc": "not a regular file"}
    if os.geteuid() == 0:
        (tc / "07-foreign.tc").write_bytes(_function("dump_counters", seq=4))
        os.chmod(tc / "07-foreign.tc", 0o600)
        os.chown(tc / "07-foreign.tc", 12345, 12345)
        expect["07-foreign.tc"] = "owned by uid 12345"
    assert rig.rx.poll() == len(expect) + 1
    assert rig.rx.poll() == 0                                  # each file taken once, never re-examined
    rig.close()
    c = rig.rx.counters
    assert c.accepted == 1 and [d.name for d in rig.dispatched] == ["dump_counters"]
    assert c.malformed == 4 and c.unauthorised == len(expect) - 4 and c.rejected == len(expect)
    messages = [ev.message for ev in rig.events.recent if ev.id == EventId.TC_REJECTED]
    for name, why in expect.items():
        assert any(name in m and why in m for m in messages), (name, messages)
    assert sorted(os.listdir(tc)) == ["done"]
    # a telecommand directory that others may write, or that another user owns: the application refuses to start
    (tmp_path / "open").mkdir(mode=0o777)
    os.chmod(tmp_path / "open", 0o777)
    with pytest.raises(UnsafeInput, match="writable by group or others"):
        _Rig(tmp_path, tc_dir=tmp_path / "open")


def test_run_refuses_an_open_telecommand_directory(tmp_path, capsys):
    cfg = sim_config(tmp_path)
    (tmp_path / "telecommands").mkdir(mode=0o777)
    os.chmod(tmp_path / "telecommands", 0o777)
    assert main(["run", "--config", str(cfg), "--duration", "1", "--out", str(tmp_path / "tlm")]) == 3
    err = capsys.readouterr().err
    assert "ccsds.tc_dir" in err and "writable by group or others" in err and "Traceback" not in err


def test_tables_and_refit_inputs_go_through_the_same_intake_rule(tmp_path):
    from magstack.firmware.flight.app import FlightApp
    from magstack.firmware.flight.config import load_config

    cfg = sim_config(tmp_path)
    (tmp_path / "tables" / "open.json").write_bytes((tmp_path / "tables" / "hmc1053.json").read_bytes())
    (tmp_path / "tables" / "open.json").chmod(0o666)
    (tmp_path / "open-tlm.csv").write_text("t_s\n")
    (tmp_path / "open-tlm.csv").chmod(0o666)
    cmd = tmp_path / "commands"
    cmd.mkdir(mode=0o700)
    (cmd / "01.json").write_text(json.dumps({"cmd": "load_table", "channel": "hmc1053", "path": "tables/open.json"}))
    (cmd / "02.json").write_text(json.dumps({"cmd": "start_refit", "channel": "hmc1053", "files": "open-tlm.csv"}))
    app = FlightApp(load_config(cfg), virtual=True, simulate=True, telemetry_dir=tmp_path / "tlm", run_id=1)
    try:
        app.run(2.0)
    finally:
        app.close()
    for name in ("01.json", "02.json"):
        res = json.loads((cmd / "done" / f"{name}.result.json").read_text())
        assert res["ok"] is False and "writable by group or others" in res["message"], res
    assert app.events.count(EventId.REFIT_STARTED) == 0 and app.slots["hmc1053"].store.load_count == 1  # config's


def test_tm_command_writes_packet_files_the_receiver_accepts_under_any_umask(tmp_path, capsys):
    cfg = sim_config(tmp_path)
    old = os.umask(0)
    try:
        assert main(["tm", "command", "--config", str(cfg), "dump_counters"]) == 0
    finally:
        os.umask(old)
    tc = tmp_path / "telecommands"
    assert stat.S_IMODE(os.stat(tc).st_mode) == 0o700
    (f,) = tc.glob("*.tc")
    assert stat.S_IMODE(os.stat(f).st_mode) == 0o600


# ------------------------------------------------------------------------------------- sequence counts
def test_sequence_window_no_lockout_and_no_replay_after_a_restart(tmp_path):
    rig = _Rig(tmp_path)
    rx = rig.rx
    assert rx.receive(_function("dump_counters", seq=5), origin=None)
    assert not rx.receive(_function("dump_counters", seq=8005), origin=None)      # far ahead: refused ...
    assert rx.counters.out_of_window == 1
    assert rx.receive(_function("dump_counters", seq=6), origin=None)             # ... and the operator goes on
    assert not rx.receive(_function("dump_counters", seq=5), origin=None) and rx.counters.replayed == 1
    assert rx.receive(_function("dump_counters", seq=40), origin=None)            # 33 lost on the way: fine
    assert rx.expected() == {1: 41}
    assert stat.S_IMODE(os.stat(tmp_path / STATE_NAME).st_mode) == 0o600
    rig.close()
    again = _Rig(tmp_path)                                                         # a restart keeps V(R)
    assert not again.rx.receive(_function("dump_counters", seq=40), origin=None)
    assert again.rx.counters.replayed == 1 and again.rx.expected() == {1: 41}
    assert again.rx.receive(_function("dump_counters", seq=41), origin=None)
    # resynchronise: exempt from the window, only for the sending source, then the count is the new one
    assert again.rx.receive(_function("resync_tc", "1", "9000", seq=12000), origin=None)
    assert again.dispatched[-1].name == "resync_tc" and again.rx.expected() == {1: 42}     # not executed yet
    again.rx.resync(1, 9000)                                                     # what the application executes
    assert not again.rx.receive(_function("dump_counters", seq=42), origin=None)
    assert again.rx.receive(_function("dump_counters", seq=9000), origin=None)
    assert not again.rx.receive(_function("resync_tc", "2", "0", seq=9001), origin=None)
    assert again.rx.counters.unauthorised == 1
    assert again.events.count(EventId.TC_RESYNC) == 1
    again.close()


def test_receiver_state_must_be_private_and_a_corrupt_one_is_reported(tmp_path):
    state = tmp_path / STATE_NAME
    state.write_text('{"format": "magstack-tc-receiver", "version": 1, "expected": {"1": 7}}\n')
    state.chmod(0o666)
    with pytest.raises(UnsafeInput, match="writable by group or others"):
        _Rig(tmp_path)
    state.chmod(0o600)
    assert _Rig(tmp_path).rx.expected() == {1: 7}
    state.write_text("{not json")
    rig = _Rig(tmp_path)
    assert rig.rx.expected() == {} and rig.rx.state_errors == 1 and rig.events.count(EventId.TC_STATE_ERROR) == 1


def test_resync_by_telecommand_through_the_flight_application(tmp_path, capsys):
    from magstack.firmware.flight.app import FlightApp
    from magstack.firmware.flight.config import load_config

    cfg = sim_config(tmp_path)
    tc = tmp_path / "telecommands"

    def command(*argv: str) -> None:
        assert main(["tm", "command", "--config", str(cfg), *argv]) == 0

    app = FlightApp(load_config(cfg), virtual=True, simulate=True, telemetry_dir=tmp_path / "tlm", run_id=1)
    try:
        command("dump_counters", "--seq", "5")
        app.run(1.0)
        command("dump_counters", "--seq", "9000")           # the ground's count jumped: out of the window
        app.run(1.0)
        command("dump_counters")                             # 9001: still out of the window, nothing moves
        app.run(1.0)
        command("resync_tc", "source_id=1", "seq=9002")      # the operator resynchronises ...
        app.run(1.0)
        command("dump_counters")                             # ... and the next count (9002) is taken
        app.run(1.0)
        rx = app.ccsds.receiver
        assert rx.counters.accepted == 3 and rx.counters.out_of_window == 2 and rx.expected() == {1: 9003}
        assert app.events.count(EventId.TC_RESYNC) == 1
        assert app.counters()["packets"]["telecommands"]["expected_seq"] == {"1": 9003}
    finally:
        app.close()
    replay = sorted((tc / "done").glob("*.tc"))[-1]
    (tc / "replay.tc").write_bytes(replay.read_bytes())
    (tc / "replay.tc").chmod(0o600)
    app = FlightApp(load_config(cfg), virtual=True, simulate=True, telemetry_dir=tmp_path / "tlm", run_id=2)
    try:
        app.run(1.0)
        assert app.ccsds.receiver.counters.replayed == 1 and app.ccsds.receiver.counters.accepted == 0
    finally:
        app.close()
    capsys.readouterr()


# ------------------------------------------------------------------------------------- full disk at the end
FSIZE_RUN = textwrap.dedent("""
    import resource, sys
    resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), resource.RLIM_INFINITY))
    from magstack.cli.main import main
    sys.exit(main(sys.argv[2:]))
""")


def test_a_full_disk_keeps_the_summary_and_counts_every_lost_packet(tmp_path):
    cfg = sim_config(tmp_path)
    tlm = tmp_path / "tlm"
    limit = 16_000                        # bytes per file: the packet file fills after about 25 of the 40 s
    r = subprocess.run([sys.executable, "-c", FSIZE_RUN, str(limit), "run", "--config", str(cfg), "--duration", "40",
                        "--out", str(tlm)], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])            # degraded, not a system error
    assert "Traceback" not in r.stderr
    assert "rate group slow" in r.stdout and "packets" in r.stdout and "DEGRADED:" in r.stdout
    summary = json.loads((tlm / "summary-0001.json").read_text())
    pk = summary["packets"]
    assert pk["send_errors"] > 0 and any("packets could not be written" in d for d in summary["degraded"])
    # every packet written or counted: channel records (CSV rows and packets are the same records)
    data = (tlm / "packets-0001.bin").read_bytes()
    rep = DecodeReport()
    packets = list(iter_packets(data, rep))
    assert rep.bad_packets == 0 and len(data) <= limit                      # no cut packet at the end
    assert len(packets) == pk["written"]
    cycles = sum(c["cycles"] for c in summary["channels"].values())
    channel_packets = sum(1 for p in packets if p.packet.name == "channel")
    assert channel_packets < cycles
    # no cut CSV row: every file, finished or broken, ends with a whole line of the header's width
    for f in list(tlm.glob("*.csv")) + list(tlm.glob("*.part")):
        text = f.read_bytes()
        assert text.endswith(b"\n"), f.name
        lines = [ln for ln in text.decode().splitlines() if ln and not ln.startswith("#")]
        width = lines[0].count(",")
        assert all(ln.count(",") == width for ln in lines), f.name
    for ch, c in summary["channels"].items():
        assert c["telemetry"]["rows"] + c["telemetry"]["rows_lost"] == c["cycles"], ch


def test_packet_stream_close_never_raises(tmp_path, monkeypatch):
    import errno

    s = PacketStream(ApidMap(("m",), ("g",)), path=tmp_path / "p.bin", udp=None)
    s.emit("ping_reply", APP_APID, 0.0, {})
    real_fsync = os.fsync

    def fail(_fd):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(os, "fsync", fail)
    s.close()
    monkeypatch.setattr(os, "fsync", real_fsync)
    assert s.sync_errors == 1 and s.sent == 1
    s.emit("ping_reply", APP_APID, 0.0, {})                     # after close: counted, not raised
    assert s.send_errors == 1


# ------------------------------------------------------------------------------------- configuration checks
def test_command_and_telemetry_directories_must_differ(tmp_path, capsys):
    cfg = sim_config(tmp_path)
    cfg.write_text(cfg.read_text().replace('command_dir = "commands"', 'command_dir = "telemetry"'))
    assert main(["run", "--config", str(cfg), "--duration", "1"]) == 3
    assert "flight.command_dir" in capsys.readouterr().err
    cfg = sim_config(tmp_path / "b")
    assert main(["run", "--config", str(cfg), "--duration", "1", "--out", str(tmp_path / "b" / "commands")]) == 3
    assert "use different directories" in capsys.readouterr().err
    with pytest.raises(FlightConfigError, match="ccsds.tc_dir"):
        from magstack.firmware.flight.config import load_config

        cfg.write_text(cfg.read_text().replace('tc_dir = "telecommands"', 'tc_dir = "commands"'))
        load_config(cfg)


def test_tm_command_refuses_what_the_receiver_refuses(tmp_path, capsys):
    cfg = sim_config(tmp_path)
    for argv, why in ((["load_table", "channel=" + "a" * 65, "path=t.json"], "longer than 64"),
                      (["resync_tc", "source_id=1", "seq=16384"], "integer in 0..16383"),
                      (["resync_tc", "source_id=x", "seq=1"], "integer in 0..65535"),
                      (["resync_tc", "source_id=2", "seq=1"], "resynchronises only itself")):
        assert main(["tm", "command", "--config", str(cfg), *argv]) == 2, argv
        assert why in capsys.readouterr().err, argv
    assert not list((tmp_path / "telecommands").glob("*.tc")) if (tmp_path / "telecommands").exists() else True


def test_listening_on_every_interface_is_warned_about(tmp_path, capsys, monkeypatch):
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    bind = socket.socket.bind
    monkeypatch.setattr(socket.socket, "bind",          # the test never listens beyond the loopback
                        lambda self, addr: bind(self, ("127.0.0.1", addr[1]) if addr[0] == "0.0.0.0" else addr))
    cfg = sim_config(tmp_path)
    text, n = re.subn(r'^#? ?tc_udp = "127\.0\.0\.1:\d+"', f'tc_udp = "0.0.0.0:{port}"', cfg.read_text(), flags=re.M)
    assert n == 1
    cfg.write_text(text)
    assert main(["run", "--config", str(cfg), "--duration", "1", "--out", str(tmp_path / "tlm")]) == 0
    assert "listens on every network interface" in capsys.readouterr().err


# ------------------------------------------------------------------------------------- kill -9
@pytest.mark.slow
def test_kill_9_loses_at_most_a_second_of_packets(tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_kill.py"), "--kills", "3", "--json",
                        "--dir", str(tmp_path)], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout)
    assert res["kills"] == 3 and res["max_loss_s"] <= 1.0 and all(k["channel_packets"] > 0 for k in res["runs"])
