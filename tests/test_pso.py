"""Riwanto PSO (firmware_py/calibration/pso.py): schedule, plane fit sign, mirror fix, determinism, model 1."""
from __future__ import annotations

import numpy as np
import pytest

from magstack.firmware.calibration import pso
from magstack.firmware.errors import FitError
from magstack.ground.studies.riwanto import (
    PAPER_MODELS,
    TRUTH_OFF_NT,
    TRUTH_S_MC,
    _generators,
    run_paper_model,
    simulate,
)

TRUTH_P = np.r_[np.linalg.inv(TRUTH_S_MC).ravel(), TRUTH_OFF_NT]


def _problem(model=1, seed=0, sign_rule="area"):
    rng, _ = _generators(seed)
    d = simulate(PAPER_MODELS[model], rng)
    return pso.Problem.build(d.b_meas_nT, d.b_ref_norm_nT, d.locus, d.omega, sign_rule)


def test_table_i_defaults_and_velocity_limit():
    o = pso.PsoOptions()
    assert (o.n_particles, o.k_max, o.v_lim, o.cf1, o.cf2) == (35, 500, 50.0, 1.0, 4e4)
    np.testing.assert_allclose(o.vmax, np.r_[np.full(9, 2 / 50), np.full(3, 10000 / 50)])   # eq. (6)


def test_schedule_reading_of_fig2():
    o = pso.PsoOptions(k_max=100, w_v_frac=0.1, c_v_frac=0.1, n_cycles=3)
    w, c1, c2 = pso.schedule(o)
    assert len(w) == len(c1) == len(c2) == 100
    for start in (0, 20, 40):                      # three cycles of 10 + 10 iterations
        assert (w[start], c1[start], c2[start]) == (5.0, 4.0, 0.0)
        assert w[start + 9] == pytest.approx(0.5)  # w ramp ends at w_f ...
        assert np.all(np.diff(w[start:start + 10]) < 0)
        assert (c1[start + 9], c2[start + 9]) == (4.0, 0.0)          # ... before c1, c2 move
        assert c1[start + 19] == pytest.approx(2.0) and c2[start + 19] == pytest.approx(2.0)
    assert np.all(w[60:] == 0.382) and np.all(c1[60:] == 2.5) and np.all(c2[60:] == 2.5)


@pytest.mark.parametrize("sign_rule", pso.SIGN_RULES)
def test_plane_normal_sign_follows_right_hand_rule(sign_rule):
    """A locus traversed counter-clockwise about +z (seen from +z) has normal +z; reversed, -z.
    Off-origin centre, partial arc and noise; batched over particles."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 2.0, 30)                  # 115 degrees
    ring = np.c_[np.cos(t), np.sin(t), np.zeros_like(t)] * 30000 + [2000.0, -500.0, 8000.0]
    pts = np.stack([ring + rng.normal(0, 300, ring.shape) for _ in range(4)])
    n = pso.plane_normals(pts, sign_rule, 10)
    assert np.all(n[:, 2] > 0.99)
    n_rev = pso.plane_normals(pts[:, ::-1], sign_rule, 10)
    assert np.all(n_rev[:, 2] < -0.99)


def test_locus_normal_is_minus_omega_at_truth():
    """Body turning positively about omega: the field turns the other way, normal = -omega (eq. 9)."""
    prob = _problem(1, 0)
    K, k = pso.unpack(TRUTH_P)
    b_hat = prob.b_meas_nT @ K.T - k
    for idx, om in zip(prob.groups, prob.omega_hat, strict=True):
        n = pso.plane_normals(b_hat[idx][None], "area")[0]
        assert n @ om < -0.999


def test_mirror_pair_has_equal_fitness_and_fix_flips_matrix_and_offset():
    prob = _problem(1, 0)
    o = pso.PsoOptions()
    f = pso.fitness(np.stack([TRUTH_P, -TRUTH_P]), prob, o)
    assert f[0] == pytest.approx(f[1], rel=1e-12)
    K, k = pso.unpack(-TRUTH_P)
    K2, k2, flipped = pso.mirror_fix(K, k)
    assert flipped
    np.testing.assert_allclose(K2, np.linalg.inv(TRUTH_S_MC))
    np.testing.assert_allclose(k2, TRUTH_OFF_NT)                  # eq. (11) alone would leave -off
    K3, k3, flipped3 = pso.mirror_fix(K2, k2)
    assert not flipped3 and K3 is K2 and k3 is k2


def test_seeded_runs_are_bit_identical_and_seed_matters():
    prob = _problem(1, 0)
    o = pso.PsoOptions(k_max=60)
    a = pso.run_pso(prob, seed=11, options=o)
    b = pso.run_pso(prob, seed=11, options=o)
    c = pso.run_pso(prob, seed=12, options=o)
    np.testing.assert_array_equal(a.K, b.K)
    np.testing.assert_array_equal(a.k_nT, b.k_nT)
    np.testing.assert_array_equal(a.history, b.history)
    assert not np.array_equal(a.history, c.history)
    assert np.all(np.diff(a.history) <= 0)                        # global best never gets worse
    assert a.n_evaluations == 35 * 61


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_model1_reaches_noise_floor(seed):
    """Model 1 (3 circles, delta 2000 nT, 100 samples): the fitness noise floor is
    delta / sqrt(n) = 200 with a sampling spread of about 200 / sqrt(200) = 14; measured over
    seeds 0-19 (docs/refit-pso.md) the PSO gave 159-228 and ended below the fitness of the true
    parameters in 19 of 20 runs (worst +11). Bounds: 200 +- 50 (3.5 sigma) and at most 15 above
    the truth's fitness on the same data."""
    r = run_paper_model(1, seed).to_dict()
    assert 150.0 < r["fitness"] < 250.0
    assert r["fitness"] < r["fitness_at_truth"] + 15.0
    assert r["dS_fro"] < 0.15 and r["doff_nT"] < 2500.0          # paper M1: 0.073, 720 nT
    assert np.linalg.det(np.array(r["K_m"])) > 0
    # seed 2's swarm converged on the mirror twin (-K, -k): the offset bound above holds only
    # because the fix flips k with K (flipping K alone would leave |d off| ~ 25 000 nT)
    assert r["mirrored"] == (seed == 2)


def test_problem_input_checks():
    prob = _problem(1, 0)
    b, r = prob.b_meas_nT, prob.b_ref_norm_nT
    with pytest.raises(FitError, match="two loci"):
        pso.Problem.build(b, r, np.zeros(len(b), int), np.eye(3))
    with pytest.raises(FitError, match="integer"):
        pso.Problem.build(b, r, np.zeros(len(b)), np.eye(3))
    with pytest.raises(FitError, match="omega"):
        pso.Problem.build(b, r, np.arange(len(b)) % 3, np.eye(2))
    with pytest.raises(FitError, match="sign_rule"):
        pso.PsoOptions(sign_rule="left")
    with pytest.raises(FitError, match="sign_rule"):
        pso.run_pso(prob, options=pso.PsoOptions(sign_rule="pair"))


def test_paper_pair_rule_fails_off_centre_area_rule_does_not():
    """The paper's step 6 uses uncentred vectors: when the circle's in-plane centre is far from
    the origin (large offset, small circle) b_1 x b_q can point the wrong way. Documented in
    docs/refit-pso.md; the default area rule uses the centred polygon."""
    t = np.linspace(np.pi / 2, np.pi, 20)          # quarter arc, counter-clockwise about +z
    arc = np.c_[np.cos(t), np.sin(t), np.zeros_like(t)] * 1000 + [5000.0, 0.0, 300.0]
    assert pso.plane_normals(arc[None], "area")[0, 2] > 0.99
    assert pso.plane_normals(arc[None], "pair", 19)[0, 2] < -0.99


def test_pair_index_stays_within_half_a_turn_for_anisotropic_sensors():
    """The automatic q of the paper's pair rule must lie between 0 and 180 degrees of true turn
    (a q at 270 degrees reverses the sign; an anisotropic S can make it look like the best pair)."""
    # uneven steps: the sample at 270 deg is further from the first one's line than any in the
    # first half-turn (sin 80 deg < sin 270 deg in size), which fooled a largest-|u_1 x u_q| choice
    ang = np.deg2rad([0, 40, 80, 120, 160, 200, 230, 270, 300, 330.0])
    ring = np.c_[np.cos(ang), np.sin(ang), np.zeros_like(ang)] * 35000
    for S in (np.eye(3), np.diag([3.0, 0.4, 1.0]), TRUTH_S_MC,
              np.array([[0.3, 2.0, 0], [-1.5, 0.2, 0], [0, 0, 1.0]])):
        b = (ring + [12600.0, -200.0, 1800.0]) @ S.T
        (q,) = pso.pair_indices(b, [np.arange(len(b))])
        assert 0 < np.rad2deg(ang[q]) < 180
        # the oriented normal of the mapped circle is along det(S) S^-T e_z (cofactor of S)
        cof_z = np.linalg.det(S) * np.linalg.solve(S.T, [0.0, 0.0, 1.0])
        assert pso.plane_normals(b[None], "pair", q)[0] @ cof_z > 0


def test_plane_normal_equals_algorithm_3_svd():
    """Our batched eigh of the scatter matrix gives the paper's U[:, argmin S] of A = [b_s - b_mean]."""
    rng = np.random.default_rng(9)
    pts = rng.normal(size=(5, 40, 3)) * [30000.0, 20000.0, 3000.0] + rng.normal(size=(5, 1, 3)) * 10000
    ours = pso.plane_normals(pts, "area")
    for p, n in zip(pts, ours, strict=True):
        A = (p - p.mean(axis=0)).T                         # 3 x n, Algorithm 3 step 2
        U, s, _ = np.linalg.svd(A)                         # step 3
        ref = U[:, np.argmin(s)]                           # steps 4-5
        assert abs(abs(ref @ n) - 1.0) < 1e-12


def test_center_seeds_one_particle_algorithm_2():
    """With ``center`` (Algorithm 2 initialisation) one particle starts on it, so even one
    iteration ends no worse than the centre's fitness."""
    prob = _problem(1, 0)
    o = pso.PsoOptions(k_max=1)
    r = pso.run_pso(prob, seed=5, options=o, center=TRUTH_P)
    assert r.fitness <= pso.fitness(TRUTH_P, prob, o)[0]
    far = pso.run_pso(prob, seed=5, options=o)                     # paper box around 0: far from truth
    assert far.fitness > 10 * r.fitness
