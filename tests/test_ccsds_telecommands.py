"""PUS-C telecommands: the receiver's checks, its reports, fuzzing, and a table activated by telecommand."""
from __future__ import annotations

import json
import socket
import struct
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.cli.main import main
from magstack.data.dictionary import APP_APID, COMMAND, TcFailure
from magstack.data.packets import ApidMap, encode_command_args, pack_tc
from magstack.data.session import read_session
from magstack.firmware import cal_table as ct
from magstack.firmware.flight.ccsds import CcsdsConfig, PacketStream
from magstack.firmware.flight.events import EventId, EventLog
from magstack.firmware.flight.telecommands import TelecommandReceiver
from magstack.ground.tm_decode import DecodeReport, iter_packets
from tests.test_ccsds_packets import sim_config


def _function(name: str, *args: str, seq: int = 1, apid: int = APP_APID, source: int = 1) -> bytes:
    app = struct.pack(">H", COMMAND[name].opcode) + encode_command_args(args)
    return pack_tc(8, 1, app, apid=apid, seq_count=seq, source_id=source)


class _Rig:
    def __init__(self, tmp_path: Path) -> None:
        self.path = tmp_path / "tm.bin"
        self.stream = PacketStream(ApidMap(("mag",), ("g",)), path=self.path, udp=None)
        self.events = EventLog()
        self.dispatched = []
        self.rx = TelecommandReceiver(CcsdsConfig(tc_hosts=("127.0.0.1",), tc_source_ids=(1,)), self.events,
                                      self.stream, self.dispatched.append, lambda: 100.0)

    def reports(self) -> list[tuple[str, dict]]:
        self.stream.close()
        rep = DecodeReport()
        return [(p.packet.name, p.raw) for p in iter_packets(self.path.read_bytes(), rep)]


def test_each_bad_packet_is_counted_reported_and_never_executed(tmp_path):
    r = _Rig(tmp_path)
    good = _function("activate_table", "mag", seq=5)
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0x40
    cases = [
        (bytes(bad_crc), "127.0.0.1", "bad_crc"),
        (good[:-3], "127.0.0.1", "malformed"),                       # truncated
        (good + b"\0", "127.0.0.1", "malformed"),                    # length field disagrees
        (_function("activate_table", "mag", seq=6, apid=0x123), "127.0.0.1", "wrong_apid"),
        (good, "10.0.0.7", "unauthorised"),                          # source address not configured
        (_function("activate_table", "mag", seq=7, source=9), "127.0.0.1", "unauthorised"),
        (pack_tc(8, 1, b"\x00\x63", seq_count=8, source_id=1), "127.0.0.1", "invalid"),    # unknown function id
        (pack_tc(8, 1, struct.pack(">H", 3) + b"\x05ab", seq_count=9, source_id=1), "127.0.0.1", "invalid"),
        (pack_tc(3, 5, b"", seq_count=10, source_id=1), "127.0.0.1", "invalid"),           # service not provided
    ]
    for data, host, counter in cases:
        before = getattr(r.rx.counters, counter)
        assert r.rx.receive(data, origin=host) is False
        assert getattr(r.rx.counters, counter) == before + 1, counter
    assert r.dispatched == [] and r.events.count(EventId.TC_REJECTED) == len(cases)
    assert r.rx.receive(good, origin="127.0.0.1") is True                       # seq 5 after the rejects: fine
    assert r.rx.receive(good, origin="127.0.0.1") is False and r.rx.counters.replayed == 1    # the same again
    assert r.rx.receive(_function("activate_table", "mag", seq=4), origin="127.0.0.1") is False   # older
    assert r.rx.counters.replayed == 2 and r.rx.counters.accepted == 1 and r.rx.counters.rejected == len(cases) + 2
    assert [(c.name, c.args) for c in r.dispatched] == [("activate_table", {"channel": "mag"})]
    reports = r.reports()
    codes = [raw["failure_code"] for name, raw in reports if name == "accept_fail"]
    # no report to an unauthorised source address; everything with a readable header gets a 1,2
    assert TcFailure.BAD_CRC in codes and TcFailure.WRONG_APID in codes and TcFailure.REPLAYED in codes
    assert len(codes) == len(cases) - 1 + 2 and sum(1 for n, _ in reports if n == "accept_ok") == 1


def test_ping_is_answered_and_completion_follows_the_command_event(tmp_path):
    r = _Rig(tmp_path)
    assert r.rx.receive(pack_tc(17, 1, seq_count=1, source_id=1), origin=None)
    assert r.rx.receive(_function("dump_counters", seq=2), origin=None)
    src = r.dispatched[0].source
    r.rx.on_event(r.events.emit(1.0, EventId.CMD_COMPLETED, src, "counters dumped"))
    names = [n for n, _ in r.reports()]
    assert names == ["accept_ok", "ping_reply", "complete_ok", "accept_ok", "complete_ok"]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.binary(max_size=80),
                          st.tuples(st.integers(0, 4), st.integers(0, 60), st.integers(0, 255))), max_size=20))
def test_fuzzed_telecommands_never_crash_and_are_all_counted(tmp_path_factory, items):
    r = _Rig(tmp_path_factory.mktemp("fuzz"))
    base = _function("load_table", "mag", "tables/x.json", seq=1)
    for k, it in enumerate(items):
        if isinstance(it, bytes):
            data = it
        else:
            kind, pos, val = it
            b = bytearray(_function("load_table", "mag", "tables/x.json", seq=k + 1))
            if kind == 0:
                b[pos % len(b)] ^= val or 1                       # corrupt one byte
            elif kind == 1:
                b = b[:pos % len(b)]                              # truncate
            elif kind == 2:
                b = bytearray(base)                               # replay the first
            elif kind == 3:
                b += bytes([val])                                 # trailing byte
            data = bytes(b)
        r.rx.receive(data, origin="127.0.0.1")
    c = r.rx.counters
    assert c.accepted + c.rejected == len(items) and len(r.dispatched) == c.accepted
    assert r.events.count(EventId.TC_REJECTED) == c.rejected


def test_udp_telecommand_from_an_allowed_host_is_received(tmp_path):
    r = _Rig(tmp_path)
    r.rx.close()
    # port 0: the system picks a free port for the receiver (no port another test could take in between)
    r.rx = TelecommandReceiver(CcsdsConfig(tc_udp=("127.0.0.1", 0)), r.events, r.stream, r.dispatched.append,
                               lambda: 1.0)
    port = r.rx.sock.getsockname()[1]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(pack_tc(17, 1, seq_count=3, source_id=1), ("127.0.0.1", port))
        s.sendto(b"\x18\xf0garbage", ("127.0.0.1", port))
    import time

    for _ in range(200):                      # the datagrams are on loopback; poll until both were taken
        r.rx.poll()
        if r.rx.counters.accepted + r.rx.counters.rejected == 2:
            break
        time.sleep(0.01)
    r.rx.close()
    assert r.rx.counters.accepted == 1 and r.rx.counters.malformed == 1


def test_table_activated_by_telecommand_shows_its_crc_in_telemetry(tmp_path, capsys):
    cfg = sim_config(tmp_path, table=False)
    (tmp_path / "tables").mkdir(exist_ok=True)
    table = ct.CalTable(device_id="hmc1053:sn1", terms=("gain_matrix", "offset"), S=np.eye(3), O=[0.1, 0.2, 0.3],
                        validity_field_uT=100.0)
    ct.save_table(table, tmp_path / "tables/new.json")
    crc = ct.load_table(tmp_path / "tables/new.json").crc32
    from magstack.firmware.flight.app import FlightApp
    from magstack.firmware.flight.config import load_config

    app = FlightApp(load_config(cfg), virtual=True, simulate=True, telemetry_dir=tmp_path / "tlm", run_id=1)
    try:
        app.run(5.0)                                  # uncalibrated: no table yet
        for seq, args in ((1, ["load_table", "channel=hmc1053", "path=tables/new.json"]),
                          (2, ["activate_table", "channel=hmc1053"])):
            assert main(["tm", "command", *args, "--config", str(cfg), "--seq", str(seq)]) == 0
        app.run(5.0)                                  # taken at the next boundary, swapped in at the one after
    finally:
        app.close()
    capsys.readouterr()
    assert main(["tm", "decode", str(tmp_path / "tlm/packets-0001.bin"), "--out", str(tmp_path / "dec")]) == 0
    s = read_session(tmp_path / "dec" / "hmc1053-0001-0001.csv")
    crcs = s.extra["table_crc32"]
    assert np.isnan(crcs[0]) and crcs[-1] == crc                 # no table, then the commanded one
    k = int(np.argmax(crcs == crc))
    assert np.all(np.isnan(crcs[:k])) and np.all(crcs[k:] == crc) and np.all(np.isfinite(s.extra["cal_x_uT"][k:]))
    hk = [json.loads(x) for x in (tmp_path / "dec" / "housekeeping.jsonl").read_text().splitlines()]
    names = [h["packet"] for h in hk]
    assert names.count("accept_ok") == 2 and names.count("complete_ok") == 2 and "accept_fail" not in names
    events = [json.loads(x)["name"] for x in (tmp_path / "dec" / "events.jsonl").read_text().splitlines()]
    assert "TABLE_LOADED" in events and "TABLE_ACTIVATED" in events
