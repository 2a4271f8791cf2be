"""An independent XTCE decoder (space_packet_parser) reads our XTCE document and packet stream and gets,
bit for bit, every field `tm decode` wrote into the session files of a 10-minute simulated run."""
from __future__ import annotations

import json
from collections import defaultdict

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.dictionary import CHANNEL_FIELDS, CUC, GROUP_HK_FIELDS
from magstack.data.session import read_session
from tests.test_ccsds_packets import sim_config

spp = pytest.importorskip("space_packet_parser")


def _raw(v):
    return getattr(v, "raw_value", v)


def test_xtce_document_is_valid_against_the_xtce_1_2_schema(tmp_path, capsys):
    from pathlib import Path

    assert main(["tm", "xtce", "--config", str(sim_config(tmp_path))]) == 0
    (tmp_path / "tm.xml").write_text(capsys.readouterr().out)
    xsd = Path(spp.__file__).parent / "xtce" / "schemas" / "SpaceSystem.xsd"       # shipped with the package
    # level "schema": its "structure" level resolves BaseContainer only among telemetry SequenceContainers, not
    # the command containers of CommandMetaData (tests/test_xtce_commands.py checks those with xmlschema)
    res = spp.validate_xtce(tmp_path / "tm.xml", level="schema", local_xsd=xsd, allow_schema_download=False,
                            raise_on_error=False, print_results=False)
    assert res.valid, [str(e) for e in res.errors][:5]


@pytest.mark.slow
def test_space_packet_parser_reproduces_every_field_of_a_10_minute_run(tmp_path, capsys):
    cfg = sim_config(tmp_path)
    assert main(["run", "--config", str(cfg), "--duration", "600", "--out", str(tmp_path / "tlm"), "-q"]) == 0
    capsys.readouterr()
    assert main(["tm", "xtce", "--config", str(cfg)]) == 0
    (tmp_path / "tm.xml").write_text(capsys.readouterr().out)
    assert main(["tm", "decode", str(tmp_path / "tlm/packets-0001.bin"), "--out", str(tmp_path / "dec"), "-q"]) == 0
    capsys.readouterr()

    defn = spp.load_xtce(tmp_path / "tm.xml")
    rows, hk, events, first = defaultdict(list), defaultdict(list), [], []
    with open(tmp_path / "tlm/packets-0001.bin", "rb") as fh:
        for raw in spp.ccsds_generator(fh):
            p = defn.parse_bytes(raw)
            keys = list(p)
            if len(first) < 4:
                first.append(p)
            t = _raw(p["CUC_COARSE"]) + _raw(p["CUC_FINE"]) / 2 ** (8 * CUC.fine_octets)
            chan = next((k[len("CHANNEL_"):-len("_raw_x")] for k in keys if k.startswith("CHANNEL_") and
                         k.endswith("_raw_x")), None)
            if chan is not None:
                rows[chan].append((t, *(_raw(p[f"CHANNEL_{chan}_{f.name}"]) for f in CHANNEL_FIELDS)))
            elif any(k.startswith("GROUP_HK_") for k in keys):
                g = next(k for k in keys if k.startswith("GROUP_HK_"))[len("GROUP_HK_"):].rsplit("_", 1)[0]
                hk[g].append(tuple(_raw(p[f"GROUP_HK_{g}_{f.name}"]) for f in GROUP_HK_FIELDS if f.name != "exec_max"))
            elif "EVENT_event_id" in p:
                events.append((_raw(p["EVENT_event_id"]), p["EVENT_source"], p["EVENT_message"]))
    assert set(rows) == {"hmc1053", "lis3mdl"} and len(rows["lis3mdl"]) == 6000 and len(rows["hmc1053"]) == 600
    # the run's identification comes first: run id and the APID -> channel map, before any channel packet
    assert [(_raw(p["APID_MAP_run_id"]), p["APID_MAP_name"]) for p in first] == [
        (1, "hmc1053"), (1, "lis3mdl"), (1, "slow"), (1, "fast")]

    for chan, got in rows.items():
        s = read_session(tmp_path / "dec" / f"{chan}-0001-0001.csv")
        got = np.array(got, dtype=float)
        assert len(s) == len(got)
        # time: CUC coarse + fine, bit for bit (the file's 6 decimals resolve 2**-16 s)
        assert np.array_equal(np.round(s.t_s * 2 ** 16), np.round(got[:, 0] * 2 ** 16))
        cols = {"dut_x_uT": s.dut_uT[:, 0], "dut_y_uT": s.dut_uT[:, 1], "dut_z_uT": s.dut_uT[:, 2],
                "temp_c": s.temp_c, "flag": s.flag.astype(float), "session": s.session.astype(float), **s.extra}
        for k, f in enumerate(CHANNEL_FIELDS, start=1):
            col = cols[f.column]
            want = np.where(np.isnan(col), f.absent if f.absent is not None else np.nan, np.round(col / f.lsb))
            assert np.array_equal(want, got[:, k]), f.name       # every raw bit of every field
    hk_dec = defaultdict(list)
    for h in map(json.loads, (tmp_path / "dec/housekeeping.jsonl").read_text().splitlines()):
        if h["packet"] == "group_hk":
            hk_dec[h["apid"]].append(tuple(h[f.name] for f in GROUP_HK_FIELDS if f.name != "exec_max"))
    assert sorted(map(tuple, hk.values())) == sorted(map(tuple, hk_dec.values())) and len(hk) == 2
    ev_dec = [(e["id"], e["source"], e["message"])
              for e in map(json.loads, (tmp_path / "dec/events.jsonl").read_text().splitlines())]
    assert events == ev_dec and len(events) >= 3
