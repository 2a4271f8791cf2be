"""The stage-per-effect error model against the frozen pre-refactor module (benchmarks/baselines/error_model_before.py).

The restructuring kept the physics. Its single-sample path does the old ``sense()`` arithmetic, so
it is bit-identical except in three places changed on purpose, each ~1 ulp: the 1/f coefficients
come from the held step (so that both paths agree exactly), the cubic term is b*b*b (numpy's power
and libm's pow round differently), and the misalignment rotation comes from scipy's Rotation
instead of a hand-written Rodrigues formula. The vector path changed its summation order to match
the single-sample one (3x3 products as explicit sums), so it agrees with the old one to rounding.
Delete this file together with the baseline once an effect's physics is changed on purpose.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.sim.error_model import ErrorModel, without
from magstack.sim.presets import PRESET_NAMES, preset
from tests.test_error_model import random_params
from tests.test_error_model_paths import WavyTruth
from tests.test_error_model_sense import _rich

_PATH = Path(__file__).resolve().parent.parent / "benchmarks" / "baselines" / "error_model_before.py"
_spec = importlib.util.spec_from_file_location("error_model_before", _PATH)
before = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("error_model_before", before)  # dataclasses look their module up there
_spec.loader.exec_module(before)


def _old(p):
    # fields added after the baseline (effects it does not have) must be neutral here, then dropped
    known = {f.name for f in dataclasses.fields(before.ErrorParams)}
    d = p.to_dict()
    assert all(not np.any(d[k]) for k in set(d) - known), "a post-baseline effect is not neutral"
    return before.ErrorParams.from_dict({k: v for k, v in d.items() if k in known})


def _singles(cls, p, t, truth, effects=None, seed=3):
    m = cls(p, seed=seed, effects=effects)
    return np.array([m.sense(x, truth) for x in t])


@pytest.mark.parametrize("name", PRESET_NAMES)
@pytest.mark.parametrize("rich", [False, True])
def test_single_sample_path_is_the_old_one(name, rich):
    p = _rich(preset(name)) if rich else preset(name)
    t = np.arange(0.0, 8.0, 1 / 80)
    truth = WavyTruth()
    eff = without("quantization")  # quantisation would hide differences below one LSB
    no_pink = dataclasses.replace(p, noise_pink_uT=(0.0, 0.0, 0.0))
    np.testing.assert_array_equal(_singles(ErrorModel, no_pink, t, truth, eff),
                                  _singles(before.ErrorModel, _old(no_pink), t, truth, eff))
    np.testing.assert_array_equal(_singles(ErrorModel, p, t, truth), _singles(before.ErrorModel, _old(p), t, truth))
    np.testing.assert_allclose(_singles(ErrorModel, p, t, truth, eff),
                               _singles(before.ErrorModel, _old(p), t, truth, eff), rtol=0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(p=random_params(), seed=st.integers(0, 2 ** 32))
def test_both_paths_match_the_old_model_for_random_params(p, seed):
    t = 2.0 + np.arange(60) / 40.0
    truth = WavyTruth()
    eff = without("quantization")
    p = dataclasses.replace(p, hysteresis_initial_state=(0.0, 0.0, 0.0))   # the baseline starts demagnetised
    exact = dataclasses.replace(p, noise_pink_uT=(0.0, 0.0, 0.0), cubic_per_uT2=(0.0, 0.0, 0.0),
                                rotation_rad=(0.0, 0.0, 0.0))
    np.testing.assert_array_equal(_singles(ErrorModel, exact, t, truth, eff, seed),
                                  _singles(before.ErrorModel, _old(exact), t, truth, eff, seed))
    new = ErrorModel(p, seed=seed, effects=eff).sense_series(t, truth)
    old = before.ErrorModel(_old(p), seed=seed, effects=eff).sense_series(t, truth)
    scale = max(1.0, float(np.abs(old).max()))
    np.testing.assert_allclose(new, old, rtol=0, atol=1e-12 * scale)
