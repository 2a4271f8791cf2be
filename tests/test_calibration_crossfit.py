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


def _same(a, b, what):
    """Two cross-fits' results equal to rounding (RTOL of each array's largest magnitude)."""
    def close(x, y, name):
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        assert x.shape == y.shape, name
        np.testing.assert_array_equal(np.isfinite(x), np.isfinite(y), err_msg=name)
        f = np.isfinite(y)
        scale = max(float(np.max(np.abs(y[f]), initial=0.0)), 1e-300)
        np.testing.assert_allclose(x[f], y[f], rtol=0, atol=RTOL * scale, err_msg=f"{what}: {name}")

    ca, cb = a.core, b.core
    for name in ("theta", "se", "conds"):
        close(getattr(ca, name), getattr(cb, name), name)
    for name in ("kappa", "sigma_uT", "cov", "dof"):
        close(np.nan_to_num(getattr(ca.posterior, name)), np.nan_to_num(getattr(cb.posterior, name)), name)
    assert [h.name for h in ca.held] == [h.name for h in cb.held]
    for name in ("holdout_blocks_uT", "holdout_sessions_uT"):
        close(getattr(a, name), getattr(b, name), name)
    assert sorted(a.holdout_per_session_uT) == sorted(b.holdout_per_session_uT)
    for s, v in b.holdout_per_session_uT.items():
        close(a.holdout_per_session_uT[s], v, f"session {s}")
    assert a.notes == b.notes
    assert (a.figures is None) == (b.figures is None) and (a.resid_uT is None) == (b.resid_uT is None)
    if b.figures is not None:
        close(a.figures.sse_uT2, b.figures.sse_uT2, "sse")
        close(a.figures.raw_sse_uT2, b.figures.raw_sse_uT2, "raw sse")
        close(a.figures.noise_floor_uT(), b.figures.noise_floor_uT(), "noise floor")
        assert (a.figures.steps is None) == (b.figures.steps is None)
    else:
        close(a.resid_uT, b.resid_uT, "residuals")
    x, y = a.acc, b.acc
    close(x.XtWX, y.XtWX, "X'WX")
    close(x.taus_s, y.taus_s, "taus")
    assert len(x.grams) == len(y.grams)
    for k, (g, h) in enumerate(zip(x.grams, y.grams, strict=True)):
        close(g, h, f"slow-noise Gram {k}")
    assert [(L, n) for L, n, _ in x.levels] == [(L, n) for L, n, _ in y.levels]
    for (L, _, u), (_, _, v) in zip(x.levels, y.levels, strict=True):
        close(u, v, f"level {L}")
    close(x.dt_s, y.dt_s, "dt")
    assert [t.name for t in x.terms] == [t.name for t in y.terms]
    close([(t.mean, t.sd) for t in x.terms], [(t.mean, t.sd) for t in y.terms], "left-out priors")
    close(x.moments.XtWG, y.moments.XtWG, "X'WG")
    close(x.moments.g2, y.moments.g2, "diag G'WG")
    close(x.moments.sum_w, y.moments.sum_w, "sum w")
    for name in ("count", "sq", "u_b", "u_t", "M", "scale_sum", "mag_max_uT"):
        close(getattr(x.bins, name), getattr(y.bins, name), f"bins {name}")
    assert sorted(a.block_sse.sse) == sorted(b.block_sse.sse)
    close([a.block_sse.sse[k] for k in sorted(b.block_sse.sse)], [b.block_sse.sse[k] for k in sorted(b.block_sse.sse)],
          "block SSE")


@pytest.mark.parametrize("terms,weights,shuffle", [
    ([], True, False),
    (["session_offset", "drift"], True, False),
    (["session_offset", "drift"], False, True),       # rows out of order: whole residuals
])
def test_shared_passes_equal_two_separate_cross_fits(terms, weights, shuffle):
    """One set of passes for a model and a wider one (the second-order tempco's candidate) gives what a cross-fit
    of each gives; without the wider one, the model's own; with a choice between them, the chosen one's (the
    other's held-out figures and block SSE, which the choice compares, and no more)."""
    from magstack.firmware.calibration.fit import build_model

    d = _sessions_data(weights=weights)
    if shuffle:
        d = d.select(np.random.default_rng(0).permutation(len(d)))
    opts = FitOptions()
    base = build_model(d, resolve_terms("eq3", terms), (), 25.0, "eq3")
    wider = build_model(d, resolve_terms("eq3", terms + ["temperature_gain2"]), (), 25.0, "eq3+temperature_gain2")
    one, two = crossfit.cross_fit(d, base, opts), crossfit.cross_fit(d, wider, opts)
    assert one.core.posterior.kappa.max() > 1.5 and one.acc.terms != two.acc.terms      # K_S2 left out of one
    seen = []
    a, b = crossfit.cross_fit_with(d, base, wider, opts, lambda cov: seen.append(cov.temp_span_c) or True)
    assert seen == [one.core.coverage.temp_span_c]
    _same(a, one, "model")
    _same(b, two, "wider model")
    alone, none = crossfit.cross_fit_with(d, base, wider, opts, lambda cov: False)
    assert none is None
    _same(alone, one, "model alone")
    for pick in (False, True):           # only the adopted model is finished; the other keeps its held-out figures
        seen_by = []
        a, b = crossfit.cross_fit_with(d, base, wider, opts, lambda cov: True,
                                       lambda x, y, pick=pick, seen_by=seen_by: seen_by.append((x, y)) or pick)
        assert seen_by == [(a, b)]
        done, other, ref, ref_other = (b, a, two, one) if pick else (a, b, one, two)
        _same(done, ref, f"adopted={pick}")
        assert other.acc is None and other.figures is None and other.resid_uT is None
        np.testing.assert_allclose(other.holdout_blocks_uT, ref_other.holdout_blocks_uT, rtol=RTOL)
        assert sorted(other.block_sse.sse) == sorted(ref_other.block_sse.sse)


def test_a_wider_model_must_have_every_column():
    d = _sessions_data(n=400, weights=False)
    m = CalModel(resolve_terms("eq3", ["drift"]), (), (), 25.0, 1.6e9)
    with pytest.raises(ValueError, match="every column"):
        crossfit.column_map(m, CalModel(resolve_terms("eq3"), (), (), 25.0, 1.6e9))
    with pytest.raises(ValueError, match="different references"):
        crossfit.column_map(m, CalModel(m.terms, (), (), 25.0, 1.6e9 + 1))
    wide = CalModel(resolve_terms("eq3", ["drift", "temperature_gain2"]), (), (), 25.0, 1.6e9)
    cols = crossfit.column_map(m, wide)
    X = wide.design(d.b_meas_uT, d.temp_c, {}, d.session, d.t_s)
    np.testing.assert_array_equal(X[:, cols], m.design(d.b_meas_uT, d.temp_c, {}, d.session, d.t_s))


def test_slow_noise_grams_only_where_the_slow_noise_fit_weighs_them():
    """Rows in order: pass 3 accumulates only the Grams the slow-noise fit of pass 2's levels weighs; they equal
    the Grams of every component accumulated in pass 2 (rows out of order) and then weighed, and the uncertainty
    (which reads them) is the same."""
    from magstack.firmware.calibration.fit import build_model
    from magstack.firmware.calibration.predictive import assemble, slow_noise

    d = _sessions_data(weights=True)
    opts = FitOptions()
    cm = build_model(d, resolve_terms("eq3", ["session_offset", "drift"]), (), 25.0, "eq3")
    lazy = crossfit.cross_fit(d, cm, opts)
    every = crossfit.cross_fit(d.select(np.random.default_rng(1).permutation(len(d))), cm, opts)
    assert lazy.figures is not None and every.figures is None
    noise = slow_noise(lazy.acc.levels, lazy.acc.dt_s, lazy.acc.taus_s)
    used = list(np.any(noise.ou_uT2 > 0, axis=0)) + [bool(np.any(noise.rw_uT2_per_s > 0))]
    assert any(used) and not all(used)
    for u, g, h in zip(used, lazy.acc.grams, every.acc.grams, strict=True):
        assert np.any(g != 0) == u
        np.testing.assert_allclose(g, h, rtol=0, atol=RTOL * max(np.abs(h).max(), 1e-300))
    noise_uT = np.full(3, 0.03)
    a = assemble(lazy.core.posterior, lazy.acc, noise_uT, lazy.core.coverage)
    b = assemble(every.core.posterior, every.acc, noise_uT, every.core.coverage)
    np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=RTOL * np.abs(b.cov).max())


def _eq3_rows(n: int, seed: int, curved: bool = False) -> FitData:
    """Eq. 3 truth with white noise over a wide temperature span (the wider model has nothing to find), or with the
    bridge's 1/(1 + a dT) sensitivity (a second order the linear tempco misses)."""
    rng = np.random.default_rng(seed)
    model = CalModel(resolve_terms("eq3"), (), (), 25.0, 0.0)
    d = make_data(model, random_theta(model, rng), n, rng, noise_uT=0.03, t0_s=0.0)
    if curved:
        dT = d.temp_c - 25.0
        d = FitData(d.b_meas_uT * (1.0 + (2.7e-3 * dT) ** 2)[:, None], d.b_ref_uT, d.temp_c, d.t_s, d.session)
    return d


@pytest.mark.parametrize("case", ["white", "slow misfit", "curved"])
def test_a_wider_model_that_cannot_gain_enough_is_ruled_out_unfitted(case):
    """The bound of the wider model's held-out gain holds against the gain the paired test measures with both
    models fitted; where it is below the adoption threshold the wider model is not fitted and the model's results
    are those of the passes that fitted both; else (a slow misfit a fold's own rows absorb; a second order the
    data need) both are fitted, as without the bound."""
    from magstack.firmware.calibration.fit import build_model
    from magstack.firmware.calibration.heldout_test import MIN_GAIN, paired_block_test

    if case == "slow misfit":
        d, terms = _sessions_data(n=20000, seed=1, weights=False), ["session_offset", "drift"]
    else:
        d, terms = _eq3_rows(60000, 5, curved=case == "curved"), []
    opts = FitOptions()
    base = build_model(d, resolve_terms("eq3", terms), (), 25.0, "eq3")
    wider = build_model(d, resolve_terms("eq3", terms + ["temperature_gain2"]), (), 25.0, "eq3+temperature_gain2")
    tests = {"both": [], "bound": []}

    def adopt(key):
        def decide(x, y):
            tests[key].append(paired_block_test(x.block_sse.sse, y.block_sse.sse))
            return tests[key][-1].significant
        return decide

    a, b = crossfit.cross_fit_with(d, base, wider, opts, lambda cov: True, adopt("both"))
    bound = crossfit.wider_gain_bound(d, *_runs_of(d, base, wider, opts))
    a2, b2 = crossfit.cross_fit_with(d, base, wider, opts, lambda cov: True, adopt("bound"), min_gain=MIN_GAIN)
    test = tests["both"][0]
    assert test.gain <= bound
    if case == "white":
        assert bound < MIN_GAIN and not test.significant
        assert b2 is None and tests["bound"] == [] and a2.wider_gain_bound == bound
        _same(a2, a, "model with the wider one ruled out")
        return
    assert bound >= MIN_GAIN and a2.wider_gain_bound is None and tests["bound"] == tests["both"]
    assert test.significant == (case == "curved")
    done, other, done2, other2 = (b, a, b2, a2) if test.significant else (a, b, a2, b2)
    _same(done2, done, "the adopted model")
    assert other.acc is None and other2.acc is None
    np.testing.assert_allclose(other2.holdout_blocks_uT, other.holdout_blocks_uT, rtol=RTOL)


def _runs_of(d, base, wider, opts):
    """The two runs after the model's pass 2, as :func:`.crossfit.cross_fit_with` has them when it bounds the wider
    model's gain: (model run, wider run, design width)."""
    cols = crossfit.column_map(base, wider)
    rows = crossfit._Rows(d, wider)
    piece = crossfit._PieceOf(d, rows, opts)
    pcs = crossfit._pieces(d, rows, piece, wider, opts)
    run = crossfit._Run(base, cols, crossfit._column_pieces(pcs, cols, wider.n_columns))
    crossfit._first_solves([run], piece, opts)
    crossfit._autocorr(d, rows, piece, [run], opts, crossfit.ordered(d),
                       crossfit.SlowNoiseGrams(wider.n_columns, 1.0))
    return run, crossfit._Run(wider, np.arange(wider.n_columns), pcs), wider.n_columns


def test_the_gain_bound_holds_on_every_fold():
    """Per fold, the wider model's own held-out sum of squares (fitted without the fold) is never below the least
    its columns reach fitted to the fold's rows: the bound's premise, on the refit of each fold."""
    from magstack.firmware.calibration.fit import build_model

    d = _sessions_data(n=5000, seed=4, weights=False)
    opts = FitOptions()
    wider = build_model(d, resolve_terms("eq3", ["temperature_gain2"]), (), 25.0, "eq3+temperature_gain2")
    fold = block_folds(d, opts)
    for f in np.unique(fold):
        train, test = d.select(fold != f), d.select(fold == f)
        r = fit(train, "eq3", ["temperature_gain2"], options=FitOptions(holdout=False, second_order_tempco="off"))
        X = r.model.design(test.b_meas_uT, test.temp_c, test.currents_A, test.session, test.t_s)
        held = np.sum((test.b_ref_uT - r.model.predict(r.theta, X)) ** 2)
        Xw = wider.design(test.b_meas_uT, test.temp_c, test.currents_A, test.session, test.t_s)
        least = sum(np.sum((Xw[:, m] @ np.linalg.lstsq(Xw[:, m], test.b_ref_uT[:, i], rcond=None)[0]
                            - test.b_ref_uT[:, i]) ** 2) for i, m in enumerate(wider.axis_mask()))
        assert least <= held


def test_the_wider_model_fitted_after_the_bound_equals_both_fitted_together(monkeypatch):
    """Where the first solves' bound is low but the final one is not, the wider model's pass 2 follows the model's
    on its own: the same results as both models sharing the pass."""
    from magstack.firmware.calibration.fit import build_model
    from magstack.firmware.calibration.heldout_test import MIN_GAIN, paired_block_test

    d = _eq3_rows(40000, 6, curved=True)
    opts = FitOptions()
    base = build_model(d, resolve_terms("eq3"), (), 25.0, "eq3")
    wider = build_model(d, resolve_terms("eq3", ["temperature_gain2"]), (), 25.0, "eq3+temperature_gain2")

    def adopt(x, y):
        return paired_block_test(x.block_sse.sse, y.block_sse.sse).significant

    together = crossfit.cross_fit_with(d, base, wider, opts, lambda cov: True, adopt, min_gain=MIN_GAIN)
    true_bound, calls = crossfit.wider_gain_bound, []

    def low_guess(*args):
        calls.append(true_bound(*args))
        return 0.0 if len(calls) == 1 else calls[-1]

    monkeypatch.setattr(crossfit, "wider_gain_bound", low_guess)
    apart = crossfit.cross_fit_with(d, base, wider, opts, lambda cov: True, adopt, min_gain=MIN_GAIN)
    assert len(calls) == 2 and calls[1] >= MIN_GAIN
    assert together[1].acc is not None and apart[1].acc is not None          # adopted both ways
    _same(apart[1], together[1], "the wider model fitted apart")
    np.testing.assert_allclose(apart[0].holdout_blocks_uT, together[0].holdout_blocks_uT, rtol=RTOL)
