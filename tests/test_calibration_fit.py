"""Calibration model and fit: recovery, identifiability, robust, held-out, streaming."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.firmware.calibration import CAL_TERMS, FitData, FitOptions, fit
from magstack.firmware.calibration.fit import diagnose_steps, noise_floor, reference_steps
from magstack.firmware.calibration.model import CalModel, resolve_terms, time_derivative
from magstack.firmware.calibration.streaming import StreamingFit
from magstack.firmware.effects import EFFECTS
from magstack.firmware.errors import FitError
from magstack.sim.synthetic_calibration import make_data, random_theta

N = 3000
T0_S = 1.6e9
ALL = ("gain_matrix", "temperature_gain", "offset", "temperature_offset", "currents", "cubic",
       "cross_products", "time_skew", "session_offset", "drift")


def _model(terms, currents=(), sessions=(), n=N):
    # t_ref = mean time of make_data's stamps, as the fit chooses it
    return CalModel(terms, currents, sessions, 25.0, T0_S + (n - 1) * 0.25 / 2)


def test_cal_terms_come_from_the_effect_catalogue():
    assert set(CAL_TERMS) == {t for e in EFFECTS.values() if e.cal_term for t in (e.cal_term, *e.cal_terms_extra)}
    assert EFFECTS["temperature_gain"].cal_terms_extra == ("temperature_gain2",)
    assert resolve_terms("eq3") == ("gain_matrix", "temperature_gain", "offset", "temperature_offset")
    with pytest.raises(FitError, match="valid:"):
        resolve_terms("eq3", ["bogus"])
    with pytest.raises(FitError, match="unknown model"):
        resolve_terms("eq9")


def test_eq3_has_24_parameters():
    m = CalModel(resolve_terms("eq3"))
    assert int(m.axis_mask().sum()) == 24
    m4 = CalModel(resolve_terms("eq3", currents=("a", "b")), ("a", "b"))
    assert int(m4.axis_mask().sum()) == 30


def test_noise_free_recovery_of_every_term():
    rng = np.random.default_rng(1)
    m = _model(ALL, ("solar", "heater"), (1, 2, 3))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng, noise_uT=0.0)
    r = fit(d, "eq3", ALL[4:], ("solar", "heater"), options=FitOptions(holdout=False))
    assert r.held == []
    mask = m.axis_mask()
    rel = np.abs(r.theta - th)[mask] / np.maximum(np.abs(th[mask]), 1e-6)
    assert rel.max() < 1e-6
    assert r.rmse_norm_uT < 1e-9


def test_standard_errors_match_the_scatter_of_refits():
    rng = np.random.default_rng(2)
    m = _model(resolve_terms("eq3"))
    th = random_theta(m, rng)
    est, ses = [], []
    for _ in range(30):
        d = make_data(m, th, 800, rng, noise_uT=0.05)
        r = fit(d, options=FitOptions(holdout=False))
        est.append(r.theta[0])
        ses.append(r.se[0])
    ratio = np.std(est, axis=0) / np.mean(ses, axis=0)
    assert np.all((ratio > 0.6) & (ratio < 1.5)), ratio


def test_temperature_terms_without_excursion_come_from_the_prior_and_are_named():
    """At one constant temperature the data cannot determine a tempco: the datasheet prior does, with its
    sd (not "held at 0"), and the report names them with the reason."""
    from magstack.drivers.cal_priors import PRIORS
    rng = np.random.default_rng(3)
    m = _model(resolve_terms("eq3"))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng, temp_span_c=(24.0, 24.0))
    r = fit(d, options=FitOptions(holdout=False, chip="hmc1053"))
    names = {h.name for h in r.held}
    assert names == {f"K_S[{i},{j}]" for i in "xyz" for j in "xyz"} | {f"K_O[{i}]" for i in "xyz"}
    assert all("temperature spans only" in h.reason for h in r.held)
    post = r.posterior
    hp = PRIORS["hmc1053"]
    S = r.params["S"]
    for h in r.held:
        i, c = h.axis, h.column
        assert post.determined_by(i, c) == "prior"
        assert r.se[i, c] == pytest.approx(post.prior.sd[i, c], rel=0.05)      # the prior's uncertainty
        if r.model.columns[c].param == "K_S":                                  # relative tempco x fitted S
            j = r.model.columns[c].index
            assert abs(r.theta[i, c] - hp.k_s_rel_per_c.mean * S[i, j]) <= 0.01 * post.prior.sd[i, c]
        else:
            assert abs(r.theta[i, c] - hp.k_o_uT_per_c.mean) <= 0.05 * hp.k_o_uT_per_c.sd
    assert "determined by the prior" in r.report() and "hmc1053" in r.report()
    with pytest.raises(FitError, match="K_S\\[x,x\\]"):
        fit(d, options=FitOptions(holdout=False, chip="hmc1053", on_unidentifiable="refuse"))


def test_temperature_gain_needs_field_and_temperature_together():
    """Belsten sec. 3.3: X saw field while heated, Y and Z only at room temperature: K_S[., y/z] would be
    informed only by the DUT's noise times temperature, so they come from the prior alone."""
    rng = np.random.default_rng(4)
    m = _model(resolve_terms("eq3"))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng)
    first = np.arange(N) < N // 2
    d.b_meas_uT[first, 1:] = rng.normal(0, 0.05, size=(first.sum(), 2))  # first half: X field only, heated
    d.temp_c[~first] = 24.0                                                # second half: room temperature
    d.b_ref_uT = m.predict(th, m.design(d.b_meas_uT, d.temp_c, {}, d.session, d.t_s))
    r = fit(d, options=FitOptions(holdout=False))
    gated = {h.name for h in r.held if h.rule == "temperature-no-field"}
    assert gated == {f"K_S[{i},{j}]" for i in "xyz" for j in "yz"}
    assert all(r.posterior.data_share[h.axis, h.column] == 0.0 for h in r.held if h.name in gated)
    kx = [c for c, col in enumerate(r.model.columns) if col.param == "K_S" and col.index == 0][0]
    np.testing.assert_allclose(r.theta[:, kx], th[:, kx], rtol=1e-3)


def test_user_prior_and_fixed_value_are_used():
    rng = np.random.default_rng(5)
    m = _model(resolve_terms("eq3"))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng, temp_span_c=(24.0, 24.0))
    r = fit(d, options=FitOptions(holdout=False, priors={"K_O[z]": 0.16}))        # a number fixes it (sd 0)
    h = [x for x in r.held if x.name == "K_O[z]"][0]
    assert h.value == 0.16 and r.params["K_O"][2] == 0.16 and "held by the user" in h.reason
    r = fit(d, options=FitOptions(holdout=False, priors={"K_O[z]": (0.2, 0.01)}))  # (mean, sd): the prior decides
    assert r.params["K_O"][2] == pytest.approx(0.2, abs=1e-3)
    k = [c for c, col in enumerate(r.model.columns) if col.param == "K_O"][0]
    assert r.se[2, k] == pytest.approx(0.01, rel=0.05)
    with pytest.raises(FitError, match="unknown parameter"):
        fit(d, options=FitOptions(holdout=False, priors={"K_O[w]": 1.0}))


def test_no_priors_is_the_unregularised_fit_and_names_what_it_cannot_determine():
    rng = np.random.default_rng(15)
    m = _model(resolve_terms("eq3"))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng, noise_uT=0.02)
    r = fit(d, options=FitOptions(holdout=False, use_priors=False))
    assert r.held == [] and "no-priors" in r.prior_name
    np.testing.assert_allclose(r.theta[m.axis_mask()], th[m.axis_mask()], atol=5e-3)
    d2 = make_data(m, th, N, rng, temp_span_c=(24.0, 24.0))
    r2 = fit(d2, options=FitOptions(holdout=False, use_priors=False))
    und = {h.name for h in r2.held}
    assert {f"K_O[{a}]" for a in "xyz"} <= und                              # dT == -1: the offset's copy
    assert all("minimum-norm" in h.reason or "data not used" in h.reason for h in r2.held)


def test_axis_never_excited_takes_its_gain_column_from_the_prior():
    rng = np.random.default_rng(6)
    m = _model(("gain_matrix", "offset"))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng)
    d.b_meas_uT[:, 2] = rng.normal(0, 0.5, N)          # Z sees no field, only 0.5 uT of noise
    r = fit(d, "gain_offset", options=FitOptions(holdout=False))
    assert {h.name for h in r.held} == {"S[x,z]", "S[y,z]", "S[z,z]"}
    assert r.params["S"][2, 2] == 1.0 and r.params["S"][0, 2] == 0.0      # the prior means, exactly
    assert all(r.posterior.data_share[h.axis, h.column] == 0.0 for h in r.held)
    d.b_meas_uT[:, 2] = 0.3 * d.b_meas_uT[:, 0] + rng.normal(0, 0.01, N)   # Z just follows X
    r = fit(d, "gain_offset", options=FitOptions(holdout=False))
    # X and Z cannot be separated: the weaker (Z) comes from the prior, the X column carries the combination
    gated = {h.name for h in r.held if h.rule == "field"}
    assert gated == {"S[x,z]", "S[y,z]", "S[z,z]"}
    assert all("more excited axes" in h.reason for h in r.held if h.name in gated)


def test_single_axis_sweep_calibrates_its_axis_despite_cross_coupling():
    """A sweep of X only: the DUT's Y and Z channels read scaled copies of X (cross-axis
    coupling). X's column is determined (its own field), Y's and Z's are held, and the fit
    removes the coupling instead of falling back to the identity."""
    rng = np.random.default_rng(16)
    n = 2000
    x = 50.0 * np.sin(np.linspace(0, 6 * np.pi, n))
    truth = np.column_stack([x, np.zeros(n), np.zeros(n)])
    S_dut = np.array([[1.1, 0.0, 0.0], [0.09, 1.0, 0.0], [-0.04, 0.0, 1.0]])   # DUT = S_dut truth + offset
    meas = truth @ S_dut.T + np.array([0.3, -0.2, 0.5]) + rng.normal(0, 0.02, (n, 3))
    d = FitData(meas, truth + rng.normal(0, 0.02, (n, 3)), np.full(n, 25.0), np.arange(n) * 0.25,
                np.zeros(n, np.int64))
    r = fit(d, "gain_offset", options=FitOptions(holdout=False))
    assert {h.name for h in r.held} == {f"S[{i},{j}]" for i in "xyz" for j in "yz"}
    np.testing.assert_allclose(r.params["S"][:, 0], [1 / 1.1, -0.09 / 1.1, 0.04 / 1.1], atol=2e-3)
    assert r.rmse_norm_uT < 0.1 < float(np.linalg.norm(r.raw_rmse_uT))


def test_exactly_collinear_current_comes_from_the_prior():
    rng = np.random.default_rng(7)
    m = _model(resolve_terms("eq3"))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng)
    d.currents_A = {"a": np.full(N, 0.7)}            # constant current == offset column
    r = fit(d, currents=("a",), options=FitOptions(holdout=False))
    assert {h.name for h in r.held} == {"D_a[x]", "D_a[y]", "D_a[z]"}
    assert all("combination" in h.reason for h in r.held)
    # the data determine the offset + 0.7 D combination; the priors split it
    assert all(r.posterior.determined_by(h.axis, h.column) in ("prior", "data+prior") for h in r.held)


def test_robust_irls_ignores_outliers():
    rng = np.random.default_rng(8)
    m = _model(resolve_terms("eq3"))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng, noise_uT=0.02)
    bad = rng.choice(N, N // 20, replace=False)
    d.b_ref_uT[bad] += rng.normal(0, 30.0, size=(bad.size, 3))
    plain = fit(d, options=FitOptions(holdout=False))
    rob = fit(d, options=FitOptions(holdout=False, robust=True))
    err_p = np.abs(plain.params["S"] - m.unpack(th)["S"]).max()
    err_r = np.abs(rob.params["S"] - m.unpack(th)["S"]).max()
    assert err_r < 1e-3 < err_p


def test_nan_and_flagged_rows_are_excluded_and_counted():
    rng = np.random.default_rng(9)
    m = _model(resolve_terms("eq3"))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng, noise_uT=0.0)
    d.b_meas_uT[5, 1] = np.nan
    d.temp_c[6] = np.nan
    d.b_ref_uT[7, 0] = 1e6  # garbage row, flagged
    d.flag = np.zeros(N, np.int64)
    d.flag[7] = 1
    r = fit(d, options=FitOptions(holdout=False))
    assert r.n_excluded == 3 and r.n_used == N - 3
    assert r.rmse_norm_uT < 1e-9


def test_weights_enter_the_fit():
    rng = np.random.default_rng(10)
    m = _model(("gain_matrix", "offset"))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng, noise_uT=0.0)
    d.b_ref_uT[: N // 2] += 1.0         # first half biased by 1 uT
    d.weights = np.r_[np.zeros(N // 2) + 1e-12, np.ones(N - N // 2)]
    r = fit(d, "gain_offset", options=FitOptions(holdout=False))
    np.testing.assert_allclose(r.params["O"], m.unpack(th)["O"], atol=1e-6)
    with pytest.raises(FitError):
        FitData(d.b_meas_uT, d.b_ref_uT, d.temp_c, d.t_s, d.session, weights=-np.ones(N))


def test_holdout_and_noise_floor_measure_the_injected_noise():
    rng = np.random.default_rng(11)
    m = _model(resolve_terms("eq3") + ("session_offset",), sessions=(1, 2, 3))
    th = random_theta(m, rng)
    d = make_data(m, th, 6000, rng, noise_uT=0.03)
    r = fit(d, terms=("session_offset",))
    assert r.rmse_uT == pytest.approx([0.03] * 3, rel=0.1)
    assert r.noise_floor_uT == pytest.approx([0.03] * 3, rel=0.15)
    assert r.holdout_blocks_uT == pytest.approx([0.03] * 3, rel=0.15)
    assert set(r.holdout_per_session_uT) == {1, 2, 3}
    # an unseen session gets the mean offset: its error is about the size of its own offset step
    assert np.all(r.holdout_sessions_uT > r.rmse_uT)
    text = r.report()
    for word in ("in-sample RMSE", "held-out time blocks", "held-out sessions", "noise floor",
                 "condition number"):
        assert word in text


def test_session_offsets_sum_to_zero_and_absorb_steps():
    rng = np.random.default_rng(12)
    m = _model(("gain_matrix", "offset", "session_offset"), sessions=(4, 9))
    th = random_theta(m, rng)
    d = make_data(m, th, N, rng, noise_uT=0.0)
    r = fit(d, "gain_offset", ("session_offset",), options=FitOptions(holdout=False))
    dO = r.params["dO"]
    np.testing.assert_allclose(dO[4] + dO[9], 0.0, atol=1e-12)
    assert r.rmse_norm_uT < 1e-9


def test_one_session_cannot_fit_session_offsets():
    rng = np.random.default_rng(13)
    m = _model(("gain_matrix", "offset"))
    d = make_data(m, random_theta(m, rng), 500, rng)
    r = fit(d, "gain_offset", ("session_offset",), options=FitOptions(holdout=False))
    assert r.model.n_columns == 4  # a single session gives no contrast columns
    assert "needs at least two sessions" not in r.report()


def test_not_enough_rows():
    rng = np.random.default_rng(14)
    m = _model(resolve_terms("eq3"))
    d = make_data(m, random_theta(m, rng), 8, rng)
    with pytest.raises(FitError, match="not enough data"):
        fit(d)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), noise=st.floats(0.0, 0.1))
def test_property_fit_never_worse_than_truth_in_sample(seed, noise):
    rng = np.random.default_rng(seed)
    m = _model(resolve_terms("eq3", currents=("a",)), ("a",), n=600)
    th = random_theta(m, rng)
    d = make_data(m, th, 600, rng, noise_uT=noise)
    r = fit(d, currents=("a",), options=FitOptions(holdout=False))
    X = m.design(d.b_meas_uT, d.temp_c, d.currents_A, d.session, d.t_s)
    sse_true = np.sum((d.b_ref_uT - m.predict(th, X)) ** 2, axis=0)
    sse_fit = np.sum((d.b_ref_uT - r.model.predict(r.theta, X)) ** 2, axis=0)
    assert np.all(sse_fit <= sse_true * (1 + 1e-9) + 1e-18)


def test_streaming_equals_batch():
    rng = np.random.default_rng(15)
    terms = ("gain_matrix", "temperature_gain", "offset", "temperature_offset", "currents", "cubic",
             "session_offset", "drift")
    m = _model(terms, ("a", "b"), (1, 2), n=5000)
    th = random_theta(m, rng)
    d = make_data(m, th, 5000, rng, noise_uT=0.02)
    batch = fit(d, "eq3", ("cubic", "session_offset", "drift"), ("a", "b"), options=FitOptions(holdout=False))
    sf = StreamingFit(batch.model)
    for k in range(0, 5000, 777):
        s = slice(k, k + 777)
        sf.add(d.b_meas_uT[s], d.b_ref_uT[s], d.temp_c[s], {n: v[s] for n, v in d.currents_A.items()},
               d.session[s], d.t_s[s])
    res = sf.solve()
    np.testing.assert_allclose(res.theta, batch.theta, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(res.rmse_uT, batch.rmse_uT, rtol=1e-6)
    assert sf.state_bytes == (batch.model.n_columns + 3) ** 2 * 8 + 24


def test_streaming_refuses_batch_only_features():
    m = CalModel(("gain_matrix", "offset", "time_skew"))
    with pytest.raises(FitError, match="batch-only"):
        StreamingFit(m)
    with pytest.raises(FitError, match="batch-only"):
        StreamingFit(CalModel(("gain_matrix", "offset")), FitOptions(robust=True))
    sf = StreamingFit(CalModel(("gain_matrix", "offset", "session_offset"), sessions=(1, 2)))
    with pytest.raises(FitError, match="not declared"):
        sf.add(np.zeros((2, 3)), np.zeros((2, 3)), session=[1, 5])


def test_time_derivative_and_time_skew_recovery():
    t = np.arange(100) * 0.5
    b = np.column_stack([np.sin(t), 2 * t, np.zeros_like(t)])
    d = time_derivative(b, t, np.zeros(100))
    np.testing.assert_allclose(d[1:-1, 1], 2.0)
    np.testing.assert_allclose(d[1:-1, 0], (np.sin(t[2:]) - np.sin(t[:-2])) / 1.0)
    # a gap breaks the run: one-sided differences at its edges, never across it
    t2 = np.r_[t[:50], t[50:] + 100.0]
    d2 = time_derivative(np.column_stack([t2, t2, t2]), t2)
    np.testing.assert_allclose(d2[:, 0], 1.0)


def test_reference_steps_marks_both_sides_of_a_transition():
    ref = np.zeros((6, 3))
    ref[3:, 0] = 10.0
    m = reference_steps(ref, np.zeros(6, np.int64), 0.1)
    assert m.tolist() == [False, False, True, True, False, False]


def test_noise_floor_ignores_slow_misfit():
    rng = np.random.default_rng(16)
    t = np.arange(20000) * 0.25
    r = np.column_stack([0.5 * np.sin(t / 300.0)] * 3) + rng.normal(0, 0.04, (20000, 3))
    nf = noise_floor(r, t, np.zeros(20000, np.int64), 1.0)
    assert nf == pytest.approx([0.04] * 3, rel=0.05)


def test_bad_options_raise():
    with pytest.raises(FitError):
        FitOptions(on_unidentifiable="maybe")
    with pytest.raises(FitError):
        FitOptions(min_temp_span_c=float("nan"))
    with pytest.raises(FitError, match="multiple of 0.01"):
        CalModel(("gain_matrix",), t0_c=25.001)
    with pytest.raises(FitError, match="gain_matrix"):
        CalModel(("offset",))


def test_parameter_names_are_unique_per_used_coefficient():
    m = CalModel(ALL, ("a",), (1, 2))
    mask = m.axis_mask()
    names = [m.param_name(i, c) for i in range(3) for c in range(m.n_columns) if mask[i, c]]
    assert len(names) == len(set(names))
    assert {"c3[x]", "c3[y]", "c3[z]", "P[y,xz]", "tau[z,x]", "D_a[y]", "dO_s2[x]", "r[z]"} <= set(names)


def _staircase(rng, n=1200, plateau=8, miss=True):
    """Reference staircase on all axes (+-5 uT steps every ``plateau`` rows, 10 nT noise); the DUT
    reads the reference through a gain and, when ``miss``, still the old plateau on the first row of
    half the new plateaus (two clocks that cannot be paired sample-exactly across a step)."""
    k = np.arange(n)
    levels = rng.uniform(-40, 40, size=(n // plateau + 1, 3))
    ref = levels[k // plateau] + rng.normal(0, 0.01, (n, 3))
    dut = ref.copy()
    if miss:
        first = (k % plateau == 0) & (k > 0) & (rng.random(n) < 0.5)
        dut[first] = ref[np.flatnonzero(first) - 1]
    dut = dut @ np.diag([1.1, 0.9, 1.05]).T + 0.3
    return FitData(dut, ref, np.full(n, 25.0), np.arange(n) * 0.5, np.zeros(n, np.int64))


def test_step_diagnosis_names_transition_rows_and_suggests_excluding_them():
    rng = np.random.default_rng(21)
    d = _staircase(rng)
    r = fit(d, "gain_offset")
    st = r.steps
    assert st is not None and st.dominant
    assert st.n_step == pytest.approx(2 * 1200 / 8, rel=0.05)          # both sides of every step
    assert np.linalg.norm(st.step_rms_uT) > 10 * np.linalg.norm(st.steady_rms_uT)
    assert f"--exclude-steps {st.threshold_uT:.2g}" in r.report()
    ex = fit(d, "gain_offset", options=FitOptions(exclude_ref_steps_uT=st.threshold_uT))
    assert ex.steps is None and ex.n_excluded_steps == st.n_step
    assert f"+ {st.n_step} at reference steps" in ex.report()
    assert ex.rmse_norm_uT < 0.5 * r.rmse_norm_uT
    # exactly paired steps: the split is reported but nothing is suggested
    clean = fit(_staircase(rng, miss=False), "gain_offset")
    assert clean.steps is not None and not clean.steps.dominant and "--exclude-steps" not in clean.report()
    # a smooth field has no steps to diagnose
    m = _model(("gain_matrix", "offset"))
    smooth = make_data(m, random_theta(m, rng), 500, rng)
    assert diagnose_steps(np.zeros((500, 3)), smooth.b_ref_uT, smooth.session) is None
