"""Error model: the plain-float single-sample path ``sense()`` reproduces ``sense_series`` bit for bit."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.drivers.errors import ConfigurationError
from magstack.sim.error_model import ErrorModel, ErrorParams, without
from magstack.sim.presets import PRESET_NAMES, preset
from magstack.sim.truth_source import StaticTruth
from tests.test_error_model import RampTruth, random_params


def _rich(p: ErrorParams) -> ErrorParams:
    """A preset with every random effect and the state-carrying effects switched on."""
    return dataclasses.replace(p, drift_walk_uT_per_sqrt_s=(1e-3, 2e-3, 3e-3), session_offset_sigma_uT=(0.5,) * 3,
                               axis_delay_s=(0.0, 0.004, 0.008), hysteresis_uT=(0.05, 0.1, 0.2),
                               hysteresis_threshold_uT=25.0, noise_pink_uT=(0.2, 0.1, 0.3),
                               cross_axis_h0_uT=800.0, interference_uT_per_A={"solar_A": (0.3, -0.2, 0.1)})


def _truth():
    return RampTruth(b0=(-30.0, 20.0, 10.0), rate=(3.0, -2.5, 1.0), temp_rate=1.5,
                     currents={"solar_A": lambda t: math.sin(t)}, session_s=2.0)


@settings(max_examples=60, deadline=None)
@given(p=random_params(), seed=st.integers(0, 2 ** 32), uniform=st.booleans())
def test_sense_loop_equals_series_for_any_params(p, seed, uniform):
    # bit for bit, quantisation included (both paths do the same operations in the same order)
    truth = RampTruth(b0=(120.0, -80.0, 40.0), rate=(-9.0, 7.0, 3.0), temp_rate=2.0,
                      currents={"solar_A": lambda t: math.cos(t)}, session_s=1.5)
    t = np.arange(64) * 0.0125 if uniform else np.cumsum(np.random.default_rng(seed % 1000).uniform(0, 0.03, 64))
    for eff in (without("quantization"), None):
        series = ErrorModel(p, seed=seed, effects=eff).sense_series(t, truth)
        m = ErrorModel(p, seed=seed, effects=eff)
        single = np.array([m.sense(x, truth) for x in t])
        np.testing.assert_array_equal(single, series)


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_interleaved_sense_and_series_continue_one_state(name):
    p = _rich(preset(name))
    truth = _truth()
    t = np.arange(0.0, 6.0, 1 / 100)
    ref = ErrorModel(p, seed=5).sense_series(t, truth)
    m = ErrorModel(p, seed=5)
    parts = [np.array([m.sense(x, truth) for x in t[:150]]), m.sense_series(t[150:400], truth),
             np.array([m.sense(x, truth) for x in t[400:410]]), m.sense_series(t[410:], truth)]
    np.testing.assert_array_equal(np.vstack(parts), ref)
    # reset() restarts every stream and state for the single-sample path too
    m.reset()
    np.testing.assert_array_equal(np.array([m.sense(x, truth) for x in t[:50]]), ref[:50])


class _SeriesTruth:
    """A truth source with the vectorised methods only (like magstack.sim.coil_programs.ProgramTruth)."""

    def __init__(self, bad_from_s=math.inf):
        self.bad_from_s = bad_from_s

    def field_series_uT(self, t):
        b = np.stack([10.0 + t, -5.0 * np.ones_like(t), 2.0 * t], axis=1)
        b[t >= self.bad_from_s, 1] = np.nan
        return b

    def temp_series_c(self, t):
        return 25.0 + 0.5 * t

    def currents_series_A(self, t):
        return {"solar_A": 0.1 * t}

    def session_series(self, t):
        return (t // 1.0).astype(np.int64)


def test_sense_uses_the_vectorised_truth_methods_and_refuses_non_finite_truth_without_consuming_state():
    p = _rich(preset("lis3mdl"))
    t = np.arange(0.0, 2.0, 0.01)
    ref = ErrorModel(p, seed=3).sense_series(t, _SeriesTruth())
    m = ErrorModel(p, seed=3)
    got = [m.sense(x, _SeriesTruth()) for x in t[:100]]
    with pytest.raises(ConfigurationError, match="non-finite field_uT"):
        m.sense(t[100], _SeriesTruth(bad_from_s=0.0))
    got += [m.sense(x, _SeriesTruth()) for x in t[100:]]
    np.testing.assert_array_equal(np.array(got), ref)


def test_sense_time_checks():
    m = ErrorModel(ErrorParams(offset_uT=(1.0, 2.0, 3.0)))
    with pytest.raises(ConfigurationError, match="finite"):
        m.sense(float("nan"), StaticTruth())
    np.testing.assert_array_equal(m.sense(1.0, StaticTruth((0, 0, 0))), [1.0, 2.0, 3.0])
    with pytest.raises(ConfigurationError, match="before the previous"):
        m.sense(0.5, StaticTruth())
    np.testing.assert_array_equal(m.sense(1.0, StaticTruth((0, 0, 0))), [1.0, 2.0, 3.0])  # equal time is fine
