"""Telemetry columns on session file v1: extra-column hook, chunked reader, typed errors."""
from __future__ import annotations

import numpy as np
import pytest

from magstack.data.errors import SessionFileError
from magstack.data.session import Session, read_session, write_session
from magstack.data.telemetry import POS_COLUMNS, QUAT_COLUMNS, iter_telemetry, read_header


def _session(n=50, with_ref=True):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    extra = {c: rng.normal(size=n) * 7000 for c in POS_COLUMNS}
    extra.update({c: q[:, k] for k, c in enumerate(QUAT_COLUMNS)})
    solar = np.where(np.arange(n) % 10 == 0, 0.5, np.nan)
    return Session(1.78e9 + np.arange(n), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), np.full(n, 20.0),
                   np.zeros(n, int), {"solar": solar}, {"source": "test"}, extra=extra)


def test_position_and_attitude_columns_round_trip_through_session_v1(tmp_path):
    s = _session()
    p = write_session(tmp_path / "t.csv", s)
    header = p.read_text().splitlines()[2]
    assert header.endswith(",current_solar_A," + ",".join(POS_COLUMNS + QUAT_COLUMNS))
    back = read_session(p)
    assert back.warnings == []
    for k in POS_COLUMNS + QUAT_COLUMNS:
        assert np.allclose(back.extra[k], s.extra[k], atol=1e-6)
    sel = back.select(np.arange(len(back)) < 5)
    assert sel.extra[POS_COLUMNS[0]].size == 5
    assert len(Session.concatenate([back, back]).extra) == 7


def test_old_files_without_telemetry_columns_still_read(tmp_path):
    s = _session()
    s.extra = {}
    back = read_session(write_session(tmp_path / "old.csv", s))
    assert back.extra == {} and back.warnings == []


def test_chunked_reader_matches_the_session_reader(tmp_path):
    s = _session(123)
    p = write_session(tmp_path / "t.csv", s)
    blocks = list(iter_telemetry(p, block_rows=40))
    assert [len(b) for b in blocks] == [40, 40, 40, 3]
    assert [b.first_row for b in blocks] == [0, 40, 80, 120]
    t = np.concatenate([b.t_s for b in blocks])
    q = np.vstack([b.q_body_eci for b in blocks])
    back = read_session(p)
    assert np.array_equal(t, back.t_s)
    assert np.array_equal(q, np.column_stack([back.extra[c] for c in QUAT_COLUMNS]))
    solar = np.concatenate([b.currents_A["solar"] for b in blocks])
    assert np.array_equal(solar, back.currents_A["solar"], equal_nan=True)
    assert read_header(p).currents == ("solar",) and read_header(p).has_ref


def test_reference_columns_are_optional(tmp_path):
    p = tmp_path / "flight.csv"
    cols = ["t_s", "dut_x_uT", "dut_y_uT", "dut_z_uT", "temp_c", "session", *POS_COLUMNS, *QUAT_COLUMNS]
    p.write_text(",".join(cols) + "\n" + "1.78e9,1,2,3,20,0,7000,0,0,1,0,0,0\n")
    (b,) = iter_telemetry(p)
    assert b.ref_uT is None and np.array_equal(b.q_body_eci[0], [1, 0, 0, 0])


@pytest.mark.parametrize("row, msg", [
    ("1.78e9,1,2,x,20,0,7000,0,0,1,0,0,0", "line 3: column 'dut_z_uT': not a"),
    ("1.78e9,1,2,3,20,0,inf,0,0,1,0,0,0", "line 3: column 'pos_ecef_x_km': infinite value"),
    ("1.78e9,1,2,3,20,0.5,7000,0,0,1,0,0,0", "'session' must be an integer"),
    ("1.78e9,1,2,3,20,0,7000,0,0,1,0,0,0,9", "line 3"),
])
def test_bad_cells_name_file_line_and_column(tmp_path, row, msg):
    p = tmp_path / "bad.csv"
    cols = ["t_s", "dut_x_uT", "dut_y_uT", "dut_z_uT", "temp_c", "session", *POS_COLUMNS, *QUAT_COLUMNS]
    p.write_text(",".join(cols) + "\n" + "1.78e9,1,2,3,20,0,7000,0,0,1,0,0,0\n" + row + "\n")
    with pytest.raises(SessionFileError, match=msg):
        list(iter_telemetry(p))


def test_missing_columns_and_missing_file(tmp_path):
    p = tmp_path / "s.csv"
    p.write_text("t_s,dut_x_uT\n1,2\n")
    with pytest.raises(SessionFileError, match="lacks telemetry columns"):
        read_header(p)
    with pytest.raises(SessionFileError, match="no such telemetry file"):
        read_header(tmp_path / "nope.csv")
