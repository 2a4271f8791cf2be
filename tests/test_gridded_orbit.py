"""The gridded orbit truth `run --sim --sim-program orbit_*` feeds the simulated sensors agrees with the direct
evaluation of the orbit truth: field to 1e-3 nT, currents, temperature and sessions to rounding."""
from __future__ import annotations

import numpy as np
import pytest

import magstack.sim.orbit_truth  # noqa: F401  (registers the orbit programmes)
from magstack.sim.coil_programs import program
from magstack.sim.error_truth import sample_truth_floats
from magstack.sim.gridded_orbit import GriddedOrbitTruth


@pytest.mark.parametrize("name", ["orbit_nadir", "orbit_inertial", "orbit_tumbling", "orbit_spinning"])
def test_interpolated_truth_matches_the_direct_evaluation(name):
    orbit = program(name, 7200.0, sessions=2)
    grid = GriddedOrbitTruth(orbit)
    t = np.sort(np.random.default_rng(3).uniform(-5.0, 7300.0, 600))
    bs, temps, cur, sessions = sample_truth_floats(grid, list(t))
    one = [(orbit.field_series_uT(np.array([x]))[0], orbit.currents_series_A(np.array([x])),
            orbit.temp_series_c(np.array([x]))[0], orbit.session_series(np.array([x]))[0]) for x in t]
    b_exact = np.array([o[0] for o in one])
    assert np.abs(np.array(bs) - b_exact).max() < 1e-6                      # uT: 1e-3 nT
    for k in ("solar", "battery", "torquer"):
        assert np.abs(np.array(cur[k]) - np.array([float(o[1][k][0]) for o in one])).max() < 1e-6, k
    assert np.abs(np.array(temps) - np.array([o[2] for o in one])).max() < 1e-9
    assert sessions == [int(o[3]) for o in one]
    # the scalar protocol gives the same values as the fast path
    assert np.array_equal(grid.field_uT(t[7]), np.array(bs[7])) and grid.temp_c(t[7]) == temps[7]
    assert grid.currents_A(t[7]) == {k: v[7] for k, v in cur.items()} and grid.session(t[7]) == sessions[7]


def test_the_grid_follows_a_new_epoch():
    orbit = program("orbit_tumbling", 3600.0, sessions=1)
    g = GriddedOrbitTruth(orbit).at_epoch(orbit.epoch_unix_s + 1000.0)
    direct = orbit.at_epoch(orbit.epoch_unix_s + 1000.0).field_series_uT(np.array([12.3]))[0]
    assert np.abs(g.field_uT(12.3) - direct).max() < 1e-6
