"""Sessions from the independent generator (tests/independent/generator.py, no magstack.sim code)
read with magstack's reader, and ``magstack fit`` recovers the generator's known parameters.

The generator writes its own CSV following docs/session-file.md, so these tests also check the
reader against a writer that is not magstack's."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from generator import CURRENT_NAMES, Scenario, make_session, write_session_csv

from magstack.cli.main import main
from magstack.data.session import load_sessions, read_session


def _as_written(x, decimals: int) -> np.ndarray:
    """What the file holds: the value formatted with ``decimals`` and parsed back (NaN: empty cell)."""
    return np.array([float(f"{v:.{decimals}f}") if np.isfinite(v) else np.nan for v in x])


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    g = make_session(Scenario(effect=None, seed=11))
    return g, g.write(tmp_path_factory.mktemp("indep") / "clean.csv")


def test_reader_reads_every_column_as_written(clean):
    g, path = clean
    s = read_session(path)
    c = g.columns
    assert len(s) == g.n and s.warnings == []
    assert s.metadata["magstack-session"] == "1"
    for k, v in g.metadata.items():
        assert s.metadata[k] == v
    np.testing.assert_array_equal(s.t_s, _as_written(c["t_s"], 6))
    for j, a in enumerate("xyz"):
        np.testing.assert_array_equal(s.ref_uT[:, j], _as_written(c[f"ref_{a}_uT"], 6))   # empty cells -> NaN
        np.testing.assert_array_equal(s.dut_uT[:, j], _as_written(c[f"dut_{a}_uT"], 6))
    np.testing.assert_array_equal(s.temp_c, _as_written(c["temp_c"], 4))
    assert s.session.dtype.kind == "i" and np.array_equal(s.session, c["session"])
    assert sorted(s.currents_A) == sorted(CURRENT_NAMES)
    for k in CURRENT_NAMES:
        np.testing.assert_array_equal(s.currents_A[k], _as_written(c[f"current_{k}_A"], 6))
    assert np.array_equal(s.flag, c["flag"]) and s.flag.sum() > 0            # dropouts are flagged
    assert np.all(np.isnan(s.ref_uT[s.flag == 1]))


def test_reader_merges_files_with_colliding_session_ids(clean, tmp_path):
    g, path = clean
    other = make_session(Scenario(effect=None, seed=12, n_sessions=2, session_s=120.0)).write(tmp_path / "b.csv")
    s, notes = load_sessions([path, other])
    assert len(s) == g.n + read_session(other).t_s.size
    assert sorted(np.unique(s.session).tolist()) == [1, 2, 3, 4, 5]       # 3 + 2 sessions, renumbered
    assert any("session 1 -> 4" in n for n in notes)


def test_reader_ignores_unknown_column_and_accepts_minimal_file(tmp_path):
    g = make_session(Scenario(effect=None, seed=13, n_sessions=1, session_s=60.0))
    cols = dict(g.columns)
    write_session_csv(tmp_path / "m.csv", cols, {}, current_names=())   # no metadata, no currents
    s = read_session(tmp_path / "m.csv")
    assert len(s) == g.n and s.currents_A == {} and s.warnings == []
    # a column name that is neither a v1 column, a current nor an identifier: ignored with a warning
    write_session_csv(tmp_path / "u.csv", cols, {}, current_names=(),
                      extra_columns={"rel.humidity": np.full(g.n, 41.5)})
    s2 = read_session(tmp_path / "u.csv")
    assert any("rel.humidity" in w for w in s2.warnings)
    np.testing.assert_array_equal(s2.dut_uT, s.dut_uT)


def test_file_without_closing_line_reads_the_same_rows(tmp_path):
    """Files from older tools have no closing line: same rows (a reader that knows the closing line
    may warn that the file could have been cut short; docs/session-file.md)."""
    g = make_session(Scenario(effect=None, seed=14, n_sessions=1, session_s=60.0))
    write_session_csv(tmp_path / "a.csv", g.columns, g.metadata)
    write_session_csv(tmp_path / "b.csv", g.columns, g.metadata, closing_line=False)
    a, b = read_session(tmp_path / "a.csv"), read_session(tmp_path / "b.csv")
    assert a.warnings == []
    np.testing.assert_array_equal(a.dut_uT, b.dut_uT)
    np.testing.assert_array_equal(a.ref_uT, b.ref_uT)
    assert all("cut short" in w for w in b.warnings)


# Tolerances for the gain+offset fit. Statistical error with ~2400 rows, ~30 nT noise and tens of uT
# of field per axis is ~1e-4 on S (the fit's own standard errors: 6e-5 to 1e-4) and ~2 nT on O. What a
# 100 nT-class calibration needs: 3e-4 on S is 15 nT at 50 uT; 10 nT on O.
S_TOL = 3e-4
O_TOL_UT = 0.010


def _noise_norm_nT(truth) -> float:
    return float(np.sqrt(3) * truth["noise_rms_nT_per_axis"])


def test_fit_gain_offset_recovers_the_generator_parameters(clean, tmp_path, capsys):
    """A user's path: fit, follow the report's --exclude-steps suggestion (the generator has coil
    steps and a 4 Hz reference: corner rows cut the corner and bias S low by ~4e-4), fit again."""
    g, path = clean
    out = tmp_path / "cal.json"
    assert main(["fit", str(path), "--model", "gain_offset", "--out", str(out)]) == 0
    report = capsys.readouterr().out
    m = re.search(r"--exclude-steps ([0-9.]+)", report)
    assert m, "the fit report should suggest --exclude-steps on a session with coil steps"
    out2 = tmp_path / "cal2.json"
    assert main(["fit", str(path), "--model", "gain_offset", "--exclude-steps", m.group(1), "--out", str(out2)]) == 0
    capsys.readouterr()
    doc = json.loads(out2.read_text())
    S = np.array(doc["parameters"]["S"]["value"])
    O = np.array(doc["parameters"]["O"]["value"])
    exp = g.truth["expected_cal"]
    dS = np.abs(S - exp["S"])
    dO = np.abs(O - exp["O_uT"])
    assert dS.max() <= S_TOL, f"S error {dS.max():.2e} (tolerance {S_TOL:g})\n{S}\n{exp['S']}"
    assert dO.max() <= O_TOL_UT, f"O error {dO.max() * 1e3:.1f} nT (tolerance {O_TOL_UT * 1e3:g} nT)"
    held_nT = doc["fit"]["holdout_blocks_rmse_norm_uT"] * 1e3
    assert held_nT <= 1.2 * _noise_norm_nT(g.truth), (held_nT, _noise_norm_nT(g.truth))
