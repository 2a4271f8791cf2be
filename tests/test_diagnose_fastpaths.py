"""The diagnosis's fast paths against the plain computations they replace, on small data.

Each fast path must give what the direct least squares gives: the tone fit's per-session 2 x 2 solves
against lstsq of the full sine/cosine design, the separable delay search against the coordinate
search of the training SSE, the surrogate test's precomputed fold solves against solving each time.
"""
from __future__ import annotations

import numpy as np
import pytest

from magstack.ground.diagnose import noise


def _sin_cos_design(t, f, session):
    cols = []
    for k in np.unique(session):
        m = session == k
        cols += [np.where(m, np.sin(2 * np.pi * f * t), 0.0), np.where(m, np.cos(2 * np.pi * f * t), 0.0)]
    return np.column_stack(cols)


def test_tone_fit_per_session_equals_the_full_design_lstsq():
    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(0, 600, 3000))
    session = np.repeat([0, 1, 2], 1000)
    session[-3:] = 7                                  # a 3-row session
    x = rng.standard_normal((3000, 3)) + 0.5 * np.sin(2 * np.pi * 0.013 * t + session)[:, None]
    f = 0.01307
    X = _sin_cos_design(t, f, session)
    coef, *_ = np.linalg.lstsq(X, x, rcond=None)
    want = X @ coef
    _, inv = np.unique(session, return_inverse=True)
    ss, fit = noise._explained(x, np.exp(2j * np.pi * f * t), inv.ravel(), 4)
    assert np.allclose(fit, want, atol=1e-10)
    assert np.isclose(ss, float(np.sum(want ** 2)), rtol=1e-10)


def test_tone_fit_of_a_session_too_short_to_tell_sine_from_cosine_is_the_minimum_norm_fit():
    t = np.array([0.0, 1.0, 2.0, 3.0, 10.0])
    session = np.array([0, 0, 0, 0, 1])               # session 1: one row, a rank-1 2 x 2 system
    x = np.arange(15.0).reshape(5, 3)
    f = 0.1
    X = _sin_cos_design(t, f, session)
    coef, *_ = np.linalg.lstsq(X, x, rcond=None)
    _, fit = noise._explained(x, np.exp(2j * np.pi * f * t), np.array([0, 0, 0, 0, 1]), 2)
    assert np.allclose(fit, X @ coef, atol=1e-9)


def _skewed_session(n=1800, seed=2):
    from magstack.data.session import Session
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 2.5
    w = 2 * np.pi * np.array([1 / 37.0, 1 / 53.0, 1 / 71.0])
    def field(tt):
        return np.column_stack([40 * np.sin(w[0] * tt), 35 * np.cos(w[1] * tt), 30 * np.sin(w[2] * tt + 1)])
    ref = field(t)
    late = np.column_stack([field(t - d)[:, j] for j, d in enumerate([0.12, 0.0, -0.07])])
    dut = late @ np.array([[1.05, 0.01, 0], [0, 0.97, 0.02], [0.01, 0, 1.02]]).T + 0.4
    dut += rng.standard_normal((n, 3)) * 0.03
    return Session(t, ref, dut, np.full(n, 25.0), np.repeat([0, 1, 2], n // 3), {})


def test_separable_delay_search_finds_what_the_coordinate_search_finds_for_every_fold(monkeypatch):
    from magstack.ground.diagnose import gap as gp
    from magstack.ground.diagnose import nonlinear as nl
    from magstack.ground.diagnose import search as sr
    monkeypatch.setattr(gp, "FOLD_CHUNK", 256)       # per-fold sums over several row chunks
    from magstack.ground.diagnose.gap import model_gap
    s = _skewed_session()
    gap = model_gap(s, ("gain_matrix", "offset"), (), "test")
    fold = np.repeat(np.arange(5), -(-s.t_s.size // 5))[: s.t_s.size][np.random.default_rng(0).permutation(s.t_s.size)]
    grid = nl.delay_grid(s.t_s)
    fold_d, all_d = sr.delay_searches(gap, fold, grid)
    for f, d in zip(np.unique(fold), fold_d, strict=True):
        want = nl.search_delays(sr.delay_sse_fn(gap, fold != f), grid)
        assert np.allclose(d, want, atol=1e-9 * np.ptp(grid))
    want_all = nl.search_delays(sr.delay_sse_fn(gap, np.ones(s.t_s.size, bool)), grid)
    assert np.allclose(all_d, want_all, atol=1e-9 * np.ptp(grid))
    # the DUT's x reads the field of 0.12 s before (dt = -0.12: "reads the field at t + dt"), z of 0.07 s
    # after (grid spacing 0.071 s)
    assert abs(all_d[0] + 0.12) < 0.03 and abs(all_d[1]) < 0.03 and abs(all_d[2] - 0.07) < 0.03


def test_coupled_deskew_keeps_the_coordinate_search():
    from magstack.ground.diagnose import nonlinear as nl
    from magstack.ground.diagnose import search as sr
    from magstack.ground.diagnose.gap import model_gap
    s = _skewed_session(900)
    gap = model_gap(s, ("gain_matrix", "offset"), (), "test")
    gap.deskew_J = np.array([[1.0, 0.1, 0], [0, 1.0, 0], [0, 0, 1.0]])    # a table's gain matrix couples the axes
    fold = np.arange(s.t_s.size) % 3
    grid = nl.delay_grid(s.t_s)
    fold_d, all_d = sr.delay_searches(gap, fold, grid)
    assert np.allclose(all_d, nl.search_delays(sr.delay_sse_fn(gap, np.ones(s.t_s.size, bool)), grid))
    assert np.allclose(fold_d[1], nl.search_delays(sr.delay_sse_fn(gap, fold != 1), grid))


def test_surrogate_statistic_with_precomputed_fold_solves_is_the_held_out_sse_reduction():
    """T of a linear candidate on the session's own target (surrogate.prepare) against per-fold least
    squares: SSE(base) - SSE(base + candidate) on each fold's held-out rows, fitted on the others."""
    from magstack.ground.diagnose import search as sr
    from magstack.ground.diagnose import surrogate as su
    from magstack.ground.diagnose.gap import model_gap
    s = _skewed_session(1500, seed=5)
    s.temp_c = 20 + 10 * np.sin(np.arange(1500) / 300.0)
    s.dut_uT[:, 0] += 0.02 * (s.temp_c - 25)
    gap = model_gap(s, ("gain_matrix", "offset"), (), "test")
    base = gap.base_design()
    cands, _, _ = sr.build_candidates(gap, base)
    cand = next(c for c in cands if c.effect == "temperature_offset")
    fold = np.arange(1500) * 5 // 1500
    shared = su.Shared(gap, base, fold, su.test_rows(gap.n))
    t_obs, _, _ = su.prepare(gap, cand, shared)
    own = sr.linear_block(gap, cand.effect, cand.terms)
    want = 0.0
    for i in range(3):
        Bi = base.X[:, base.mask[i]]
        Zi = np.hstack([Bi, own.X[:, own.mask[i]]])
        y = gap.target[:, i]
        for f in range(5):
            tr, te = fold != f, fold == f
            for X, sign in ((Bi, 1.0), (Zi, -1.0)):
                th, *_ = np.linalg.lstsq(X[tr], y[tr], rcond=None)
                want += sign * float(np.sum((y[te] - X[te] @ th) ** 2))
    assert np.isclose(t_obs, want, rtol=1e-8)


def test_surrogate_test_rows_thin_long_sessions_evenly():
    from magstack.ground.diagnose import surrogate as su
    assert su.test_rows(1000).size == 1000
    r = su.test_rows(su.MAX_TEST_ROWS * 3 + 1)
    assert r.size <= su.MAX_TEST_ROWS and np.all(np.diff(r) == 4)


def test_chunked_excitation_check_agrees_with_the_least_squares_residual():
    from magstack.ground.diagnose import search as sr
    rng = np.random.default_rng(1)
    n = 3 * sr.EXCITATION_CHUNK + 17
    base = np.column_stack([np.ones(n), rng.standard_normal(n), np.linspace(0, 1, n)])
    inside = base @ np.array([[0.3], [2.0], [-1.0]])                     # a combination of the base columns
    assert not sr._excited(inside, base)
    nudged = inside.copy()
    nudged[n // 2, 0] += 1e-2 * np.linalg.norm(inside)                    # one row off the base's span
    assert sr._excited(nudged, base)
    assert sr._excited(np.hstack([inside, rng.standard_normal((n, 1))]), base)


@pytest.mark.parametrize("option_floats", [1_000_000, 3000])
def test_hysteresis_threshold_choice_by_normal_equations_is_the_refit_choice(monkeypatch, option_floats):
    """choose_thresholds against refitting base + hysteresis_block for every option (the search's rule); also
    with the options of each axis formed one threshold at a time (a long session's memory bound)."""
    from magstack.ground.diagnose import nonlinear as nl
    from magstack.ground.diagnose import search as sr
    monkeypatch.setattr(sr, "HYST_OPTION_FLOATS", option_floats)
    from magstack.ground.diagnose.gap import model_gap, predict, solve
    s = _skewed_session(2400, seed=7)
    exc = (np.arange(2400) % 800 >= 100) & (np.arange(2400) % 800 < 220)   # one large X excursion per power cycle
    s.ref_uT[exc, 0] = 180.0 * np.where(np.arange(2400)[exc] // 800 % 2, -1, 1)
    s.dut_uT[exc, 0] = 1.05 * s.ref_uT[exc, 0]
    state = nl.hysteresis_state(s.dut_uT, np.array([150.0, np.inf, np.inf]), np.array([1.0, 1, 1]))
    s.dut_uT += 0.3 * state[:, :1]
    gap = model_gap(s, ("gain_matrix", "offset"), (), "test")
    base = gap.base_design()
    cands = nl.hysteresis_thresholds(*gap.history())
    assert any(cands)
    rows = np.arange(2400) % 5 != 2
    got = sr.choose_thresholds(gap, base, gap.target, cands, rows)
    thr, init = np.full(3, np.inf), np.ones(3)
    for j in range(3):
        best = (np.inf, None, None)
        for c in cands[j]:
            for s0 in (-1.0, 1.0):
                t_, i_ = thr.copy(), init.copy()
                t_[j], i_[j] = c, s0
                from magstack.ground.diagnose.gap import Block
                blk = Block.join([base, sr.hysteresis_block(gap, t_, i_)], gap.n)
                th = solve(blk.X, gap.target, blk.mask, rows)
                sse = float(np.sum((gap.target[rows] - predict(blk.X[rows], th, blk.mask)) ** 2))
                if sse < best[0]:
                    best = (sse, c, s0)
        if best[1] is not None:
            thr[j], init[j] = best[1], best[2]
    assert np.array_equal(got[0], thr) and np.array_equal(got[1], init)


def test_lag_and_linear_columns_built_on_a_row_subset_equal_the_whole_gaps_rows():
    """The surrogate test builds row-wise candidate columns on its tested rows only (Gap.rows_view)."""
    from magstack.ground.diagnose import search as sr
    from magstack.ground.diagnose.gap import model_gap
    s = _skewed_session(1500, seed=3)
    s.temp_c = 20 + 10 * np.sin(np.arange(1500) / 200.0)
    gap = model_gap(s, ("gain_matrix", "offset"), (), "test")
    rows = np.arange(0, 1500, 7)
    whole = sr.lag_block(gap, 60.0)
    assert np.allclose(sr.lag_block(gap, 60.0, rows).X, whole.X[rows], rtol=0, atol=1e-12)
    # the forward lag columns formed directly equal the calibration model's design of the lagged temperature
    import dataclasses
    lagged = dataclasses.replace(gap.session)
    lagged.temp_c = sr.lagged_temperature(gap, 60.0)
    ref = dataclasses.replace(gap, session=lagged).term_design(sr.LAG_TERMS)
    assert np.array_equal(whole.X, ref.X) and np.array_equal(whole.mask, ref.mask) and whole.units == ref.units
    assert [[n.removesuffix("@lag") for n in row] for row in whole.names] == ref.names
    cands, _, _ = sr.build_candidates(gap, gap.base_design())
    linear = [c for c in cands if c.kind == "linear"]
    assert {"temperature_gain", "cross_axis", "nonlinearity"} <= {c.effect for c in linear}
    for c in linear:
        full = sr.linear_block(gap, c.effect, c.terms)
        sub = sr.linear_block(gap.rows_view(rows), c.effect, c.terms)
        if c.effect == "drift":     # the pivot is the rows' mean time: the same span with the constant
            assert np.allclose(np.diff(sub.X, axis=0), np.diff(full.X[rows], axis=0), atol=1e-12)
            continue
        assert np.allclose(sub.X, full.X[rows], rtol=0, atol=1e-12), c.effect


def test_out_of_fold_over_blocks_in_chunks_equals_the_joined_design(monkeypatch):
    from magstack.ground.diagnose import gap as gp
    from magstack.ground.diagnose.gap import Block, out_of_fold, out_of_fold_blocks
    monkeypatch.setattr(gp, "FOLD_CHUNK", 97)
    rng = np.random.default_rng(8)
    n = 1000
    a = Block(rng.standard_normal((n, 4)), np.array([[1, 1, 0, 1], [1, 0, 1, 1], [0, 1, 1, 1]], bool),
              [["a"] * 4] * 3, ["u"] * 4)
    b = Block(rng.standard_normal((n, 2)), np.array([[1, 0], [0, 1], [1, 1]], bool), [["b"] * 2] * 3, ["u"] * 2)
    Y = rng.standard_normal((n, 3))
    fold = rng.integers(0, 5, n)
    j = Block.join([a, b], n)
    want, _ = out_of_fold(j.X, Y, j.mask, fold)
    assert np.allclose(out_of_fold_blocks([a, b], Y, fold), want, rtol=0, atol=1e-10)


# ---------------------------------------------------------------- the 4 x 900-row fixed cost
def test_solve_normal_is_the_checked_cholesky_solve_bit_for_bit_and_falls_back_like_it():
    """solve_normal calls LAPACK without scipy's per-call checks: the same bits as cho_factor/cho_solve of the
    equilibrated system; a singular system and a non-finite one take the pseudo-inverse path as before."""
    import scipy.linalg

    from magstack.ground.diagnose.gap import RCOND, solve_normal
    rng = np.random.default_rng(5)
    for p in (1, 4, 9):
        X = rng.standard_normal((50, p)) * rng.uniform(0.1, 100, p)
        G, C = X.T @ X, X.T @ rng.standard_normal((50, 3))
        d = np.sqrt(np.diag(G))
        c = scipy.linalg.cho_factor(G / np.outer(d, d))
        want = scipy.linalg.cho_solve(c, C / d[:, None]) / d[:, None]
        assert np.array_equal(solve_normal(G, C), want)
    X = rng.standard_normal((50, 3))
    X = np.column_stack([X, X[:, 0] + X[:, 1]])                    # rank 3 of 4
    G, C = X.T @ X, X.T @ rng.standard_normal((50, 2))
    d = np.sqrt(np.diag(G))
    want = np.linalg.pinv(G / np.outer(d, d), rcond=RCOND, hermitian=True) @ (C / d[:, None]) / d[:, None]
    assert np.allclose(solve_normal(G, C), want, rtol=1e-9, atol=1e-12)
    G[0, 0] = np.nan
    try:
        out = solve_normal(G, C)
    except np.linalg.LinAlgError:
        out = None                     # numpy's SVD refuses NaN: the caller sees that, as before
    assert out is None or not np.all(np.isfinite(out))


def test_axis_cross_is_numpys_cross_with_the_unit_vector():
    from magstack.ground.diagnose.rotation import axis_cross
    b = np.random.default_rng(1).standard_normal((20, 3))
    for a in range(3):
        assert np.array_equal(axis_cross(a, b) + 0.0, np.cross(np.eye(3)[a], b) + 0.0)


def test_surrogates_do_not_depend_on_how_many_are_transformed_at_once(monkeypatch):
    from magstack.ground.diagnose import surrogate as su
    rng = np.random.default_rng(2)
    x = np.cumsum(rng.standard_normal((700, 3)), axis=0) * 0.02 + rng.standard_normal((700, 3))
    src = su.SurrogateSource(x, 0)
    pos = np.argsort(np.arange(700) % 3, kind="stable")
    got = []
    for bins in (1e7, 5000, 10):                       # all at once, a few per call, one per call
        monkeypatch.setattr(su, "TRANSFORM_BINS", bins)
        src.rng = np.random.default_rng(7)
        got.append(src.draw(23, pos))
    assert np.array_equal(got[0], got[1]) and np.array_equal(got[0], got[2])
    src.rng = np.random.default_rng(7)
    assert np.array_equal(src.draw(23)[:, :, pos], got[0])


def test_hysteresis_options_are_the_state_columns_of_each_threshold_and_initial_state():
    from magstack.ground.diagnose import nonlinear as nl
    from magstack.ground.diagnose import search as sr
    from magstack.ground.diagnose.gap import model_gap
    s = _skewed_session(900)
    s.dut_uT[100:140, 1] = 120.0
    s.dut_uT[500:530, 1] = -120.0
    gap = model_gap(s, ("gain_matrix", "offset"), (), "test")
    hist, idx = gap.history()
    cands = [[30.0], [50.0, 100.0], []]
    U = sr.hysteresis_options(gap, cands, 1)
    assert U.shape == (gap.n, 4)
    for k, c in enumerate(cands[1]):
        for m, s0 in enumerate((-1.0, 1.0)):
            want = nl.hysteresis_state(hist, np.array([np.inf, c, np.inf]), np.array([1.0, s0, 1.0]))[idx, 1]
            assert np.array_equal(U[:, 2 * k + m], want)
    assert sr.hysteresis_options(gap, cands, 1) is U                 # kept for the next fold


def test_lag_train_sse_reaches_each_folds_least_squares_minimum_over_the_starting_offsets():
    """lag.train_sse (Gauss-Newton in the starting offsets, in normal-equation space) against a direct bounded
    minimisation of each fold's training SSE over the stretches' starting offsets (L-BFGS-B on full refits, the
    same bounds); the continuous lag (offsets 0) is never better; the lagged temperature is kept read-only."""
    import scipy.optimize

    from magstack.ground.diagnose import lag as lg
    from magstack.ground.diagnose import nonlinear as nl
    from magstack.ground.diagnose.gap import Block, model_gap, predict, solve
    s = _skewed_session(900)
    s.temp_c = 20 + 10 * np.sin(2 * np.pi * s.t_s / 300.0) + 8.0 * (s.session == 1)   # session 1 starts warmer
    lagged = nl.lagged_temperature(s.t_s, s.temp_c, s.session, 40.0)
    first1 = np.flatnonzero(s.session == 1)[0]
    u1 = s.temp_c[first1] - lagged[first1]                     # the die restarted at the board's temperature
    die = lagged + np.where(s.session == 1, u1 * np.exp(-(s.t_s - s.t_s[first1]) / 40.0), 0.0)
    s.dut_uT[:, 0] += 0.5 * (die - 25)
    gap = model_gap(s, ("gain_matrix", "offset"), (), "test")
    base, Y = gap.base_design(), gap.target
    fold = np.arange(gap.n) * 7 % 4
    grid = np.array([10.0, 40.0, 90.0])
    got = lg.train_sse(gap, base, Y, fold, grid)

    def sse(tau, rows, delta):
        dz = lg.design(gap, tau)
        blk = Block.join([base, lg.lag_block(gap, tau, temp=lg.die_temperature(gap, dz, np.asarray(delta)))], gap.n)
        th = solve(blk.X, Y, blk.mask, rows)
        return float(np.sum((Y[rows] - predict(blk.X[rows], th, blk.mask)) ** 2))
    for k, tau in enumerate(grid):
        dz = lg.design(gap, tau)
        for f in range(4):
            tr = fold != f
            best = scipy.optimize.minimize(lambda d, tau=tau, tr=tr: sse(tau, tr, d), np.zeros(3), method="L-BFGS-B",
                                           bounds=list(zip(dz.lo, dz.hi, strict=True)),
                                           options={"ftol": 1e-14, "gtol": 1e-10}).fun
            assert got[f, k] <= sse(tau, tr, np.zeros(3)) * (1 + 1e-12)
            assert abs(got[f, k] - best) <= 1e-3 * best, (tau, f, got[f, k], best)
    assert np.argmin(got.sum(axis=0)) == 1
    dz = lg.design(gap, 40.0)
    fit = lg.fits(gap, base, Y, fold, dz)
    assert dz.R == 3 and abs(u1) > 4 and abs(fit.delta[-1][1] - u1) < 0.5, (u1, fit.delta[-1])
    kept = lg.lagged_temperature(gap, 40.0)
    assert kept is lg.lagged_temperature(gap, 40.0) and not kept.flags.writeable
    assert np.array_equal(kept, nl.lagged_temperature(s.t_s, s.temp_c, s.session, 40.0))


def test_batched_normal_solves_equal_one_by_one_and_route_rank_deficient_systems_to_the_pseudo_inverse():
    from magstack.ground.diagnose.gap import solve_normal, solve_normal_batch
    rng = np.random.default_rng(11)
    Gs, Cs = [], []
    for k in range(5):
        X = rng.standard_normal((40, 6)) * rng.uniform(0.01, 50, 6)
        if k == 2:
            X[:, 5] = X[:, 0] - 2 * X[:, 3]                 # rank 5 of 6
        if k == 4:
            X[:, 1] = 0.0                                   # an empty column
        Gs.append(X.T @ X)
        Cs.append(X.T @ rng.standard_normal((40, 3)))
    G, C = np.stack(Gs), np.stack(Cs)
    head = solve_normal_batch(G[:4], C[:4])            # Cholesky of the batch succeeds; system 2 fails the rank test
    got = solve_normal_batch(G, C)                      # system 4 is not positive definite: numpy refuses the batch
    assert np.allclose(head, got[:4], rtol=1e-12, atol=1e-15)
    for k in range(5):
        want = solve_normal(G[k], C[k])
        assert np.allclose(G[k] @ got[k], G[k] @ want, rtol=1e-9, atol=1e-9 * np.abs(C[k]).max())
        if k != 2:
            assert np.allclose(got[k], want, rtol=1e-9, atol=1e-12)
    assert np.array_equal(got[2], solve_normal(G[2], C[2]))      # the pseudo-inverse path, as alone
    assert solve_normal_batch(np.zeros((0, 3, 3)), np.zeros((0, 3, 2))).shape == (0, 3, 2)


def test_field_rate_of_all_runs_at_once_is_np_gradient_run_by_run():
    """Runs of one row, two rows, evenly spaced (np.gradient's scalar-spacing formula) and jittered ones, split by
    sessions, pauses and a repeated time stamp: bit for bit what np.gradient gives per run."""
    from magstack.ground.diagnose.nonlinear import runs
    from magstack.ground.diagnose.where import field_rate_uT_per_s, run_slices
    rng = np.random.default_rng(4)
    steps = np.full(400, 0.4)
    steps[100:180] += rng.uniform(-0.05, 0.05, 80)       # jittered stretch
    steps[[30, 31, 60, 70, 72, 250, 251, 252]] = 5.0    # pauses: runs of one row (30, 250, 251) and two (70-71)
    steps[300] = 0.0                                    # a repeated time stamp breaks the run
    t = np.cumsum(steps)
    session = np.repeat([3, 7], 200)
    b = rng.standard_normal((400, 3)) * 20
    want = np.zeros(400)
    for idx in run_slices(runs(t, session)):
        if idx.stop - idx.start >= 2:
            want[idx] = np.linalg.norm(np.gradient(b[idx], t[idx], axis=0), axis=1)
    got = field_rate_uT_per_s(b, t, session)
    assert np.array_equal(got, want)
    assert np.any(got == 0) and np.all(np.isfinite(got))


def test_lagged_temperature_with_precomputed_groups_is_the_same_series():
    """The time order passed in (nonlinear.lag_groups, kept by the search) changes nothing, with sessions one
    after another and with two recordings overlapping in time (filtered one by one)."""
    from magstack.ground.diagnose import nonlinear as nl
    rng = np.random.default_rng(8)
    t = np.r_[np.arange(300.0), 1000 + np.arange(200.0)]
    temp = 20 + np.cumsum(rng.standard_normal(500)) * 0.05
    for session in (np.repeat([0, 1], [300, 200]), np.tile([4, 5], 250)):
        groups = nl.lag_groups(t, session)
        for tau in (3.0, 40.0):
            assert np.array_equal(nl.lagged_temperature(t, temp, session, tau, groups),
                                  nl.lagged_temperature(t, temp, session, tau))
    assert len(nl.lag_groups(t, np.tile([4, 5], 250))) == 2
    assert len(nl.lag_groups(t, np.repeat([0, 1], [300, 200]))) == 1
