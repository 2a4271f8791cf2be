"""Orbit telemetry in the diagnosis: the refit's reference and its error budget."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from magstack.ground.diagnose import diagnose_model
from magstack.ground.diagnose.figures import _bars, headline_rows
from magstack.ground.diagnose.orbit import reference_budget, without_missing_currents
from magstack.ground.diagnose.validate import simulate_orbit


def test_reference_budget_attitude_term_is_the_rotation_error_perpendicular_to_the_field():
    b = np.tile([40.0, 0.0, 0.0], (10, 1))
    out = reference_budget(b, np.zeros(10), attitude_sd_deg=0.1)
    # delta B = delta theta x B: x (along B) gets nothing, y and z 40 uT x 1.745e-3 rad = 69.8 nT
    assert out["attitude_axes_nT"] == pytest.approx([0.0, 69.81, 69.81], abs=0.01)
    quiet = np.hypot(out["crustal_nT_per_axis"], out["external_nT_per_axis"])
    assert out["axes_nT"][0] == pytest.approx(quiet)
    # the auroral zone adds its external field
    polar = reference_budget(b, np.full(10, 70.0), attitude_sd_deg=0.1)
    assert polar["auroral_rows"] == 10 and polar["total_nT"] > out["total_nT"]


def _orbit(effect, scale=1.0, seed=200_007):
    s, notes = without_missing_currents(simulate_orbit(effect, scale, seed))
    return diagnose_model(s, "gain_offset", notes=notes).to_dict()


@pytest.mark.parametrize("effect", ["interference", "temperature_gain"])
def test_an_orbit_effect_is_found_through_the_igrf_attitude_reference(effect):
    j = _orbit(effect)
    assert j["verdict"] == effect
    b = j["reference_budget"]
    assert b is not None and b["attitude_sd_deg"] == 0.1
    assert j["floor_with_reference_nT"] == pytest.approx(np.hypot(j["noise_floor_nT"], b["total_nT"]))
    assert j["after_rmse_nT"] <= 1.2 * j["floor_with_reference_nT"]
    # on orbit a rotation per power cycle is attitude knowledge error, not a remount
    nt = {x["effect"]: x["reason"] for x in j["not_testable"]}
    assert "attitude knowledge" in nt["mount_rotation"]


def test_the_orbit_floor_states_its_parts_and_compares_the_after_gap_with_their_sum():
    """Sensor white (measured) and the reference's budget (IGRF + attitude), their root sum square, and what the
    after-gap holds beyond the white level against the budget (the validation's attitude error, 0.1 deg wandering
    with 300 s correlation, against the default 0.1 deg budget)."""
    j = _orbit("temperature_gain")
    f = j["floor"]
    assert f["sensor_white_nT"] == pytest.approx(j["noise_floor_nT"])
    assert f["reference_budget_nT"] == pytest.approx(j["reference_budget"]["total_nT"])
    assert f["total_nT"] == pytest.approx(np.hypot(f["sensor_white_nT"], f["reference_budget_nT"]))
    assert f["after_over_total"] == pytest.approx(j["after_rmse_nT"] / f["total_nT"])
    assert f["slow_nT"] == pytest.approx(np.sqrt(j["after_rmse_nT"] ** 2 - j["noise_floor_nT"] ** 2))
    # what remains beyond the white level is the attitude error: within the budget, at least half of it
    assert 0.5 <= f["slow_over_budget"] <= 1.0 and "within the reference's budget" in f["text"]
    assert f["text"].startswith(f"floor {f['total_nT']:.1f} nT = sensor white")
    # the HTML report's headline and bar chart judge the gap against the same floor, budget included
    rows = dict(headline_rows(j))
    assert rows["noise floor: sensor white + reference budget (root sum square)"] == f"{f['total_nT']:.1f}"
    assert rows["sensor white level (from the data)"] == f"{f['sensor_white_nT']:.1f}"
    assert "noise floor (from the data)" not in rows
    fig = _bars(j)
    floor_lines = [ln for ln in fig.axes[0].get_lines() if "reference budget" in ln.get_label()]
    assert len(floor_lines) == 1 and floor_lines[0].get_ydata()[0] == pytest.approx(f["total_nT"])
    assert fig.axes[0].get_ylim()[0] == 0.0


def test_orbit_telemetry_with_a_wandering_attitude_error_and_nothing_unmodelled_gives_none():
    assert _orbit(None)["verdict"] == "none"


@pytest.mark.slow
def test_cli_diagnoses_flight_telemetry_without_ref_columns(tmp_path):
    sim = tmp_path / "orbit.csv"
    out = subprocess.run([sys.executable, "-m", "magstack", "simulate", "--program", "orbit_inertial", "--seconds",
                          "5700", "--rate-hz", "0.5", "--effects", "gain,offset,noise,quantization,interference",
                          "--out", str(sim), "-q"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    flight = tmp_path / "flight.csv"
    rows = []
    for line in sim.read_text().splitlines():
        if line.startswith("#"):
            rows.append(line)
        else:
            rows.append(",".join(c for i, c in enumerate(line.split(",")) if i not in (1, 2, 3)))
    flight.write_text("\n".join(rows) + "\n")
    assert "ref_x_uT" not in flight.read_text()
    out = subprocess.run([sys.executable, "-m", "magstack", "diagnose", str(flight), "--json"],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    j = json.loads(out.stdout)
    assert j["verdict"] == "interference"
    assert j["reference"]["reference"] == "igrf" and j["reference_budget"]["total_nT"] > 0
    assert any("IGRF at the GPS position" in n for n in j["notes"])
