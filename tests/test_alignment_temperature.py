"""Alignment on thermally cycled sessions: the temperature model (belsten Eq. 3 terms) in the
offset/skew/axis-map regressions, its uncertainty, and the fallback to the plain model."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.ground.alignment import align_streams, estimate_clock_offset
from magstack.ground.errors import AlignmentError
from magstack.sim.coil_programs import program
from magstack.sim.error_model import without
from magstack.sim.measurement_sim import simulate_measurement
from magstack.sim.presets import preset

HMC1053_AXIS_DELAY_S = (0.0, 0.05, 0.10)  # sim/presets.py: sequential X, Y, Z conversion


def _thermal_pair(offset_s: float, seed: int, *, duration_s: float = 300.0, prog: str = "temp_cycling",
                  skew: bool = False):
    """HMC1053 error model (gain tempco -2700 ppm/degC) on a coil program; the reference on its
    own clock (``t_ref = t_truth - offset_s``), 4 Hz, starting at another phase than the DUT's
    2.5 Hz. The logged temperature is the truth plus 0.05 degC noise, rounded to 0.01 degC."""
    truth = program(prog, duration_s, sessions=1)
    effects = None if skew else without("time_skew")
    dut = simulate_measurement(preset("hmc1053"), truth, duration_s=duration_s, rate_hz=2.5, seed=seed,
                               effects=effects)
    ref = simulate_measurement(preset("hmc1053"), truth, duration_s=duration_s - 1.0, rate_hz=4.0,
                               seed=seed + 100, t_start_s=0.137)
    temp = np.round(dut.temp_c + np.random.default_rng(seed).normal(0.0, 0.05, dut.t_s.size), 2)
    return dut.t_s, dut.dut_uT, ref.t_s - offset_s, ref.ref_uT, temp


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_thermal_cycling_offset_within_its_sigma_and_plain_model_is_not(seed):
    """-20..60 degC cycling swings the DUT gain by ~+-11 %: with the temperature terms the offset
    is found within 3 sigma and sigma is a few ms; the plain model (no temperature terms) is refused
    or >= 10x less precise (it can report +3.80 +- 0.98 s on a bench session whose true offset was 0)."""
    true_offset = 1.234 + 0.1 * seed
    t_dut, dut, t_ref, ref, temp = _thermal_pair(true_offset, seed)
    est = estimate_clock_offset(t_dut, dut, t_ref, ref, prior_s=0.0, search_halfwidth_s=10.0, temp_c=temp)
    assert est.model.startswith("linear+temperature") and "dT^2" in est.model
    assert 0.0 < est.sigma_s < 0.05
    assert abs(est.offset_s - true_offset) <= 3 * est.sigma_s
    assert est.r2 > 0.9999
    # Eq. 3 alone (first order in dT) is also right, with a larger but honest sigma
    eq3 = estimate_clock_offset(t_dut, dut, t_ref, ref, prior_s=0.0, search_halfwidth_s=10.0, temp_c=temp,
                                temp_order=1)
    assert "dT^2" not in eq3.model and abs(eq3.offset_s - true_offset) <= 3 * eq3.sigma_s < 0.5
    try:
        plain = estimate_clock_offset(t_dut, dut, t_ref, ref, prior_s=0.0, search_halfwidth_s=10.0, temp_c=temp,
                                      temp_model="off")
    except AlignmentError:
        return
    assert plain.model.startswith("linear (") and plain.sigma_s > 10 * est.sigma_s


def test_thermal_cycling_skews_and_axis_map_use_the_temperature_model():
    """With the per-axis conversion delays on, each axis's effective offset (offset - skew_i) is
    the true one less that axis's delay; the axis map is determined (identity)."""
    true_offset = 2.5
    t_dut, dut, t_ref, ref, temp = _thermal_pair(true_offset, 7, skew=True)
    rep = align_streams(t_dut, dut, t_ref, ref, prior_s=0.0, search_halfwidth_s=10.0, temp_c=temp)
    assert rep.model == rep.offset.model and rep.model.startswith("linear+temperature")
    # the joint offset lies among the per-axis effective offsets
    assert true_offset - 0.1 - 3 * rep.offset.sigma_s <= rep.offset.offset_s <= true_offset + 3 * rep.offset.sigma_s
    for i, e in enumerate(rep.skew_s):
        # X and Y rotate 8 times; Z follows one slow half cosine, so its timing is ~10x less certain
        assert e.determined and 0 < e.sigma < (0.02 if i < 2 else 0.2)
        sig = math.hypot(e.sigma, rep.offset.sigma_s)
        assert rep.offset.offset_s - e.value == pytest.approx(true_offset - HMC1053_AXIS_DELAY_S[i],
                                                              abs=max(0.005, 4 * sig))
    assert rep.axis_map.perm == (0, 1, 2) and rep.axis_map.sign == (1, 1, 1) and all(rep.axis_map.determined)
    # the temperature model explains the thermal gain: far smaller residual than the plain fit
    assert rep.rmse_model_uT is not None and rep.rmse_model_uT["vector"] < rep.rmse_uT["vector"] / 10
    assert rep.as_dict()["model"] == rep.model


def test_temperature_model_falls_back_when_absent_constant_or_sparse():
    t_dut, dut, t_ref, ref, _ = _thermal_pair(1.5, 3, duration_s=200.0, prog="sweeps")
    kw = {"prior_s": 0.0, "search_halfwidth_s": 5.0}
    base = estimate_clock_offset(t_dut, dut, t_ref, ref, **kw)
    assert base.model == "linear (no temperature column)"
    const = estimate_clock_offset(t_dut, dut, t_ref, ref, temp_c=np.full(t_dut.size, 25.0), **kw)
    assert const.model.startswith("linear (temperature span 0.00 degC")
    assert const.offset_s == base.offset_s and const.sigma_s == base.sigma_s
    # a material span on too few rows: plain model, said so
    temp = np.linspace(20.0, 40.0, t_dut.size)
    temp[::2] = np.nan
    sparse = estimate_clock_offset(t_dut, dut, t_ref, ref, temp_c=temp, **kw)
    assert "finite on only 50%" in sparse.model and sparse.offset_s == base.offset_s
    # small span (< 1 degC): auto keeps the plain model, "on" forces the temperature terms
    small = 25.0 + 0.2 * np.sin(np.linspace(0, 3, t_dut.size))
    assert estimate_clock_offset(t_dut, dut, t_ref, ref, temp_c=small, **kw).model.startswith("linear (temperature")
    forced = estimate_clock_offset(t_dut, dut, t_ref, ref, temp_c=small, temp_model="on", **kw)
    assert forced.model.startswith("linear+temperature")
    assert forced.offset_s == pytest.approx(1.5, abs=max(0.01, 3 * forced.sigma_s))
    with pytest.raises(AlignmentError, match="temp_model"):
        estimate_clock_offset(t_dut, dut, t_ref, ref, temp_c=small, temp_model="always", **kw)
    with pytest.raises(AlignmentError, match="temp_c has"):
        estimate_clock_offset(t_dut, dut, t_ref, ref, temp_c=small[:-1], **kw)


def test_a_few_missing_temperatures_are_interpolated():
    true_offset = 0.8
    t_dut, dut, t_ref, ref, temp = _thermal_pair(true_offset, 4, duration_s=200.0)
    holes = temp.copy()
    holes[np.random.default_rng(0).choice(t_dut.size, t_dut.size // 20, replace=False)] = np.nan
    holes[:3] = np.nan  # before the first finite value: those rows are left out
    full = estimate_clock_offset(t_dut, dut, t_ref, ref, prior_s=0.0, search_halfwidth_s=5.0, temp_c=temp)
    gap = estimate_clock_offset(t_dut, dut, t_ref, ref, prior_s=0.0, search_halfwidth_s=5.0, temp_c=holes)
    assert gap.model.startswith("linear+temperature") and f"on {t_dut.size - 3} rows" in gap.model
    assert abs(gap.offset_s - true_offset) <= 3 * gap.sigma_s
    assert gap.offset_s == pytest.approx(full.offset_s, abs=max(0.002, gap.sigma_s))


def test_cli_align_on_a_thermally_cycled_bench_session(tmp_path, capsys):
    """End to end (the reported repro, shortened): simulated bench, temp_cycling -> magstack align."""
    from magstack.hil.bench import build_sim_bench, run_bench

    sb = build_sim_bench("hmc1053", program="temp_cycling", seconds=200.0, instrument_name="t_al_temp")
    path = tmp_path / "tc.csv"
    run_bench(sb.dut, sb.ref, sb.clock, path, seconds=200.0, ref_clock=sb.ref_clock)
    capsys.readouterr()
    assert main(["align", "--json", str(path)]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["model"].startswith("linear+temperature")
    # both streams carry the virtual host clock: the true offset is 0 up to the HMC1053's per-axis
    # conversion delays (0 / 50 / 100 ms), among which the joint offset lies
    assert 0 < rep["offset_sigma_s"] < 0.1
    assert -0.1 - 3 * rep["offset_sigma_s"] <= rep["offset_s"] <= 3 * rep["offset_sigma_s"] + 0.05
    assert all(rep["axis_map"]["determined"]) and rep["rmse_model_uT"]["vector"] < rep["rmse_uT"]["vector"]
    assert main(["align", str(path), "--temp-model", "off"]) in (0, 2)
    out = capsys.readouterr()
    assert "model: linear (temperature model switched off)" in out.out or "do not determine" in out.err
