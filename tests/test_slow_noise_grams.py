"""The slow-noise score Grams of the predictive inflation against their definitions, summed pair by pair."""
from __future__ import annotations

import numpy as np
import pytest

from magstack.firmware.calibration.predictive import BINS_PER_TAU, OUGram, RandomWalkGram


def _rows(seed: int, n: int = 900, p: int = 4):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.2, 0.6, n))
    x = rng.standard_normal((n, p)) + np.array([1.0, 0.0, 0.5, -2.0])
    session = np.repeat([3, 7], [n // 3, n - n // 3])
    return x, t, session


@pytest.mark.parametrize("tau_s", [5.0, 40.0, 400.0])
def test_ou_gram_is_the_kernel_sum_within_its_bin_tolerance(tau_s):
    x, t, session = _rows(1)
    exact = np.zeros((x.shape[1], x.shape[1]))
    for s in np.unique(session):
        m = session == s
        K = np.exp(-np.abs(t[m][:, None] - t[m][None, :]) / tau_s)
        exact += x[m].T @ K @ x[m]
    g = OUGram(x.shape[1], tau_s)
    for lo in range(0, len(t), 128):                     # fed in calls, as the fit's blocks of rows
        g.add(x[lo:lo + 128], t[lo:lo + 128], session[lo:lo + 128])
    got = g.result()
    scale = np.sqrt(np.outer(np.diag(exact), np.diag(exact)))
    assert np.max(np.abs(got - exact) / scale) <= 0.5 / BINS_PER_TAU     # measured: 0.07-0.44 %


def test_random_walk_gram_is_the_min_kernel_sum():
    # a walk from 0 at each session's first row: cov(u_i, u_j) = time from the first row to the earlier of the two
    x, t, session = _rows(2)
    exact = np.zeros((x.shape[1], x.shape[1]))
    for s in np.unique(session):
        m = session == s
        tt = t[m] - t[m][0]
        exact += x[m].T @ np.minimum(tt[:, None], tt[None, :]) @ x[m]
    g = RandomWalkGram(x.shape[1])
    for lo in range(0, len(t), 100):
        g.add(x[lo:lo + 100], t[lo:lo + 100], session[lo:lo + 100])
    np.testing.assert_allclose(g.result(), exact, rtol=1e-9, atol=1e-9 * np.abs(exact).max())


@pytest.mark.parametrize("bins", [64, 512])
def test_binned_random_walk_gram_is_within_a_bin_of_the_exact_sum(bins):
    """Rows summed over bins of span / bins: every entry within 2 bins' share of the span (scaled by the diagonal);
    the sampling interval the slow-noise Grams report stays that of the rows."""
    from magstack.firmware.calibration.predictive import SlowNoiseGrams

    x, t, session = _rows(3)
    g_exact = RandomWalkGram(x.shape[1])
    g_exact.add(x, t, session)
    exact = g_exact.result()
    width = (t[-1] - t[0]) / bins
    g = RandomWalkGram(x.shape[1], width)
    for lo in range(0, len(t), 100):
        g.add(x[lo:lo + 100], t[lo:lo + 100], session[lo:lo + 100])
    got = g.result()
    scale = np.sqrt(np.outer(np.diag(exact), np.diag(exact)))
    err = np.max(np.abs(got - exact) / scale)
    assert 0 < err <= 2.0 / bins * 3          # sessions span a third of the data or more
    sn = SlowNoiseGrams(x.shape[1], float(t[-1] - t[0]))
    for lo in range(0, len(t), 100):
        sn.add(x[lo:lo + 100], t[lo:lo + 100], session[lo:lo + 100])
    spans = sum(float(t[session == s][-1] - t[session == s][0]) for s in np.unique(session))
    assert sn.mean_dt_s == pytest.approx(spans / (len(t) - 1), rel=1e-12)


def test_slow_noise_grams_bin_once_as_each_gram_alone():
    """The Grams binned once for every correlation time (each time's bins from the previous one's, the sums as a
    sparse product) equal each correlated Gram fed its rows alone, to rounding; so do the sparse segment sums and
    ``reduceat``'s."""
    from magstack.firmware.calibration.predictive import SlowNoiseGrams, segment_sums

    x, t, session = _rows(4, n=3000)
    starts = np.r_[0, np.flatnonzero(np.diff(np.floor(t / 1.7))) + 1]
    want = np.add.reduceat(x, starts, axis=0)
    np.testing.assert_allclose(segment_sums(x, starts), want, rtol=0, atol=1e-14 * np.abs(want).max())
    sn = SlowNoiseGrams(x.shape[1], float(t[-1] - t[0]))
    for lo in range(0, len(t), 256):
        sn.add(x[lo:lo + 256], t[lo:lo + 256], session[lo:lo + 256])
    taus, grams, _, _ = sn.result()
    assert len(taus) >= 3
    for tau, got in zip(taus, grams, strict=True):
        alone = OUGram(x.shape[1], tau)
        for lo in range(0, len(t), 256):
            alone.add(x[lo:lo + 256], t[lo:lo + 256], session[lo:lo + 256])
        want = alone.result()
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
