"""Attitude-independent scalar calibration (firmware_py/calibration/scalar.py) and the refit entry point."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from magstack.firmware.cal_table import load_table, save_table, validate
from magstack.firmware.calibration.scalar import fit_scalar, oriented_normal, refit_scalar
from magstack.firmware.errors import FitError
from magstack.ground.studies.riwanto import TRUTH_OFF_NT, TRUTH_S_MC, PaperModel, simulate

S_TRUE = np.array([[1.08, 0.04, -0.03], [-0.05, 0.93, 0.06], [0.02, -0.07, 1.12]])
OFF_TRUE_UT = np.array([3.2, -1.5, 7.9])


def _sphere(n: int, seed: int, varying: bool):
    """Noiseless data: uniform directions, |b| constant 45 uT or 20..60 uT; b_meas = S (b + off)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    mag = rng.uniform(20.0, 60.0, n) if varying else np.full(n, 45.0)
    b = d * mag[:, None]
    return (b + OFF_TRUE_UT) @ S_TRUE.T, b


@pytest.mark.parametrize("varying", [False, True])
def test_noiseless_reference_gauge_recovers_truth(varying):
    b_meas, b = _sphere(400, 1, varying)
    fit = fit_scalar(b_meas, b, gauge="reference")
    assert fit.rms_residual < 1e-9
    np.testing.assert_allclose(fit.K, np.linalg.inv(S_TRUE), atol=1e-9)
    np.testing.assert_allclose(fit.k, OFF_TRUE_UT, atol=1e-8)


def test_symmetric_gauge_fixes_shape_and_centre_only():
    b_meas, b = _sphere(300, 2, False)
    fit = fit_scalar(b_meas, np.linalg.norm(b, axis=1))
    K = np.linalg.inv(S_TRUE)
    np.testing.assert_allclose(fit.K, fit.K.T, atol=1e-12)
    assert np.linalg.eigvalsh(fit.K).min() > 0
    np.testing.assert_allclose(fit.K.T @ fit.K, K.T @ K, atol=1e-9)                  # A = K^T K
    np.testing.assert_allclose(np.linalg.solve(fit.K, fit.k), S_TRUE @ OFF_TRUE_UT, atol=1e-8)  # centre K^-1 k
    # the answer is the truth up to a rotation: Q = K_fit K_true^-1 is proper orthogonal
    Q = fit.K @ S_TRUE
    np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(Q) == pytest.approx(1.0, abs=1e-9)


def test_lower_triangular_and_prior_gauges():
    Kt = np.array([[0.95, 0.0, 0.0], [0.04, 1.06, 0.0], [-0.03, 0.05, 0.9]])
    b_meas, b = _sphere(300, 3, True)
    b_meas = b @ np.linalg.inv(Kt).T + 1.0      # K b_meas - k = b with k = K @ [1, 1, 1]
    k_true = Kt @ np.ones(3)
    r = np.linalg.norm(b, axis=1)
    tri = fit_scalar(b_meas, r, gauge="lower_triangular")
    np.testing.assert_allclose(tri.K, Kt, atol=1e-9)
    np.testing.assert_allclose(tri.k, k_true, atol=1e-8)
    R = Rotation.from_euler("xyz", [3.0, -2.0, 5.0], degrees=True).as_matrix()
    pri = fit_scalar(b_meas, r, gauge="prior", K_prior=R @ Kt)
    np.testing.assert_allclose(pri.K, R @ Kt, atol=1e-9)


def test_axes_gauge_two_great_circles_noiseless():
    """Two great circles do not determine an ellipsoid from magnitudes alone (every quadric
    sphere + mu x y contains both); the axis residuals must fix it."""
    d = simulate(PaperModel(3, 2, (35000.0, 35000.0), 0.0), np.random.default_rng(0))
    fit = fit_scalar(d.b_meas_nT, d.b_ref_norm_nT, gauge="axes", locus=d.locus, omega=d.omega)
    np.testing.assert_allclose(np.linalg.inv(fit.K), TRUTH_S_MC, atol=1e-6)
    np.testing.assert_allclose(fit.k, TRUTH_OFF_NT, atol=1e-3)


def test_oriented_normal_follows_sample_order():
    t = np.linspace(0, 1.5 * np.pi, 40)
    ring = np.c_[np.cos(t), np.sin(t), np.full_like(t, 0.3)] * 50 + [5.0, -2.0, 1.0]
    np.testing.assert_allclose(oriented_normal(ring), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(oriented_normal(ring[::-1]), [0, 0, -1], atol=1e-12)


@pytest.mark.parametrize("kw, msg", [
    ({"b_meas": np.zeros((20, 2))}, "shape"),
    ({"b_meas": np.ones((5, 3)), "b_ref": np.ones(5)}, "at least 12"),
    ({"b_ref": -np.ones(30)}, "positive"),
    ({"gauge": "bogus"}, "unknown gauge"),
    ({"gauge": "reference"}, "vectors"),
    ({"gauge": "prior"}, "K_prior"),
    ({"gauge": "prior", "K_prior": np.eye(2)}, "3x3"),
    ({"gauge": "axes"}, "locus"),
])
def test_bad_inputs_raise_fit_error(kw, msg):
    b_meas, b = _sphere(30, 4, False)
    args = {"b_meas": b_meas, "b_ref": np.linalg.norm(b, axis=1), **kw}
    with pytest.raises(FitError, match=msg):
        fit_scalar(args.pop("b_meas"), args.pop("b_ref"), **args)


def test_refit_scalar_table_round_trip(tmp_path):
    rng = np.random.default_rng(7)
    b_meas, b = _sphere(500, 5, True)
    b_meas = b_meas + rng.normal(0, 0.05, b_meas.shape)
    res = refit_scalar(b_meas, b, gauge="reference")
    assert res.method == "scalar" and res.gauge == "reference"
    assert res.rms_residual_uT < 0.1 < res.rms_raw_uT
    table = res.to_table("dut-1", created_utc="2026-01-01T00:00:00Z")
    assert validate(table).ok, validate(table).problems
    back = load_table(save_table(table, tmp_path / "cand.json"))
    np.testing.assert_allclose(back.S, res.S)
    np.testing.assert_allclose(back.O, res.O_uT)
    b_cal = b_meas @ back.S.T + back.O
    assert np.sqrt(np.mean(np.sum((b_cal - b) ** 2, axis=1))) < 0.2
    assert back.fit_stats["method"] == "attitude-independent scalar"


def test_refit_scalar_default_gauge_and_method_errors():
    b_meas, b = _sphere(60, 6, False)
    r = np.linalg.norm(b, axis=1)
    assert refit_scalar(b_meas, r).gauge == "symmetric"
    assert refit_scalar(b_meas, r, K_prior=np.eye(3)).gauge == "prior"
    with pytest.raises(FitError, match="method"):
        refit_scalar(b_meas, r, method="ekf")
    with pytest.raises(FitError, match="locus"):
        refit_scalar(b_meas, r, method="pso")


def test_refit_pso_method_works_in_uT():
    """The PSO runs in nT internally (the paper's weights); refit_scalar takes and returns uT."""
    d = simulate(PaperModel(1, 3, (35000.0, 35000.0), 200.0), np.random.default_rng(5))
    res = refit_scalar(d.b_meas_nT / 1e3, d.b_ref_norm_nT / 1e3, method="pso", locus=d.locus,
                       omega_body=d.omega, seed=3)
    assert res.method == "pso" and res.gauge == "axes" and np.isfinite(res.fitness)
    assert np.linalg.norm(np.linalg.inv(res.S) - TRUTH_S_MC) < 0.05
    assert np.linalg.norm(res.O_uT + TRUTH_OFF_NT / 1e3) < 0.5
    assert res.rms_residual_uT < 0.5 < res.rms_raw_uT
    with pytest.raises(FitError, match="gauge"):
        refit_scalar(d.b_meas_nT / 1e3, d.b_ref_norm_nT / 1e3, method="pso", locus=d.locus, omega_body=d.omega,
                     gauge="symmetric")


def test_single_rotation_plane_is_refused():
    """Points on one circle fit many ellipsoids exactly: refuse rather than return one of them."""
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    b = np.c_[np.cos(t), np.sin(t), 0 * t] * 40
    b_meas = b @ np.diag([1.1, 0.9, 1.0]).T + [2.0, 3.0, 4.0]
    with pytest.raises(FitError, match="determine|ellipsoid"):
        fit_scalar(b_meas, 40.0)
    noisy = b_meas + np.random.default_rng(0).normal(0, 0.5, b_meas.shape)
    with pytest.raises(FitError, match="determine|ellipsoid"):
        fit_scalar(noisy, 40.0)


def test_standard_errors_scale_with_noise_where_determined():
    b_meas, b = _sphere(400, 8, False)
    r = np.linalg.norm(b, axis=1)
    rng = np.random.default_rng(1)
    se = [fit_scalar(b_meas + rng.normal(0, s, b_meas.shape), r).se_params for s in (0.01, 0.1)]
    assert np.all(np.isfinite(se[0])) and se[0].shape == (9,)
    np.testing.assert_allclose(se[1] / se[0], 10.0, rtol=0.3)


def test_real_bench_data_magnitude_fit_beats_vector_fit_on_magnitude():
    """AV-MagEval tests 3-7 (tests/data/av-mageval, step rows excluded as in the vector fit): the
    scalar fit must reach a magnitude residual at least as small as the vector gain+offset fit's
    (it minimises exactly that), and its diagonal scale must agree with the vector fit's. The
    cross terms need not: the coil sweeps run along the axes (docs/refit-pso.md)."""
    from pathlib import Path

    from magstack.data.session import Session
    from magstack.firmware.calibration import FitData, FitOptions, fit
    from magstack.firmware.calibration.fit import reference_steps
    from magstack.ground import mageval_import as mi

    pairs = {3: ("data2.csv", "ref3.csv"), 4: ("data3.csv", "ref4.csv"), 5: ("data5.csv", "ref5.csv"),
             6: ("data6.csv", "ref6.csv"), 7: ("data7.csv", "ref7.csv")}
    root = Path(__file__).parent / "data" / "av-mageval"
    parts = [mi.import_mageval(root / d, root / r, session_id=n, onto=0.25, clock_offset_s=mi.AUTHORS_OFFSET_S)
             for n, (d, r) in pairs.items()]
    fd = FitData.from_session(Session.concatenate(parts))
    keep = ~reference_steps(fd.b_ref_uT, fd.session, 0.1)
    b_meas, b_ref = fd.b_meas_uT[keep], fd.b_ref_uT[keep]
    vec = fit(fd, "gain_offset", options=FitOptions(exclude_ref_steps_uT=0.1))
    p = vec.model.unpack(vec.theta)
    r = np.linalg.norm(b_ref, axis=1)
    vec_mag_rms = np.sqrt(np.mean((np.linalg.norm(b_meas @ p["S"].T + p["O"], axis=1) - r) ** 2))
    sc = fit_scalar(b_meas, r)
    assert sc.rms_residual <= vec_mag_rms + 1e-9
    assert sc.rms_residual < 0.1 < sc.rms_raw                    # uT
    A_vec, A_sc = p["S"].T @ p["S"], sc.K.T @ sc.K
    np.testing.assert_allclose(np.diag(A_sc), np.diag(A_vec), rtol=0.06)


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), varying=st.booleans())
def test_any_well_conditioned_noiseless_problem_is_recovered(seed, varying):
    """Random gain (cond <= ~3, det > 0), offsets up to 50 uT, 200 random directions."""
    rng = np.random.default_rng(seed)
    Q = Rotation.random(random_state=rng).as_matrix()
    S = Q @ np.diag(rng.uniform(0.6, 1.8, 3)) @ Rotation.random(random_state=rng).as_matrix()
    off = rng.uniform(-50, 50, 3)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = d * (rng.uniform(20, 60, 200) if varying else np.full(200, 45.0))[:, None]
    b_meas = (b + off) @ S.T
    fit = fit_scalar(b_meas, b, gauge="reference")
    np.testing.assert_allclose(fit.K, np.linalg.inv(S), atol=1e-7)
    np.testing.assert_allclose(fit.k, off, atol=1e-5)


def _random_loci(rng):
    """Random gain/offset and 2-3 loci about random axes, field on a 40-90 deg cone, 150-360 deg arcs."""
    S = Rotation.random(random_state=rng).as_matrix() @ np.diag(rng.uniform(0.6, 1.8, 3)) \
        @ Rotation.random(random_state=rng).as_matrix()
    off = rng.uniform(-50, 50, 3)
    n_loci = int(rng.integers(2, 4))
    axes = Rotation.random(n_loci, random_state=rng).apply([0.0, 0.0, 1.0])
    b, lab = [], []
    for l in range(n_loci):
        cone = np.deg2rad(rng.uniform(40, 90))
        perp = np.cross(axes[l], rng.normal(size=3))
        perp /= np.linalg.norm(perp)
        b0 = (np.cos(cone) * axes[l] + np.sin(cone) * perp) * 45.0
        turn = np.linspace(0, np.deg2rad(rng.uniform(150, 360)), 40)
        b.append(Rotation.from_rotvec(-turn[:, None] * axes[l]).apply(b0))
        lab += [l] * 40
    b = np.vstack(b)
    return S, off, b, np.array(lab), axes


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_axes_gauge_recovers_general_loci_noiseless(seed):
    """Two or three loci about random axes, the field on a cone of 40-90 deg round each axis (small
    circles, as on orbit), arcs of 150-360 deg: the 12 parameters are recovered exactly. (A probe
    of 600 such draws found one failure with a single least-squares start; two starts fix it.)"""
    rng = np.random.default_rng(seed)
    S, off, b, lab, axes = _random_loci(rng)
    fit = fit_scalar((b + off) @ S.T, b, gauge="axes", locus=lab, omega=axes)
    np.testing.assert_allclose(fit.K, np.linalg.inv(S), atol=1e-6)
    np.testing.assert_allclose(fit.k, off, atol=1e-4)


def test_two_small_circles_need_more_than_one_start():
    """Regression (probe seed 23): two cones of 41 and 72 deg about axes 54 deg apart; the joint
    cost's valley along the quadric pencil is about 0.001 rad wide, and the best coarse start
    alone converged to a reflection."""
    rng = np.random.default_rng(23)
    S, off, b, lab, axes = _random_loci(rng)
    assert len(axes) == 2
    fit = fit_scalar((b + off) @ S.T, b, gauge="axes", locus=lab, omega=axes)
    np.testing.assert_allclose(fit.K, np.linalg.inv(S), atol=1e-6)
