"""AV-MagEval import: axis map, kelvin -> degC, estimated offset, no extrapolation, gaps, bad input."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.errors import SessionFileError
from magstack.data.session import read_session, write_session
from magstack.ground.errors import AlignmentError
from magstack.ground.mageval_import import (
    AUTHORS_OFFSET_S,
    FLAG_NO_REF,
    import_mageval,
    read_mageval_data,
    read_mageval_ref,
)

DATA = Path(__file__).parent / "data" / "av-mageval"
D5, R5 = DATA / "data5.csv", DATA / "ref5.csv"


def test_attribution_and_byte_copies_present():
    readme = (DATA / "README.md").read_text()
    assert "MIT-STARLab/AV-MagEval-Data" in readme and "release 1.0" in readme and "Belsten" in readme
    first = D5.read_text().splitlines()[1]
    assert first == "1598371866.645,0.693,0.600,-0.699,-2.933,1.200,-2.040,-1.293,0.360,-3.213,298.994,297.129"


def test_import_pairs_with_authors_axis_map_and_kelvin():
    s = import_mageval(D5, R5)
    cols, _ = read_mageval_data(D5)
    t_ref, ref_raw, _ = read_mageval_ref(R5)
    assert np.array_equal(s.t_s, cols["time"])  # onto DUT timestamps by default
    assert np.allclose(s.temp_c, cols["temp_pi"] - 273.15)
    assert np.array_equal(s.dut_uT[:, 0], cols["x_test"])
    off = float(s.metadata["clock_offset_s"])
    # one row checked by hand: reference interpolated at t - offset, then X<-col3, Y<-col2, Z<- -col4
    k = 200
    tq = s.t_s[k] - off
    j = np.searchsorted(t_ref, tq)
    w = (tq - t_ref[j - 1]) / (t_ref[j] - t_ref[j - 1])
    b = ref_raw[j - 1] * (1 - w) + ref_raw[j] * w
    assert s.ref_uT[k] == pytest.approx([b[1], b[0], -b[2]], abs=1e-6)
    assert s.metadata["clock_offset_method"].startswith("estimated")
    assert abs(off - AUTHORS_OFFSET_S) < 0.5 and float(s.metadata["clock_offset_sigma_s"]) < 0.05
    t_mag = import_mageval(D5, R5, temp_column="temp_mag", clock_offset_s=off)
    assert np.allclose(t_mag.temp_c, cols["temp_mag"] - 273.15)


def test_never_extrapolates_gap_rows_flagged_or_dropped():
    s = import_mageval(D5, R5)
    t_ref, _, _ = read_mageval_ref(R5)
    off = float(s.metadata["clock_offset_s"])
    outside = (s.t_s < t_ref[0] + off) | (s.t_s > t_ref[-1] + off)
    assert outside.sum() > 0
    assert np.all(np.isnan(s.ref_uT[outside])) and np.all(s.flag[outside] == FLAG_NO_REF)
    assert np.all(np.isfinite(s.ref_uT[~outside]))
    assert int(s.metadata["gap_rows"]) == outside.sum()
    d = import_mageval(D5, R5, gaps="drop", clock_offset_s=off)
    assert len(d) == len(s) - outside.sum() and d.metadata["gap_rows"] == str(outside.sum())


def test_gap_inside_reference_is_not_bridged(tmp_path):
    lines = R5.read_text().splitlines(keepends=True)
    ref = tmp_path / "ref_gap.csv"
    ref.write_text("".join(lines[:300] + lines[320:]))  # ~5 s hole
    t_ref, _, _ = read_mageval_ref(ref)
    s = import_mageval(D5, ref, clock_offset_s=AUTHORS_OFFSET_S, max_gap_s=1.0)
    hole = (s.t_s > t_ref[299] + AUTHORS_OFFSET_S) & (s.t_s < t_ref[300] + AUTHORS_OFFSET_S)
    assert hole.sum() >= 8 and np.all(np.isnan(s.ref_uT[hole]))


@pytest.mark.parametrize("onto", ["ref", 0.25])
def test_other_resampling_targets(onto):
    s = import_mageval(D5, R5, onto=onto, clock_offset_s=AUTHORS_OFFSET_S, gaps="drop")
    assert len(s) > 700 and np.all(np.isfinite(s.dut_uT)) and np.all(np.isfinite(s.temp_c))
    if onto == 0.25:
        assert np.allclose(np.diff(s.t_s), 0.25)


def test_static_field_falls_back_to_prior_or_raises():
    s = import_mageval(DATA / "data3.csv", DATA / "ref4.csv")
    assert s.metadata["clock_offset_method"].startswith("prior (the data do not determine the clock offset: ")
    assert float(s.metadata["clock_offset_s"]) == AUTHORS_OFFSET_S
    with pytest.raises(AlignmentError):
        import_mageval(DATA / "data3.csv", DATA / "ref4.csv", on_undetermined="raise")


def test_bad_input_typed_errors_and_skip_counts(tmp_path):
    bad = tmp_path / "data_bad.csv"
    lines = D5.read_text().splitlines(keepends=True)
    bad.write_text("".join(lines[:10] + ["1598371870.0,0.1,garbage,0.3,1,1,1,1,1,1,298,297\n"] + lines[10:]))
    with pytest.raises(SessionFileError, match="line 11"):
        import_mageval(bad, R5)
    s = import_mageval(bad, R5, bad_lines="skip", clock_offset_s=AUTHORS_OFFSET_S)
    assert s.metadata["skipped_bad_lines"] == "dut=1 ref=0" and len(s) == len(lines) - 1
    wrong = tmp_path / "wrong.csv"
    wrong.write_text("t,a,b\n1,2,3\n")
    with pytest.raises(SessionFileError, match="header"):
        import_mageval(wrong, R5)
    with pytest.raises(SessionFileError, match="no such file"):
        import_mageval(tmp_path / "missing.csv", R5)
    nan_ref = tmp_path / "ref_nan.csv"
    nan_ref.write_text(R5.read_text().replace("0.575,0.425,0.249", "nan,0.425,0.249", 1))
    with pytest.raises(SessionFileError, match="non-finite"):
        import_mageval(D5, nan_ref)
    for kw in ({"temp_column": "temp_x"}, {"gaps": "fill"}, {"onto": "grid"}, {"onto": -1.0},
               {"on_undetermined": "guess"}, {"axis_map": ((0, 1), (0, 1), (2, 1))}):
        with pytest.raises(ValueError):
            import_mageval(D5, R5, clock_offset_s=AUTHORS_OFFSET_S, **kw)


def test_no_overlap_at_given_offset_raises():
    for gaps in ("drop", "nan"):   # a file of nothing but gap rows is not written either
        with pytest.raises(AlignmentError, match="no paired rows"):
            import_mageval(D5, R5, clock_offset_s=0.0, gaps=gaps)


def test_non_finite_offset_and_absurd_grid_are_refused(tmp_path):
    with pytest.raises(ValueError, match="clock_offset_s must be finite"):
        import_mageval(D5, R5, clock_offset_s=float("nan"))
    with pytest.raises(ValueError, match="more than 10x"):
        import_mageval(D5, R5, clock_offset_s=AUTHORS_OFFSET_S, onto=1e-9)
    with pytest.raises(SessionFileError, match="cannot read"):
        import_mageval(D5, tmp_path)                       # a directory


def test_roundtrip_through_session_file_and_cli(tmp_path, capsys):
    s = import_mageval(D5, R5)
    p = write_session(tmp_path / "s5.csv", s)
    back = read_session(p)
    assert np.allclose(back.t_s, s.t_s) and back.metadata["clock_offset_s"] == s.metadata["clock_offset_s"]
    assert np.array_equal(np.isnan(back.ref_uT), np.isnan(s.ref_uT))
    assert np.allclose(back.ref_uT[np.isfinite(s.ref_uT)], s.ref_uT[np.isfinite(s.ref_uT)], atol=1e-6)
    out = tmp_path / "cli.csv"
    assert main(["import-mageval", str(D5), str(R5), "--out", str(out), "--drop-gaps", "--onto", "0.25"]) == 0
    assert "wrote" in capsys.readouterr().out
    c = read_session(out)
    assert c.metadata["gap_policy"] == "drop" and not np.isnan(c.ref_uT).any()


@pytest.mark.parametrize("extra, offset_words", [
    ([], "estimated (min residual of ref ~ A dut + b), +0.0314 s vs the authors', sigma 0.0236 s"),
    (["--authors-offset"], "given, +0.0000 s vs the authors'"),
])
@pytest.mark.parametrize("gaps, gap_words", [
    ([], "32 rows without a reference partner kept (reference empty, flagged)"),
    (["--drop-gaps"], "32 rows without a reference partner dropped"),
])
def test_import_summary_names_no_nan_and_says_what_became_of_the_gap_rows(tmp_path, capsys, extra, offset_words,
                                                                           gaps, gap_words):
    assert main(["import-mageval", str(D5), str(R5), "--out", str(tmp_path / "s.csv"), *extra, *gaps]) == 0
    out, err = capsys.readouterr()
    assert err == "" and "nan" not in out.lower()
    assert f"({offset_words}); {gap_words}" in out


def test_a_fallback_offset_is_explained_once_on_stderr_not_repeated_on_stdout(tmp_path, capsys):
    assert main(["import-mageval", str(DATA / "data3.csv"), str(DATA / "ref4.csv"), "--out",
                 str(tmp_path / "p.csv")]) == 0
    out, err = capsys.readouterr()
    reason = "best linear fit explains only"
    assert reason not in out and err.count(reason) == 1 and err.count("do not determine") == 1
    assert "nan" not in out.lower() and "the authors' value: the data do not determine it, see the warning" in out
