"""Session file reliability: strict numbers,
closing line, same file twice, BOM, write errors naming the file, extra columns, and fuzzing
(only SessionFileError may escape the reader)."""
from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magstack.data import session as session_mod
from magstack.data.errors import SessionFileError
from magstack.data.session import REQUIRED_COLUMNS, Session, load_sessions, read_session, write_session

HEADER = ",".join(REQUIRED_COLUMNS)


def _session(n=6, extra=False) -> Session:
    rng = np.random.default_rng(1)
    ref, dut = rng.normal(0, 30, (n, 3)), rng.normal(0, 30, (n, 3))
    ref[::2] = np.nan   # interleaved raw rows: gaps
    return Session(1.7e9 + np.arange(n) * 0.5, ref, dut, np.full(n, 21.5), np.zeros(n, int),
                   {"coil": rng.uniform(-1, 1, n)}, {"dut_chip": "hmc1053"}, np.zeros(n, int),
                   extra={"pos_x_km": rng.uniform(-7000, 7000, n)} if extra else {})


# ------------------------------------------------------------------ item 3: plain decimals only
@pytest.mark.parametrize("cell", ["1_000", "inf", "-Infinity", "0x10", "1e", "--1", "1.2.3", "+nan", "-nan",
                                  "1 000", "١٢", "nanx", "1e400"])
def test_cells_must_be_plain_decimals_naming_file_line_column(tmp_path, cell):
    p = tmp_path / "s.csv"
    p.write_text(f"{HEADER}\n1,1,2,3,4,5,6,25,0\n2,1,{cell},3,4,5,6,25,0\n3,1,2,3,4,5,6,25,0\n", encoding="utf-8")
    with pytest.raises(SessionFileError, match=r"s\.csv: line 3: column 'ref_y_uT'"):
        read_session(p)


def test_plain_decimal_forms_and_gaps_are_accepted():
    text = f"{HEADER}\n1,+1.5,-.5,2.,1e3,1E-3,0007,NaN,0\n2,,nan, 4 ,5,6,7,,1\n"
    s = read_session(io.StringIO(text))
    assert s.ref_uT[0].tolist() == [1.5, -0.5, 2.0] and s.dut_uT[0].tolist() == [1000.0, 0.001, 7.0]
    assert np.isnan(s.temp_c).all() and np.isnan(s.ref_uT[1, :2]).all() and s.ref_uT[1, 2] == 4.0


# ------------------------------------------------------------------ item 4: closing line
def test_finished_file_has_closing_line_and_a_cut_file_is_flagged(tmp_path):
    p = write_session(tmp_path / "s.csv", _session(10))
    lines = p.read_text().splitlines()
    assert lines[-1].startswith("# magstack-end: rows=10 crc32=0x")
    assert read_session(p).warnings == []
    # cut at a row boundary: the closing line goes with the cut
    cut = tmp_path / "cut.csv"
    cut.write_text("\n".join(lines[:-4]) + "\n")
    s = read_session(cut)
    assert len(s) == 7 and any("no closing" in w and "cut short" in w for w in s.warnings)
    # rows removed but the closing line kept: row count and checksum disagree
    edited = tmp_path / "edited.csv"
    edited.write_text("\n".join(lines[:-3] + lines[-1:]) + "\n")
    w = read_session(edited).warnings
    assert any("closing line says 10 rows" in x and "8 rows" in x for x in w)
    # same count, one digit changed: the checksum catches it
    changed = tmp_path / "changed.csv"
    changed.write_text(p.read_text().replace(lines[5], lines[5].replace("21.5000", "21.5001")))
    assert any("crc32" in x for x in read_session(changed).warnings)
    # line endings converted to CRLF (a Windows checkout): the same data, no warning
    crlf = tmp_path / "crlf.csv"
    crlf.write_bytes(p.read_bytes().replace(b"\n", b"\r\n"))
    assert read_session(crlf).warnings == [] and len(read_session(crlf)) == 10


def test_part_file_stays_readable_without_closing_line(tmp_path):
    from magstack.data.session import SessionWriter
    w = SessionWriter(tmp_path / "run.csv", block_rows=3)
    for k in range(7):
        w.write_row(k, (k, 0, 0), (0, k, 0), 20.0, 1)
    w.flush()
    s = read_session(tmp_path / "run.csv.part")
    assert len(s) == 7 and s.warnings == []
    w.close()
    assert read_session(tmp_path / "run.csv").warnings == []


# ------------------------------------------------------------------ item 5: same file twice
def test_same_file_twice_is_read_once_and_said(tmp_path):
    p = write_session(tmp_path / "a.csv", _session(6))
    os.symlink(p, tmp_path / "link.csv")
    merged, notes = load_sessions([p, str(p), tmp_path / "link.csv"])
    assert len(merged) == 6
    assert sum("same file as" in n and "read once" in n for n in notes) == 2
    other = write_session(tmp_path / "b.csv", _session(4))
    merged, notes = load_sessions([p, other])
    assert len(merged) == 10 and not any("same file" in n for n in notes)


def test_fit_cli_counts_a_repeated_file_once(tmp_path, capsys):
    from magstack.cli.main import main
    from magstack.firmware.calibration.model import CalModel, resolve_terms
    from magstack.sim.synthetic_calibration import make_data, random_theta

    m = CalModel(resolve_terms("eq3"), (), (), 25.0, 0.0)
    d = make_data(m, random_theta(m, np.random.default_rng(0)), 1500, np.random.default_rng(0), noise_uT=0.03,
                  t0_s=1.6e9)
    p = write_session(tmp_path / "a.csv", Session(d.t_s, d.b_ref_uT, d.b_meas_uT, d.temp_c, np.ones(1500, int),
                                                  metadata={"device_id": "hmc1053:sn7"}))
    assert main(["fit", str(p), str(p), "--out", str(tmp_path / "t.json")]) == 0
    out = capsys.readouterr().out
    assert "same file as" in out and "read once" in out
    assert "session 1 -> 2" not in out     # not renumbered as if it were a second session


# ------------------------------------------------------------------ item 12: BOM, write errors
def test_utf8_bom_is_accepted(tmp_path):
    p = tmp_path / "bom.csv"
    p.write_bytes(b"\xef\xbb\xbf" + f"# magstack-session: 1\n{HEADER}\n1,1,2,3,4,5,6,25,0\n".encode())
    s = read_session(p)
    assert len(s) == 1 and s.metadata["magstack-session"] == "1"
    q = tmp_path / "bom2.csv"
    q.write_bytes(b"\xef\xbb\xbf" + f"{HEADER}\n1,1,2,3,4,5,6,25,0\n".encode())
    assert len(read_session(q)) == 1


FSIZE_CHILD = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from magstack.data.session import Session, write_session
    from magstack.data.errors import FileWriteError
    resource.setrlimit(resource.RLIMIT_FSIZE, (20000, resource.RLIM_INFINITY))
    n = 5000
    s = Session(np.arange(n) * 1.0, np.ones((n, 3)), np.ones((n, 3)), np.full(n, 20.0), np.zeros(n))
    try:
        write_session(sys.argv[1], s, block_rows=100)
    except FileWriteError as exc:
        print("FileWriteError", exc.exit_code, exc)
""")


def test_file_too_large_names_the_file(tmp_path):
    out = tmp_path / "big.csv"
    r = subprocess.run([sys.executable, "-c", FSIZE_CHILD, str(out)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("FileWriteError 4 ") and "big.csv.part" in r.stdout and "File too large" in r.stdout
    assert not out.exists()


# ------------------------------------------------------------------ extra columns (telemetry)
def test_extra_numeric_columns_are_preserved(tmp_path):
    s = _session(5, extra=True)
    p = write_session(tmp_path / "x.csv", s)
    assert "current_coil_A,pos_x_km,flag" in p.read_text()
    b = read_session(p)
    assert list(b.extra) == ["pos_x_km"] and np.allclose(b.extra["pos_x_km"], s.extra["pos_x_km"], atol=1e-6)
    assert len(b.select(b.t_s > b.t_s[1]).extra["pos_x_km"]) == 3
    # a column whose name is not an identifier is ignored with a warning, as before
    q = tmp_path / "y.csv"
    q.write_text(f"{HEADER},bad name\n1,1,2,3,4,5,6,25,0,7\n")
    r = read_session(q)
    assert r.extra == {} and any("bad name" in w for w in r.warnings)


# ------------------------------------------------------------------ fast path == line parser
def _line_parse(text: str) -> np.ndarray:
    lines = text.split("\n")
    return session_mod._line_table("\n".join(lines[1:]), 2, lines[0].split(","), "<t>")


cells = st.one_of(st.just(""), st.just("nan"), st.floats(-1e6, 1e6).map(lambda x: f"{x:.6f}"),
                  st.integers(-10**6, 10**6).map(str), st.floats(1e-8, 1e8).map(lambda x: f"{x:.3e}"))


@settings(max_examples=80, deadline=None)
@given(st.lists(st.lists(cells, min_size=9, max_size=9), min_size=1, max_size=30))
def test_fast_path_reads_what_the_line_parser_reads(rows):
    rows = [r[:8] + [str(abs(hash(r[8])) % 5)] for r in rows]   # integer session column
    text = HEADER + "\n" + "".join(",".join(r) + "\n" for r in rows)
    fast = session_mod._fast_table(text.split("\n", 1)[1].encode(), 9)
    ref = _line_parse(text)
    assert fast is not None
    np.testing.assert_array_equal(fast, ref)


# ------------------------------------------------------------------ fuzz: typed errors only
def _valid_bytes() -> bytes:
    n = 6
    s = _session(n)
    buf = io.BytesIO()
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        p = write_session(os.path.join(d, "v.csv"), s)
        buf.write(p.read_bytes())
    return buf.getvalue()


VALID = _valid_bytes()


def _read_bytes(tmp_path_factory, data: bytes, suffix: str) -> None:
    p = tmp_path_factory.mktemp("fz") / f"f.csv{suffix}"
    p.write_bytes(data)
    try:
        s = read_session(p)
    except SessionFileError:
        return
    assert s.ref_uT.shape == (len(s), 3) and s.session.dtype == np.int64
    assert not np.isinf(s.ref_uT).any() and not np.isinf(s.t_s).any()


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=400), st.sampled_from(["", ".part"]))
def test_fuzz_arbitrary_bytes_raise_only_session_file_error(tmp_path_factory, data, suffix):
    _read_bytes(tmp_path_factory, data, suffix)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.integers(0, len(VALID) - 1), st.binary(min_size=0, max_size=4)), min_size=1,
                max_size=6), st.integers(0, len(VALID)), st.sampled_from(["", ".part"]))
def test_fuzz_mutated_valid_files_raise_only_session_file_error(tmp_path_factory, edits, cut, suffix):
    data = bytearray(VALID[:cut] if cut > len(VALID) // 2 else VALID)
    for pos, repl in edits:
        pos = min(pos, len(data))
        data[pos:pos + 1] = repl
    _read_bytes(tmp_path_factory, bytes(data), suffix)


class _ListHandler(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record):
        self.records.append(record)


def test_reader_warnings_are_logged(tmp_path):
    """The warning reaches a handler on the module's own logger, whatever an earlier in-process CLI
    run did to the ``magstack`` logger's propagation (not via the root logger, as caplog would)."""
    p = write_session(tmp_path / "s.csv", _session(4))
    cut = tmp_path / "cut.csv"
    cut.write_text("\n".join(p.read_text().splitlines()[:-1]) + "\n")
    logger = logging.getLogger("magstack.data.session")
    handler = _ListHandler()
    logger.addHandler(handler)
    try:
        read_session(cut)
    finally:
        logger.removeHandler(handler)
    assert any("cut.csv: no closing" in r.getMessage() for r in handler.records)
