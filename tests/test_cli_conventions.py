"""CLI conventions shared by every ``magstack`` command (cli/options.py, cli/output.py, cli/main.py).

--json / -v / -q on every command from one parent parser; result objects with stable keys and
strictly valid JSON; the documented exit codes; option values validated at parse time.
"""
from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from magstack.cli.main import build_parser, main
from magstack.cli.options import finite_float, float_list, int_range, name_list, named_vector, nonempty_path
from magstack.cli.output import CommandResult, dumps, json_safe
from magstack.data.session import read_session

DATA = __import__("pathlib").Path(__file__).parent / "data" / "av-mageval"


def strict_json(text: str):
    """json.loads that refuses NaN / Infinity (RFC 8259), as strict parsers do."""
    def refuse(c):
        raise ValueError(f"non-standard JSON constant {c}")
    return json.loads(text, parse_constant=refuse)


def _subcommands(parser: argparse.ArgumentParser, prefix=()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*prefix, name), sub
                yield from _subcommands(sub, (*prefix, name))


def test_every_command_has_the_common_flags():
    cmds = dict(_subcommands(build_parser()))
    assert {("align",), ("apply",), ("bench",), ("demo",), ("fit",), ("import-mageval",), ("probe",), ("read",),
            ("simulate",), ("table",), ("table", "show"), ("table", "validate")} <= set(cmds)
    for name, p in cmds.items():
        opts = {o for a in p._actions for o in a.option_strings}
        assert {"--json", "-v", "--verbose", "-q", "--quiet"} <= opts, name


def test_json_safe_is_strict():
    data = {"a": math.inf, "b": [math.nan, np.float32(1.5), np.int64(3)], "c": np.array([[1.0, -math.inf]]),
            "d": (1, 2), "e": __import__("pathlib").Path("/x"), "f": b"\x01\xff", "g": np.bool_(True)}
    assert strict_json(dumps(data)) == {"a": None, "b": [None, 1.5, 3], "c": [[1.0, None]], "d": [1, 2],
                                        "e": "/x", "f": "01ff", "g": True}
    r = CommandResult("x", {"v": math.nan}, ["line"], 1)
    assert r.to_dict() == {"command": "x", "exit_code": 1, "v": None} and r.text() == "line"
    with pytest.raises(TypeError):
        json_safe(object())


def test_option_types_name_the_range():
    f = finite_float(0, 10, lo_open=True, unit="Hz")
    assert f("2.5") == 2.5 and f.help_range == "(0, 10] Hz"
    for bad in ("0", "11", "nan", "inf", "-inf", "x", ""):
        with pytest.raises(argparse.ArgumentTypeError):
            f(bad)
    i = int_range(1, 5)
    assert i("3") == 3
    for bad in ("0", "6", "1.5", "1e3", "x", "9" * 30):
        with pytest.raises(argparse.ArgumentTypeError):
            i(bad)
    assert float_list(2, -1, 1, ordered=True)("-0.5,0.5") == (-0.5, 0.5)
    for bad in ("0.5,-0.5", "1", "0,2", "0,nan"):
        with pytest.raises(argparse.ArgumentTypeError):
            float_list(2, -1, 1, ordered=True)(bad)
    assert name_list(["a", "b"])("a,,b") == ["a", "b"]
    with pytest.raises(argparse.ArgumentTypeError, match="unknown effect 'c'"):
        name_list(["a", "b"], "effect")("a,c")
    assert named_vector(3)("solar_A=1,2,3") == ("solar_A", (1.0, 2.0, 3.0))
    for bad in ("=1,2,3", "x=1,2", "x 1,2,3", "a-b=1,2,3"):
        with pytest.raises(argparse.ArgumentTypeError):
            named_vector(3)(bad)
    with pytest.raises(argparse.ArgumentTypeError):
        nonempty_path("")


def test_usage_errors_exit_2_without_systemexit(capsys):
    assert main(["nosuchcommand"]) == 2
    assert main([]) == 2
    assert main(["simulate", "--out", "x.csv", "--bogus"]) == 2
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err
    assert main(["--version"]) == 0
    assert main(["probe", "--json", "--quiet", "--verbose"]) == 2   # -v and -q exclude each other
    capsys.readouterr()
    assert main(["simulate", "--json", "--t0", "nan", "--out", "x.csv"]) == 2   # scripts asking JSON get JSON
    doc = strict_json(capsys.readouterr().out)
    assert doc == {"command": "simulate", "exit_code": 2,
                   "error": "argument --t0: expected a finite number [0, 4102444800] s, got 'nan' (not finite)"}


@pytest.fixture(scope="module")
def sim_session(tmp_path_factory):
    d = tmp_path_factory.mktemp("conv")
    path = d / "s.csv"
    assert main(["simulate", "--chip", "lis3mdl", "--program", "steps_xyz", "--seconds", "120", "--out",
                 str(path), "--quiet"]) == 0
    return path


def _json(capsys, argv, code=0):
    assert main([*argv, "--json"]) == code
    cap = capsys.readouterr()
    return strict_json(cap.out), cap.err


def test_every_command_prints_strict_json_with_stable_keys(tmp_path, capsys, sim_session):
    """One JSON object on stdout per command (nothing else there), keys pinned here."""
    common = {"command", "exit_code"}
    cases = [
        (["simulate", "--program", "steps_x", "--seconds", "30", "--out", str(tmp_path / "sim.csv")],
         {"out", "rows", "rows_requested", "chip", "program", "seconds", "rate_hz", "sessions", "effects", "seed",
          "complete", "stopped_by"}),
        (["bench", "--dut", "lis3mdl", "--seconds", "3", "--out", str(tmp_path / "bench.csv")],
         {"path", "rows", "dut_samples", "ref_samples", "dut_errors", "ref_errors", "ref_skipped", "dut_overflows",
          "duration_s", "completed", "stopped_early", "stopped_by"}),
        (["fit", str(sim_session), "--no-holdout", "--out", str(tmp_path / "cal.json")],
         {"out", "device_id", "crc32", "model", "terms", "currents", "stats", "validation", "notes"}),
        (["table", "show", str(tmp_path / "cal.json")],
         {"table", "action", "valid", "problems", "crc32", "device_id", "model", "terms", "worst_output_uT",
          "max_cond", "document", "format", "image"}),
        (["table", "validate", str(tmp_path / "cal.json")],
         {"table", "action", "valid", "problems", "crc32", "device_id", "model", "terms", "worst_output_uT",
          "max_cond", "document", "format", "image"}),
        (["table", "export", str(tmp_path / "cal.json"), "--image", str(tmp_path / "cal.mcal")],
         {"table", "action", "device_id", "source_crc32", "image_crc32", "image_bytes", "written"}),
        (["table", "show", str(tmp_path / "cal.mcal")],
         {"table", "action", "valid", "problems", "crc32", "device_id", "model", "terms", "worst_output_uT",
          "max_cond", "document", "format", "image"}),
        (["apply", str(tmp_path / "cal.json"), str(sim_session), "--out", str(tmp_path / "calibrated.csv")],
         {"out", "rows", "applier", "table_crc32", "flag_counts", "calibrated_vs_ref_rms_nT",
          "calibrated_vs_ref_rms_away_from_steps_nT", "rows_selected", "cal_sigma_nT", "notes"}),
        (["align", str(sim_session)],
         {"offset_s", "offset_sigma_s", "r2", "n_pairs", "runner_up_ratio", "model", "rmse_model_uT", "skew_s",
          "axis_map", "rmse_uT", "notes", "out", "paired_rows", "gap_rows"}),
        (["import-mageval", str(DATA / "data5.csv"), str(DATA / "ref5.csv"), "--out", str(tmp_path / "mag.csv")],
         {"out", "rows", "clock_offset_s", "clock_offset_vs_authors_s", "clock_offset_sigma_s", "clock_offset_method",
          "gap_rows", "gap_policy", "warning", "rows_selected"}),
        (["probe"], {"bus", "devices", "supported_found"}),
        (["read", "--chip", "hmc5983", "-n", "3"], {"chip", "bus", "config", "samples"}),
    ]
    for argv, keys in cases:
        doc, err = _json(capsys, argv)
        assert set(doc) == keys | common, argv[0]
        assert doc["command"] == argv[0] and doc["exit_code"] == 0
        assert err == "", (argv[0], err)   # no progress bar, no chatter under --json
    doc, _ = _json(capsys, ["read", "--chip", "hmc5983", "-n", "3"])
    assert len(doc["samples"]) == 3 and len(doc["samples"][0]["b_uT"]) == 3


def test_align_json_has_no_infinity(capsys, sim_session):
    """`align --json` prints no `Infinity` (no runner-up minimum is null), which strict parsers would reject."""
    assert main(["align", "--json", str(sim_session)]) == 0
    out = capsys.readouterr().out
    assert "Infinity" not in out and "NaN" not in out
    assert strict_json(out)["runner_up_ratio"] is None


def test_errors_under_json_and_exit_codes(tmp_path, capsys, sim_session):
    bad = tmp_path / "bad.csv"
    bad.write_text("# magstack_session: 1\nt_s,x\n1,2\n")
    doc, err = _json(capsys, ["align", str(bad)], 3)              # bad input data
    assert doc["exit_code"] == 3 and doc["command"] == "align" and "bad.csv" in doc["error"]
    assert err.startswith("magstack align: error:") and "Traceback" not in err
    doc, _ = _json(capsys, ["fit", str(sim_session), "--out", str(tmp_path / "no" / "cal.json")], 4)  # system
    assert "does not exist" in doc["error"]
    doc, _ = _json(capsys, ["probe", "--bus", "sim"])
    assert doc["supported_found"] == 3


def test_verbosity_controls_library_logging(tmp_path, capsys):
    out = tmp_path / "a.csv"
    assert main(["bench", "--dut", "lis3mdl", "--seconds", "2", "--out", str(out), "-v"]) == 0
    err = capsys.readouterr().err
    assert "magstack: INFO: bench: recording 2 s of lis3mdl" in err
    assert main(["bench", "--dut", "lis3mdl", "--seconds", "2", "--out", str(tmp_path / "b.csv")]) == 0
    assert "INFO" not in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["align", "S", "--out", ""], ["align", "S", "--min-r2", "1.5"],
                                  ["align", "S", "--max-gap-s", "inf"], ["apply", "T", "S", "--out", ""],
                                  ["import-mageval", "D", "R", "--out", ""],
                                  ["import-mageval", "D", "R", "--out", "x.csv", "--max-gap-s", "nan"]])
def test_empty_or_non_finite_options_are_usage_errors(tmp_path, capsys, argv, monkeypatch):
    """`align --out ''` is a usage error, not a run that writes nothing; every option is checked at parse time."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    opt = next(a for a, b in zip(argv, argv[1:], strict=False) if a.startswith("--") and b in ("", "1.5", "inf",
                                                                                               "nan"))
    assert f"argument {opt}:" in err
    assert list(tmp_path.iterdir()) == []


def test_import_mageval_onto_grid_step_is_checked(tmp_path, capsys):
    out = tmp_path / "x.csv"
    for bad in ("0", "nan", "1e9", "grid"):
        assert main(["import-mageval", str(DATA / "data5.csv"), str(DATA / "ref5.csv"), "--out", str(out),
                     "--onto", bad]) == 2
        assert "--onto must be 'dut', 'ref' or a grid step in s" in capsys.readouterr().err
    assert not out.exists()


def _nested_table(path, depth: int):
    path.write_text('{"schema": "magstack-cal-table", "a": ' + "[" * depth + "]" * depth + "}")
    return path


@pytest.mark.parametrize("depth", [100_000, 990])
def test_deeply_nested_table_is_a_clean_error(tmp_path, capsys, sim_session, depth):
    """A deeply nested JSON table is one line, not a RecursionError, in table validate|show and apply.
    Not a table document at all: bad input (exit 3), also for `validate`."""
    t = _nested_table(tmp_path / "deep.json", depth)
    assert main(["table", "validate", str(t)]) == 3
    err = capsys.readouterr().err
    assert "nested" in err and "Traceback" not in err and "RecursionError" not in err
    assert main(["table", "show", str(t)]) == 3
    assert "magstack table: error:" in capsys.readouterr().err
    assert main(["apply", str(t), str(sim_session), "--out", str(tmp_path / "c.csv")]) == 3
    assert "magstack apply: error:" in capsys.readouterr().err
    assert not (tmp_path / "c.csv").exists()


def test_simulate_streams_rows_while_generating(tmp_path, monkeypatch):
    """`simulate` streams its rows: they reach the .part file block by block, so a kill loses at most a
    block; an interrupted run keeps an exact prefix of the complete run."""
    import magstack.cli.commands.simulate as sim_cmd

    monkeypatch.setattr(sim_cmd, "BLOCK_ROWS", 500)
    full = tmp_path / "full.csv"
    argv = ["simulate", "--chip", "lis3mdl", "--program", "steps_x", "--seconds", "60", "--quiet"]
    assert main([*argv, "--out", str(full)]) == 0
    n_full = len(read_session(full))
    real_blocks = sim_cmd.simulate_measurement_blocks

    def killed_after_two_blocks(*a, **kw):
        for i, blk in enumerate(real_blocks(*a, **kw)):
            if i == 2:
                raise KeyboardInterrupt   # what a kill during generation would interrupt
            yield blk

    monkeypatch.setattr(sim_cmd, "simulate_measurement_blocks", killed_after_two_blocks)
    cut = tmp_path / "cut.csv"
    assert main([*argv, "--out", str(cut)]) == 130
    part = read_session(tmp_path / "cut.csv.part")
    assert not cut.exists() and len(part) == 1000 < n_full
    whole = read_session(full)
    np.testing.assert_array_equal(part.t_s, whole.t_s[:1000])
    np.testing.assert_array_equal(part.dut_uT, whole.dut_uT[:1000])
    np.testing.assert_array_equal(part.ref_uT, whole.ref_uT[:1000])


def test_simulate_stops_on_request_and_keeps_the_part(tmp_path, monkeypatch, capsys):
    import contextlib

    import magstack.cli.commands.simulate as sim_cmd
    from magstack.cli.interrupt import StopEvent

    @contextlib.contextmanager
    def sigterm_already():
        ev = StopEvent()
        ev.signal_name = "SIGTERM"
        ev.set()
        yield ev

    monkeypatch.setattr(sim_cmd, "BLOCK_ROWS", 500)
    monkeypatch.setattr(sim_cmd, "graceful_stop", sigterm_already)
    out = tmp_path / "s.csv"
    assert main(["simulate", "--chip", "lis3mdl", "--program", "steps_x", "--seconds", "60", "--out", str(out)]) == 143
    assert "stopped by SIGTERM" in capsys.readouterr().out
    assert not out.exists() and len(read_session(tmp_path / "s.csv.part")) == 500


def test_simulate_blocks_match_the_one_shot_simulation():
    from magstack.sim.coil_programs import program
    from magstack.sim.measurement_sim import simulate_measurement, simulate_measurement_blocks
    from magstack.sim.presets import preset

    truth = program("full", 120.0)
    one = simulate_measurement(preset("hmc5983"), truth, duration_s=120.0, rate_hz=75.0, seed=4)
    blocks = list(simulate_measurement_blocks(preset("hmc5983"), truth, duration_s=120.0, rate_hz=75.0, seed=4,
                                              block_rows=1000))
    assert len(blocks) == 10 and sum(len(b.t_s) for b in blocks) == len(one.t_s)
    np.testing.assert_array_equal(np.concatenate([b.t_s for b in blocks]), one.t_s)
    np.testing.assert_array_equal(np.concatenate([b.ref_uT for b in blocks]), one.ref_uT)
    dut = np.concatenate([b.dut_uT for b in blocks])
    lsb = np.asarray(preset("hmc5983").lsb_uT)
    # equal up to floating-point rounding of the noise-filter state: at most an occasional 1-LSB flip
    assert np.all(np.abs(dut - one.dut_uT) <= lsb * 1.0001)
    assert np.mean(np.any(dut != one.dut_uT, axis=1)) < 0.01


def test_no_module_imports_a_cli_command_module():
    """Library code (and the demo) never imports from cli/commands/: step logic lives in library layers."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    offenders = []
    for folder in ("magstack", "drivers", "data", "firmware_py", "sim", "ground", "hil", "cli"):
        for path in (root / folder).rglob("*.py"):
            if path.parent.name == "commands" or path.name == "main.py" and path.parent.name == "cli":
                continue
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                offenders += [f"{path.relative_to(root)}: {n}" for n in names if n.startswith("magstack.cli.commands")]
    assert offenders == []
