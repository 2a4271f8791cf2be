"""Orbit telemetry from a generator that shares no code with magstack (ppigrf + ERFA directly), diagnosed by the
CLI through the refit's reference path."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
from orbit_generator import orbit_telemetry


def _diagnose(path):
    out = subprocess.run([sys.executable, "-m", "magstack", "diagnose", str(path), "--json"], capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_the_igrf_attitude_reference_matches_an_independent_field_to_the_noise(tmp_path):
    j = _diagnose(orbit_telemetry(tmp_path / "null.csv", tempco=0.0, seed=1))
    assert j["verdict"] == "none"
    assert j["reference"]["reference"] == "igrf"
    # no attitude error here: frames, IGRF evaluation and attitude convention agree to the DUT's own noise
    assert j["baseline_rmse_nT"] <= 1.1 * j["noise_floor_nT"], (j["baseline_rmse_nT"], j["noise_floor_nT"])


@pytest.mark.slow
@pytest.mark.parametrize("tempco", [-2.7e-3, -1.35e-3])
def test_a_sensitivity_tempco_on_orbit_is_named(tmp_path, tempco):
    j = _diagnose(orbit_telemetry(tmp_path / "tc.csv", tempco=tempco, seed=2))
    assert j["verdict"] == "temperature_gain", j["ranking"][:3]
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"]
    k = j["parameters"]["K_S[x,x]"]["value"]
    assert k == pytest.approx(1.08 * tempco, rel=0.1)
