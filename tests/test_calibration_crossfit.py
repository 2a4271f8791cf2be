"""The cross-fit: held-out figures from per-piece R factors equal refitting each fold's rows."""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from magstack.firmware.calibration import FitData, FitOptions, crossfit, fit
from magstack.firmware.calibration.blocking import BlockingInflation
from magstack.firmware.calibration.estimator import autocorr_inflation
from magstack.firmware.calibration.fit import block_folds
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.sim.synthetic_calibration import make_data, random_theta

RTOL = 1e-9


def _sessions_data(n=4000, seed=3, weights=True):
    rng = np.random.default_rng(seed)
    model = CalModel(resolve_terms("eq3", ["session_offset", "drift"]), (), (2, 5, 7, 11), 25.0, 1.6e9 + n / 8)
    d = make_data(model, random_theta(model, rng), n, rng, noise_uT=0.03)
    # slow (autocorrelated) misfit so that kappa > 1 and the per-fold autocorrelation matters
    ref = d.b_ref_uT + 0.05 * np.sin(d.t_s / 40.0)[:, None]
    w = rng.uniform(0.5, 2.0, n) if weights else None
    return FitData(d.b_meas_uT, ref, d.temp_c, d.t_s, d.session, weights=w)


def _refit_path(data, *args, **kw):
    keep = crossfit.applies
    crossfit.applies = lambda model, options: False
    try:
        return fit(data, *args, **kw)
    finally:
        crossfit.applies = keep


def _direct_holdout(d: FitData, terms, opts: FitOptions):
    """Held-out RMS by refitting each fold's training rows on their own (no cross-fit state shared)."""
    one = FitOptions(holdout=False)

    def out(train, test):
        r = fit(train, "eq3", terms, options=one)
        X = r.model.design(test.b_meas_uT, test.temp_c, test.currents_A, test.session, test.t_s)
        return test.b_ref_uT - r.model.predict(r.theta, X)

    fold = block_folds(d, opts)
    blocks = np.vstack([out(d.select(fold != f), d.select(fold == f)) for f in np.unique(fold)])
    per = {int(s): out(d.select(d.session != s), d.select(d.session == s)) for s in np.unique(d.session)}
    rms = lambda r: np.sqrt(np.mean(r ** 2, axis=0))  # noqa: E731
    return rms(blocks), rms(np.vstack(list(per.values()))), {s: rms(r) for s, r in per.items()}


def test_cross_fit_held_out_figures_equal_a_direct_refit_of_every_fold():
    d = _sessions_data()
    terms = ["session_offset", "drift"]
    res = fit(d, "eq3", terms, options=FitOptions())
    assert crossfit.applies(res.model, FitOptions()) and res.posterior.kappa.max() > 1.5
    blocks, sessions, per = _direct_holdout(d, terms, FitOptions())
    np.testing.assert_allclose(res.holdout_blocks_uT, blocks, rtol=RTOL)
    np.testing.assert_allclose(res.holdout_sessions_uT, sessions, rtol=RTOL)
    assert sorted(res.holdout_per_session_uT) == sorted(per)
    for s, v in per.items():
        np.testing.assert_allclose(res.holdout_per_session_uT[s], v, rtol=RTOL)
    # a leak (the fold's own rows in its training set) would give about the in-sample figure
    assert np.all(res.holdout_blocks_uT > 1.001 * res.rmse_uT)


@pytest.mark.parametrize("model,terms,kw,shuffle", [
    ("eq3", ["session_offset", "drift"], {}, False),
    ("eq3", ["session_offset", "drift"], {}, True),        # rows out of (session, time) order
    ("eq3", [], {"use_priors": False}, False),
    ("gain_offset", ["drift"], {"autocorr": False}, False),
    ("eq3", ["session_offset"], {"on_unidentifiable": "refuse", "min_temp_span_c": 1e3}, False),
])
def test_cross_fit_equals_the_refit_path(model, terms, kw, shuffle):
    d = _sessions_data(weights=False)
    if shuffle:
        d = d.select(np.random.default_rng(0).permutation(len(d)))
    try:
        slow = _refit_path(d, model, terms, options=FitOptions(**kw))
    except Exception as exc:          # the full fit refuses: so must the cross-fit, with the same message
        with pytest.raises(type(exc), match="data cannot determine"):
            fit(d, model, terms, options=FitOptions(**kw))
        return
    fast = fit(d, model, terms, options=FitOptions(**kw))
    for a in ("theta", "se", "rmse_uT", "noise_floor_uT", "holdout_blocks_uT", "holdout_sessions_uT",
              "cond_scaled", "cond_raw"):
        np.testing.assert_allclose(getattr(fast, a), getattr(slow, a), rtol=RTOL, err_msg=a)
    np.testing.assert_allclose(fast.posterior.kappa, slow.posterior.kappa, rtol=RTOL)
    assert fast.notes == slow.notes
    assert [h.name for h in fast.held] == [h.name for h in slow.held]


def test_a_fold_model_is_a_linear_map_of_the_full_design():
    d = _sessions_data(n=800, weights=False)
    full = CalModel(resolve_terms("eq3", ["session_offset", "drift"]), (), (2, 5, 7, 11), 25.0, 1.6e9 + 50)
    sub = CalModel(full.terms, (), (5, 11), 25.0, 1.6e9 + 80)          # the first session left out
    rows = np.isin(d.session, sub.sessions)
    X = full.design(d.b_meas_uT[rows], d.temp_c[rows], {}, d.session[rows], d.t_s[rows])
    Xs = sub.design(d.b_meas_uT[rows], d.temp_c[rows], {}, d.session[rows], d.t_s[rows])
    np.testing.assert_allclose(X @ crossfit.basis_change(full, sub), Xs, rtol=0, atol=1e-9)


def _blocking_definition(r, s, min_blocks=16):
    """kappa by its definition: block means of L = 2, 4, ... rows from each session's start."""
    r = r - r.mean(axis=0)
    v = np.mean(r ** 2, axis=0)
    best, L = np.ones(3), 2
    while True:
        means = [r[s == k][: (np.sum(s == k) // L) * L].reshape(-1, L, 3).mean(axis=1) for k in np.unique(s)]
        m = np.vstack(means)
        if m.shape[0] < min_blocks:
            return best
        best = np.maximum(best, L * np.mean(m ** 2, axis=0) / v)
        L *= 2


def test_blocking_accumulated_in_uneven_pieces_equals_its_definition():
    rng = np.random.default_rng(7)
    n = 5000
    r = np.cumsum(rng.normal(size=(n, 3)), axis=0) * 0.02 + rng.normal(size=(n, 3))
    s = np.repeat([3, 4, 9], [1700, 1, 3299])
    acc = BlockingInflation()
    cuts = np.r_[0, np.sort(rng.choice(np.arange(1, n), 40, replace=False)), n]
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        acc.add((r[a:b] - 0.1).T, s[a:b])        # any centre: the spread is about the accumulated mean
    want = _blocking_definition(r, s)
    assert want.max() > 2.0
    np.testing.assert_allclose(acc.kappa(), want, rtol=1e-12)
    perm = rng.permutation(n)                   # the one-shot form sorts by (session, time) itself
    np.testing.assert_allclose(autocorr_inflation(r[perm], np.arange(n)[perm], s[perm]), want, rtol=1e-12)


def test_cross_fit_memory_per_row_is_below_one_copy_of_the_design():
    """Memory that grows with the rows is a few columns (residuals, fold ids, the noise floor's differences),
    less than one copy of the weighted N x (p + 3) [X | Y] (the refit path held several: ~450 B/row here)."""
    rng = np.random.default_rng(0)
    cur = ("solar", "heater")
    model = CalModel(resolve_terms("eq3", currents=cur), cur, (), 25.0, 0.0)
    theta = random_theta(model, rng)

    def peak(n):
        d = make_data(model, theta, n, np.random.default_rng(1), noise_uT=0.03, t0_s=0.0)
        tracemalloc.start()
        fit(d, "eq3", currents=cur, options=FitOptions())
        out = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return out

    per_row = (peak(300_000) - peak(100_000)) / 200_000
    assert per_row < 8 * (model.n_columns + 3)
