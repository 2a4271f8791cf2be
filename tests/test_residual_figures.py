"""Streamed residual figures (memory flat in rows): exact medians of replayed blocks, and the noise
floor, step diagnosis and RMSE of ``fit``'s block-wise path equal to the whole-array functions."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from magstack.firmware.calibration import FitData, FitOptions, crossfit, fit, rank_select
from magstack.firmware.calibration.fit import build_model, diagnose_steps, noise_floor
from magstack.firmware.calibration.model import resolve_terms
from magstack.firmware.calibration.rank_select import ExactMedian, MedianAbsDeviation
from magstack.firmware.calibration.residual_figures import ResidualFigures


def _replay(stat, x: np.ndarray, chunk: int) -> int:
    """Feed ``x`` in blocks of ``chunk`` until ``stat`` has its value; the number of passes."""
    passes = 0
    while True:
        passes += 1
        for a in range(0, x.size, chunk):
            stat.feed(x[a:a + chunk])
        stat.end_pass()
        if not stat.pending:
            return passes


def _cases():
    rng = np.random.default_rng(1)
    return [rng.standard_normal(10001), rng.standard_normal(10000) * 1e-3 + 5.0,
            np.round(rng.standard_normal(5000), 1),                      # many ties
            np.zeros(1000), np.r_[np.zeros(500), -np.zeros(500)], rng.integers(-3, 3, 4000).astype(float),
            np.array([5.0]), np.array([1.0, 2.0]), rng.standard_cauchy(7777),
            np.r_[np.full(600, 2.5), rng.standard_normal(401)],           # the median inside a run of ties
            -rng.exponential(size=20001) * 1e5, np.r_[rng.standard_normal(3000), np.full(3000, 1e-300)]]


@pytest.mark.parametrize("cap", [1 << 18, 64, 3])
def test_exact_median_and_mad_equal_numpy(monkeypatch, cap):
    monkeypatch.setattr(rank_select, "COLLECT_CAP", cap)
    for x in _cases():
        med, mad = ExactMedian(), MedianAbsDeviation()
        _replay(med, x, 997)
        passes = _replay(mad, x, 1000)
        assert med.value == np.median(x)
        assert mad.value == np.median(np.abs(x - np.median(x)))
        assert passes <= 8
    assert np.isnan(ExactMedian().value)


def test_mad_of_well_centred_values_takes_three_passes(monkeypatch):
    """The bracketed deviations: the median's bin and the deviations counted in the same pass."""
    monkeypatch.setattr(rank_select, "COLLECT_CAP", 4096)
    x = np.random.default_rng(2).standard_normal(200_001)
    mad = MedianAbsDeviation()
    assert _replay(mad, x, 65536) == 3
    assert mad.value == np.median(np.abs(x - np.median(x)))


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.integers(1, 400), elements=st.floats(-1e6, 1e6, allow_nan=False, width=64)),
       st.integers(1, 50), st.sampled_from([2, 5, 1 << 18]))
def test_exact_median_equals_numpy_on_any_values(x, chunk, cap):
    keep = rank_select.COLLECT_CAP
    rank_select.COLLECT_CAP = cap
    try:
        med, mad = ExactMedian(), MedianAbsDeviation()
        _replay(med, x, chunk)
        _replay(mad, x, chunk)
    finally:
        rank_select.COLLECT_CAP = keep
    assert med.value == np.median(x)
    assert mad.value == np.median(np.abs(x - np.median(x)))


@settings(max_examples=80, deadline=None)
@given(arrays(np.float64, st.integers(1, 300), elements=st.floats(-50, 50, allow_nan=False, width=16)),
       st.lists(st.tuples(st.floats(-60, 60), st.floats(0, 40)), min_size=1, max_size=4),
       st.floats(-60, 60), st.integers(1, 40))
def test_bracket_ranks_are_exact_or_none(x, spans, c, chunk):
    """A bracket answers a rank only when it is sure: the value numpy sorts there, or None."""
    b = rank_select.Bracket([(lo, lo + w) for lo, w in spans], 1 << 20)
    for a in range(0, x.size, chunk):
        b.feed(x[a:a + chunk])
    srt, dev = np.sort(x), np.sort(np.abs(x - c))
    for r in {0, x.size // 3, (x.size - 1) // 2, x.size // 2, x.size - 1}:
        got, got_dev = b.rank_value(r), b.deviation_rank_value(c, r)
        assert got is None or got == srt[r]
        assert got_dev is None or got_dev == dev[r]
    everything = rank_select.Bracket([(-np.inf, np.inf)], 1 << 20)
    everything.feed(x)
    assert everything.rank_value(x.size // 2) == srt[x.size // 2]
    assert everything.deviation_rank_value(c, x.size // 2) == dev[x.size // 2]


def test_guessed_bracket_gives_exact_medians_in_one_pass(monkeypatch):
    """Stationary values: median and MAD exact after the one pass the guess brackets (the bracket far smaller
    than the stream); a first block unlike the rest: exact after more passes, the guess only lost."""
    monkeypatch.setattr(rank_select, "COLLECT_CAP", 1 << 14)
    rng = np.random.default_rng(5)
    x = rng.standard_normal(300_001) * 0.03 + 0.001
    med, mad = ExactMedian(expected_n=x.size), MedianAbsDeviation(expected_n=x.size)
    assert _replay(med, x, 65536) == 1 and _replay(mad, x, 65536) == 1
    assert med.value == np.median(x)
    assert mad.value == np.median(np.abs(x - np.median(x)))
    drift = np.r_[rng.standard_normal(70_000) * 3.0 + 1.0, x]                # the guess from the first block
    med, mad = ExactMedian(expected_n=drift.size), MedianAbsDeviation(expected_n=drift.size)
    assert _replay(med, drift, 65536) > 1 and _replay(mad, drift, 65536) > 1
    assert med.value == np.median(drift)
    assert mad.value == np.median(np.abs(drift - np.median(drift)))


@pytest.mark.parametrize("cap", [1 << 18, 64, 3])
def test_guessed_medians_equal_numpy(monkeypatch, cap):
    """Whatever the guess, the bracket too small or too full: the values numpy gives."""
    monkeypatch.setattr(rank_select, "COLLECT_CAP", cap)
    monkeypatch.setattr(rank_select, "GUESS_MIN_VALUES", 4)
    for x in _cases():
        for chunk in (997, 50):
            med, mad = ExactMedian(expected_n=x.size), MedianAbsDeviation(expected_n=x.size)
            _replay(med, x, chunk)
            _replay(mad, x, chunk)
            assert med.value == np.median(x)
            assert mad.value == np.median(np.abs(x - np.median(x)))


def _ordered_rows(rng, n: int, irregular: bool):
    """Rows in (session, time) order: 1-3 sessions, steps in the reference, residuals with ties."""
    s = np.sort(rng.integers(0, int(rng.integers(1, 4)), n)) * 3 + 2
    t = np.concatenate([np.sort(rng.uniform(0, n / 4, (s == k).sum())) if irregular
                        else 100.0 * k + np.arange((s == k).sum()) * 0.25 for k in np.unique(s)])
    ref = np.cumsum(rng.standard_normal((n, 3)) * 0.01, axis=0) + 5 * (rng.uniform(size=(n, 1)) < 0.02).cumsum(0)
    meas = ref + rng.standard_normal((n, 3))
    return s, t, ref, meas


@pytest.mark.parametrize("seed", range(8))
def test_streamed_figures_equal_the_whole_array_functions(monkeypatch, seed):
    rng = np.random.default_rng(seed)
    monkeypatch.setattr(rank_select, "COLLECT_CAP", [1 << 18, 50, 7][seed % 3])
    n = int(rng.integers(200, 5000))
    s, t, ref, meas = _ordered_rows(rng, n, irregular=seed % 2 == 1)
    r = np.round(rng.standard_normal((n, 3)), 2 if seed % 4 == 0 else 12)      # ties at seed 0, 4
    fig = ResidualFigures(meas, ref, t, s, 1.0)
    chunk = int(rng.integers(3, 700))
    while True:
        for a in range(0, n, chunk):
            fig.add(a, np.ascontiguousarray(r[a:a + chunk].T))
        fig.end_pass()
        if not fig.pending:
            break
    np.testing.assert_array_equal(fig.noise_floor_uT(), noise_floor(r, t, s, 1.0))
    direct = diagnose_steps(r, ref, s)
    assert direct is not None and direct.n_step > 10
    got = fig.steps
    assert (got.threshold_uT, got.n_step, got.n_steady) == (direct.threshold_uT, direct.n_step, direct.n_steady)
    np.testing.assert_allclose(got.step_rms_uT, direct.step_rms_uT, rtol=1e-13)
    np.testing.assert_allclose(got.steady_rms_uT, direct.steady_rms_uT, rtol=1e-13)
    assert got.step_share == pytest.approx(direct.step_share, rel=1e-13)
    np.testing.assert_allclose(fig.sse_uT2, np.sum(r ** 2, axis=0), rtol=1e-13)
    np.testing.assert_allclose(fig.raw_sse_uT2, np.sum((ref - meas) ** 2, axis=0), rtol=1e-13)


def test_too_few_pairs_or_no_steps_give_what_the_functions_give():
    t = np.array([0.0, 0.25, 0.5, 3.0, 9.0])
    s = np.zeros(5, dtype=np.int64)
    ref = np.ones((5, 3))
    r = np.random.default_rng(0).standard_normal((5, 3))
    fig = ResidualFigures(ref, ref, t, s, 1.0)
    while True:
        fig.add(0, np.ascontiguousarray(r.T))
        fig.end_pass()
        if not fig.pending:
            break
    assert np.isnan(fig.noise_floor_uT()).all() and np.isnan(noise_floor(r, t, s, 1.0)).all()
    assert fig.steps is None and diagnose_steps(r, ref, s) is None


def _step_session(n=6000, seed=4, shuffle=False, nan_rows=0):
    """Coil steps (held 12 s) in three sessions, a DUT with gain, offset and tempco; optionally rows shuffled
    and some rows with a NaN DUT field (excluded by the fit)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.25
    level = rng.uniform(-40, 40, (n // 48 + 1, 3))[np.arange(n) // 48]
    temp = 20 + 10 * np.sin(t / 300)
    b = level + rng.standard_normal((n, 3)) * 0.05
    dut = 1.05 * b + 0.4 + 0.002 * (temp - 25)[:, None] + rng.standard_normal((n, 3)) * 0.03
    ref = b + 0.3 * np.sin(t / 50)[:, None] * (np.abs(np.diff(level, axis=0, prepend=level[:1])) > 0)
    session = (np.arange(n) * 3 // n) + 1
    if nan_rows:
        dut[rng.choice(n, nan_rows, replace=False), 1] = np.nan
    o = rng.permutation(n) if shuffle else np.arange(n)
    return FitData(dut[o], ref[o], temp[o], t[o], session[o])


@pytest.mark.parametrize("shuffle, nan_rows", [(False, 0), (False, 37), (True, 0), (True, 37)])
def test_fit_figures_equal_the_direct_functions(shuffle, nan_rows):
    """Streamed (rows in order) or whole-array (shuffled rows): the figures of the functions on the residuals."""
    data = _step_session(shuffle=shuffle, nan_rows=nan_rows)
    opts = FitOptions()
    res = fit(data, "eq3", ["session_offset"], options=opts)
    ok = data.usable(res.model.terms, ())
    d = data.select(ok)
    assert res.n_used == len(d) and res.n_excluded == nan_rows
    cm = build_model(d, resolve_terms("eq3", ["session_offset"], ()), (), 25.0, res.model.name)
    cross = crossfit.cross_fit(d, cm, opts)
    assert (cross.figures is None) == shuffle and (cross.resid_uT is None) == (not shuffle)
    resid = d.b_ref_uT - res.model.predict(res.theta, res.model.design(d.b_meas_uT, d.temp_c, {}, d.session,
                                                                          d.t_s))
    np.testing.assert_allclose(res.noise_floor_uT, noise_floor(resid, d.t_s, d.session, 1.0), rtol=1e-12)
    direct = diagnose_steps(resid, d.b_ref_uT, d.session)
    if shuffle:                             # no step stands out among shuffled rows
        assert direct is None and res.steps is None
    else:
        assert direct is not None and direct.dominant and res.steps.dominant
        assert (res.steps.threshold_uT, res.steps.n_step) == (direct.threshold_uT, direct.n_step)
        np.testing.assert_allclose(res.steps.step_rms_uT, direct.step_rms_uT, rtol=1e-12)
        np.testing.assert_allclose(res.steps.steady_rms_uT, direct.steady_rms_uT, rtol=1e-12)
    dof = len(d) - res.posterior.dof
    np.testing.assert_allclose(res.rmse_uT, np.sqrt(np.sum(resid ** 2, axis=0) / (len(d) - dof)), rtol=1e-12)
    np.testing.assert_allclose(res.raw_rmse_uT, np.sqrt(np.mean((d.b_ref_uT - d.b_meas_uT) ** 2, axis=0)),
                               rtol=1e-12)
