"""Housekeeping currents interpolated from their own sampling instants, block by block."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.data.telemetry import TelemetryBlock
from magstack.firmware.calibration.housekeeping import interpolate_currents
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
