"""Alignment and AV-MagEval import reliability."""
from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.errors import SessionFileError
from magstack.data.session import Session, write_session
from magstack.ground import alignment
from magstack.ground.alignment import align_streams, estimate_clock_offset
from magstack.ground.errors import AlignmentError
from magstack.ground.mageval_import import AUTHORS_OFFSET_S, import_mageval

DATA = Path(__file__).parent / "data" / "av-mageval"


def _raw(n=600, const=False, seed=0, dt=0.1):
    rng = np.random.default_rng(seed)
    t = 1.7e9 + np.arange(n) * dt
    b = np.zeros((n, 3)) if const else np.column_stack([30 * np.sin(t / 3.1), 20 * np.sin(t / 1.7 + 1),
                                                       10 * np.sin(t / 5.3 + 2)])
    ref, dut = b.copy(), b + rng.normal(0, 0.05, (n, 3))
    ref[::2], dut[1::2] = np.nan, np.nan
    return Session(t, ref, dut, np.full(n, 25.0), np.zeros(n, int), metadata={"dut_chip": "sim"})


# ------------------------------------------------------------------ item 7: constant reference
@pytest.mark.parametrize("dut_noise", [0.0, 0.05])
def test_constant_reference_says_offset_cannot_be_determined(dut_noise):
    rng = np.random.default_rng(0)
    t = np.arange(400) * 0.1
    ref = np.tile([20.0, 5.0, -30.0], (400, 1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # no RuntimeWarning ("All-NaN slice", divide by zero)
        with pytest.raises(AlignmentError, match="cannot determine a clock offset: the reference field is constant"):
            estimate_clock_offset(t, ref + rng.normal(0, dut_noise, ref.shape), t, ref, prior_s=0.0,
                                  search_halfwidth_s=5.0)


def test_align_cli_on_zero_field_session_is_a_clean_error(tmp_path, capsys):
    p = write_session(tmp_path / "zero.csv", _raw(const=True))
    assert main(["align", str(p)]) == 3
    err = capsys.readouterr().err
    assert "cannot determine a clock offset" in err and "Traceback" not in err


# ------------------------------------------------------------------ item 12: unsorted --out, strict JSON
def test_align_out_on_unsorted_timestamps_names_file_and_line(tmp_path, capsys):
    s = _raw()
    s.t_s[[300, 302]] = s.t_s[[302, 300]]          # two DUT rows swapped (rows 301/303 in 1-based data rows)
    p = write_session(tmp_path / "unsorted.csv", s)
    code = main(["align", str(p), "--out", str(tmp_path / "o.csv")])
    err = capsys.readouterr().err
    assert code == 3
    # data row 303 (0-based 302) is the first out-of-order DUT row: 2 metadata lines + 1 header + 303
    assert f"{p}: line 306: t_s" in err and "DUT timestamps must strictly increase" in err
    assert not (tmp_path / "o.csv").exists()


def test_align_json_is_strict_json_with_null_for_non_finite(tmp_path, capsys):
    p = write_session(tmp_path / "s.csv", _raw(n=300))
    assert main(["align", str(p), "--json", "--prior-s", "0", "--halfwidth-s", "0.5"]) == 0
    text = capsys.readouterr().out
    assert "Infinity" not in text and "NaN" not in text
    rep = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-strict JSON token {c}"))
    assert rep["runner_up_ratio"] is None          # no other minimum within +-0.5 s: was Infinity


# ------------------------------------------------------------------ item 6: bounded memory, same answer
def test_streamed_search_gives_the_same_answer_as_one_chunk(monkeypatch):
    s = _raw(n=2000, seed=3)
    d, r = np.all(np.isfinite(s.dut_uT), axis=1), np.all(np.isfinite(s.ref_uT), axis=1)
    args = (s.t_s[d], s.dut_uT[d], s.t_s[r] - 0.3, s.ref_uT[r])
    kw = {"prior_s": 0.0, "search_halfwidth_s": 2.0}
    monkeypatch.setattr(alignment, "MAX_CHUNK_ELEMENTS", 10**9)
    one = align_streams(*args, **kw)
    monkeypatch.setattr(alignment, "MAX_CHUNK_ELEMENTS", 500)       # a few rows per chunk
    many = align_streams(*args, **kw)
    assert one.offset.offset_s == pytest.approx(0.3, abs=0.02)
    assert many.offset.offset_s == pytest.approx(one.offset.offset_s, abs=1e-9)
    assert many.offset.sigma_s == pytest.approx(one.offset.sigma_s, rel=1e-6)
    for a, b in zip(one.skew_s, many.skew_s, strict=True):
        assert (a.determined, b.determined) == (a.determined, a.determined)
        assert math.isclose(a.value, b.value, abs_tol=1e-9) or (math.isnan(a.value) and math.isnan(b.value))


def test_search_memory_does_not_grow_with_rows(monkeypatch):
    import tracemalloc

    peaks = []
    for n in (4000, 16000):
        s = _raw(n=n, seed=1, dt=0.05)
        d, r = np.all(np.isfinite(s.dut_uT), axis=1), np.all(np.isfinite(s.ref_uT), axis=1)
        tracemalloc.start()
        estimate_clock_offset(s.t_s[d], s.dut_uT[d], s.t_s[r], s.ref_uT[r], prior_s=0.0, search_halfwidth_s=2.0)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    # the inputs grow 4x (~0.2 -> 0.8 MB of arrays); before streaming the fine stage alone held
    # (candidates x rows x columns) arrays: ~40 MB -> ~160 MB
    assert peaks[1] < 2.5 * peaks[0] + 4e6, peaks


# ------------------------------------------------------------------ item 3: AV-MagEval values
def _with_cell(tmp_path, name, line_index, col, value):
    lines = (DATA / name).read_text().splitlines()
    cells = lines[line_index].split(",")
    cells[col] = value
    lines[line_index] = ",".join(cells)
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


@pytest.mark.parametrize("value,match", [("1e300", r"1e\+300 uT is outside the physical range"),
                                         ("1_000", "not a plain decimal number"),
                                         ("inf", "infinite value"), ("0x1p3", "not a plain decimal")])
def test_mageval_refuses_values_beyond_physical_range_naming_the_line(tmp_path, value, match):
    bad = _with_cell(tmp_path, "data5.csv", 40, 2, value)    # y_test on file line 41
    with pytest.raises(SessionFileError, match=rf"data5\.csv: line 41: column 'y_test'.*{match}"):
        import_mageval(bad, DATA / "ref5.csv")


def test_mageval_refuses_absurd_reference_and_temperature(tmp_path):
    bad = _with_cell(tmp_path, "ref5.csv", 9, 3, "-5e4")
    with pytest.raises(SessionFileError, match=r"ref5\.csv: line 10: column 'bz': -50000 uT"):
        import_mageval(DATA / "data5.csv", bad)
    hot = _with_cell(tmp_path, "data5.csv", 5, 11, "2970.1")
    with pytest.raises(SessionFileError, match=r"line 6: column 'temp_pi': 2970.1 K"):
        import_mageval(hot, DATA / "ref5.csv")
    s = import_mageval(hot, DATA / "ref5.csv", bad_lines="skip", clock_offset_s=AUTHORS_OFFSET_S)
    assert s.metadata["skipped_bad_lines"] == "dut=1 ref=0"


def test_import_mageval_cli_exits_3_on_1e300_and_warns_on_fallback(tmp_path, capsys):
    bad = _with_cell(tmp_path, "data5.csv", 40, 2, "1e300")
    assert main(["import-mageval", str(bad), str(DATA / "ref5.csv"), "--out", str(tmp_path / "o.csv")]) == 3
    assert "line 41" in capsys.readouterr().err and not (tmp_path / "o.csv").exists()
    # data3 with ref4: the data do not determine the offset -> the fallback is said on stderr
    assert main(["import-mageval", str(DATA / "data3.csv"), str(DATA / "ref4.csv"), "--out",
                 str(tmp_path / "p.csv")]) == 0
    assert "WARNING: import-mageval: clock offset NOT estimated" in capsys.readouterr().err


# ------------------------------------------------------------------ item 6: progress
def test_alignment_reports_progress_per_stage():
    s = _raw(n=2000, seed=2)
    d, r = np.all(np.isfinite(s.dut_uT), axis=1), np.all(np.isfinite(s.ref_uT), axis=1)
    seen: list[tuple[str, float]] = []
    align_streams(s.t_s[d], s.dut_uT[d], s.t_s[r] - 0.2, s.ref_uT[r], prior_s=0.0, search_halfwidth_s=2.0,
                  progress=lambda stage, f: seen.append((stage, f)))
    stages = list(dict.fromkeys(st for st, _ in seen))
    assert stages[0] == "clock offset: coarse search" and "clock offset: fine search" in stages
    assert stages[-1] == "per-axis skew"
    for st in stages:
        fr = [f for s_, f in seen if s_ == st]
        assert fr == sorted(fr) and fr[-1] == pytest.approx(1.0) and all(0 < f <= 1 for f in fr)


def test_library_progress_drives_a_bar_only_on_a_terminal(monkeypatch):
    """align_streams reports progress(stage, fraction); the CLI's fraction_bar shows it only on a TTY."""
    import io as _io

    from magstack.cli import progress as prog

    class Tty(_io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(prog.sys, "stderr", _io.StringIO())          # not a terminal: silent
    with prog.fraction_bar("align") as p:
        p("clock offset: coarse search", 0.5)
    assert prog.sys.stderr.getvalue() == ""
    out = Tty()
    monkeypatch.setattr(prog.sys, "stderr", out)
    prog.set_progress_policy(json_mode=False, quiet=False)
    with prog.fraction_bar("align") as p:
        p("clock offset: coarse search", 1.0)
        p("per-axis skew", 1.0)
    assert "per-axis skew" in out.getvalue() and "100%" in out.getvalue()

@pytest.mark.slow
def test_long_search_work_grows_with_rows_not_with_range_times_rows(monkeypatch):
    """A wide search on a long session: the medium stage evaluates passes of at most 81 offsets,
    not 4 x (range/4000)/h offsets on every row (800 here, ~900 x rows interpolations in all)."""
    rng = np.random.default_rng(5)
    freqs, phases = rng.uniform(0.0003, 0.003, (3, 8)), rng.uniform(0, 6.3, (3, 8))   # coarse step 25 s resolves it

    def field(t):
        return np.stack([np.sin(2 * np.pi * freqs[i] * t[:, None] + phases[i]).sum(axis=1) for i in range(3)], 1)

    t_dut = np.arange(0, 100_000, 2.0)
    t_ref = np.arange(0, 100_000, 0.25)
    dut = field(t_dut - 3.7) + rng.normal(0, 0.01, (t_dut.size, 3))
    ref = field(t_ref)
    queries = []
    real = alignment._interp_batch

    def counting(t_src, y_src, tq, gap):
        queries.append(tq.size)
        return real(t_src, y_src, tq, gap)

    monkeypatch.setattr(alignment, "_interp_batch", counting)
    est = estimate_clock_offset(t_dut, dut, t_ref, ref, prior_s=0.0, search_halfwidth_s=50_000.0)
    assert est.offset_s == pytest.approx(3.7, abs=0.05)
    assert sum(queries) < 450 * t_dut.size, sum(queries) / t_dut.size


def test_mageval_files_with_a_utf8_bom_are_read(tmp_path):
    d = tmp_path / "data5.csv"
    d.write_bytes(b"\xef\xbb\xbf" + (DATA / "data5.csv").read_bytes())
    r = tmp_path / "ref5.csv"
    r.write_bytes(b"\xef\xbb\xbf" + (DATA / "ref5.csv").read_bytes())
    a = import_mageval(d, r, clock_offset_s=AUTHORS_OFFSET_S)
    b = import_mageval(DATA / "data5.csv", DATA / "ref5.csv", clock_offset_s=AUTHORS_OFFSET_S)
    assert len(a) == len(b) and np.array_equal(a.t_s, b.t_s)
