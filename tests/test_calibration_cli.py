"""magstack fit / table / apply end to end on synthetic session files."""
from __future__ import annotations

import json

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import Session, read_session, write_session
from magstack.firmware.cal_table import load_table
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.firmware.float_applier import apply_float
from magstack.ground.apply_session import FLAG_SHIFT
from magstack.sim.synthetic_calibration import make_data, random_theta


def _session_file(path, seed, session, n=1500, currents=("solar",)):
    rng = np.random.default_rng(seed)
    m = CalModel(resolve_terms("eq3", currents=currents), currents, (), 25.0, 0.0)
    th = random_theta(m, np.random.default_rng(0))      # same device in every file
    d = make_data(m, th, n, rng, noise_uT=0.03, t0_s=1.6e9 + 1e4 * seed)
    s = Session(d.t_s, d.b_ref_uT, d.b_meas_uT, d.temp_c, np.full(n, session), dict(d.currents_A),
                {"dut_chip": "hmc1053", "device_id": "hmc1053:sn7"})
    write_session(path, s)
    return m, th


def test_fit_show_validate_apply(tmp_path, capsys):
    _session_file(tmp_path / "a.csv", 1, 0)
    _, th = _session_file(tmp_path / "b.csv", 2, 0)       # same session id: renumbered
    out = tmp_path / "cal.json"
    # a generous validity sd: this synthetic bench's fields never come near zero, so the default region (where the
    # predictive sd stays within 5x its RMS over the data) would leave it; this test is about the flags
    rc = main(["fit", str(tmp_path / "a.csv"), str(tmp_path / "b.csv"), "--currents", "solar",
               "--terms", "session_offset", "--validity-sd", "2000", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    assert "session 0 -> 1" in text and "session 0 -> 2" in text
    assert "held-out sessions" in text and "table validates" in text
    assert json.loads(out.read_text())["device_id"] == "hmc1053:sn7"
    assert main(["table", "validate", str(out)]) == 0
    assert main(["table", "show", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "D_solar (uT/A)" in shown and "valid:" in shown
    assert main(["table", "validate", str(out), "--device-id", "other"]) == 1   # verdict: not valid

    # apply: NaN rows are kept and flagged, never dropped
    s = read_session(tmp_path / "a.csv")
    s.dut_uT[10] = np.nan
    s.temp_c[11] = np.nan
    s.dut_uT[12, 0] = 500.0                                    # outside the validity field range
    s.flag = np.zeros(len(s), np.int64)
    s.flag[13] = 3                                             # an upstream flag is preserved
    write_session(tmp_path / "in.csv", s)
    for applier in ("float", "fixed"):
        cal = tmp_path / f"cal_{applier}.csv"
        assert main(["apply", str(out), str(tmp_path / "in.csv"), "--out", str(cal), "--applier", applier]) == 0
        c = read_session(cal)
        assert len(c) == len(s) and c.metadata["calibrated"] == "true" and c.metadata["cal_applier"] == applier
        assert np.all(np.isnan(c.dut_uT[10])) and np.all(np.isnan(c.dut_uT[11]))
        assert c.flag[10] >> FLAG_SHIFT == 1 and c.flag[11] >> FLAG_SHIFT == 1
        assert c.flag[12] >> FLAG_SHIFT == 2 and c.flag[13] == 3
        ok = np.ones(len(c), bool)
        ok[10:14] = False
        rms = np.sqrt(np.mean((c.dut_uT[ok] - c.ref_uT[ok]) ** 2, axis=0))
        assert np.all(rms < 0.05)    # 30 nT noise + small session-offset residual
    # the fixed path sees inputs quantised to nT, centi-degC and mA: on those, it matches float64
    table = load_table(out)
    q_ref, _ = apply_float(table, np.round(s.dut_uT * 1e3) / 1e3, np.round(s.temp_c * 100) / 100,
                           {"solar": np.round(s.currents_A["solar"] * 1e3) / 1e3})
    b = read_session(tmp_path / "cal_fixed.csv")
    # rows outside the validity box get no value, as on board (apply --extrapolate keeps them)
    outside = (b.flag >> FLAG_SHIFT) & 2 != 0
    assert np.all(np.isnan(b.dut_uT[outside]))
    fin = np.isfinite(q_ref) & ~outside[:, None]
    assert np.abs(q_ref[fin] - b.dut_uT[fin]).max() <= 0.5e-3 + 1e-6   # 0.5 nT (+ CSV 1 pT rounding)


def test_cli_errors_are_clean(tmp_path, capsys):
    _session_file(tmp_path / "a.csv", 1, 0)
    out = tmp_path / "cal.json"
    assert main(["fit", str(tmp_path / "a.csv"), "--currents", "nope", "--out", str(out)]) == 3
    assert "no current 'nope'" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "a.csv"), "--terms", "bogus", "--out", str(out)]) == 2
    assert main(["fit", str(tmp_path / "a.csv"), "--currents", "solar", "--out", str(out), "--no-holdout"]) == 0
    (tmp_path / "broken.json").write_text(out.read_text()[:50])
    assert main(["table", "show", str(tmp_path / "broken.json")]) == 3
    assert "corrupt or truncated" in capsys.readouterr().err
    assert main(["apply", str(tmp_path / "broken.json"), str(tmp_path / "a.csv"), "--out",
                 str(tmp_path / "x.csv")]) == 3
    assert not (tmp_path / "x.csv").exists()


def test_fit_refuses_unidentifiable_on_request(tmp_path, capsys):
    rng = np.random.default_rng(5)
    m = CalModel(resolve_terms("eq3"), (), (), 25.0, 0.0)
    d = make_data(m, random_theta(m, rng), 800, rng, temp_span_c=(24.0, 24.3))
    write_session(tmp_path / "s.csv", Session(d.t_s, d.b_ref_uT, d.b_meas_uT, d.temp_c, d.session,
                                              metadata={"device_id": "x"}))
    rc = main(["fit", str(tmp_path / "s.csv"), "--refuse-unidentifiable", "--out", str(tmp_path / "c.json")])
    assert rc == 3 and "cannot determine" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "s.csv"), "--out", str(tmp_path / "c.json")]) == 0
    assert "determined by the prior, not the data" in capsys.readouterr().out


@pytest.mark.parametrize("model", ["eq3", "gain_offset"])
def test_model_choice(tmp_path, capsys, model):
    _session_file(tmp_path / "a.csv", 3, 0, currents=())
    assert main(["fit", str(tmp_path / "a.csv"), "--model", model, "--no-holdout",
                 "--out", str(tmp_path / "c.json")]) == 0
    assert json.loads((tmp_path / "c.json").read_text())["model"]["name"] == model


def test_calibrate_session_accepts_a_table_that_was_never_saved(tmp_path):
    """A table straight from the fit (crc32 not yet computed) still labels its output."""
    from magstack.firmware.cal_table import table_from_fit
    from magstack.firmware.calibration import FitData, fit
    from magstack.ground.apply_session import calibrate_session

    _session_file(tmp_path / "a.csv", 1, 0, currents=())
    s = read_session(tmp_path / "a.csv")
    table = table_from_fit(fit(FitData.from_session(s), "eq3"), "hmc1053:sn7", validity_sd_uT=2.0)
    assert table.crc32 is None
    out = calibrate_session(table, s, "fixed")
    assert out.metadata["cal_table_crc32"] == table.to_document()["crc32"]
    assert np.isfinite(out.dut_uT).all()


def test_cli_refuses_bad_arguments_and_never_overwrites_good_files(tmp_path, capsys):
    _session_file(tmp_path / "a.csv", 1, 0, currents=())
    out = tmp_path / "cal.json"
    assert main(["fit", str(tmp_path / "a.csv"), "--no-holdout", "--out", str(out)]) == 0
    good = out.read_bytes()
    # wrong arguments: exit 2, typed message, the existing table untouched
    for extra, msg in ((["--validity-temp", "30,20"], "argument --validity-temp: expected increasing values"),
                       (["--validity-field", "nan"], "argument --validity-field: expected a finite number"),
                       (["--validity-temp=-100,20"], "argument --validity-temp: must be within [-55, 125] degC"),
                       # an empty --out is a usage error naming the option, not a traceback
                       (["--out", ""], "argument --out: expected a file name, got an empty string"),
                       (["--t0", "inf"], "argument --t0: expected a finite number"),
                       (["--block-s", "0"], "argument --block-s: must be within (0, 10000000] s")):
        capsys.readouterr()
        assert main(["fit", str(tmp_path / "a.csv"), "--no-holdout", "--out", str(out), *extra]) == 2
        assert msg in capsys.readouterr().err
        assert out.read_bytes() == good
    assert main(["fit", str(tmp_path / "a.csv"), "--no-holdout", "--out", str(tmp_path / "no" / "c.json")]) == 4
    assert "does not exist" in capsys.readouterr().err
    # an invalid (but correctly signed) table: `table validate` answers 1, `table show` exits 3 (bad input)
    doc = json.loads(good)
    doc["parameters"]["S"]["value"][1][1] = None
    from magstack.firmware.cal_table import _crc
    doc["crc32"] = f"0x{_crc(doc):08x}"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    for action, code in (("validate", 1), ("show", 3)):
        assert main(["table", action, str(bad)]) == code
        assert "parameters.S.value[1][1]: must be a finite number" in capsys.readouterr().err
    # apply: never onto its own input, never twice
    assert main(["apply", str(out), str(tmp_path / "a.csv"), "--out", str(tmp_path / "a.csv")]) == 2
    assert "write the result elsewhere" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "a.csv"), "--out", str(tmp_path / "a.csv")]) == 2   # a table over the data
    assert "write the result elsewhere" in capsys.readouterr().err and read_session(tmp_path / "a.csv")
    assert main(["apply", str(out), str(tmp_path / "a.csv"), "--out", str(tmp_path / "c.csv")]) == 0
    assert main(["apply", str(out), str(tmp_path / "c.csv"), "--out", str(tmp_path / "cc.csv")]) == 3
    assert "already calibrated" in capsys.readouterr().err
    assert not (tmp_path / "cc.csv").exists()


def test_fit_report_diagnoses_step_rows_on_the_real_data(tmp_path, capsys):
    """AV-MagEval tests 3, 5, 6, 7 as imported: rows at coil steps dominate the residual; the
    report says so and names the --exclude-steps threshold, which removes most of the misfit."""
    from pathlib import Path
    data = Path(__file__).parent / "data" / "av-mageval"
    files = []
    for n, (d, r) in {3: ("data2.csv", "ref3.csv"), 5: ("data5.csv", "ref5.csv"),
                      6: ("data6.csv", "ref6.csv"), 7: ("data7.csv", "ref7.csv")}.items():
        files.append(str(tmp_path / f"s{n}.csv"))
        assert main(["import-mageval", str(data / d), str(data / r), "--out", files[-1], "--session-id", str(n)]) == 0
    assert main(["fit", *files, "--out", str(tmp_path / "c.json")]) == 0
    text = capsys.readouterr().out
    assert "rows at steps" in text and "other rows" in text
    thr = text.split("--exclude-steps ")[1].split()[0]
    assert 0.05 < float(thr) < 0.3
    assert "session 5 left out: the other sessions cannot determine S[x,x]" in text
    assert main(["fit", *files, "--out", str(tmp_path / "c.json"), "--exclude-steps", thr]) == 0
    text2 = capsys.readouterr().out
    assert "at reference steps" in text2 and "Consider --exclude-steps" not in text2
    rmse = lambda t: float(t.split("in-sample RMSE")[1].split()[3])  # noqa: E731
    assert rmse(text2) < 0.5 * rmse(text)
