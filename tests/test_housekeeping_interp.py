"""Housekeeping currents interpolated from their own sampling instants, block by block."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.data.telemetry import TelemetryBlock
from magstack.firmware.calibration.housekeeping import interpolate_currents, merge_currents
from magstack.firmware.errors import InputDataError


def _blocks(t, sess, cur, size):
    n = t.size
    for a in range(0, n, size):
        s = slice(a, a + size)
        m = t[s].size
        yield TelemetryBlock("mem", a, t[s], np.zeros((m, 3)), np.zeros(m), sess[s], np.zeros((m, 3)),
                             np.tile([1.0, 0, 0, 0], (m, 1)), {k: v[s] for k, v in cur.items()})


def _run(t, sess, cur, size, gap=60.0):
    out = list(interpolate_currents(_blocks(t, sess, cur, size), list(cur), gap))
    return {k: np.concatenate([b.currents_A[k] for b in out]) for k in cur}, np.concatenate([b.t_s for b in out])


def test_linear_interpolation_between_own_samples_with_gaps_and_sessions():
    t = np.arange(200.0)
    sess = np.where(t < 150, 0, 1)
    truth = 0.01 * t + 0.3
    solar = np.where(t % 10 == 0, truth, np.nan)
    solar[(t > 60) & (t < 140)] = np.nan            # 80 s gap: beyond the 60 s limit
    got, tt = _run(t, sess, {"solar": solar}, 37)
    assert np.array_equal(tt, t)
    ok = (t <= 60) | ((t >= 140) & (t < 150)) | (t >= 150)
    sol = got["solar"]
    # t = 140: a sample; 141..149: next sample at 150 is another session -> NaN; session 1 from 150 on
    assert np.allclose(sol[t <= 60], truth[t <= 60])
    assert np.isnan(sol[(t > 60) & (t < 140)]).all()
    assert sol[140] == pytest.approx(truth[140]) and np.isnan(sol[141:150]).all()
    assert np.allclose(sol[150:191], truth[150:191]) and np.isnan(sol[191:]).all()
    assert ok.sum() > 0


@settings(max_examples=30, deadline=None)
@given(size=st.integers(1, 80), period=st.integers(1, 25))
def test_result_does_not_depend_on_block_boundaries(size, period):
    t = np.arange(300.0) * 0.5
    sess = np.zeros(300, int)
    a = np.where(np.arange(300) % period == 0, np.sin(t / 10), np.nan)
    b = np.where(np.arange(300) % 7 == 3, np.cos(t / 7), np.nan)
    ref, _ = _run(t, sess, {"a": a, "b": b}, 300)
    got, tt = _run(t, sess, {"a": a, "b": b}, size)
    assert np.array_equal(tt, t)
    for k in ref:
        assert np.array_equal(got[k], ref[k], equal_nan=True)


def test_time_going_backwards_is_refused():
    t = np.array([0.0, 1.0, 0.5])
    with pytest.raises(InputDataError, match="time order"):
        _run(t, np.zeros(3, int), {"a": np.ones(3)}, 2)


def _reference_rule(t, sess, x, gap):
    """The rule written out row by row (samples at/before and at/after in time order)."""
    out = np.full(t.size, np.nan)
    idx = np.flatnonzero(np.isfinite(x))
    for r in range(t.size):
        if np.isfinite(x[r]):
            out[r] = x[r]
            continue
        before, after = idx[idx < r], idx[idx > r]
        if not before.size or not after.size:
            continue
        a, b = before[-1], after[0]
        if sess[a] == sess[r] == sess[b] and t[b] - t[a] <= gap:
            out[r] = x[a] + (t[r] - t[a]) / (t[b] - t[a]) * (x[b] - x[a])
    return out


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), size=st.integers(1, 120), gap=st.sampled_from([3.0, 20.0, 1000.0]))
def test_streaming_and_whole_array_paths_follow_the_written_rule(seed, size, gap):
    rng = np.random.default_rng(seed)
    n = 300
    t = np.cumsum(rng.uniform(0.1, 2.0, n))
    sess = np.cumsum(rng.random(n) < 0.01)
    x = np.where(rng.random(n) < rng.uniform(0.02, 0.5), rng.normal(size=n), np.nan)
    want = _reference_rule(t, sess, x, gap)
    got, _ = _run(t, sess, {"a": x}, size, gap)
    assert np.allclose(got["a"], want, equal_nan=True, rtol=0, atol=1e-12)
    whole = merge_currents(t, sess, {"a": x}, ["a"], gap)["a"]
    assert np.allclose(whole, want, equal_nan=True, rtol=0, atol=1e-12)
    perm = rng.permutation(n)                     # apply's sessions need not be in time order
    shuffled = merge_currents(t[perm], sess[perm], {"a": x[perm]}, ["a"], gap)["a"]
    assert np.array_equal(shuffled, whole[perm], equal_nan=True)


def test_blocks_come_out_as_they_went_in():
    t = np.arange(100.0)
    x = np.where(t % 10 == 0, t, np.nan)
    blocks = list(_blocks(t, np.zeros(100, int), {"a": x}, 16))
    out = list(interpolate_currents(iter(blocks), ["a"], 60.0))
    assert [len(b) for b in out] == [len(b) for b in blocks]
    assert all(o.t_s is b.t_s for o, b in zip(out, blocks, strict=True))      # no copies of the rows
    assert np.isnan(blocks[0].currents_A["a"][1])                             # inputs untouched
    assert np.allclose(np.concatenate([b.currents_A["a"] for b in out])[:91], t[:91])
