"""One ``--json [FILE]`` rule and one output-path
rule for every command, run over every command the parser knows (a new command without a case here
fails :func:`test_every_command_is_covered`)."""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pytest

from magstack.cli.main import build_parser, main

DATA = Path(__file__).parent / "data" / "av-mageval"
NUMBER_TEXT = re.compile(r"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*$|^\s*[-+]?(nan|inf|infinity)\s*$", re.I)


def strict_json(text: str):
    def refuse(c):
        raise ValueError(f"non-standard JSON constant {c}")
    return json.loads(text, parse_constant=refuse)


def numbers_as_text(x, where="") -> list[str]:
    """Paths in a JSON document whose string value is a number written as text ("70", "nan")."""
    if isinstance(x, dict):   # text by definition: hex bytes, the policy named "nan", unit "1"
        return [p for k, v in x.items() if not (k.endswith("_hex") or k in ("gap_policy", "unit"))
                for p in numbers_as_text(v, f"{where}.{k}")]
    if isinstance(x, list):
        return [p for i, v in enumerate(x) for p in numbers_as_text(v, f"{where}[{i}]")]
    return [f"{where}={x!r}"] if isinstance(x, str) and NUMBER_TEXT.match(x) else []


def _commands(parser, prefix=()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                subs = list(_commands(sub, (*prefix, name)))
                yield from subs or [(*prefix, name)]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("schema")
    f = {"dir": d, "session": d / "s.csv", "params": d / "p.json", "table": d / "cal.json", "tlm": d / "tl.csv"}
    assert main(["simulate", "--program", "full", "--seconds", "600", "--out", str(f["session"]),
                 "--save-params", str(f["params"]), "-q"]) == 0
    assert main(["fit", str(f["session"]), "--no-holdout", "--out", str(f["table"]), "-q"]) == 0
    f["hand"] = d / "hand.csv"
    assert main(["simulate", "--chip", "hmc5983", "--program", "hand", "--seconds", "80", "--sessions", "1",
                 "--rate-hz", "50", "--out", str(f["hand"]), "-q"]) == 0
    assert main(["simulate", "--program", "orbit_tumbling", "--seconds", "3600", "--rate-hz", "1", "--sessions", "1",
                 "--t0", "1780272000", "--effects", "gain,offset,noise", "--out", str(f["tlm"]), "-q"]) == 0
    from magstack.firmware.flight.config import example_config_text
    from tests.netutil import own_tc_port

    text = own_tc_port(example_config_text()).replace("spi0.0,start=6,reset=13,drdy=19,sr=5", "sim").replace(
        'bus = "1"', 'bus = "sim"')
    text = text.replace('table = "tables/hmc1053.json"', "")
    (d / "flight.toml").write_text(text)
    # refit telemetry split into magnetometer rows and an ADCS file (merge); a packet stream (tm decode)
    from magstack.data.session import Session, read_session, write_session
    from magstack.data.telemetry import POS_COLUMNS, QUAT_COLUMNS
    s = read_session(f["tlm"])
    cols = (*POS_COLUMNS, *QUAT_COLUMNS)
    write_session(d / "mag.csv", Session(s.t_s, s.ref_uT, s.dut_uT, s.temp_c, s.session, dict(s.currents_A),
                                         dict(s.metadata), s.flag,
                                         extra={k: v for k, v in s.extra.items() if k not in cols}))
    rows = ["t_s," + ",".join(cols)] + [",".join(f"{v:.9f}" for v in (t, *(s.extra[c][k] for c in cols)))
                                        for k, t in enumerate(s.t_s)]
    (d / "adcs.csv").write_text("\n".join(rows) + "\n")
    assert main(["run", "--config", str(d / "flight.toml"), "--duration", "5", "--out", str(d / "tlm0"), "-q"]) == 0
    f["packets"] = next((d / "tlm0").glob("packets-*.bin"))
    return f


def _cases(f, tmp: Path) -> dict[tuple[str, ...], list[str]]:
    s, t = str(f["session"]), str(f["table"])
    return {
        ("align",): ["align", s],
        ("apply",): ["apply", t, s, "--out", str(tmp / "c.csv")],
        ("bench",): ["bench", "--dut", "lis3mdl", "--seconds", "2", "--out", str(tmp / "b.csv")],
        ("calibrate",): ["calibrate", str(f["hand"]), "--chip", "hmc5983", "--site", "52,4.36", "--date",
                         "2026-06-01", "--out", str(tmp / "hand.json")],
        ("demo",): ["demo", "--out", str(tmp / "demo"), "--seconds", "300"],
        ("diagnose",): ["diagnose", s, "--block-s", "60"],
        ("fit",): ["fit", s, "--no-holdout", "--out", str(tmp / "cal2.json")],
        ("import-mageval",): ["import-mageval", str(DATA / "data5.csv"), str(DATA / "ref5.csv"), "--out",
                              str(tmp / "m.csv")],
        ("probe",): ["probe"],
        ("read",): ["read", "--chip", "lis3mdl", "-n", "2"],
        ("refit",): ["refit", str(f["tlm"]), "--out", str(tmp / "cand.json")],
        ("run",): ["run", "--config", str(f["dir"] / "flight.toml"), "--duration", "5", "--out", str(tmp / "tlm")],
        ("simulate",): ["simulate", "--program", "steps_x", "--seconds", "20", "--out", str(tmp / "sim.csv")],
        ("table", "show"): ["table", "show", t],
        ("table", "validate"): ["table", "validate", t],
        ("table", "export"): ["table", "export", t, "--image", str(tmp / "t.mcal")],
        ("validate-diagnosis",): ["validate-diagnosis", "--out", str(tmp / "vd")],
        ("merge",): ["merge", str(f["dir"] / "mag.csv"), "--adcs", str(f["dir"] / "adcs.csv"), "--out",
                     str(tmp / "merged.csv")],
        ("tm", "xtce"): ["tm", "xtce", "--config", str(f["dir"] / "flight.toml")],
        ("tm", "dictionary"): ["tm", "dictionary"],
        ("tm", "decode"): ["tm", "decode", str(f["packets"]), "--out", str(tmp / "dec")],
        ("tm", "command"): ["tm", "command", "ping", "--config", str(f["dir"] / "flight.toml"), "--out",
                           str(tmp / "ping.tc")],
    }


def test_every_command_is_covered(files, tmp_path):
    assert set(_commands(build_parser())) == set(_cases(files, tmp_path))


@pytest.fixture
def quick_validation(monkeypatch):
    """validate-diagnosis simulates ~100 sessions: its CLI layer is checked on a stand-in of the same shape."""
    import magstack.ground.diagnose.validate as v

    def fake(out, **kw):
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "summary.md").write_text("summary\n")
        return {"targets": {"detect": True}, "seconds": kw["duration_s"], "nan_figure": float("nan")}
    monkeypatch.setattr(v, "run_validation", fake)
    monkeypatch.setattr(v, "jobs_count", lambda *a: 1)


@pytest.mark.slow
def test_every_command_prints_one_strict_json_object_with_numbers_as_numbers(files, tmp_path, capsys,
                                                                            quick_validation, shared_demo):
    for name, argv in _cases(files, tmp_path).items():
        if name == ("demo",):   # the shared run of this same command line with --json (tests/conftest.py)
            code, cap = shared_demo["code"], argparse.Namespace(out=shared_demo["stdout"], err=shared_demo["stderr"])
        else:
            code = main([*argv, "--json"])
            cap = capsys.readouterr()
        doc = strict_json(cap.out)          # the whole of stdout is one object
        assert isinstance(doc, dict) and doc["command"] == name[0] and doc["exit_code"] == code, (name, cap.err)
        assert code in (0, 1), (name, doc)
        assert numbers_as_text(doc) == [], name


def test_json_file_dash_and_positional(files, tmp_path, capsys):
    s = str(files["session"])
    out = tmp_path / "a.json"
    assert main(["align", s, "--json", str(out)]) == 0      # a FILE: the JSON there, the text on stdout
    text = capsys.readouterr().out
    assert "clock offset" in text and strict_json(out.read_text())["command"] == "align"
    assert main(["align", s, "--json", "-"]) == 0            # '-' is stdout, no file named '-'
    assert strict_json(capsys.readouterr().out)["command"] == "align" and not Path("-").exists()
    assert main(["align", "--json", s]) == 0                 # not a .json name: the command's own argument
    assert strict_json(capsys.readouterr().out)["command"] == "align"
    assert main(["diagnose", s, "--json", str(tmp_path / "d.json"), "--block-s", "60"]) == 0
    doc = strict_json((tmp_path / "d.json").read_text())
    assert doc["command"] == "diagnose" and "verdict" in doc
    capsys.readouterr()
    assert main(["probe", "--json", str(tmp_path / "no" / "p.json")]) == 4     # missing directory: system error
    assert "does not exist" in capsys.readouterr().err
    assert main(["probe", "--json=x.txt"]) == 2
    assert "ending in .json" in capsys.readouterr().err


def test_an_output_is_never_an_input_or_another_output(files, tmp_path, capsys):
    """`refit tl.csv --out c.json --json tl.csv` is refused: the report never replaces the telemetry."""
    tlm = tmp_path / "tl.csv"
    tlm.write_bytes(files["tlm"].read_bytes())
    tab = tmp_path / "cal.json"
    tab.write_bytes(files["table"].read_bytes())
    before = {p: p.read_bytes() for p in (tlm, tab)}
    link = tmp_path / "link.json"
    link.symlink_to(tab)
    for argv in (["refit", str(tlm), "--out", str(tmp_path / "c.json"), "--json", str(tlm) + ".json"],
                 ["refit", str(tlm), "--out", str(tmp_path / "c.json"), "--active", str(tab), "--json", str(tab)],
                 ["refit", str(tlm), "--out", str(tmp_path / "x.json"), "--json", str(tmp_path / "x.json")],
                 ["refit", str(tlm), "--active", str(tab), "--out", str(link)],
                 ["diagnose", str(files["session"]), "--table", str(tab), "--json", str(link)],
                 ["apply", str(tab), str(files["session"]), "--out", str(tmp_path / "c.csv"), "--json", str(tab)],
                 ["simulate", "--out", str(tmp_path / "sim.csv"), "--save-params", str(tmp_path / "sim.csv")]):
        if argv[-1].endswith("tl.csv.json"):   # the issue's `--json tl.csv`: not a .json name, so not the FILE
            argv = [*argv[:-2], "--json", str(tlm)]
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "write the result elsewhere" in err or "name the same file" in err or "unrecognized" in err, err
    for p, b in before.items():
        assert p.read_bytes() == b
    assert not (tmp_path / "x.json").exists()


def test_temporary_outputs_never_follow_a_planted_symlink(tmp_path):
    """A pre-existing temporary name pointing at a victim file is never followed or overwritten."""
    import os

    from magstack.data.io import atomic_write_text, open_exclusive

    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    out = tmp_path / "out.json"
    planted = tmp_path / f".out.json.tmp-{os.getpid()}"
    planted.symlink_to(victim)
    with pytest.raises(OSError):
        atomic_write_text(out, "{}")
    assert victim.read_text() == "keep me" and not out.exists() and planted.is_symlink()
    with pytest.raises(FileExistsError):
        open_exclusive(planted)
    assert victim.read_text() == "keep me"


@pytest.mark.slow
def test_report_and_json_writers_use_exclusive_temp_files(files, tmp_path, capsys):
    """The diagnose report and --json FILE go through the exclusive writer: a planted .part is never followed."""
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    (tmp_path / "d.json.part").symlink_to(victim)
    (tmp_path / "rep").mkdir()
    (tmp_path / "rep" / "diagnosis.html.part").symlink_to(victim)
    assert main(["diagnose", str(files["session"]), "--block-s", "60", "--json", str(tmp_path / "d.json"),
                 "--report", str(tmp_path / "rep")]) == 0
    assert victim.read_text() == "keep me"
    assert strict_json((tmp_path / "d.json").read_text())["command"] == "diagnose"
    assert (tmp_path / "rep" / "diagnosis.html").read_text().startswith("<!DOCTYPE html>")


@pytest.mark.parametrize("content, what", [
    (None, "not a regular file"),                                   # a directory
    ("[" * 50 + "]" * 50, "nested"),
    ('{"schema": 1' + "0" * 400 + "}", "digits"),
])
def test_table_inputs_are_bounded_before_reading(tmp_path, capsys, files, content, what):
    """Not a table document at all -> exit 3, one line, for every reader."""
    p = tmp_path / "t.json"
    if content is None:
        p.mkdir()
    else:
        p.write_text(content)
    for argv in (["table", "validate", str(p)], ["table", "show", str(p)],
                 ["apply", str(p), str(files["session"]), "--out", str(tmp_path / "c.csv")],
                 ["diagnose", str(files["session"]), "--table", str(p)],
                 ["diagnose", str(files["session"]), "--sim", str(p)],
                 ["refit", str(files["tlm"]), "--active", str(p), "--out", str(tmp_path / "cand.json")]):
        assert main(argv) == 3, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and what in err and "Traceback" not in err, (argv, err)


def test_dev_zero_is_refused_without_reading(capsys):
    assert main(["table", "validate", "/dev/zero"]) == 3
    assert "not a regular file" in capsys.readouterr().err


def test_read_json_bounded_limits():
    from magstack.data.io import parse_json_bounded
    from magstack.errors import InputDataError

    assert parse_json_bounded(b'\xef\xbb\xbf{"a": [1, 2.5, "x]]"]}', "f") == {"a": [1, 2.5, "x]]"]}
    for raw, msg in ((b'{"a": NaN}', "NaN"), (b'{"a": 1' + b"0" * 40 + b"}", "digits"), (b"[" * 40, "nested"),
                     (b'{"a": ', "not valid JSON"), (b"\xff", "UTF-8")):
        with pytest.raises(InputDataError, match=msg):
            parse_json_bounded(raw, "f")


@pytest.mark.parametrize("argv, text", [
    (["fit", "S", "--out", "c.json", "--validity-temp", "-20,60", "--no-holdout"], None),   # negative first value
    (["refit", "T", "--out", "c.json", "--device-id", ""], "argument --device-id: expected a non-empty name"),
    (["fit", "S", "--out", "c.json", "--device-id", " "], "argument --device-id: expected a non-empty name"),
    (["diagnose", "S", "--model", "gain++offset"], "argument --model: expected effect names joined by '+'"),
])
def test_option_values(files, tmp_path, capsys, monkeypatch, argv, text):
    monkeypatch.chdir(tmp_path)
    argv = [str(files["session"]) if a == "S" else str(files["tlm"]) if a == "T" else a for a in argv]
    code = main(argv)
    err = capsys.readouterr().err
    if text is None:
        assert code == 0, err
        assert json.loads(Path("c.json").read_text())["validity"]["temp_c"] == [-20.0, 60.0]
    else:
        assert code == 2 and text in err, err


def test_every_option_has_help_text():
    def walk(p, name=()):
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for n, sub in a.choices.items():
                    yield from walk(sub, (*name, n))
            elif name:
                yield name, a
    missing = [(n, a.option_strings or a.dest) for n, a in walk(build_parser()) if not a.help]
    assert missing == []


def test_demo_out_and_out_dir_alias():
    p = build_parser()
    assert p.parse_args(["demo", "--out", "x"]).out == Path("x") == p.parse_args(["demo", "--out-dir", "x"]).out


def test_probe_addresses_are_hex_strings_and_columns_align(capsys):
    assert main(["probe", "--json"]) == 0
    doc = strict_json(capsys.readouterr().out)
    assert [d["address"] for d in doc["devices"]] == ["0x1c", "0x1e", "0x1e"]
    assert main(["probe"]) == 0
    lines = capsys.readouterr().out.splitlines()
    starts = {ln.index(d["chip"]) for ln, d in zip(lines[1:], doc["devices"], strict=True)}
    assert starts == {lines[0].index("type")}


def test_import_mageval_numbers_are_numbers(tmp_path, capsys):
    assert main(["import-mageval", str(DATA / "data5.csv"), str(DATA / "ref5.csv"), "--out",
                 str(tmp_path / "m.csv"), "--json"]) == 0
    doc = strict_json(capsys.readouterr().out)
    assert isinstance(doc["gap_rows"], int) and isinstance(doc["clock_offset_s"], float)
    assert doc["gap_policy"] == "nan"     # a policy name stays text
    assert np.isfinite(doc["clock_offset_sigma_s"])


def test_verbose_logs_the_decisions_and_quiet_silences_warnings(files, tmp_path, capsys):
    """-v / -vv log the decisions of the main commands; -q silences the warnings."""
    s = str(files["session"])
    expect = {("fit", s, "--no-holdout", "--out", str(tmp_path / "c.json")): ["fit: model eq3", "fit: rows used"],
              ("apply", str(files["table"]), s, "--out", str(tmp_path / "a.csv")): ["apply: table 0x",
                                                                                   "apply: not calibrated"],
              ("diagnose", s, "--block-s", "60"): ["diagnose: simulator --model", "diagnose: verdict"],
              ("align", s): ["align: model"],
              ("simulate", "--program", "steps_x", "--seconds", "20", "--out", str(tmp_path / "x.csv")):
                  ["simulate: effects on:"],
              ("refit", str(files["tlm"]), "--out", str(tmp_path / "cand.json")): ["refit: rows selected:"]}
    for argv, texts in expect.items():
        main([*argv, "-v"])
        err = capsys.readouterr().err
        assert all(f"magstack: INFO: {t}" in err for t in texts), (argv[0], err)
        assert "DEBUG" not in err
    main(["simulate", "--program", "steps_x", "--seconds", "20", "--out", str(tmp_path / "y.csv"), "-vv"])
    assert "magstack: DEBUG: simulate: error-model parameters" in capsys.readouterr().err


def test_fit_warns_when_the_field_cannot_support_the_table(tmp_path, capsys):
    """A zero-field session gives a table with a warning that the field cannot support it."""
    from magstack.data.session import read_session, write_session

    src = tmp_path / "s.csv"
    assert main(["simulate", "--program", "steps_xyz", "--seconds", "120", "--out", str(src), "-q"]) == 0
    s = read_session(src)
    s.ref_uT[:] = 0.02 * np.random.default_rng(0).standard_normal(s.ref_uT.shape)
    s.dut_uT[:] = s.ref_uT + 0.3
    write_session(tmp_path / "zero.csv", s)
    capsys.readouterr()
    assert main(["fit", str(tmp_path / "zero.csv"), "--no-holdout", "--model", "gain_offset", "--out",
                 str(tmp_path / "c.json"), "--json"]) == 0
    cap = capsys.readouterr()
    assert "magstack: WARNING: fit: the reference field never reaches 5 uT on axis x, y, z" in cap.err
    assert any("never reaches" in n for n in strict_json(cap.out)["notes"])
    assert main(["fit", str(tmp_path / "zero.csv"), "--no-holdout", "--model", "gain_offset", "--out",
                 str(tmp_path / "c.json"), "-q"]) == 0
    assert "WARNING" not in capsys.readouterr().err
    # as text: the warning is said once, on stderr, not repeated as a note on stdout
    assert main(["fit", str(tmp_path / "zero.csv"), "--no-holdout", "--model", "gain_offset", "--out",
                 str(tmp_path / "c.json")]) == 0
    cap = capsys.readouterr()
    assert cap.err.count("never reaches 5 uT") == 1 and "never reaches" not in cap.out


def test_a_missing_output_directory_is_a_system_error_for_every_writer(files, tmp_path, capsys):
    """`simulate --out no/s.csv` and every other writer: a missing directory is a system error (exit 4), not bad
    input (3)."""
    no = tmp_path / "no"
    for argv in (["simulate", "--program", "steps_x", "--seconds", "20", "--out", str(no / "s.csv")],
                 ["bench", "--dut", "lis3mdl", "--seconds", "2", "--out", str(no / "b.csv")],
                 ["apply", str(files["table"]), str(files["session"]), "--out", str(no / "c.csv")],
                 ["import-mageval", str(DATA / "data5.csv"), str(DATA / "ref5.csv"), "--out", str(no / "m.csv")],
                 ["probe", "--json", str(no / "p.json")]):
        assert main(argv) == 4, argv
        assert "does not exist" in capsys.readouterr().err
    assert not no.exists()
