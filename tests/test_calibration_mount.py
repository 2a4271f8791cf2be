"""Per-session mount rotations: simulated remounts recovered, sensor unchanged, real data honest."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magstack.cli.main import main
from magstack.data.session import Session, write_session
from magstack.firmware.cal_table import table_from_fit, validate
from magstack.firmware.calibration import FitData, FitOptions, fit
from magstack.firmware.calibration.model import CAL_TERMS
from magstack.firmware.effects import EFFECTS
from magstack.firmware.errors import FitError
from magstack.sim.calibration_benches import remount_bench, sweep_sessions_bench
from magstack.sim.coil_programs import ProgramTruth, rotation_profile
from magstack.sim.error_model import ErrorModel
from magstack.sim.error_params import ErrorParams

ROT = {1: (2e-3, -4e-3, 3e-3), 2: (-5e-3, 1e-3, 6e-3), 3: (1e-3, 3e-3, -2e-3)}    # rad, session 0 = frame


@pytest.fixture(scope="module")
def remounted():
    d = remount_bench(ROT, seconds_per_session=300.0)
    return d, fit(d, "gain_offset", ["mount_rotation"], options=FitOptions(holdout=False))


def test_the_catalogue_names_the_effect_and_the_calibration_term():
    e = EFFECTS["mount_rotation"]
    assert e.cal_term == "mount_rotation" and "mount_rotation" in CAL_TERMS
    names = list(EFFECTS)             # acts on the body-frame field (after interference), before the sensor's own
    assert names.index("interference") < names.index("mount_rotation") < names.index("misalignment")


def test_error_model_stage_rotates_each_session_single_equals_vector():
    truth = ProgramTruth("t", 40.0, rotation_profile(40.0), sessions=2)
    p = ErrorParams(mount_rotation_rad={1: (0.0, 0.0, np.pi / 8)})
    t = np.array([5.0, 25.0, 30.0])
    b = truth.field_series_uT(t)
    out = ErrorModel(p, effects=["mount_rotation"]).sense_series(t, truth)
    np.testing.assert_array_equal(out[0], b[0])                                  # session 0: not listed
    np.testing.assert_allclose(out[1:], Rotation.from_rotvec([0, 0, np.pi / 8]).inv().apply(b[1:]), atol=1e-12)
    m = ErrorModel(p, effects=["mount_rotation"])
    np.testing.assert_array_equal(np.array([m.sense(x, truth) for x in t]), out)  # single = vector, bit for bit
    assert ErrorParams.from_dict(p.to_dict()) == p                               # session ids survive JSON
    for bad in ({0: (1.0, np.nan, 0.0)}, {"a": (0, 0, 0)}, {0: (1.0, 0.0, 0.0)}):
        with pytest.raises(ValueError, match="mount_rotation_rad"):
            ErrorParams(mount_rotation_rad=bad)


def test_simulated_remounts_are_recovered_within_their_standard_errors(remounted):
    _, r = remounted
    assert r.mount.frame == 0 and r.mount.held == []
    for k, rv in ROT.items():
        z = (r.mount.rotvec_rad[k] - np.asarray(rv)) / r.mount.se_rad[k]
        assert np.all(np.abs(z) < 4.0), (k, z)
        assert np.all(r.mount.se_rad[k] < 1e-4)                                   # 0.1 mrad or better
    assert r.comparison["rotation_explains"] is True
    text = r.report()
    assert "mount rotations relative to session 0" in text and "session 2: x -" in text


def test_sensor_parameters_do_not_change_with_the_remounts(remounted):
    d, r = remounted
    still = fit(remount_bench({}, seconds_per_session=300.0), "gain_offset", options=FitOptions(holdout=False))
    z = (r.theta - still.theta) / np.hypot(r.se, still.se)
    assert np.all(np.abs(z) < 4.0)
    ignored = fit(d, "gain_offset", options=FitOptions(holdout=False))          # remounts not modelled
    assert np.max(np.abs((ignored.theta - still.theta) / still.se)) > 20
    assert ignored.rmse_norm_uT > 3 * r.rmse_norm_uT
    # the table carries the sensor only: no mount term, angles in the fit statistics
    t = table_from_fit(r, "hmc1053:sim")
    assert "mount_rotation" not in t.terms and validate(t).ok
    assert set(t.fit_stats["mount_rotation"]["angles_rad"]) == {"0", "1", "2", "3"}


def test_a_per_session_gain_change_is_not_explained_by_a_rotation():
    d = remount_bench(ROT, seconds_per_session=120.0)
    m = d.session == 2
    b = d.b_meas_uT.copy()
    b[m, 1] *= 1.004                                     # session 2: Y sensitivity +0.4 %, not a rotation
    d2 = FitData(b, d.b_ref_uT, d.temp_c, d.t_s, d.session)
    r = fit(d2, "gain_offset", ["mount_rotation"], options=FitOptions())
    c = r.comparison
    assert c["rotation_explains"] is False and c["F_p_value"] < 1e-6
    assert np.linalg.norm(c["holdout_session_map_uT"]) < 0.9 * np.linalg.norm(c["holdout_mount_uT"])
    assert "does NOT explain" in r.report()


def test_named_frame_and_refusal():
    d = remount_bench(ROT, seconds_per_session=120.0)
    r = fit(d, "gain_offset", ["mount_rotation"], options=FitOptions(holdout=False, mount_frame=2))
    assert r.mount.frame == 2 and np.all(r.mount.rotvec_rad[2] == 0)
    # relative to session 2: R_2^T R_s
    want = (Rotation.from_rotvec(ROT[2]).inv() * Rotation.from_rotvec(ROT[1])).as_rotvec()
    assert np.all(np.abs(r.mount.rotvec_rad[1] - want) < 4 * r.mount.se_rad[1])
    with pytest.raises(FitError, match="frame session 9"):
        fit(d, "gain_offset", ["mount_rotation"], options=FitOptions(holdout=False, mount_frame=9))
    single = d.select(d.session == 1)
    b = single.b_meas_uT.copy()
    b[:, 1:] = 0.01 * b[:, 1:]                           # a session that excites x only
    with pytest.raises(FitError, match="mount angles"):
        fit(FitData(np.vstack([d.b_meas_uT, b]), np.vstack([d.b_ref_uT, single.b_ref_uT * [1, 0.01, 0.01]]),
                    np.full(len(d) + len(single), 25.0), np.concatenate([d.t_s, single.t_s + 1e4]),
                    np.concatenate([d.session, np.full(len(single), 7)])),
            "gain_offset", ["mount_rotation"], options=FitOptions(holdout=False, on_unidentifiable="refuse"))


def test_cli_fit_with_mount_rotation(tmp_path, capsys):
    d = remount_bench(ROT, seconds_per_session=120.0)
    s = Session(d.t_s, d.b_ref_uT, d.b_meas_uT, d.temp_c, d.session, {},
                {"device_id": "hmc1053:sim", "reference": "fvm400"})
    write_session(tmp_path / "s.csv", s)
    out = tmp_path / "cal.json"
    assert main(["fit", str(tmp_path / "s.csv"), "--model", "gain_offset", "--terms", "mount_rotation",
                 "--mount-frame", "1", "--no-holdout", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "mount rotations relative to session 1" in text and "verdict:" in text
    doc = json.loads(out.read_text())
    assert "mount_rotation" not in doc["model"]["terms"]
    assert doc["fit"]["mount_rotation"]["frame_session"] == 1
    assert main(["fit", str(tmp_path / "s.csv"), "--terms", "mount_rotation", "--mount-frame", "5",
                 "--out", str(tmp_path / "x.json")]) == 2
    assert not (tmp_path / "x.json").exists()


def test_an_axis_swept_in_two_sessions_determines_their_relative_rotation():
    # like the real bench (one axis per session) but X and Y swept twice: only relative rotations of
    # sessions sweeping the same axis are visible; one angle of each pair is held (the gauge), the other
    # is the relative rotation
    rot = {1: (0.0, 0.0, 0.0), 2: (2e-3, 0.0, 3e-3), 3: (-1e-3, 2e-3, 0.0), 4: (3e-3, -4e-3, 5e-3),
           5: (-2e-3, 3e-3, -4e-3)}
    d = sweep_sessions_bench(["", "x", "y", "z", "x", "y"], rot, seconds_per_session=120.0, seed=1)
    r = fit(d, "gain_offset", ["mount_rotation"], options=FitOptions())
    plain = fit(d, "gain_offset", options=FitOptions())
    m = r.mount
    rel = (Rotation.from_rotvec(rot[1]).inv() * Rotation.from_rotvec(rot[4])).as_rotvec()   # session 4 vs 1
    got = (Rotation.from_rotvec(m.rotvec_rad[1]).inv() * Rotation.from_rotvec(m.rotvec_rad[4])).as_rotvec()
    held = {(k, a) for k, a, _ in m.held}
    assert (4, 0) in held and (1, 0) in held                    # about x: unobservable in an X sweep
    for a in (1, 2):                                            # about y and z: one of the pair is the gauge
        assert ((1, a) in held) != ((4, a) in held)
        se = np.nan_to_num(m.se_rad[1][a]) + np.nan_to_num(m.se_rad[4][a])
        assert 0 < se < 1e-4 and abs(got[a] - rel[a]) < 4 * se
    assert np.linalg.norm(r.holdout_blocks_uT) < 0.5 * np.linalg.norm(plain.holdout_blocks_uT)
    assert r.comparison["rotation_explains"] is True
