"""Binary table image (firmware_py/cal_image.py): round trip, refusals, the flight loader and the CLI.

The C loader's side (same codes, every bit flip refused) is tests/c_applier/test_c_applier.py.
"""
from __future__ import annotations

import json
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.firmware import cal_image
from magstack.firmware import cal_table as ct
from magstack.firmware import fixed_point as fp
from magstack.firmware.corrector import TableCorrector
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.flight.tables import FlightTableStore

ROOT = Path(__file__).resolve().parent.parent


def _table(**kw) -> ct.CalTable:
    args = dict(device_id="hmc1053:sn1", terms=("gain_matrix", "temperature_gain", "temperature_gain2", "offset",
                                                "temperature_offset", "currents", "time_skew"),
                S=[[1.1, 0.05, -0.02], [0.01, 1.12, 0.03], [0.0, 0.07, 1.11]], K_S=np.full((3, 3), 1e-3),
                K_S2=[1e-5, -2e-5, 3e-6], O=[-0.34, -0.09, 0.46], K_O=[0.01, -0.02, 0.16],
                D=(("heater", [1.0, 2.0, -3.0]),), validity_temp_c=(-40.0, 85.0), validity_field_uT=100.0,
                validity_currents_A=(("heater", (0.0, 2.0)),), ground_only={"tau_s": 0.001},
                created_utc="2026-01-01T00:00:00Z", description="bench fit")
    args.update(kw)
    return ct.table_from_document(ct.CalTable(**args).to_document())   # as read from its JSON file


@st.composite
def _valid_tables(draw):
    f = st.floats
    k = draw(st.integers(0, 4))
    S = np.diag(draw(st.lists(f(0.5, 3.0), min_size=3, max_size=3))) + np.array(
        draw(st.lists(f(-0.3, 0.3), min_size=9, max_size=9))).reshape(3, 3) * (1 - np.eye(3))
    lo = draw(f(-55, 20))
    t0 = round(draw(f(-20, 60)), 2)
    field = draw(f(0.001, 120))
    terms = ["gain_matrix", "offset"] + draw(st.sets(st.sampled_from(["temperature_gain", "temperature_gain2",
                                                                       "temperature_offset"])).map(sorted))
    return ct.table_from_document(ct.CalTable(
        device_id=draw(st.text("abcdefghijklmnopqrstuvwxyz0123456789:-_ ", min_size=1, max_size=32)).strip() or "x",
        terms=tuple(terms + (["currents"] if k else [])), S=S,
        K_S=np.array(draw(st.lists(f(-0.01, 0.01), min_size=9, max_size=9))).reshape(3, 3)
        if "temperature_gain" in terms else np.zeros((3, 3)),
        K_S2=draw(st.lists(f(-2e-4, 2e-4), min_size=3, max_size=3)) if "temperature_gain2" in terms else [0, 0, 0],
        O=draw(st.lists(f(-500, 500), min_size=3, max_size=3)),
        K_O=draw(st.lists(f(-5, 5), min_size=3, max_size=3)) if "temperature_offset" in terms else [0, 0, 0],
        D=tuple((f"c{j}", draw(st.lists(f(-200, 200), min_size=3, max_size=3))) for j in range(k)), t0_c=t0,
        validity_temp_c=(lo, draw(f(max(lo, t0), 125))) if lo <= t0 else (t0, 125.0),
        validity_field_uT=field, validity_field_axes_uT=draw(st.one_of(st.none(), st.tuples(
            *[st.one_of(f(0.001, field), st.just(field))] * 3))),
        validity_field_norm_uT=draw(st.one_of(st.none(), f(0.001, 200))),
        validity_currents_A=tuple((f"c{j}", (-draw(f(0, 5)), draw(f(0, 5)))) for j in range(k))).to_document())


@settings(max_examples=120, deadline=None)
@given(table=_valid_tables())
def test_round_trip_gives_the_same_integers_and_a_valid_table(table):
    v = ct.validate(table)
    if not v.ok:   # (conditioning or headroom of an extreme draw): an invalid table has no image
        with pytest.raises(CalTableInvalid):
            cal_image.image_from_table(table)
        return
    fixed = fp.FixedPointTable.from_table(table)
    quantised = cal_image.table_from_image(cal_image.pack_fixed(
        fixed, device_id=table.device_id, terms=table.terms, current_names=table.currents, source_crc32=table.crc32))
    if not ct.validate(quantised).ok:   # a coefficient at a bound, past it by less than one LSB once quantised
        with pytest.raises(CalTableInvalid, match="quantised image"):
            cal_image.image_from_table(table)
        return
    raw = cal_image.image_from_table(table)
    assert len(raw) == cal_image.SIZE and cal_image.check_image(raw) == cal_image.ImageResult.OK
    back = cal_image.table_from_image(raw, "x.mcal")
    assert fp.FixedPointTable.from_table(back) == fp.FixedPointTable.from_table(table)
    assert ct.validate(back).ok and back.crc32 == table.crc32 and back.device_id == table.device_id
    assert set(back.terms) == set(table.terms) and back.currents == table.currents
    assert cal_image.image_from_table(back) == raw    # an image of an image's table is the same image


def test_what_an_image_carries_and_what_it_does_not():
    t = _table()
    img = cal_image.decode_image(cal_image.image_from_table(t))
    assert img.source_crc32 == t.crc32 and img.device_id == "hmc1053:sn1" and img.current_names == ("heater",)
    assert "time_skew" not in img.terms and set(img.terms) == set(t.terms) - {"time_skew"}
    back = cal_image.table_from_image(cal_image.image_from_table(t))
    assert back.posterior is None and not back.fit_stats and not back.ground_only and back.created_utc == ""


def test_per_axis_and_magnitude_limits_travel_in_the_image(tmp_path, capsys):
    """The validity region's per-axis and magnitude limits (on the calibrated field) are in the image, come back in
    its table, and flag the same samples in the flight store as the JSON table does."""
    t = _table(validity_field_axes_uT=(100.0, 80.5, 90.0004), validity_field_norm_uT=120.0)
    raw = cal_image.image_from_table(t)
    img = cal_image.decode_image(raw)
    assert img.fixed.field_limits_nT == (100_000, 80_500, 90_000) and img.fixed.field_norm_nT == 120_000
    assert raw[14] == cal_image.OPT_TEMP_RANGE | cal_image.OPT_FIELD_AXES | cal_image.OPT_FIELD_NORM
    back = cal_image.table_from_image(raw)
    assert fp.FixedPointTable.from_table(back) == fp.FixedPointTable.from_table(t) == img.fixed
    assert back.validity_field_norm_uT == 120.0 and back.validity_field_axes_uT[1] == 80.5
    plain = cal_image.decode_image(cal_image.image_from_table(_table()))
    assert plain.fixed.field_limits_nT is None and plain.fixed.field_norm_nT is None
    ct.save_table(t, tmp_path / "cal.json")
    (tmp_path / "cal.mcal").write_bytes(raw)
    outs = []
    for name in ("cal.json", "cal.mcal"):
        store = FlightTableStore("hmc1053:sn1", "hmc1053", [tmp_path], tmp_path)
        store.load_and_activate(name)
        corr = TableCorrector(store)
        # calibrated: (14.0, 78.7, 16.5), (14.2, 84.3, 16.8) uT: y beyond 80.5; (90.1, 68.8, 38.0) |B| 119.5 uT,
        # (90.0, 69.0, 43.5) |B| 121.4 uT: beyond 120
        outs.append([corr.correct(b, 25.0, {"heater": 0.0}) for b in ((10.0, 70.0, 10.0), (10.0, 75.0, 10.0),
                                                                       (80.0, 60.0, 30.0), (80.0, 60.0, 35.0))])
    assert outs[0] == outs[1]
    assert [c.status for c in outs[0]] == ["ok", "out_of_validity", "ok", "out_of_validity"]
    assert main(["table", "show", str(tmp_path / "cal.mcal"), "--json"]) == 0
    ints = json.loads(capsys.readouterr().out)["image"]["integers"]
    assert ints["field_limits_nT"] == [100_000, 80_500, 90_000] and ints["field_norm_nT"] == 120_000


@pytest.mark.parametrize("kw, match", [
    (dict(terms=("gain_matrix", "offset", "cubic"), c3=[1e-6, 0, 0], D=(), validity_currents_A=()), "float-only"),
    (dict(device_id="x" * 33), "1..32 printable ASCII"),
    (dict(device_id="capteur-é"), "printable ASCII"),
    (dict(D=(("a_very_long_current_name", [1.0, 2.0, -3.0]),),
          validity_currents_A=(("a_very_long_current_name", (0.0, 2.0)),)), "1..16 printable ASCII"),
    (dict(S=np.eye(3) * 20), "validation failed"),
])
def test_tables_without_an_image_are_refused_by_name(kw, match):
    with pytest.raises(CalTableInvalid, match=match):
        cal_image.image_from_table(_table(**kw))


def test_image_module_loads_without_scipy_pandas_matplotlib():
    code = ("import sys, magstack.firmware.cal_image, magstack.firmware.flight.tables; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('scipy', 'pandas', 'matplotlib')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr


# ---------------------------------------------------------------------- flight loader
def test_flight_store_loads_an_image_as_it_loads_json(tmp_path):
    t = _table()
    ct.save_table(t, tmp_path / "cal.json")
    (tmp_path / "cal.mcal").write_bytes(cal_image.image_from_table(t))
    outs = []
    for name in ("cal.json", "cal.mcal"):
        store = FlightTableStore("hmc1053:sn1", "hmc1053", [tmp_path], tmp_path)
        store.load_and_activate(name)
        corr = TableCorrector(store)
        outs.append([corr.correct((12.3, -45.6, 7.8), temp_c, {"heater": 1.5}) for temp_c in (-39.0, 25.0, 61.37, 90)])
        assert store.telemetry()["active_crc32"] == f"0x{t.crc32:08x}"
    assert outs[0] == outs[1] and [c.status for c in outs[0]] == ["ok", "ok", "ok", "out_of_validity"]


def test_flight_store_refuses_a_bad_image_and_keeps_the_active_table(tmp_path):
    raw = cal_image.image_from_table(_table())
    (tmp_path / "good.mcal").write_bytes(raw)
    bad = bytearray(raw)
    bad[100] ^= 0x10
    (tmp_path / "bad.mcal").write_bytes(bytes(bad))
    (tmp_path / "short.mcal").write_bytes(raw[:200])
    store = FlightTableStore("hmc1053:sn1", "hmc1053", [tmp_path], tmp_path)
    store.load_and_activate("good.mcal")
    for name, match in (("bad.mcal", "CRC-32 mismatch"), ("short.mcal", "200 bytes")):
        with pytest.raises(CalTableInvalid, match=match):
            store.load(name)
    assert store.active is not None and store.reject_count == 2
    other = FlightTableStore("lis3mdl:sn2", "lis3mdl", [tmp_path], tmp_path)
    with pytest.raises(CalTableInvalid, match="table is for device 'hmc1053:sn1'"):
        other.load("good.mcal")


def test_flight_run_with_an_image_publishes_what_the_json_table_does(tmp_path, capsys):
    """`magstack run` with `table = "tables/hmc1053.mcal"`: the same calibrated telemetry and table CRC."""
    from magstack.firmware.flight.config import example_config_text

    text = example_config_text().replace("spi0.0,start=6,reset=13,drdy=19,sr=5", "sim").replace('bus = "1"',
                                                                                                 'bus = "sim"')
    assert 'table = "tables/hmc1053.json"' in text
    (tmp_path / "tables").mkdir()
    t = ct.CalTable(device_id="hmc1053:sn1", terms=("gain_matrix", "offset"), S=np.eye(3) * 1.01, O=[0.1, 0.2, 0.3],
                    validity_field_uT=100.0)
    ct.save_table(t, tmp_path / "tables/hmc1053.json")
    assert main(["table", "export", str(tmp_path / "tables/hmc1053.json"), "--image",
                 str(tmp_path / "tables/hmc1053.mcal"), "-q"]) == 0
    runs = {}
    for ext in ("json", "mcal"):
        cfg = tmp_path / f"flight-{ext}.toml"
        cfg.write_text(text.replace('table = "tables/hmc1053.json"', f'table = "tables/hmc1053.{ext}"'))
        assert main(["run", "--config", str(cfg), "--duration", "10", "--out", str(tmp_path / ext), "-q"]) == 0
        runs[ext] = read_session(tmp_path / ext / "hmc1053-0001-0001.csv")
    a, b = runs["json"], runs["mcal"]
    assert len(a) == len(b) == 10
    for col in ("cal_x_uT", "cal_y_uT", "cal_z_uT", "table_crc32"):
        assert np.array_equal(np.asarray(a.extra[col]), np.asarray(b.extra[col]), equal_nan=True), col
    assert np.all(np.isfinite(np.asarray(a.extra["cal_x_uT"], dtype=float)))
    capsys.readouterr()


# ---------------------------------------------------------------------- CLI
def test_cli_export_show_validate(tmp_path, capsys):
    t = _table()
    src = ct.save_table(t, tmp_path / "cal.json")
    img = tmp_path / "cal.mcal"
    assert main(["table", "export", str(src), "--image", str(img), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["image_bytes"] == cal_image.SIZE == 336 and doc["source_crc32"] == f"0x{ct.load_table(src).crc32:08x}"
    assert img.read_bytes() == cal_image.image_from_table(ct.load_table(src))
    assert main(["table", "validate", str(img)]) == 0
    assert "valid: worst-case output" in capsys.readouterr().out
    assert main(["table", "show", str(img), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["format"] == "image" and doc["valid"] and doc["image"]["integers"]["t0_cdeg"] == 2500
    assert main(["table", "show", str(img)]) == 0
    out = capsys.readouterr().out
    assert "image v2, 336 bytes" in out and "calibrated field per axis within +-[100000, 100000, 100000] nT" in out
    assert "K_S2 (2^-40 /degC^2)" in out and "not carried" in out
    bad = bytearray(img.read_bytes())
    bad[200] ^= 1
    img.write_bytes(bytes(bad))
    assert main(["table", "validate", str(img)]) == 1
    assert "CRC-32 mismatch" in capsys.readouterr().err
    assert main(["table", "show", str(img)]) == 3
    assert "CRC-32 mismatch" in capsys.readouterr().err


def test_cli_export_refusals_write_nothing(tmp_path, capsys):
    src = ct.save_table(_table(terms=("gain_matrix", "offset", "cubic"), c3=[1e-6, 0, 0], D=(),
                               validity_currents_A=()), tmp_path / "cubic.json")
    out = tmp_path / "x.mcal"
    assert main(["table", "export", str(src), "--image", str(out), "--c", str(tmp_path / "c")]) == 3
    assert "float-only" in capsys.readouterr().err and not out.exists() and not (tmp_path / "c").exists()
    good = ct.save_table(_table(), tmp_path / "cal.json")
    assert main(["table", "export", str(good)]) == 2
    assert main(["table", "export", str(good), "--image", str(out), "--c-array"]) == 2
    assert main(["table", "export", str(good), "--image", str(out), "--device-id", "other"]) == 3
    assert not out.exists()
    capsys.readouterr()


def test_export_of_an_image_is_the_same_image(tmp_path):
    src = ct.save_table(_table(), tmp_path / "cal.json")
    assert main(["table", "export", str(src), "--image", str(tmp_path / "a.mcal"), "-q"]) == 0
    assert main(["table", "export", str(tmp_path / "a.mcal"), "--c", str(tmp_path / "c"), "-q"]) == 0
    assert (tmp_path / "c" / "table.mcal").read_bytes() == (tmp_path / "a.mcal").read_bytes()
    assert (tmp_path / "c" / "magstack_cal.c").read_bytes() == (ROOT / "firmware_c" / "magstack_cal.c").read_bytes()


# ---------------------------------------------------------------------- docs
def test_the_documented_layout_is_the_code_layout():
    """docs/cal-table.md's image table: one row per field with its offset, size and type, in order."""
    text = (ROOT / "docs" / "cal-table.md").read_text()
    section = text[text.index("## Binary image"):]
    rows = re.findall(r"^\| (\d+) \| (\d+) \| `(\w+)` \| `([\w\[\]]+)` \|", section, re.M)
    want = [(str(f.offset), str(struct.calcsize("<" + f.fmt)), f.name, f.c_type) for f in cal_image.FIELDS]
    assert rows == want
