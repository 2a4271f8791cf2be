"""Session file v1: round trip, optional columns, corrupt input, crash safety (SIGKILL mid-session)."""
from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.data.errors import SessionFileError
from magstack.data.session import REQUIRED_COLUMNS, Session, SessionWriter, read_session, write_session


def _session(n=5, currents=("solar",), flag=True) -> Session:
    rng = np.random.default_rng(0)
    return Session(1.7e9 + np.arange(n) * 0.25, rng.normal(0, 30, (n, 3)), rng.normal(0, 30, (n, 3)),
                   np.full(n, 24.5), np.arange(n) // 3, {c: rng.uniform(0, 1, n) for c in currents},
                   {"dut_chip": "hmc1053", "reference": "fvm400"}, np.zeros(n, int) if flag else None)


def test_round_trip_with_metadata_currents_and_flag(tmp_path):
    s = _session()
    s.ref_uT[2, 1] = np.nan  # a gap
    p = write_session(tmp_path / "s.csv", s)
    text = p.read_text()
    assert text.startswith("# magstack-session: 1\n# dut_chip: hmc1053\n# reference: fvm400\n")
    assert "t_s,ref_x_uT,ref_y_uT,ref_z_uT,dut_x_uT,dut_y_uT,dut_z_uT,temp_c,session,current_solar_A,flag\n" in text
    b = read_session(p)
    assert b.metadata["dut_chip"] == "hmc1053" and list(b.currents_A) == ["solar"]
    assert np.allclose(b.t_s, s.t_s, atol=1e-6, rtol=0)
    assert np.array_equal(np.isnan(b.ref_uT), np.isnan(s.ref_uT))
    assert np.allclose(np.nan_to_num(b.ref_uT), np.nan_to_num(s.ref_uT), atol=1e-6)
    assert b.session.tolist() == s.session.tolist() and b.flag.tolist() == [0] * 5
    assert not (tmp_path / "s.csv.part").exists()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e5, 1e5), st.floats(-1e5, 1e5), st.floats(-60, 150),
                          st.integers(0, 1000)), min_size=1, max_size=20))
def test_round_trip_property(tmp_path_factory, rows):
    n = len(rows)
    a = np.array([r[:3] for r in rows])
    s = Session(1.6e9 + np.arange(n), np.column_stack([a[:, 0]] * 3), np.column_stack([a[:, 1]] * 3), a[:, 2],
                [r[3] for r in rows])
    p = write_session(tmp_path_factory.mktemp("rt") / "s.csv", s)
    b = read_session(p)
    assert np.allclose(b.ref_uT, s.ref_uT, atol=1e-6) and np.allclose(b.temp_c, s.temp_c, atol=1e-4)
    assert b.session.tolist() == s.session.tolist()


def test_reader_accepts_files_without_optional_columns():
    text = "# magstack-session: 1\n" + ",".join(REQUIRED_COLUMNS) + "\n1.0,1,2,3,4,5,6,25,0\n"
    s = read_session(io.StringIO(text))
    assert s.currents_A == {} and s.flag is None and s.dut_uT.tolist() == [[4, 5, 6]]
    # no metadata at all is accepted too
    assert len(read_session(io.StringIO(",".join(REQUIRED_COLUMNS) + "\n1,1,2,3,4,5,6,,0\n"))) == 1


@pytest.mark.parametrize("text,match", [
    ("", "no header row"),
    ("# magstack-session: 2\nt_s\n", "unsupported session format version"),
    ("t_s,ref_x_uT\n1,2\n", "lacks required columns"),
    (",".join(REQUIRED_COLUMNS) + "\n1,1,2,3,4,5,6,25,0\n1,1,x,3,4,5,6,25,0\n", "line 3: column 'ref_y_uT'"),
    (",".join(REQUIRED_COLUMNS) + "\n1,1,2,3,4,5,6,25\n2,1,2,3,4,5,6,25,0\n", "8 cells"),
    (",".join(REQUIRED_COLUMNS) + "\n1,1,2,3,4,5,6,25,0.5\n", "integers"),
    (",".join(REQUIRED_COLUMNS) + "\n1,inf,2,3,4,5,6,25,0\n", "infinite"),
    (",".join(REQUIRED_COLUMNS) + "\n1,1,2,3,4,5,6,25,1e30\n", "'session' column must hold integers"),
    (",".join(REQUIRED_COLUMNS) + ",flag\n1,1,2,3,4,5,6,25,0,0\n2,1,2,3,4,5,6,25,0,1.5\n",
     "'flag' column must hold integers .*data row 2"),
])
def test_corrupt_files_raise_typed_errors_naming_the_line(text, match):
    with pytest.raises(SessionFileError, match=match):
        read_session(io.StringIO(text))


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(SessionFileError, match="no such session file"):
        read_session(tmp_path / "nope.csv")
    with pytest.raises(SessionFileError, match="cannot read"):
        read_session(tmp_path)                                   # a directory
    s = Session([1.0], [[1, 2, 3]], [[4, 5, 6]], [25.0], [0])
    with pytest.raises(SessionFileError, match="does not exist"):
        write_session(tmp_path / "no_dir" / "s.csv", s)
    with pytest.raises(SessionFileError, match="is a directory"):
        write_session(tmp_path, s)
    # an empty flag cell means "no flag" (0)
    text = ",".join(REQUIRED_COLUMNS) + ",flag\n1,1,2,3,4,5,6,25,0,\n"
    assert read_session(io.StringIO(text)).flag.tolist() == [0]
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(SessionFileError, match="not a text session file"):
        read_session(tmp_path / "bin.csv")


def test_writer_refuses_inf_bad_metadata_and_missing_currents(tmp_path):
    with SessionWriter(tmp_path / "a.csv", {"k": "v"}, current_names=["solar"]) as w:
        with pytest.raises(ValueError, match="lacks currents"):
            w.write_row(1.0, (1, 2, 3), (1, 2, 3), 25.0, 0)
        with pytest.raises(ValueError, match="infinite"):
            w.write_row(1.0, (float("inf"), 2, 3), (1, 2, 3), 25.0, 0, {"solar": 0.1})
    with pytest.raises(ValueError, match="metadata key"):
        SessionWriter(tmp_path / "b.csv", {"bad key": "v"})
    with pytest.raises(ValueError, match="one line"):
        SessionWriter(tmp_path / "c.csv", {"k": "two\nlines"})


def test_abort_keeps_part_and_new_writer_does_not_truncate_it(tmp_path):
    out = tmp_path / "s.csv"
    with pytest.raises(RuntimeError):
        with SessionWriter(out, block_rows=100) as w:
            for k in range(7):
                w.write_row(k, (k, 0, 0), (0, k, 0), 20.0, 1)
            raise RuntimeError("operator pulled the plug")
    part = tmp_path / "s.csv.part"
    assert part.exists() and not out.exists()
    assert read_session(part).t_s.tolist() == list(range(7))
    with pytest.raises(SessionFileError, match="interrupted session"):
        SessionWriter(out)
    assert len(read_session(part)) == 7


def test_unterminated_last_line_of_part_is_dropped_even_if_it_parses(tmp_path):
    part = tmp_path / "x.csv.part"
    part.write_text(",".join(REQUIRED_COLUMNS) + "\n1,1,2,3,4,5,6,25,12\n2,1,2,3,4,5,6,25,1")
    s = read_session(part)
    assert len(s) == 1 and "write cut short" in s.warnings[0]
    # a finished file without a final newline keeps its parsable last row
    done = tmp_path / "x.csv"
    done.write_text(",".join(REQUIRED_COLUMNS) + "\n1,1,2,3,4,5,6,25,12\n2,1,2,3,4,5,6,25,1")
    assert len(read_session(done)) == 2


def test_concatenate_and_select():
    a, b = _session(4), _session(3)
    c = Session.concatenate([a, b])
    assert len(c) == 7 and c.columns[-1] == "flag"
    assert len(c.select(c.session == 0)) == 6
    with pytest.raises(SessionFileError, match="current columns differ"):
        Session.concatenate([a, _session(2, currents=())])


CHILD = textwrap.dedent("""
    import sys
    from magstack.data.session import SessionWriter
    w = SessionWriter(sys.argv[1], {"dut_chip": "sim"}, current_names=["coil"], block_rows=7)
    k = 0
    while True:
        w.write_row(1.7e9 + k, (k, -k, 0.5), (k + 0.25, 1, 2), 25.0, 3, {"coil": k * 0.001})
        k += 1
        if k % 7 == 0:  # a block was flushed and fsynced: report it
            print(k, flush=True)
""")


def test_sigkill_mid_session_leaves_every_flushed_row_readable(tmp_path):
    out = tmp_path / "killed.csv"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(out)], stdout=subprocess.PIPE, text=True, env=env)
    reported = 0
    deadline = time.monotonic() + 30
    try:
        while reported < 700 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            reported = int(line)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    assert reported >= 700
    part = tmp_path / "killed.csv.part"
    assert part.exists() and not out.exists()
    s = read_session(part)
    n = len(s)
    assert n >= reported  # every row reported as flushed is there (more may have been flushed since)
    k = np.arange(n)
    assert np.allclose(s.t_s, 1.7e9 + k) and np.allclose(s.ref_uT[:, 0], k) and np.allclose(s.dut_uT[:, 0], k + 0.25)
    assert np.allclose(s.currents_A["coil"], k * 0.001) and set(s.session.tolist()) == {3}
    assert s.metadata["dut_chip"] == "sim"
