"""``magstack merge``: ADCS position/attitude + magnetometer-only telemetry -> refit input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import Session, read_session, write_session
from magstack.data.telemetry import NO_ADCS_FLAG, POS_COLUMNS, QUAT_COLUMNS, AdcsTrack, iter_telemetry
from magstack.firmware.calibration.refit import refit
from magstack.ground.merge_adcs import adcs_at, gaps

EFFECTS = "interference,misalignment,gain,temperature_gain,offset,temperature_offset,noise"
HOLE = (3000.0, 3600.0)          # s after the start: no ADCS samples here


def _write_adcs(path, t, pos, q, comment=True):
    lines = (["# adcs: simulated, every second telemetry row"] if comment else []) + \
        ["t_s,pos_ecef_x_km,pos_ecef_y_km,pos_ecef_z_km,mode,q_body_eci_w,q_body_eci_x,q_body_eci_y,q_body_eci_z"]
    lines += [f"{a:.6f},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f},3,{w[0]:.12f},{w[1]:.12f},{w[2]:.12f},{w[3]:.12f}"
              for a, p, w in zip(t, pos, q, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    """A simulated orbit split into magnetometer-only telemetry and an ADCS file (0.5 Hz, with a hole)."""
    d = tmp_path_factory.mktemp("merge")
    orig = d / "orbit.csv"
    assert main(["simulate", "--program", "orbit_tumbling", "--seconds", "7200", "--rate-hz", "1", "--sessions",
                 "1", "--seed", "4", "--t0", "1780272000", "--effects", EFFECTS, "--out", str(orig)]) == 0
    s = read_session(orig)
    cols = (*POS_COLUMNS, *QUAT_COLUMNS)
    mag = Session(s.t_s, s.ref_uT, s.dut_uT, s.temp_c, s.session, dict(s.currents_A), dict(s.metadata), s.flag,
                  extra={k: v for k, v in s.extra.items() if k not in cols})
    write_session(d / "mag.csv", mag)
    pos = np.column_stack([s.extra[c] for c in POS_COLUMNS])
    q = np.column_stack([s.extra[c] for c in QUAT_COLUMNS])
    rel = s.t_s - s.t_s[0]
    keep = (np.arange(len(s)) % 2 == 0) & ~((rel >= HOLE[0]) & (rel <= HOLE[1]))
    _write_adcs(d / "adcs.csv", s.t_s[keep], pos[keep], q[keep])
    return d, orig, s


def test_merged_telemetry_refits_like_the_original(split, capsys):
    d, orig, s = split
    out = d / "merged.csv"
    assert main(["merge", str(d / "mag.csv"), "--adcs", str(d / "adcs.csv"), "--out", str(out), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    f = rep["files"][0]
    rel = s.t_s - s.t_s[0]
    in_hole = (rel > HOLE[0] - 2) & (rel < HOLE[1] + 2)   # between the ADCS samples at 2998 and 3602 s
    assert f["rows"] == len(s) and f["without_adcs"] == f["rows"] - f["merged"] > 500
    assert len(f["gaps"]) == 1 and f["gaps"][0]["rows"] == f["without_adcs"]
    assert f["gaps"][0]["t_first_s"] == pytest.approx(s.t_s[0] + HOLE[0] - 1)
    assert f["without_adcs"] == in_hole.sum() == 603
    m = read_session(out)
    flagged = (m.flag & NO_ADCS_FLAG) != 0
    assert flagged.sum() == f["without_adcs"] and np.all(flagged <= in_hole)
    assert np.isnan(m.extra["pos_ecef_x_km"][flagged]).all()
    # merged rows: the position/attitude of the original file (exact at ADCS instants, interpolated between)
    pos0 = np.column_stack([s.extra[c] for c in POS_COLUMNS])
    pos1 = np.column_stack([m.extra[c] for c in POS_COLUMNS])
    assert np.max(np.linalg.norm(pos1 - pos0, axis=1)[~flagged]) < 0.01          # km: 10 m
    q0 = np.column_stack([s.extra[c] for c in QUAT_COLUMNS])
    q1 = np.column_stack([m.extra[c] for c in QUAT_COLUMNS])
    assert np.min(np.abs(np.sum(q0 * q1, axis=1))[~flagged]) > np.cos(np.radians(0.3) / 2)   # tumbling: slerp over 2 s
    # refit on the merged file and on the original agree; the merge's flagged rows are counted, not lost
    a, b = refit([orig]), refit([out])
    assert b.counts.get("flag: not a good sample") == f["without_adcs"]
    assert b.rows == a.rows
    se = np.maximum(np.abs(a.fit.theta) * 1e-3, 1e-4)
    assert np.max(np.abs(b.fit.theta - a.fit.theta) / se) < 10
    assert np.linalg.norm(b.holdout_candidate_uT) < 1.2 * np.linalg.norm(a.holdout_candidate_uT)
    assert sum(len(x) for x in iter_telemetry(out)) == len(s)


def test_nearest_method_and_tolerance(split, tmp_path):
    d, _, s = split
    tight, loose = tmp_path / "tight.csv", tmp_path / "loose.csv"
    args = ["merge", str(d / "mag.csv"), "--adcs", str(d / "adcs.csv"), "--method", "nearest"]
    assert main([*args, "--tolerance", "0.5", "--out", str(tight)]) == 0
    assert main([*args, "--tolerance", "1", "--out", str(loose)]) == 0
    ft, fl = ((read_session(p).flag & NO_ADCS_FLAG) != 0 for p in (tight, loose))
    rel = s.t_s - s.t_s[0]
    outside = ~((rel >= HOLE[0]) & (rel <= HOLE[1]))
    assert np.array_equal(ft[outside], (np.arange(len(s)) % 2 == 1)[outside])    # odd rows are 1 s from ADCS
    assert not fl[outside].any()


def test_interpolation_rule_and_gap_runs():
    track = AdcsTrack("mem", np.array([0.0, 2.0, 10.0]), np.array([[7000.0, 0, 0], [7000.0, 2.0, 0], [0, 7000.0, 0]]),
                      np.array([[1.0, 0, 0, 0], [0.0, 0, 0, 1.0], [1.0, 0, 0, 0]]))
    pos, q, ok = adcs_at(track, np.array([-1.0, 0.0, 1.0, 2.0, 5.0, 10.0, 11.0]), "interpolate", 3.0)
    assert ok.tolist() == [False, True, True, True, False, True, False]
    assert pos[2].tolist() == [7000.0, 1.0, 0.0]
    assert abs(q[2, 0]) == pytest.approx(np.cos(np.pi / 4)) and abs(q[2, 3]) == pytest.approx(np.sin(np.pi / 4))
    assert [(g.t_first_s, g.t_last_s, g.rows) for g in gaps(np.arange(7.0), ~ok)] == [(0, 0, 1), (4, 4, 1), (6, 6, 1)]


def test_bad_inputs_are_refused_with_the_line(split, tmp_path, capsys):
    d, orig, s = split
    back = _write_adcs(tmp_path / "back.csv", np.array([1.0, 3.0, 2.0]), np.full((3, 3), 7000.0),
                       np.tile([1.0, 0, 0, 0], (3, 1)), comment=False)
    assert main(["merge", str(d / "mag.csv"), "--adcs", str(back), "--out", str(tmp_path / "o.csv")]) == 3
    assert "back.csv: line 4" in capsys.readouterr().err
    noquat = _write_adcs(tmp_path / "q.csv", s.t_s[:3], np.full((3, 3), 7000.0), np.tile([2.0, 0, 0, 0], (3, 1)))
    assert main(["merge", str(d / "mag.csv"), "--adcs", str(noquat), "--out", str(tmp_path / "o.csv")]) == 3
    assert "q.csv: line 3: quaternion norm" in capsys.readouterr().err
    far = _write_adcs(tmp_path / "far.csv", s.t_s[:3] + 1e6, np.full((3, 3), 7000.0), np.tile([1.0, 0, 0, 0], (3, 1)))
    assert main(["merge", str(d / "mag.csv"), "--adcs", str(far), "--out", str(tmp_path / "o.csv")]) == 3
    assert "no telemetry row has ADCS" in capsys.readouterr().err
    assert main(["merge", str(orig), "--adcs", str(d / "adcs.csv"), "--out", str(tmp_path / "o.csv")]) == 3
    assert "already has position/attitude" in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


def test_several_telemetry_files_merge_into_an_existing_directory(split, tmp_path, capsys):
    """`--out DIR/` (docs/how-to/refit-on-orbit.md): one output per input, same name; a missing directory is a
    one-line usage error that says to create it."""
    d, _orig, _s = split
    ins = []
    for name in ("a.csv", "b.csv"):
        ins.append(tmp_path / name)
        ins[-1].write_bytes((d / "mag.csv").read_bytes())
    out = tmp_path / "merged"
    assert main(["merge", *map(str, ins), "--adcs", str(d / "adcs.csv"), "--out", f"{out}/"]) == 2
    assert "create it first" in capsys.readouterr().err
    out.mkdir()
    assert main(["merge", *map(str, ins), "--adcs", str(d / "adcs.csv"), "--out", f"{out}/"]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == ["a.csv", "b.csv"]
    assert len(read_session(out / "b.csv")) == len(read_session(ins[1]))
