"""The validity search's worst case (quadratic forms in the calibrated field, every current corner at once) equals
the per-row predictive variance evaluated feature by feature at the mapped readings."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from magstack.firmware.cal_uncertainty import Predictive


def _posterior(rng):
    post = {}
    for a in "xyz":
        names = [f"S[{a},x]", f"S[{a},y]", f"S[{a},z]", f"K_S[{a},{a}]", f"O[{a}]", f"K_O[{a}]", f"K_O2[{a}]",
                 f"c3[{a}]", f"P[{a},xy]", f"D_solar[{a}]", f"D_heater[{a}]"]
        A = rng.standard_normal((len(names), len(names))) * 1e-3
        post[a] = {"names": names, "cov": (A @ A.T).tolist()}
    post["noise_uT"] = [0.03, 0.04, 0.05]
    return post


def _feature_by_feature(pred, temp_c, cal, currents):
    """(m,) the worst vector variance over the current corners at calibrated points ``cal``: every feature
    evaluated at the mapped readings through the per-row methods (a current not given is 0)."""
    b = pred.to_reading(cal, temp_c)
    t = np.full(b.shape[0], temp_c)
    used = sorted({nm[2:nm.index("[")] for names in pred.names for nm in names if nm.startswith("D_")})
    worst = np.full(b.shape[0], -np.inf)
    for combo in itertools.product(*[sorted(set((currents or {}).get(k, (0.0, 0.0)))) for k in used]):
        cur = {k: np.full(b.shape[0], v) for k, v in zip(used, combo, strict=True)}
        v = (pred.param_var_uT2(b, t, cur) + pred.disc_var_uT2(b, t)).sum(axis=1) + np.sum(pred.noise_uT ** 2)
        worst = np.maximum(worst, v)
    return worst


def test_quadratic_forms_equal_the_per_row_variance_at_every_point():
    rng = np.random.default_rng(7)
    pred = Predictive(_posterior(rng), 25.0)
    currents = {"solar": (0.0, 0.9), "heater": (-0.5, 1.2)}
    cal = rng.uniform(-60, 60, (300, 3))
    for temp in (-10.0, 25.0, 58.5):
        np.testing.assert_allclose(pred._worst_at(temp, cal, currents), _feature_by_feature(pred, temp, cal, currents),
                                   rtol=1e-10, atol=1e-15)


def test_worst_over_temperatures_equals_the_single_temperature_worst_case():
    rng = np.random.default_rng(8)
    pred = Predictive(_posterior(rng), 25.0)
    currents = {"solar": (0.0, 0.9), "heater": (-0.5, 1.2)}
    temps = np.linspace(-5.0, 45.0, 41)
    per_t = pred.worst_per_temperature_uT(temps, [40.0, 50.0, 60.0], 70.0, currents)
    assert len(per_t) == temps.size
    for t in temps[::8]:
        one = pred.worst_vector_sd_uT(float(t), [40.0, 50.0, 60.0], 70.0, currents)
        assert per_t[float(t)] == pytest.approx(one, rel=1e-9)


def _full_posterior(rng):
    post = {}
    for a in "xyz":
        names = [f"S[{a},x]", f"S[{a},y]", f"S[{a},z]", f"K_S[{a},x]", f"K_S[{a},{a}]", f"K_S2[{a}]", f"K_S3[{a}]",
                 f"O[{a}]", f"K_O[{a}]", f"K_O2[{a}]", f"c3[{a}]", f"P[{a},xy]", f"P[{a},yz]", f"D_solar[{a}]",
                 f"D_heater[{a}]"]
        A = rng.standard_normal((len(names), len(names))) * 1e-3
        post[a] = {"names": names, "cov": (A @ A.T).tolist()}
    post["noise_uT"] = [0.03, 0.04, 0.05]
    post["discrepancy"] = {"d0_uT2": [1e-3, 2e-3, 1.5e-3], "dB_uT2": [2e-3, 1e-3, 3e-3], "dT_uT2": [1e-3, 1e-3, 2e-3],
                           "field_ref_uT": 50.0, "field_max_uT": 45.0, "temp_ref_c": 20.0,
                           "temp_centre_c": 22.0, "temp_range_c": [5.0, 40.0]}
    return post


@pytest.mark.parametrize("with_currents", [True, False])
def test_quadratic_forms_equal_the_feature_by_feature_worst_case(with_currents):
    """The worst case over a region from 4 x 4 quadratic forms in the calibrated field (polynomial features
    from the mapped readings) equals the feature-by-feature evaluation at the mapped readings (calibration
    applied, discrepancy with its clamps, current corners)."""
    rng = np.random.default_rng(11)
    cal = (np.eye(3) + rng.standard_normal((3, 3)) * 0.05, rng.standard_normal((3, 3)) * 1e-3,
           rng.standard_normal(3) * 1e-5, rng.standard_normal(3) * 2.0, rng.standard_normal(3) * 0.01)
    pred = Predictive(_full_posterior(rng), 25.0, cal)
    currents = {"solar": (0.0, 0.9), "heater": (-0.5, 1.2)} if with_currents else None
    temps = np.linspace(-30.0, 80.0, 45)
    per_t = pred.worst_per_temperature_uT(temps, [40.0, 50.0, 60.0], 55.0, currents)
    cal = pred._region_cal_points([40.0, 50.0, 60.0], 55.0)
    for t in temps[::4]:
        one = np.sqrt(_feature_by_feature(pred, float(t), cal, currents).max())
        assert per_t[float(t)] == pytest.approx(one, rel=1e-9)
