"""Strict table reader: the CRC covers exactly what is applied.

Each case is an edited table whose CRC was recomputed, so only the schema check can refuse it.
Before the strict reader these files loaded (a duplicate "S" before the real one kept the CRC
valid for a reader keeping the last key while a first-key reader applied a 5x gain).
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magstack.firmware import cal_table as ct
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.table_schema import MAX_DEPTH


def _good() -> ct.CalTable:
    return ct.CalTable(device_id="hmc1053:sn1",
                       terms=("gain_matrix", "temperature_gain", "offset", "temperature_offset", "currents"),
                       S=[[1.1, 0.05, -0.02], [0.01, 1.12, 0.03], [0.0, 0.07, 1.11]], K_S=np.full((3, 3), 1e-3),
                       O=[-0.34, -0.09, 0.46], K_O=[0.01, -0.02, 0.16], D=(("solar", [1.0, 2.0, -3.0]),),
                       validity_temp_c=(-40.0, 85.0), validity_field_uT=100.0,
                       validity_currents_A=(("solar", (0.0, 2.0)),), created_utc="2026-01-01T00:00:00Z")


def _doc() -> dict:
    return json.loads(_good().to_json())


def _signed_text(doc: dict) -> str:
    doc = dict(doc)
    doc["crc32"] = f"0x{ct._crc(doc):08x}"
    return json.dumps(doc, indent=1)


def test_duplicate_key_before_the_real_one_is_refused(tmp_path):
    text = ct.save_table(_good(), tmp_path / "cal.json").read_text()
    # insert a 5x gain "S" object before the real one: json.loads keeps the last, so the CRC still matches
    evil = text.replace('"parameters": {', '"parameters": {\n  "S": {"unit": "1", "value": '
                        '[[5.5, 0, 0], [0, 5.6, 0], [0, 0, 5.55]]},', 1)
    assert json.loads(evil)["parameters"]["S"] == json.loads(text)["parameters"]["S"]   # last key wins
    p = tmp_path / "evil.json"
    p.write_text(evil)
    with pytest.raises(CalTableInvalid, match="duplicate key 'S'"):
        ct.load_table(p)


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(schema_version=True), "unsupported schema_version True"),
    (lambda d: d.update(schema_version=1.0), "unsupported schema_version 1.0"),
    (lambda d: d.update(extra_gain=2.0), r"unknown key\(s\) \['extra_gain'\]"),
    (lambda d: d["model"].update(gain_scale=2), r"model: unknown key\(s\) \['gain_scale'\]"),
    (lambda d: d["parameters"]["S"].update(scale=2), r"parameters.S: unknown key\(s\) \['scale'\]"),
    (lambda d: d["validity"].pop("field_uT"), r"validity: missing required key\(s\) \['field_uT'\]"),
    (lambda d: d.pop("device_id"), r"missing required key\(s\) \['device_id'\]"),
    (lambda d: d["parameters"]["S"].update(value=[1.1, 0, 0, 0, 1.1, 0, 0, 0, 1.1]), "must be a 3x3 matrix"),
    (lambda d: d["parameters"]["S"]["value"][0].__setitem__(0, "1.1"), r"S.value\[0\]\[0\]: must be a finite"),
    (lambda d: d["parameters"]["O"]["value"].__setitem__(2, True), r"O.value\[2\]: must be a finite number"),
    (lambda d: d["model"].update(t0_c="25"), "model.t0_c: must be a finite number"),
    (lambda d: d["validity"].update(temp_c=[-40, "85"]), r"validity.temp_c\[1\]"),
    (lambda d: d["validity"].update(field_uT=False), "validity.field_uT: must be a finite number"),
    (lambda d: d["parameters"].update(c3={"unit": "1/uT^2", "value": [1e-5, 0, 0]}),
     r"parameters: unknown key\(s\) \['c3'\]"),       # coefficients for a term the table does not declare
    (lambda d: d["model"]["terms"].remove("temperature_offset"), r"parameters: unknown key\(s\) \['K_O'\]"),
    (lambda d: d["model"]["terms"].append("cubic"), r"parameters: missing required key\(s\) \['c3'\]"),
    (lambda d: d["model"]["terms"].append("offset"), "repeats a term"),
    (lambda d: d["parameters"]["D"]["value"].update(heater=[0, 0, 1]), r"unknown key\(s\) \['heater'\]"),
    (lambda d: d["validity"]["currents_A"].update(heater=[0, 1]), r"unknown key\(s\) \['heater'\]"),
    (lambda d: d["model"].update(currents=[]), "non-empty exactly when"),
])
def test_edited_and_resigned_tables_are_refused(tmp_path, edit, match):
    doc = _doc()
    edit(doc)
    p = tmp_path / "cal.json"
    p.write_text(_signed_text(doc))
    with pytest.raises(CalTableInvalid, match=match):
        ct.load_table(p)


def test_deep_nesting_is_a_typed_error_not_recursion(tmp_path):
    doc = _doc()
    p = tmp_path / "deep.json"
    text = _signed_text(doc)
    p.write_text(text.replace('"fit": {', '"fit": {"x": ' + "[" * 100_000 + "]" * 100_000 + ",", 1))
    with pytest.raises(CalTableInvalid, match=f"nested deeper than {MAX_DEPTH}"):
        ct.load_table(p)


def test_every_saved_table_reads_back():
    """The schema accepts everything the writer produces (with and without optional terms)."""
    for terms in (("gain_matrix", "offset"), ("gain_matrix", "offset", "cubic", "cross_products"),
                  ("gain_matrix", "temperature_gain", "offset", "temperature_offset", "currents")):
        kw = {} if "currents" in terms else {"D": (), "validity_currents_A": ()}
        t = ct.CalTable(**{**_good().__dict__, "terms": terms, "crc32": None, **kw})
        u = ct.table_from_document(json.loads(t.to_json()), "mem")
        assert u.terms == terms


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(st.data())
def test_fuzzed_tables_raise_only_typed_errors(tmp_path_factory, data):
    """Byte flips, truncations and insertions: the reader returns a table or raises CalTableInvalid."""
    raw = bytearray(ct.save_table(_good(), tmp_path_factory.mktemp("t") / "c.json").read_bytes())
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["flip", "cut", "insert"]))
        i = data.draw(st.integers(0, len(raw) - 1))
        if op == "flip":
            raw[i] ^= 1 << data.draw(st.integers(0, 7))
        elif op == "cut":
            del raw[i:i + data.draw(st.integers(1, 40))]
        else:
            raw[i:i] = data.draw(st.binary(min_size=1, max_size=12))
        if not raw:
            raw = bytearray(b"{")
    p = tmp_path_factory.mktemp("f") / "c.json"
    p.write_bytes(bytes(raw))
    try:
        ct.load_table(p)
    except CalTableInvalid:
        pass
