"""The validity search's shortcut over current corners equals the per-row predictive variance at each corner."""
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


def test_corner_shortcut_equals_the_variance_at_every_corner():
    rng = np.random.default_rng(7)
    pred = Predictive(_posterior(rng), 25.0)
    b = rng.uniform(-60, 60, (500, 3))
    t = rng.uniform(-10, 60, 500)
    corners = [dict(zip(("heater", "solar"), c, strict=True)) for c in itertools.product((-0.5, 1.2), (0.0, 0.9))]
    fast = pred._param_var_corners(b, t, corners)
    for k, c in enumerate(corners):
        cur = {name: np.full(500, v) for name, v in c.items()}
        np.testing.assert_allclose(fast[k], pred.param_var_uT2(b, t, cur).sum(axis=1), rtol=1e-10, atol=1e-15)


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
