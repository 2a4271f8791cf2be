"""Orbit truth: geometry, attitude modes, eclipse thermal cycle, currents, simulate --program orbit_*."""
from __future__ import annotations

import math

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.reference import frames, geomag
from magstack.sim.coil_programs import PROGRAMS
from magstack.sim.orbit_truth import OrbitTruth, sso_inclination_deg
from magstack.sim.truth_source import TruthSource

T = np.arange(0.0, 6000.0, 5.0)


def test_sun_synchronous_inclination_and_circular_orbit():
    # a 500 km circular SSO has i = 97.4 deg (J2 nodal rate = 360 deg / tropical year)
    assert sso_inclination_deg(500.0) == pytest.approx(97.40, abs=0.02)
    o = OrbitTruth(duration_s=6000.0)
    r, v = o.pos_vel_gcrs_km(T)
    assert np.allclose(np.linalg.norm(r, axis=1), 6878.137)
    assert np.allclose(np.sum(r * v, axis=1), 0.0, atol=1e-6)
    period = 2 * math.pi / o.n_rad_s
    assert period == pytest.approx(5676.98, abs=0.1)      # 94.6 min
    pe = o.pos_ecef_series_km(T)
    assert np.allclose(np.linalg.norm(pe, axis=1), 6878.137)


@pytest.mark.parametrize("mode", ["inertial", "nadir", "tumbling", "spinning"])
def test_attitude_modes_keep_field_magnitude_and_are_unit_quaternions(mode):
    o = OrbitTruth(duration_s=6000.0, attitude=mode)
    assert isinstance(o, TruthSource)
    b = o.field_series_uT(T)
    ta = o.epoch_unix_s + T
    b_ref = geomag.igrf_ecef_nT(ta, o.pos_ecef_series_km(T)) / 1e3
    assert np.allclose(np.linalg.norm(b, axis=1), np.linalg.norm(b_ref, axis=1))
    q = o.q_body_eci_series(T)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0) and np.all(q[:, 0] >= 0)
    # the telemetry's own columns give back the body field
    assert np.allclose(geomag.body_field_uT(ta, o.pos_ecef_series_km(T), q), b, atol=1e-9)


def test_nadir_pointing_body_z_looks_down_and_spin_rate():
    o = OrbitTruth(duration_s=6000.0, attitude="nadir")
    r, _ = o.pos_vel_gcrs_km(T)
    down = o.attitude_series(T).apply(-r / np.linalg.norm(r, axis=1, keepdims=True))
    assert np.allclose(down, [0.0, 0.0, 1.0], atol=1e-12)
    s = OrbitTruth(duration_s=6000.0, attitude="spinning", spin_rate_deg_s=6.0, precession_s=1e9)
    a = s.attitude_series(np.array([100.0, 101.0]))
    step = (a[1] * a[0].inv()).magnitude()
    assert math.degrees(step) == pytest.approx(6.0, abs=1e-6)


def test_eclipse_thermal_cycle_and_currents():
    o = OrbitTruth(duration_s=12000.0)
    t = np.arange(0.0, 12000.0, 10.0)
    ecl = o.eclipse_series(t)
    # 500 km, 10:30 LTAN in June: about 35 % of the orbit in the Earth's shadow
    assert 0.28 < ecl.mean() < 0.40
    temp = o.temp_series_c(t)
    assert temp[ecl].mean() < temp[~ecl].mean() - 5
    assert o.temp_eclipse_c <= temp.min() and temp.max() <= o.temp_sun_c
    c = o.currents_series_A(t)
    assert np.all(c["solar"][ecl] == 0) and c["solar"].max() > 0.5
    assert np.all(c["battery"][ecl] < 0)
    assert abs(np.corrcoef(c["battery"], c["solar"])[0, 1]) < 0.999
    assert set(np.unique(c["torquer"])) == {-0.08, 0.0, 0.08}


def test_bad_configuration():
    with pytest.raises(ConfigurationError):
        OrbitTruth(attitude="sideways")
    with pytest.raises(ConfigurationError):
        OrbitTruth(altitude_km=50.0)


def test_simulate_orbit_program_writes_telemetry(tmp_path):
    assert {"orbit_nadir", "orbit_inertial", "orbit_tumbling", "orbit_spinning"} <= set(PROGRAMS)
    out = tmp_path / "o.csv"
    assert main(["simulate", "--program", "orbit_spinning", "--seconds", "120", "--rate-hz", "1",
                 "--t0", "1780272000", "--out", str(out)]) == 0
    s = read_session(out)
    assert s.warnings == [] and len(s) == 121
    assert set(s.extra) == {"pos_ecef_x_km", "pos_ecef_y_km", "pos_ecef_z_km", "q_body_eci_w", "q_body_eci_x",
                            "q_body_eci_y", "q_body_eci_z"}
    assert s.metadata["orbit_attitude"] == "spinning"
    # housekeeping at its own rate: solar every 10 s, torquer every row
    assert np.isfinite(s.currents_A["solar"]).sum() == 13 and np.isfinite(s.currents_A["torquer"]).all()
    pos = np.column_stack([s.extra[f"pos_ecef_{a}_km"] for a in "xyz"])
    q = np.column_stack([s.extra[f"q_body_eci_{a}"] for a in "wxyz"])
    assert np.max(np.abs(geomag.body_field_uT(s.t_s, pos, q) - s.ref_uT)) < 5e-4
    lat = frames.ecef_to_geodetic(pos)[0]
    assert np.all(np.abs(lat) < 90)
