"""Error model: the single-sample path (``sense``) and the vector path (``sense_series``) agree bit for bit.

Property tests over every catalogue effect (alone, with and without time skew), every preset (as
published and with every stateful and random effect switched on) and random parameters: a model
fed one sample at a time, a model fed one series, and a model fed a random mix of single samples
and series chunks give identical samples, so state (hysteresis, drift random walk, 1/f noise,
random streams, session offsets) carries across calls the same way on both paths.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.firmware.effects import EFFECT_NAMES
from magstack.sim.error_model import ErrorModel, ErrorParams
from magstack.sim.error_stages import FIELD, STAGES, TEMPERATURE, build_stages
from magstack.sim.presets import PRESET_NAMES, preset
from tests.test_error_model import ONE_EFFECT, random_params
from tests.test_error_model_sense import _rich


class WavyTruth:
    """Scalar-protocol truth: a large rotating-ish field (crosses hysteresis thresholds both ways),
    temperature swings, one named current, a new session every ``session_s`` seconds."""

    def __init__(self, amp_uT=(180.0, 120.0, 240.0), session_s=0.7):
        self.amp = amp_uT
        self.session_s = session_s

    def field_uT(self, t):
        a = self.amp
        return np.array([a[0] * math.sin(1.3 * t), a[1] * math.cos(0.7 * t + 0.4), a[2] * math.sin(2.1 * t + 1.0)])

    def temp_c(self, t):
        return 25.0 + 30.0 * math.sin(0.5 * t)

    def currents_A(self, t):
        return {"solar_A": 0.5 + 0.5 * math.sin(3.0 * t)}

    def session(self, t):
        return int(t // self.session_s)


class WavySeriesTruth:
    """The same truth through the vectorised methods only (like ProgramTruth): both paths then use these."""

    def __init__(self, amp_uT=(180.0, 120.0, 240.0), session_s=0.7):
        self.amp = amp_uT
        self.session_s = session_s

    def field_series_uT(self, t):
        a = self.amp
        return np.stack([a[0] * np.sin(1.3 * t), a[1] * np.cos(0.7 * t + 0.4), a[2] * np.sin(2.1 * t + 1.0)], axis=1)

    def temp_series_c(self, t):
        return 25.0 + 30.0 * np.sin(0.5 * t)

    def currents_series_A(self, t):
        return {"solar_A": 0.5 + 0.5 * np.sin(3.0 * t)}

    def session_series(self, t):
        return (t // self.session_s).astype(np.int64)


@st.composite
def time_grids(draw, n_min=40, n_max=90):
    """Non-decreasing instants (s): near-uniform (k / rate), exactly uniform, irregular, with repeats."""
    n = draw(st.integers(n_min, n_max))
    kind = draw(st.sampled_from(["rate", "dyadic", "irregular", "repeats"]))
    t0 = draw(st.sampled_from([0.0, 3.7, 1234.5]))
    if kind == "rate":
        return t0 + np.arange(n) / draw(st.sampled_from([2.5, 20.0, 75.0, 80.0, 155.0]))
    if kind == "dyadic":
        return t0 + np.arange(n) * draw(st.sampled_from([0.125, 0.0625]))
    steps = np.array(draw(st.lists(st.floats(0.001, 0.1), min_size=n, max_size=n)))
    if kind == "repeats":
        steps[::7] = 0.0
    return t0 + np.cumsum(steps)


@st.composite
def call_plans(draw, n):
    """Split n samples into consecutive calls: ('one', k) = k sense() calls, ('series', k) = one sense_series."""
    plan, left = [], n
    while left:
        k = draw(st.integers(1, min(left, 40)))
        plan.append((draw(st.sampled_from(["one", "series"])), k))
        left -= k
    return plan


def _paths(params, effects, seed, t, truth, plan):
    """(every sample by sense(), one sense_series, the mixed plan) of fresh models of one seed."""
    m = ErrorModel(params, seed=seed, effects=effects)
    singles = np.array([m.sense(x, truth) for x in t])
    series = ErrorModel(params, seed=seed, effects=effects).sense_series(t, truth)
    m = ErrorModel(params, seed=seed, effects=effects)
    parts, i = [], 0
    for how, k in plan:
        chunk = t[i:i + k]
        parts.append(np.array([m.sense(x, truth) for x in chunk]) if how == "one" else m.sense_series(chunk, truth))
        i += k
    return singles, series, np.vstack(parts)


def _assert_same(singles, series, mixed):
    np.testing.assert_array_equal(singles, series)
    np.testing.assert_array_equal(mixed, series)


def test_every_catalogue_effect_has_one_stage_in_catalogue_order():
    assert list(STAGES) == list(EFFECT_NAMES)
    stages = build_stages(ErrorParams(), 0, EFFECT_NAMES)
    assert [s.name for s in stages.values()] == list(EFFECT_NAMES)
    for name, s in stages.items():  # both forms written for every field / reading stage
        if name != "time_skew":
            assert callable(s.vector) and callable(s.single)


@pytest.mark.parametrize("name", EFFECT_NAMES)
@settings(max_examples=25, deadline=None)
@given(data=st.data(), seed=st.integers(0, 2 ** 32), skew=st.booleans(), series_truth=st.booleans())
def test_single_and_vector_paths_agree_for_each_effect(name, data, seed, skew, series_truth):
    p = data.draw(random_params()) if data.draw(st.booleans()) else ONE_EFFECT[name]
    t = data.draw(time_grids())
    plan = data.draw(call_plans(t.size))
    effects = [name, "time_skew"] if skew and STAGES[name].kind in (FIELD, TEMPERATURE) else [name]
    if name == "thermal_lag":   # visible only through the temperature effects
        effects += ["temperature_offset", "temperature_gain"]
    truth = WavySeriesTruth() if series_truth else WavyTruth()
    _assert_same(*_paths(p, effects, seed, t, truth, plan))


@pytest.mark.parametrize("name", PRESET_NAMES)
@settings(max_examples=25, deadline=None)
@given(data=st.data(), seed=st.integers(0, 2 ** 32), rich=st.booleans(), series_truth=st.booleans())
def test_single_and_vector_paths_agree_for_every_preset(name, data, seed, rich, series_truth):
    p = _rich(preset(name)) if rich else preset(name)
    t = data.draw(time_grids())
    plan = data.draw(call_plans(t.size))
    truth = WavySeriesTruth() if series_truth else WavyTruth()
    _assert_same(*_paths(p, None, seed, t, truth, plan))


@settings(max_examples=60, deadline=None)
@given(p=random_params(), data=st.data(), seed=st.integers(0, 2 ** 32))
def test_single_and_vector_paths_agree_with_every_effect_on(p, data, seed):
    t = data.draw(time_grids())
    plan = data.draw(call_plans(t.size))
    _assert_same(*_paths(p, None, seed, t, WavyTruth(), plan))


def test_long_uniform_run_with_1_over_f_noise_is_one_filter_pass_and_still_exact():
    # 2000 samples at 80 Hz from t0 = 1000 s: the steps differ in their last bits, the vector path
    # filters the run in one pass (held step), the single-sample path steps through it
    p = dataclasses.replace(preset("lis3mdl"), lsb_uT=(0.0, 0.0, 0.0))
    t = 1000.0 + np.arange(2000) / 80.0
    assert np.unique(np.diff(t)).size > 1
    singles, series, mixed = _paths(p, None, 4, t, WavySeriesTruth(), [("series", 700), ("one", 300), ("series", 1000)])
    _assert_same(singles, series, mixed)


def test_reset_restarts_both_paths():
    p = _rich(preset("hmc1053"))
    t = np.arange(0.0, 3.0, 0.01)
    m = ErrorModel(p, seed=8)
    first = m.sense_series(t, WavyTruth())
    m.reset()
    np.testing.assert_array_equal(np.array([m.sense(x, WavyTruth()) for x in t]), first)


def test_adding_an_effect_is_one_catalogue_entry_and_one_stage(monkeypatch):
    """The extension recipe of docs/error-model.md, on a toy per-session mount rotation."""
    from types import MappingProxyType

    from scipy.spatial.transform import Rotation

    from magstack.firmware import effects as catalogue
    from magstack.sim import error_model, error_stages
    from magstack.sim.error_random import session_rng

    toy = catalogue.Effect("toy_mount_rotation", 25, "per-session rotation of the field before the sensor",
                           "b <- R_s b", "rad", "test only", None)
    table = MappingProxyType({e.name: e for e in sorted([*catalogue.EFFECTS.values(), toy], key=lambda e: e.order)})
    for mod in (catalogue, error_stages, error_model):
        monkeypatch.setattr(mod, "EFFECT_NAMES", tuple(table))
    monkeypatch.setattr(catalogue, "EFFECTS", table)
    monkeypatch.setattr(error_stages, "STAGES", dict(error_stages.STAGES))
    with pytest.raises(RuntimeError, match="toy_mount_rotation"):  # a catalogue entry without a stage is loud
        ErrorModel(ErrorParams())

    @error_stages.stage
    class ToyMountRotation(error_stages.Stage):
        name, kind = "toy_mount_rotation", FIELD

        def __init__(self, params, seed, enabled):
            super().__init__(params, seed, enabled)
            self._rows: dict[int, np.ndarray] = {}

        def _matrix(self, session):  # rot_mount_from_body of one session, fixed by (seed, session)
            m = self._rows.get(session)
            if m is None:
                rotvec = session_rng(self.seed, 0x70, session).standard_normal(3) * 0.01
                m = self._rows[session] = Rotation.from_rotvec(rotvec).as_matrix()
            return m

        def vector(self, b_body_uT, at):
            out = np.empty_like(b_body_uT)
            for s in np.unique(at.session):
                rows = at.session == s
                out[rows] = error_stages._matvec_series(self._matrix(int(s)), b_body_uT[rows])
            return out

        def single(self, b_body_uT, at):
            return error_stages._matvec_one(self._matrix(at.session).tolist(), *b_body_uT)

    p = _rich(preset("hmc1053"))
    t = np.arange(0.0, 4.0, 1 / 50)
    singles, series, mixed = _paths(p, None, 2, t, WavyTruth(), [("one", 50), ("series", 100), ("one", 50)])
    _assert_same(singles, series, mixed)
    base = ErrorModel(p, seed=2, effects=[n for n in table if n != "toy_mount_rotation"]).sense_series(t, WavyTruth())
    assert 1e-3 < np.abs(series - base).max() < 20.0  # ~0.01 rad of ~200 uT
