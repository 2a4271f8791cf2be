"""Calibration table file: CRC, schema, validation, atomic writes, active-slot store."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from magstack.firmware import cal_table as ct
from magstack.firmware.calibration import FitOptions, fit
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.firmware.errors import CalTableInvalid
from magstack.sim.synthetic_calibration import make_data, random_theta


def _good(device="hmc1053:sn1", **kw) -> ct.CalTable:
    args = dict(device_id=device, terms=("gain_matrix", "temperature_gain", "offset", "temperature_offset",
                                         "currents"),
                S=[[1.1, 0.05, -0.02], [0.01, 1.12, 0.03], [0.0, 0.07, 1.11]], K_S=np.full((3, 3), 1e-3),
                O=[-0.34, -0.09, 0.46], K_O=[0.01, -0.02, 0.16], D=(("solar", [1.0, 2.0, -3.0]),),
                validity_temp_c=(-40.0, 85.0), validity_field_uT=100.0,
                validity_currents_A=(("solar", (0.0, 2.0)),), created_utc="2026-01-01T00:00:00Z")
    args.update(kw)
    return ct.CalTable(**args)


def test_round_trip_and_header_fields(tmp_path):
    t = _good()
    p = ct.save_table(t, tmp_path / "cal.json")
    doc = json.loads(p.read_text())
    for key in ("schema", "schema_version", "table_name", "device_id", "description", "created_utc", "model",
                "parameters", "validity", "fit", "crc32"):
        assert key in doc
    assert doc["parameters"]["K_S"]["unit"] == "1/degC" and doc["parameters"]["D"]["unit"] == "uT/A"
    u = ct.load_table(p)
    assert u.crc32 == int(doc["crc32"], 16)
    for name in ("S", "K_S", "O", "K_O"):
        np.testing.assert_array_equal(getattr(u, name), getattr(t, name))
    assert u.D[0][0] == "solar" and u.currents == ("solar",)
    assert u.validity_currents_A == (("solar", (0.0, 2.0)),)
    assert ct.validate(u).ok
    with pytest.raises(ValueError):
        u.S[0, 0] = 3.0   # immutable snapshot


def test_crc_catches_a_single_changed_digit(tmp_path):
    p = ct.save_table(_good(), tmp_path / "cal.json")
    text = p.read_text()
    p.write_text(text.replace("1.12", "1.13", 1))
    with pytest.raises(CalTableInvalid, match="CRC-32 mismatch"):
        ct.load_table(p)


@pytest.mark.parametrize("mutate, match", [
    (lambda t: t[: len(t) // 2], "corrupt or truncated"),
    (lambda t: "", "corrupt or truncated"),
    (lambda t: t.replace("magstack-cal-table", "other-table"), "foreign file"),
    (lambda t: t.replace('"schema_version": 1', '"schema_version": 7'), "unsupported schema_version"),
    (lambda t: t.replace('"crc32"', '"crc"'), r"missing required key\(s\) \['crc32'\]"),
    (lambda t: "[1, 2, 3]", "not a JSON object"),
    (lambda t: t.replace("1.12", "NaN", 1), "corrupt or truncated"),
])
def test_bad_files_raise_clear_errors(tmp_path, mutate, match):
    p = ct.save_table(_good(), tmp_path / "cal.json")
    p.write_text(mutate(p.read_text()))
    with pytest.raises(CalTableInvalid, match=match):
        ct.load_table(p)


def test_binary_garbage_and_missing_file(tmp_path):
    p = tmp_path / "cal.json"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(CalTableInvalid, match="not UTF-8 text"):
        ct.load_table(p)
    with pytest.raises(CalTableInvalid, match="cannot read"):
        ct.load_table(tmp_path / "nope.json")


def _resigned(doc: dict) -> dict:
    doc["crc32"] = f"0x{ct._crc(doc):08x}"
    return doc


def test_structurally_bad_but_correctly_signed_documents(tmp_path):
    doc = _good().to_document()
    d1 = json.loads(json.dumps(doc))
    del d1["parameters"]["K_O"]
    with pytest.raises(CalTableInvalid, match=r"parameters: missing required key\(s\) \['K_O'\]"):
        ct.table_from_document(_resigned(d1))
    d2 = json.loads(json.dumps(doc))
    d2["parameters"]["O"]["unit"] = "nT"
    with pytest.raises(CalTableInvalid, match="unit"):
        ct.table_from_document(_resigned(d2))
    d3 = json.loads(json.dumps(doc))
    d3["parameters"]["S"]["value"] = [[1, 2], [3, 4]]
    with pytest.raises(CalTableInvalid, match=r"parameters.S.value: must be a 3x3 matrix"):
        ct.table_from_document(_resigned(d3))
    d4 = json.loads(json.dumps(doc))
    d4["model"]["terms"].append("warp_drive")
    with pytest.raises(CalTableInvalid, match=r"model.terms: unknown term\(s\) \['warp_drive'\]"):
        ct.table_from_document(_resigned(d4))


@pytest.mark.parametrize("edit, match", [
    (lambda d: d["parameters"].update(S=[1, 2, 3]), "parameters.S: must be a JSON object"),
    (lambda d: d["parameters"]["D"].update(value=[[1, 2, 3]]), "parameters.D.value: must be a JSON object"),
    (lambda d: d["validity"].update(currents_A=[1]), "validity.currents_A: must be a JSON object"),
    (lambda d: d.update(fit=[1]), "fit: must be a JSON object"),
    (lambda d: d.update(device_id=None), "device_id: must be a non-empty string"),
    (lambda d: d.update(model=["eq3"]), "model: must be a JSON object"),
    (lambda d: d["model"].update(terms="gain_matrix"), "model.terms: must be a list of term names"),
])
def test_wrongly_typed_but_correctly_signed_documents(edit, match):
    """Wrong JSON types anywhere give CalTableInvalid, never AttributeError/TypeError."""
    doc = json.loads(json.dumps(_good().to_document()))
    edit(doc)
    with pytest.raises(CalTableInvalid, match=match):
        ct.table_from_document(_resigned(doc))


def test_absurd_scalars_fail_validation_without_crashing():
    for kw, match in ((dict(t0_c=1e308), "t0_c"), (dict(validity_field_uT=1e308), "validity field_uT")):
        res = ct.validate(_good(**kw))
        assert not res.ok and any(match in p for p in res.problems), res.problems


def test_non_finite_table_is_not_written(tmp_path):
    with pytest.raises(CalTableInvalid, match="not written"):
        ct.save_table(_good(validity_field_uT=float("nan")), tmp_path / "cal.json")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kw, match", [
    (dict(S=np.eye(3) * 20), "S diagonal"),
    (dict(S=[[1, 6, 0], [0, 1, 0], [0, 0, 1]]), "off-diagonal"),
    (dict(K_S=np.full((3, 3), 0.5)), "K_S max"),
    (dict(O=[2000.0, 0, 0]), "O max"),
    (dict(K_O=[50.0, 0, 0]), "K_O max"),
    (dict(D=(("solar", [5000.0, 0, 0]),)), "D_solar beyond"),
    (dict(S=[[1, 1, 0], [1, 1.0001, 0], [0, 0, 1]]), "condition number"),
    (dict(validity_temp_c=(-100.0, 85.0)), "validity temp_c"),
    (dict(validity_temp_c=(50.0, 10.0)), "validity temp_c"),
    (dict(validity_field_uT=0.0), "validity field_uT"),
    (dict(validity_field_uT=1900.0, S=np.eye(3) * 9.0), "would saturate"),
    (dict(t0_c=25.001), "multiple of 0.01"),
    (dict(S=[[np.nan, 0, 0], [0, 1, 0], [0, 0, 1]]), "non-finite"),
    (dict(device_id=""), "device_id is empty"),
])
def test_validation_refuses_out_of_bounds(kw, match):
    res = ct.validate(_good(**kw))
    assert not res.ok
    assert any(match in p for p in res.problems), res.problems
    with pytest.raises(CalTableInvalid, match="validation failed"):
        res.raise_if_bad()


def test_store_lifecycle_and_active_table_stays_in_force(tmp_path):
    store = ct.CalTableStore("hmc1053:sn1")
    assert store.active is None and store.telemetry()["active"] is False   # never loaded: explicit
    good = ct.save_table(_good(), tmp_path / "good.json")
    store.load(good)
    assert store.active is None                        # staged, not yet active
    store.request_activation()
    assert store.cycle_boundary() is True and store.active is not None
    assert store.active_fixed is not None
    first = store.active
    bad_files = {
        "corrupt": lambda p: p.write_text(p.read_text().replace("1.12", "9.99", 1)),
        "truncated": lambda p: p.write_text(p.read_text()[:100]),
        "foreign": lambda p: ct.save_table(_good(device="lis3mdl:other"), p),
        "bounds": lambda p: ct.save_table(_good(O=[5000.0, 0, 0]), p),
    }
    for name, make in bad_files.items():
        p = tmp_path / f"{name}.json"
        ct.save_table(_good(), p)
        make(p)
        with pytest.raises(CalTableInvalid):
            store.load(p)
        assert store.active is first, name
        assert store.cycle_boundary() is False
    tm = store.telemetry()
    assert tm["reject_count"] == 4 and tm["load_count"] == 1 and tm["last_error"]
    assert tm["active_crc32"] == f"0x{first.crc32:08x}"
    with pytest.raises(CalTableInvalid, match="no validated table"):
        store.request_activation()


def test_atomic_write_keeps_old_file_on_failure(tmp_path, monkeypatch):
    p = ct.save_table(_good(), tmp_path / "cal.json")
    before = p.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")
    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        ct.save_table(_good(O=[1.0, 2.0, 3.0]), p)
    assert p.read_bytes() == before
    assert [x.name for x in tmp_path.iterdir()] == ["cal.json"]   # no temp file left


def test_table_from_fit_carries_model_validity_and_stats(tmp_path):
    rng = np.random.default_rng(3)
    terms = resolve_terms("eq3", ["session_offset"], ["heater"])
    m = CalModel(terms, ("heater",), (1, 2), 25.0, 1.6e9 + 1999 * 0.25 / 2)
    th = random_theta(m, rng)
    d = make_data(m, th, 2000, rng)
    r = fit(d, "eq3", ["session_offset"], ["heater"], options=FitOptions(holdout=False, chip="hmc1053"))
    # a bound wide enough for the data's own region: the region holds the data and says so
    t = ct.table_from_fit(r, "dev1", validity_sd_uT=1.0)
    assert t.validity_temp_c[0] <= d.temp_c.min() and t.validity_temp_c[1] >= d.temp_c.max()
    assert min(t.field_limits_uT) >= np.abs(d.b_meas_uT).max()
    assert t.validity_field_norm_uT >= np.linalg.norm(d.b_meas_uT, axis=1).max()
    # by default (5x the RMS over the rows at most) the corners of the data's own region that no row reached
    # (every axis near +-60 uT at once: B_x B_y up to 3600 uT^2, the rows' at most 2431) are beyond what the
    # table can defend: the region is narrower than the data, and the fit says so
    g = ct.table_from_fit(r, "dev1")
    assert any("narrower than the data" in n for n in g.fit_stats["validity"]["notes"])
    assert (g.validity_temp_c[1] - g.validity_temp_c[0] < d.temp_c.max() - d.temp_c.min()
            or g.validity_field_norm_uT < np.linalg.norm(d.b_meas_uT, axis=1).max())
    assert "session_offset_uT" in t.ground_only
    p = ct.save_table(t, tmp_path / "c.json")
    u = ct.load_table(p)
    assert ct.validate(u).ok
    assert u.fit_stats["rmse_norm_uT"] == pytest.approx(r.rmse_norm_uT)
    np.testing.assert_allclose(u.S, r.params["S"])
    np.testing.assert_allclose(u.D[0][1], r.params["D"]["heater"])
