"""Hostile inputs to the ground tools: each is one line with the documented exit code, never a traceback
and never silently accepted."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from magstack.cli.main import main
from magstack.data.session import read_session


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    d = tmp_path_factory.mktemp("hostile")
    p = d / "s.csv"
    assert main(["simulate", "--program", "steps_xyz", "--seconds", "1200", "--out", str(p),
                 "--save-params", str(d / "p.json"), "-q"]) == 0
    assert main(["fit", str(p), "--no-holdout", "--out", str(d / "cal.json"), "-q"]) == 0
    return p


def _rows(path: Path) -> tuple[list[str], int]:
    lines = [ln for ln in path.read_text().split("\n") if not ln.startswith("# magstack-end")]
    return lines, next(i for i, ln in enumerate(lines) if ln.startswith("t_s"))


def _one_line_error(capsys, argv, code):
    assert main(argv) == code, argv
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith(f"magstack {argv[0]}: error:"), err
    return err


@pytest.mark.parametrize("kind", ["header_only", "all_nan_ref", "empty_part"])
def test_align_on_a_file_without_finite_rows(tmp_path, capsys, session, kind):
    lines, h = _rows(session)
    if kind == "all_nan_ref":
        for i in range(h + 1, len(lines)):
            if lines[i]:
                c = lines[i].split(",")
                c[1:4] = ["nan"] * 3
                lines[i] = ",".join(c)
    else:
        lines = lines[:h + 1] + [""]
    p = tmp_path / ("x.csv.part" if kind == "empty_part" else "x.csv")
    p.write_text("\n".join(lines))
    err = _one_line_error(capsys, ["align", str(p)], 3)
    assert "finite samples" in err


def test_align_refuses_unsorted_rows_as_align_out_does(tmp_path, capsys, session):
    lines, h = _rows(session)
    lines[h + 10], lines[h + 11] = lines[h + 11], lines[h + 10]
    p = tmp_path / "u.csv"
    p.write_text("\n".join(lines))
    assert "must strictly increase" in _one_line_error(capsys, ["align", str(p)], 3)


def test_session_cells_beyond_the_physical_range_are_bad_input(tmp_path, capsys, session):
    lines, h = _rows(session)
    for i in range(h + 1, len(lines), 50):
        if lines[i]:
            c = lines[i].split(",")
            c[1] = "1e30"
            lines[i] = ",".join(c)
    p = tmp_path / "huge.csv"
    p.write_text("\n".join(lines))
    err = _one_line_error(capsys, ["apply", str(session.parent / "cal.json"), str(p), "--out",
                                   str(tmp_path / "c.csv")], 3)
    assert "outside the physical range" in err and "line" in err
    assert not (tmp_path / "c.csv").exists()


def test_diagnose_block_longer_than_the_session(capsys, session):
    err = _one_line_error(capsys, ["diagnose", str(session), "--block-s", "86400"], 2)
    assert "--block-s 86400" in err and "fewer than --folds 5" in err


@pytest.mark.parametrize("edit, text", [
    (lambda d: d.update(version=99), "version 99"),
    (lambda d: d["params"].update(delay_x_s=1e300), "beyond any physical"),
    (lambda d: d.update(nest=json.loads("[" * 40 + "]" * 40)), "nested"),
    (lambda d: d.update(seed=10 ** 400), "digits"),
])
def test_diagnose_sim_params_are_bounded(tmp_path, capsys, session, edit, text):
    doc = json.loads((session.parent / "p.json").read_text())
    edit(doc)
    p = tmp_path / "p.json"
    p.write_text(json.dumps(doc))
    assert text in _one_line_error(capsys, ["diagnose", str(session), "--sim", str(p)], 3)


def test_numpy_warnings_do_not_reach_stderr(capsys, monkeypatch):
    """Python warnings raised while a command runs are logged at DEBUG (-vv), not printed."""
    import warnings

    import magstack.cli.commands.probe as probe

    real = probe.run

    def noisy(args):
        warnings.warn("invalid value encountered in divide", RuntimeWarning, stacklevel=1)
        return real(args)
    monkeypatch.setattr(probe, "run", noisy)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["probe"]) == 0
        assert "RuntimeWarning" not in capsys.readouterr().err
        assert main(["probe", "-vv"]) == 0
        assert "magstack: DEBUG:" in capsys.readouterr().err


def test_telemetry_with_a_byte_order_mark_is_read(tmp_path):
    from magstack.data.telemetry import iter_telemetry

    p = tmp_path / "t.csv"
    assert main(["simulate", "--program", "orbit_tumbling", "--seconds", "120", "--rate-hz", "1", "--sessions", "1",
                 "--out", str(p), "-q"]) == 0
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    rows = sum(b.t_s.size for b in iter_telemetry(bom))
    assert rows == len(read_session(p)) == sum(b.t_s.size for b in iter_telemetry(p))


def test_integer_extra_columns_are_written_as_integers(tmp_path):
    """Integer extra columns (flight telemetry's `table_crc32`) are written as integers, not 3350503024.000000."""
    import numpy as np

    from magstack.data.session import SessionWriter

    with SessionWriter(tmp_path / "t.csv", extra_names=["table_crc32", "x"], integer_extras=["table_crc32"]) as w:
        w.write_block(np.array([[1.0, 0, 0, 0, 0, 0, 0, 25.0, 0, 3350503024.0, 0.5],
                                [2.0, 0, 0, 0, 0, 0, 0, 25.0, 0, np.nan, 0.5]]))
    rows = [ln for ln in (tmp_path / "t.csv").read_text().splitlines() if ln[:1].isdigit()]
    assert rows[0].endswith(",3350503024,0.500000") and rows[1].endswith(",,0.500000")
    s = read_session(tmp_path / "t.csv")
    assert s.extra["table_crc32"][0] == 3350503024 and np.isnan(s.extra["table_crc32"][1])
