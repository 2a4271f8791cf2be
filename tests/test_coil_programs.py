"""Truth generators: bench coil programs implement TruthSource, series == scalar, documented shapes."""
from __future__ import annotations

import re

import numpy as np
import pytest

from magstack.drivers.errors import ConfigurationError
from magstack.sim.coil_programs import (
    PROGRAMS,
    ProgramTruth,
    STEP_LEVELS_uT,
    constant_field,
    constant_temp,
    cycling_temp,
    excursion_profile,
    heating_profile,
    piecewise_linear,
    program,
    pulse_current,
    register_program,
    rotation_profile,
    spiral_rotation,
    square_current,
    steps_profile,
    sweep_profile,
)
from magstack.sim.truth_source import TruthSource

REQUIRED = {"steps_x", "steps_y", "steps_z", "sweep_x", "sweep_y", "sweep_z", "rotation", "zero_field",
            "large_field", "heating", "temp_cycling", "currents"}


def test_required_programs_exist_and_are_truth_sources():
    assert REQUIRED <= set(PROGRAMS)
    for name in PROGRAMS:
        tr = program(name, 120.0, sessions=3)
        assert isinstance(tr, TruthSource)
        t = np.linspace(-5.0, 130.0, 97)
        b = tr.field_series_uT(t)
        assert b.shape == (97, 3) and np.isfinite(b).all()
        # scalar protocol agrees with the vectorised one
        for x in t[::8]:
            np.testing.assert_array_equal(tr.field_uT(x), tr.field_series_uT(np.array([x]))[0])
            assert tr.temp_c(x) == tr.temp_series_c(np.array([x]))[0]
            assert tr.session(x) == tr.session_series(np.array([x]))[0]
            assert tr.currents_A(x) == {k: v[0] for k, v in tr.currents_series_A(np.array([x])).items()}


def test_unknown_program_names_valid_ones():
    with pytest.raises(ValueError, match="valid: .*steps_x"):
        program("orbit_leo")
    with pytest.raises(ConfigurationError):
        program("steps_x", -1.0)


def test_steps_visit_every_plateau_on_its_axis_only():
    tr = program("steps_y", 420.0, sessions=1)
    hold = 420.0 / len(STEP_LEVELS_uT)
    mids = (np.arange(len(STEP_LEVELS_uT)) + 0.5) * hold
    b = tr.field_series_uT(mids)
    np.testing.assert_array_equal(b[:, 1], STEP_LEVELS_uT)
    assert np.all(b[:, [0, 2]] == 0)
    assert max(STEP_LEVELS_uT) == 50.0 and min(STEP_LEVELS_uT) == -50.0
    # transitions are finite-rate ramps: never a jump larger than slope * dt
    t = np.arange(0, 420, 0.01)
    assert np.abs(np.diff(tr.field_series_uT(t)[:, 1])).max() <= 10.0 / 0.5 * 0.01 + 1e-9


def test_sweep_is_triangle_pm50_with_constant_rate():
    tr = program("sweep_z", 200.0, sessions=1)
    t = np.linspace(0, 200, 2001)
    z = tr.field_series_uT(t)[:, 2]
    assert z.max() == pytest.approx(50.0) and z.min() == pytest.approx(-50.0)
    rate = np.abs(np.diff(z) / np.diff(t))
    np.testing.assert_allclose(rate, 4 * 50.0 / 200.0, rtol=1e-6)  # 0 -> +50 -> -50 -> 0 = 200 uT in 200 s


def test_rotation_keeps_magnitude_and_covers_the_sphere():
    f = rotation_profile(600.0, magnitude_uT=50.0)
    b = f(np.linspace(0, 600, 6001))
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), 50.0)
    u = b / 50.0
    # both hemispheres and all azimuth octants visited
    assert u[:, 2].max() > 0.99 and u[:, 2].min() < -0.99
    oct_ = {(np.sign(x), np.sign(y)) for x, y in u[:, :2] if abs(x) > 0.1 and abs(y) > 0.1}
    assert len(oct_) == 4


def test_rotation_profile_is_the_spiral_rotation_of_z_in_the_stated_convention():
    d, turns = 600.0, 4.0
    t = np.linspace(-10.0, 610.0, 3001)
    u = np.clip(t, 0.0, d) / d
    theta, phi = np.pi * u, 2.0 * np.pi * turns * u
    # independent closed form: unit vector at polar angle theta, azimuth phi
    expected = 50.0 * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    np.testing.assert_allclose(rotation_profile(d, 50.0, turns)(t), expected, rtol=0, atol=1e-12)
    # R = Rz(phi) @ Ry(theta), active: columns are the turning frame's axes in body coordinates
    k = 1234
    c, s_ = np.cos, np.sin
    rz = np.array([[c(phi[k]), -s_(phi[k]), 0], [s_(phi[k]), c(phi[k]), 0], [0, 0, 1]])
    ry = np.array([[c(theta[k]), 0, s_(theta[k])], [0, 1, 0], [-s_(theta[k]), 0, c(theta[k])]])
    rot = spiral_rotation(d, turns)(t[k:k + 1])
    assert rot.shape == (1, 3, 3)
    np.testing.assert_allclose(rot[0], rz @ ry, atol=1e-14)
    # the same rotation as scipy's intrinsic Z-then-Y Euler angles, at every instant
    from scipy.spatial.transform import Rotation

    np.testing.assert_allclose(spiral_rotation(d, turns)(t), Rotation.from_euler("ZY", np.stack([phi, theta], 1))
                               .as_matrix(), rtol=0, atol=1e-14)
    assert rotation_profile(d)(np.array([])).shape == (0, 3)


def test_large_field_reaches_pm150_on_each_axis_then_returns_to_zero():
    tr = program("large_field", 300.0, sessions=1)
    t = np.linspace(0, 300, 30001)
    b = tr.field_series_uT(t)
    for i in range(3):
        assert b[:, i].max() == pytest.approx(150.0) and b[:, i].min() == pytest.approx(-150.0)
    assert np.all(b[-10:] == 0)


def test_heating_and_cycling_temperature_profiles():
    tr = program("heating", 1800.0, sessions=1)
    temp = tr.temp_series_c(np.linspace(0, 1800, 1801))
    assert temp[0] == pytest.approx(25.0) and temp.max() == pytest.approx(65.0)
    peak = int(np.argmax(temp))
    assert np.all(np.diff(temp[:peak]) >= 0) and np.all(np.diff(temp[peak:]) <= 0)
    c = cycling_temp(1000.0, mean_c=20.0, amplitude_c=40.0, cycles=2.0)(np.linspace(0, 1000, 4001))
    assert c.max() == pytest.approx(60.0, abs=0.01) and c.min() == pytest.approx(-20.0, abs=0.01)
    h = heating_profile(100.0, 20.0, 60.0)
    assert h(np.array([-10.0]))[0] == 20.0  # holds outside the run


def test_current_names_leave_the_unit_to_the_session_column():
    """A session file names a current's column ``current_<name>_A``: a name carrying the unit itself would give
    ``current_solar_A_A``."""
    for name in PROGRAMS:
        if not name.startswith("orbit_"):
            for current in program(name, 60.0, sessions=1).currents_series_A(np.array([0.0])):
                assert re.fullmatch(r"[a-z0-9]+(_[a-z0-9]+)*", current) and not current.endswith("_a"), (name, current)


def test_named_current_profiles():
    tr = program("currents", 600.0, sessions=1)
    cur = tr.currents_series_A(np.linspace(0, 600, 6001))
    assert set(cur) == {"solar", "torquer"}
    assert set(np.unique(cur["solar"])) == {0.0, 0.5}
    assert cur["solar"].mean() == pytest.approx(0.25, abs=0.01)
    assert set(np.unique(cur["torquer"])) == {0.0, 0.1}
    assert cur["torquer"].mean() == pytest.approx(0.1 * 2 / 20, abs=0.003)
    s = square_current(1.0, 10.0, duty=0.3)(np.array([0.0, 2.9, 3.1, 10.0]))
    np.testing.assert_array_equal(s, [1.0, 1.0, 0.0, 1.0])
    p = pulse_current(2.0, 5.0, 1.0, start_s=1.0)(np.array([0.5, 1.5, 2.5, 6.2]))
    np.testing.assert_array_equal(p, [0.0, 2.0, 0.0, 2.0])
    with pytest.raises(ConfigurationError):
        square_current(1.0, 0.0)
    with pytest.raises(ConfigurationError):
        pulse_current(1.0, 1.0, 2.0)


@pytest.mark.parametrize("sessions", [1, 3, 5])
def test_power_cycles_split_run_into_equal_sessions(sessions):
    tr = program("zero_field", 100.0, sessions=sessions)
    t = np.linspace(0, 100, 1001)
    s = tr.session_series(t)
    assert list(np.unique(s)) == list(range(sessions))
    assert np.all(np.diff(s) >= 0)
    np.testing.assert_allclose(tr.session_starts_s(), np.arange(sessions) * 100.0 / sessions)
    assert tr.session(1e9) == sessions - 1 and tr.session(-1.0) == 0
    with pytest.raises(ConfigurationError):
        program("zero_field", 100.0, sessions=0)


def test_full_program_combines_all_patterns():
    tr = program("full", 400.0, sessions=4)
    t = np.linspace(0, 400, 40001)
    b = tr.field_series_uT(t)
    assert np.abs(b).max() == pytest.approx(150.0)  # excursions in the last quarter
    assert np.ptp(tr.temp_series_c(t)) > 40
    assert set(tr.currents_series_A(t)) == {"solar", "torquer"}
    assert list(np.unique(tr.session_series(t))) == [0, 1, 2, 3]


def test_building_blocks_validate_input():
    with pytest.raises(ConfigurationError):
        piecewise_linear([0, 2, 1], [0, 1, 2])
    with pytest.raises(ConfigurationError):
        piecewise_linear([0, 1], [0, 1, 2])
    with pytest.raises(ConfigurationError):
        steps_profile("w", 10.0)
    with pytest.raises(ConfigurationError):
        ProgramTruth("p", 0.0, constant_field())
    with pytest.raises(ConfigurationError):
        constant_field()(np.array([np.nan]))


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("build, word", [
    (lambda: constant_field((NAN, 0.0, 0.0)), "b_uT"),
    (lambda: constant_field((1.0, 2.0)), "b_uT"),
    (lambda: steps_profile("", 10.0), "axes"),
    (lambda: steps_profile("x", NAN), "duration_s"),
    (lambda: steps_profile("x", 10.0, levels_uT=[0.0, NAN]), "levels_uT"),
    (lambda: steps_profile("x", 10.0, slew_s=-1.0), "slew_s"),
    (lambda: steps_profile("x", 10.0, background_uT=(0.0, INF, 0.0)), "background_uT"),
    (lambda: sweep_profile("", 10.0), "axes"),
    (lambda: sweep_profile("y", 10.0, amplitude_uT=NAN), "amplitude_uT"),
    (lambda: rotation_profile(0.0), "duration_s"),
    (lambda: rotation_profile(10.0, magnitude_uT=INF), "magnitude_uT"),
    (lambda: excursion_profile("z", 10.0, peak_uT=NAN), "peak_uT"),
    (lambda: constant_temp(NAN), "temp_c"),
    (lambda: heating_profile(10.0, cool_tau_fraction=0.0), "cool_tau_fraction"),
    (lambda: heating_profile(10.0, heat_fraction=1.5), "heat_fraction"),
    (lambda: heating_profile(10.0, peak_c=NAN), "peak_c"),
    (lambda: cycling_temp(10.0, amplitude_c=NAN), "amplitude_c"),
    (lambda: square_current(NAN, 1.0), "amplitude_A"),
    (lambda: square_current(1.0, INF), "period_s"),
    (lambda: pulse_current(1.0, 10.0, 1.0, start_s=NAN), "start_s"),
])
def test_profile_parameters_are_validated_when_built(build, word):
    """A bad parameter fails when the profile is built, not as NaN truth (or a ZeroDivisionError) later."""
    with pytest.raises(ConfigurationError, match=word):
        build()


def test_register_program_plugs_in_another_generator():
    name = "test_plugin_const"
    if name not in PROGRAMS:
        register_program(name, lambda d, s: ProgramTruth(name, d, constant_field((1, 2, 3)), sessions=s), 10.0,
                         "constant test field")
    tr = program(name, 5.0, sessions=2)
    np.testing.assert_array_equal(tr.field_uT(1.0), [1, 2, 3])
    with pytest.raises(ValueError, match="already registered"):
        register_program(name, lambda d, s: None, 1.0, "dup")
