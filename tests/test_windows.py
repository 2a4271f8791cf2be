"""Time windows (data/windows.py) and their CLI options on import-mageval, fit and apply."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.data.windows import TimeWindow, describe, parse_window, select_rows, window_arg

DATA = Path(__file__).parent / "data" / "av-mageval"


def test_parse_relative_absolute_and_open_ends():
    assert parse_window("30:600") == TimeWindow(30.0, 600.0, False)
    assert parse_window(":120") == TimeWindow(None, 120.0, False)
    assert parse_window("600:") == TimeWindow(600.0, None, False)
    assert parse_window("@1598371900.5:@1598372100") == TimeWindow(1598371900.5, 1598372100.0, True)
    assert str(parse_window("@1598371900.25:@1598372100")) == "@1598371900.25:@1598372100"
    for bad in ("", "1", "1:2:3", ":", "a:5", "5:1", "@:5", "@1:5", "nan:5", "1:inf"):
        with pytest.raises(ValueError):
            parse_window(bad)
    with pytest.raises(argparse.ArgumentTypeError, match="not a number"):
        window_arg("3:x")


def test_select_rows_relative_to_each_session_union_and_drop():
    t = np.concatenate([100.0 + np.arange(10), 500.0 + np.arange(10)])
    s = np.repeat([1, 2], 10)
    keep = select_rows(t, s, [parse_window("2:4")])
    assert keep.sum() == 6 and np.array_equal(t[keep], [102, 103, 104, 502, 503, 504])
    keep = select_rows(t, s, [parse_window(":1"), parse_window("8:")], [parse_window("@501:@509")])
    assert np.array_equal(t[keep], [100, 101, 108, 109, 500])
    assert select_rows(t, s).all()
    assert describe([parse_window("2:4")], [], 6, 20).endswith("6 of 20 rows")


def test_cli_windows_on_import_fit_and_apply(tmp_path, capsys):
    out = tmp_path / "s5.csv"
    assert main(["import-mageval", str(DATA / "data5.csv"), str(DATA / "ref5.csv"), "--out", str(out),
                 "--onto", "0.25", "--authors-offset", "--session-id", "5"]) == 0
    full = read_session(out)
    w = tmp_path / "w5.csv"
    assert main(["import-mageval", str(DATA / "data5.csv"), str(DATA / "ref5.csv"), "--out", str(w),
                 "--onto", "0.25", "--authors-offset", "--window", "20:150", "--drop-window", "50:60"]) == 0
    ws = read_session(w)
    rel = ws.t_s - full.t_s.min()
    assert rel.min() >= 20 and rel.max() <= 150 and not np.any((rel >= 50) & (rel <= 60))
    assert len(ws) == int(np.sum((full.t_s - full.t_s.min() >= 20) & (full.t_s - full.t_s.min() <= 150))) \
        - int(np.sum((full.t_s - full.t_s.min() >= 50) & (full.t_s - full.t_s.min() <= 60)))
    assert f"{len(ws)} of {len(full)} rows" in ws.metadata["rows_selected"]
    capsys.readouterr()
    cal = tmp_path / "cal.json"
    assert main(["fit", str(out), "--window", "0:120", "--exclude-steps", "0.1", "--no-holdout",
                 "--device-id", "dut", "--out", str(cal)]) == 0
    text = capsys.readouterr().out
    assert "time windows: keep 0:120" in text
    import json
    stats = json.loads(cal.read_text())["fit"]
    assert "keep 0:120" in stats["selection"]["windows"] and stats["selection"]["reference"] == "fvm400 +-100 uT"
    assert main(["apply", str(cal), str(out), "--out", str(tmp_path / "c.csv"), "--drop-window", ":30"]) == 0
    c = read_session(tmp_path / "c.csv")
    assert (c.t_s - full.t_s.min()).min() > 30 and "drop :30" in c.metadata["rows_selected"]
    # a bad window is a usage error (exit 2), nothing written
    assert main(["fit", str(out), "--window", "9:1", "--out", str(tmp_path / "x.json")]) == 2
    assert "end before start" in capsys.readouterr().err and not (tmp_path / "x.json").exists()
    assert main(["fit", str(out), "--window", "1e6:2e6", "--out", str(tmp_path / "x.json")]) == 2
