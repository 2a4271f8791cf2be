"""CCSDS TM packets: encoding by the dictionary, the flight app's packet stream, `tm decode`, `tm xtce`."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.cli.main import main
from magstack.data.dictionary import APP_APID, CHANNEL_FIELDS, FIELD_LSB_UT, TM_PACKET
from magstack.data.errors import SessionFileError
from magstack.data.packets import PacketError, TmEncoder, cuc_bytes, cuc_seconds, decode_tm, from_raw, pack_tc
from magstack.data.session import read_session
from magstack.ground.tm_decode import DecodeReport, decode_files, iter_packets
from tests.test_flight_run_cli import _sim_config

FIELD = {f.name: f for f in CHANNEL_FIELDS}


def sim_config(tmp_path: Path, *, csv: bool = True, table: bool = True) -> Path:
    """The shipped example configuration on simulated buses (its [ccsds] table included)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    p = _sim_config(tmp_path, table=table)
    if not csv:
        p.write_text(p.read_text().replace("csv = true ", "csv = false"))
    return p


@given(st.lists(st.one_of(st.none(), st.floats(-300.0, 300.0)), min_size=6, max_size=6),
       st.one_of(st.none(), st.floats(-50, 120)), st.integers(0, 0xFFFF), st.floats(0, 4e9))
def test_channel_packet_round_trip(b, temp, flag, t_s):
    vals = {**dict(zip(("raw_x", "raw_y", "raw_z", "cal_x", "cal_y", "cal_z"), b, strict=True)), "temp": temp,
            "flag": flag, "table_crc32": 0x1234ABCD, "error_count": 7}
    p = decode_tm(TmEncoder().pack(TM_PACKET["channel"], 0x101, t_s, vals))
    assert p.apid == 0x101 and p.packet.name == "channel" and abs(p.t_s - t_s) <= 2 ** -17
    for k, v in vals.items():
        got = from_raw(FIELD[k], p.raw[k])
        if v is None:
            assert math.isnan(got)
        else:
            assert abs(got - v) <= FIELD[k].lsb / 2 + 1e-9


def test_out_of_range_values_are_clipped_not_sent_as_absent():
    p = decode_tm(TmEncoder().pack(TM_PACKET["channel"], 0x100, 0.0, {"raw_x": 1e9, "raw_y": -1e9, "temp": 1e6}))
    assert p.raw["raw_x"] == 2 ** 31 - 1 and p.raw["raw_y"] == -(2 ** 31) + 1 and p.raw["temp"] == 2 ** 15 - 1
    assert cuc_seconds(cuc_bytes(12.5)) == 12.5


def test_decode_tm_refuses_bad_crc_length_and_telecommands():
    good = TmEncoder().pack(TM_PACKET["ping_reply"], APP_APID, 1.0, {})
    bad = bytearray(good)
    bad[-1] ^= 1
    with pytest.raises(PacketError) as e:
        decode_tm(bytes(bad))
    assert e.value.kind == "crc"
    with pytest.raises(PacketError) as e:
        decode_tm(good + b"\0")
    assert e.value.kind == "length"
    with pytest.raises(PacketError):
        decode_tm(pack_tc(17, 1))


def _run(tmp_path: Path, cfg: Path, duration: float) -> Path:
    assert main(["run", "--config", str(cfg), "--duration", str(duration), "--out", str(tmp_path / "tlm"), "-q"]) == 0
    return tmp_path / "tlm"


def test_run_writes_packets_and_tm_decode_gives_the_run_csv_columns(tmp_path, capsys):
    tlm = _run(tmp_path, sim_config(tmp_path), 30)
    capsys.readouterr()
    assert main(["tm", "decode", str(tlm / "packets-0001.bin"), "--out", str(tmp_path / "dec"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["bad_packets"] == 0 and rep["seq_missing"] == 0 and rep["by_packet"]["channel"] == 30 + 300
    for ch in ("hmc1053", "lis3mdl"):
        run, dec = read_session(tlm / f"{ch}-0001-0001.csv"), read_session(tmp_path / "dec" / f"{ch}-0001-0001.csv")
        assert run.columns == dec.columns and len(run) == len(dec)
        assert np.max(np.abs(run.t_s - dec.t_s)) <= 2 ** -16
        assert np.nanmax(np.abs(run.dut_uT - dec.dut_uT)) <= FIELD_LSB_UT / 2 + 1e-6
        assert np.array_equal(run.flag, dec.flag) and np.array_equal(run.session, dec.session)
        for k in ("cal_x_uT", "table_crc32", "error_count"):
            assert np.array_equal(np.isnan(run.extra[k]), np.isnan(dec.extra[k]))
            assert np.nanmax(np.abs(run.extra[k] - dec.extra[k]), initial=0) <= FIELD_LSB_UT / 2 + 1e-6
        assert dec.metadata["device_id"] == run.metadata["device_id"]
    # the table the example activates shows in the packets (its CRC) and hmc1053 is calibrated
    dec = read_session(tmp_path / "dec" / "hmc1053-0001-0001.csv")
    assert np.all(dec.extra["table_crc32"] > 0) and np.all(np.isfinite(dec.extra["cal_x_uT"]))
    events = [json.loads(x) for x in (tmp_path / "dec" / "events.jsonl").read_text().splitlines()]
    assert [e["name"] for e in events][:2] == ["TABLE_ACTIVATED", "EXEC_STARTED"]


def test_csv_false_writes_packets_only(tmp_path):
    tlm = _run(tmp_path, sim_config(tmp_path, csv=False), 5)
    assert not list(tlm.glob("*.csv")) and (tlm / "packets-0001.bin").stat().st_size > 0


def test_xtce_names_exactly_the_configured_packets(tmp_path, capsys):
    cfg = sim_config(tmp_path)
    assert main(["tm", "xtce", "--config", str(cfg)]) == 0
    doc = capsys.readouterr().out
    for name in ("TM_CHANNEL_hmc1053", "TM_CHANNEL_lis3mdl", "TM_GROUP_HK_slow", "TM_GROUP_HK_fast", "TM_EVENT",
                 "TM_ACCEPT_FAIL", "TM_APP_HK"):
        assert f'name="{name}"' in doc
    cfg.write_text(re.sub(r"\ntc_udp = .*", "", cfg.read_text()).replace('name = "lis3mdl"', 'name = "mag2"')
                   .replace('tc_dir = "telecommands"', ""))
    assert main(["tm", "xtce", "--config", str(cfg)]) == 0
    doc = capsys.readouterr().out
    assert 'name="TM_CHANNEL_mag2"' in doc and "TM_CHANNEL_lis3mdl" not in doc
    assert "TM_ACCEPT_OK" not in doc and "TM_PING_REPLY" not in doc and "TM_EVENT" in doc   # no telecommand input
    cfg.write_text(cfg.read_text().split("[ccsds]")[0])
    assert main(["tm", "xtce", "--config", str(cfg)]) == 3
    assert "produces no packets" in capsys.readouterr().err


def _stream(n: int = 12) -> list[bytes]:
    enc = TmEncoder()
    return [enc.pack(TM_PACKET["channel"], 0x100, float(i), {"raw_x": float(i), "flag": i}) for i in range(n)]


def test_every_kind_of_bad_packet_is_counted_once():
    pk = _stream()
    bad_crc = bytearray(pk[2])
    bad_crc[20] ^= 0xFF
    long_len = bytearray(pk[5])
    long_len[5] += 3                                   # length field 3 bytes too long
    foreign = TmEncoder().pack(TM_PACKET["channel"], 0x100, 0.0, {})
    foreign = bytes([foreign[0] & 0xF8, 0x50]) + foreign[2:]   # APID 0x050: not ours (CRC now wrong too)
    stream = (pk[0] + pk[1] + bytes(bad_crc) + pk[3] + pk[3] + pk[4] + bytes(long_len) + pk[6] + b"\xff" * 9
              + pk[7] + pk[9] + foreign + pk[10] + pk[11][:-4])
    rep = DecodeReport()
    got = [p.raw["flag"] for p in iter_packets(stream, rep)]
    assert got == [0, 1, 3, 3, 4, 6, 7, 9, 10]
    assert (rep.bad_crc, rep.bad_length, rep.truncated) == (1, 3, 1)   # long length, 9 garbage bytes, foreign
    assert rep.seq_repeated == 1 and rep.seq_missing == 3   # 2, 5, 8 lost (the cut 11 is the last: no gap seen)
    assert rep.bad_packets == 5


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["keep", "flip", "cut", "junk", "dup", "len"]), st.integers(0, 10_000)),
                min_size=1, max_size=14))
def test_fuzzed_streams_never_crash_and_every_bad_packet_is_counted(ops):
    pk = _stream(len(ops))
    parts, intact, corrupt = [], 0, 0
    for (op, r), p in zip(ops, pk, strict=True):
        b = bytearray(p)
        if op == "keep":
            intact += 1
        elif op == "dup":
            parts.append(bytes(p))
            intact += 2
        elif op == "flip":
            b[r % len(b)] ^= 1 << (r % 8)
            corrupt += 1
        elif op == "cut":
            b = b[:r % len(b)]
            corrupt += 1 if b else 0
        elif op == "junk":
            parts.append(bytes((r * 37 + k) % 256 for k in range(1 + r % 40)))
            intact += 1
            corrupt += 1
        elif op == "len":
            b[4:6] = ((int.from_bytes(b[4:6], "big") + 1 + r % 300) % 65536).to_bytes(2, "big")
            corrupt += 1
        parts.append(bytes(b))
    rep = DecodeReport()
    good = list(iter_packets(b"".join(parts), rep))
    assert len(good) == rep.packets_ok == intact
    assert (rep.bad_packets > 0) == (corrupt > 0) and rep.bad_packets <= corrupt


def test_decode_of_a_file_without_packets_is_bad_input(tmp_path, capsys):
    (tmp_path / "x.bin").write_bytes(b"not packets at all")
    assert main(["tm", "decode", str(tmp_path / "x.bin"), "--out", str(tmp_path / "d")]) == 3
    assert "no valid packet" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()                        # a failed decode writes nothing
    rep = DecodeReport()
    assert list(iter_packets(b"not packets at all", rep)) == []
    assert rep.bad_length == 1 and rep.skipped_bytes == 18
    with pytest.raises(SessionFileError, match="no valid packet"):
        decode_files([tmp_path / "x.bin"], tmp_path / "d2")
    assert not (tmp_path / "d2").exists()


def test_a_packet_that_cannot_be_sent_is_counted_and_reported_not_raised():
    from magstack.data.packets import ApidMap
    from magstack.firmware.flight.ccsds import PacketStream

    errors = []
    s = PacketStream(ApidMap(("m",), ("g",)), path=None, udp=("256.0.0.1", 9), on_error=errors.append)
    for _ in range(5):
        s.emit("ping_reply", APP_APID, 0.0, {})
    s.close()
    s.emit("ping_reply", APP_APID, 0.0, {})        # after close: counted too
    assert s.send_errors == 6 and s.sent == 0 and len(errors) == 3     # events at the 1st, 2nd and 4th


def test_ccsds_config_errors_name_the_key(tmp_path, capsys):
    cases = [('tm_udp = "localhost"', "ccsds.tm_udp: must be"), ('tc_udp = "127.0.0.1:0"', "ccsds.tc_udp: must be"),
             ("bogus = 1", "ccsds: unknown key(s) ['bogus']")]
    for k, (line, expect) in enumerate(cases):
        cfg = sim_config(tmp_path / str(k))
        text = cfg.read_text() if not line.startswith("tc_udp") else re.sub(r"\ntc_udp = .*", "", cfg.read_text())
        cfg.write_text(text.replace("[ccsds]\n", f"[ccsds]\n{line}\n"))
        assert main(["run", "--config", str(cfg), "--duration", "1"]) == 3
        assert expect in capsys.readouterr().err
    cfg = sim_config(tmp_path / "nocmd")
    cfg.write_text(cfg.read_text().replace('command_dir = "commands"', ""))
    assert main(["run", "--config", str(cfg), "--duration", "1"]) == 3
    assert "need flight.command_dir" in capsys.readouterr().err


def test_a_failing_csv_writer_does_not_stop_the_packets(tmp_path):
    from magstack.firmware.flight.app import FlightApp
    from magstack.firmware.flight.config import load_config

    app = FlightApp(load_config(sim_config(tmp_path)), virtual=True, simulate=True, telemetry_dir=tmp_path / "tlm",
                    run_id=1)
    slot = app.slots["hmc1053"]

    def disk_full(_rec):
        raise OSError(28, "No space left on device")

    from magstack.firmware.flight.ccsds import _tee

    slot.channel.sink = _tee(disk_full, app.ccsds.stream.record)     # the CSV writer replaced by a full disk
    try:
        app.run(3.0)
    finally:
        app.close()
    rep = DecodeReport()
    chans = [p for p in iter_packets((tmp_path / "tlm/packets-0001.bin").read_bytes(), rep) if p.apid == 0x100]
    assert len(chans) == 3 and slot.channel.health.telemetry_errors == 3
