"""A table's predictive uncertainty and validity region (firmware/cal_uncertainty.py): the parts add as
documented, the worst case over a field box is at its corners, and the region keeps its promise everywhere
inside it (checked by brute force on a dense grid)."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from magstack.firmware.cal_uncertainty import Predictive, features, validity_region

T0_C = 25.0
LIMITS_C = (-40.0, 85.0)


def _posterior(seed: int, *, left_out: bool = True, disc: bool = True) -> dict:
    """A random posterior with linear and temperature parameters on every axis (and left-out ones: K_S2 and a
    cross product), noise and discrepancy."""
    rng = np.random.default_rng(seed)
    out: dict = {}
    left = []
    for a in "xyz":
        names = [f"S[{a},{j}]" for j in "xyz"] + [f"K_S[{a},{j}]" for j in "xyz"] + [f"O[{a}]", f"K_O[{a}]"]
        scale = [1e-4] * 3 + [3e-6] * 3 + [5e-3, 2e-4]
        if left_out:
            names += [f"K_S2[{a}]", f"P[{a},xy]"]
            scale += [3e-7, 1e-6]
            left += [f"K_S2[{a}]", f"P[{a},xy]"]
        A = rng.normal(size=(len(names), len(names))) * np.array(scale)
        out[a] = {"names": names, "cov": (A @ A.T).tolist()}
    out["noise_uT"] = [0.02, 0.03, 0.025]
    if left_out:
        out["left_out"] = left
    if disc:
        out["discrepancy"] = {"d0_uT2": [1e-4, 4e-4, 2e-4], "dB_uT2": [1e-4, 0.0, 3e-4], "dT_uT2": [0.0, 2e-4, 1e-4],
                              "field_ref_uT": 50.0, "temp_ref_c": 10.0, "temp_centre_c": 25.0,
                              "temp_range_c": [20.0, 30.0], "field_max_uT": 60.0}
    return out


def test_the_parts_add_up_and_each_is_what_the_docstring_says():
    post = _posterior(0)
    pred = Predictive(post, T0_C)
    rng = np.random.default_rng(1)
    b = rng.uniform(-80, 80, size=(50, 3))
    t = rng.uniform(0, 60, size=50)
    sd = pred.sd_axes_uT(b, t)
    par, disc = pred.param_var_uT2(b, t), pred.disc_var_uT2(b, t)
    np.testing.assert_allclose(sd ** 2, par + disc + np.array(post["noise_uT"]) ** 2)
    for i, a in enumerate("xyz"):           # parameter part: f' C f over the table's and the left-out features
        F = features(post[a]["names"], b, t - T0_C)
        quad = np.einsum("nk,kl,nl->n", F, np.array(post[a]["cov"]), F)
        np.testing.assert_allclose(par[:, i], quad, rtol=1e-12, atol=1e-15)
    # discrepancy: clamped to the data's field and temperature range
    d = post["discrepancy"]
    mag = np.minimum(np.linalg.norm(b, axis=1), 60.0) / 50.0
    u = (np.clip(t, 20.0, 30.0) - 25.0) / 10.0
    want = (np.array(d["d0_uT2"]) + np.array(d["dB_uT2"]) * (mag ** 2)[:, None]
            + np.array(d["dT_uT2"]) * (u ** 2)[:, None])
    np.testing.assert_allclose(disc, want)


def test_a_table_without_the_newer_keys_gives_the_parameter_part_only():
    post = _posterior(3, left_out=False, disc=False)
    del post["noise_uT"]
    pred = Predictive(post, T0_C)
    assert not pred.complete
    b = np.array([[10.0, -20.0, 30.0]])
    np.testing.assert_allclose(pred.sd_axes_uT(b, [30.0]) ** 2, pred.param_var_uT2(b, [30.0]))


@pytest.mark.parametrize("seed", range(3))
def test_the_worst_case_over_a_field_box_is_at_its_corners(seed):
    """Exact at the corners for features affine in the field and with a cross product (affine along every
    coordinate line); with a magnitude limit it is the region's maximum to the sphere sampling's spacing."""
    g = np.linspace(-1, 1, 9)
    F = np.array([40.0, 25.0, 55.0])
    pts = np.array(list(itertools.product(g, g, g))) * F
    for left_out in (False, True):
        pred = Predictive(_posterior(seed, left_out=left_out), T0_C)
        for t in (5.0, 25.0, 47.0):
            corner = pred.worst_vector_sd_uT(t, F)
            dense = np.sqrt(np.max(np.sum(pred.sd_axes_uT(pts, np.full(len(pts), t)) ** 2, axis=1)))
            assert corner == pytest.approx(dense, rel=1e-9)
    pred = Predictive(_posterior(seed, left_out=False), T0_C)
    R = 45.0
    ball = pts[np.linalg.norm(pts, axis=1) <= R]
    u = np.random.default_rng(seed).normal(size=(4000, 3))
    sphere = np.clip(R * u / np.linalg.norm(u, axis=1)[:, None], -F, F)
    inside = np.vstack([ball, sphere])
    dense = np.sqrt(np.max(np.sum(pred.sd_axes_uT(inside, np.full(len(inside), 30.0)) ** 2, axis=1)))
    assert pred.worst_vector_sd_uT(30.0, F, R) == pytest.approx(dense, rel=1e-2)    # 192 directions: ~1 %


@pytest.mark.parametrize("seed", range(3))
def test_a_cubic_term_is_searched_inside_the_box_too(seed):
    """``c3`` is not convex along its axis: its worst case can lie inside the box, on the inner shells."""
    post = _posterior(seed, left_out=False)
    rng = np.random.default_rng(100 + seed)
    for a in "xyz":
        names = post[a]["names"] + [f"c3[{a}]"]
        A = rng.normal(size=(len(names), len(names))) * np.array([1e-4] * 3 + [3e-6] * 3 + [5e-3, 2e-4, 1e-7])
        post[a] = {"names": names, "cov": (A @ A.T).tolist()}
    pred = Predictive(post, T0_C)
    F = np.array([40.0, 25.0, 55.0])
    g = np.linspace(-1, 1, 21)
    pts = np.array(list(itertools.product(g, g, g))) * F
    for t in (5.0, 47.0):
        dense = np.sqrt(np.max(np.sum(pred.sd_axes_uT(pts, np.full(len(pts), t)) ** 2, axis=1)))
        assert dense <= pred.worst_vector_sd_uT(t, F) * 1.01


def _check_region(pred, bound, tbox, F, R):
    """Brute force: twice the vector sd within the bound on a dense grid of the region (box and ball)."""
    g = np.linspace(-1, 1, 7)
    pts = np.array(list(itertools.product(g, g, g))) * F
    pts = pts[np.linalg.norm(pts, axis=1) <= R]
    u = np.random.default_rng(0).normal(size=(2000, 3))
    pts = np.vstack([pts, np.clip(R * u / np.linalg.norm(u, axis=1)[:, None], -F, F)])
    for t in np.linspace(tbox[0], tbox[1], 41):
        v = np.sqrt(np.sum(pred.sd_axes_uT(pts, np.full(len(pts), t)) ** 2, axis=1))
        assert 2 * v.max() <= bound * 1.01      # the sphere is sampled by 192 directions: ~1 %


def _region(pred, bound, **kw):
    args = dict(centre_c=25.0, data_temp_c=(20.0, 30.0), data_field_uT=np.array([50.0, 50.0, 50.0]),
                data_norm_uT=60.0, temp_limits_c=LIMITS_C, field_caps_uT=np.array([100.0, 100.0, 100.0]),
                norm_cap_uT=120.0)
    args.update(kw)
    return validity_region(pred, bound, **args)


@pytest.mark.parametrize("seed", range(3))
def test_the_region_keeps_its_bound_everywhere_inside_and_covers_the_data(seed):
    pred = Predictive(_posterior(seed), T0_C)
    data_F = np.array([50.0, 50.0, 50.0])
    bound = 2 * 1.2 * pred.worst_over_region_uT(np.linspace(20, 30, 21), data_F, 60.0)
    tbox, F, R, notes = _region(pred, bound)
    assert not notes
    _check_region(pred, bound, tbox, F, R)
    assert tbox[0] <= 20.0 and tbox[1] >= 30.0 and np.all(F >= data_F) and R >= 60.0
    assert tbox[0] > LIMITS_C[0] or tbox[1] < LIMITS_C[1] or R < 120.0     # it grew until the bound stopped it


def test_a_bound_the_data_cannot_meet_gives_a_region_narrower_than_the_data_or_none():
    pred = Predictive(_posterior(4), T0_C)
    data_F = np.array([50.0, 50.0, 50.0])
    at_data = pred.worst_over_region_uT(np.linspace(20, 30, 41), data_F, 60.0)
    at_centre = pred.worst_vector_sd_uT(25.0, np.zeros(3), 0.0)
    bound = 2 * 0.5 * (at_data + at_centre)
    tbox, F, R, notes = _region(pred, bound)
    assert any("narrower than the data" in n for n in notes)
    assert tbox[1] - tbox[0] < 10.0 or np.any(F < data_F) or R < 60.0
    _check_region(pred, bound, tbox, F, R)
    tbox, F, R, notes = _region(pred, 1.9 * at_centre)
    assert tbox is None and F is None and R is None and "no validity region" in notes[0]
