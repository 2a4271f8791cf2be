"""The vectorised IGRF-14 evaluation (geomag.igrf_spherical_nT) against ppigrf and pyIGRF14."""
from __future__ import annotations

import datetime as dt
import math

import numpy as np
import ppigrf
import pytest

from magstack.firmware import blas
from magstack.firmware.reference import geomag


def _ppigrf_direct(t_s, p_km):
    """ppigrf's own igrf_gc at one sample's date and position, as ECEF nT."""
    r = float(np.linalg.norm(p_km))
    th = min(max(math.acos(p_km[2] / r), geomag.POLE_EPS_RAD), math.pi - geomag.POLE_EPS_RAD)
    ph = math.atan2(p_km[1], p_km[0])
    d = dt.datetime.fromtimestamp(t_s, dt.UTC).replace(tzinfo=None)
    br, bt, bp = (x.ravel()[0] for x in ppigrf.igrf_gc(r, math.degrees(th), math.degrees(ph), d))
    return geomag.spherical_to_ecef(np.array([th]), np.array([ph]), br, bt, bp)[0]


def test_equals_ppigrf_on_random_points_and_dates_over_the_whole_model():
    rng = np.random.default_rng(11)
    ep = geomag.igrf_epochs_s()
    n = 60
    t = np.round(rng.uniform(ep[0], ep[-1], n))          # whole seconds: ppigrf takes datetimes
    p = rng.normal(size=(n, 3))
    p[:3] = [[0.0, 0.0, 1.0], [1e-7, 0.0, -1.0], [1.0, 1e-3, 1e-9]]   # at and near the poles, equator
    p *= (rng.uniform(6300.0, 40_000.0, n) / np.linalg.norm(p, axis=1))[:, None]
    ours = geomag.igrf_ecef_nT(t, p)
    theirs = np.array([_ppigrf_direct(t[k], p[k]) for k in range(n)])
    assert np.max(np.abs(ours - theirs)) < 1e-6


def test_blocks_and_segments_do_not_change_the_result(monkeypatch):
    rng = np.random.default_rng(5)
    ep = geomag.igrf_epochs_s()
    t = np.sort(rng.uniform(ep[-4], ep[-1], 3000))       # three epoch segments in one call
    p = rng.normal(size=(t.size, 3))
    p *= (6878.0 / np.linalg.norm(p, axis=1))[:, None]
    whole = geomag.igrf_ecef_nT(t, p)
    monkeypatch.setattr(geomag, "CHUNK", 7)
    assert np.max(np.abs(geomag.igrf_ecef_nT(t, p) - whole)) < 1e-8
    one = np.vstack([geomag.igrf_ecef_nT(t[k:k + 1], p[k:k + 1]) for k in range(0, t.size, 301)])
    assert np.max(np.abs(one - whole[::301])) < 1e-8


def test_evaluation_does_not_go_through_ppigrf(monkeypatch):
    geomag.coefficients()        # the coefficients come from ppigrf's file (read once) ...

    def refuse(*a, **k):
        raise AssertionError("ppigrf.igrf_gc called")

    monkeypatch.setattr(ppigrf, "igrf_gc", refuse)          # ... the field does not
    t = np.full(4, dt.datetime(2026, 6, 1, tzinfo=dt.UTC).timestamp())
    p = np.array([[7000.0, 0, 0], [0, 7000.0, 0], [0, 0, 7000.0], [4000.0, 4000.0, 4000.0]])
    assert np.all(np.linalg.norm(geomag.igrf_ecef_nT(t, p), axis=1) > 1e4)


def test_coefficients_are_read_from_ppigrfs_file():
    c = geomag.coefficients()
    g, h = ppigrf.ppigrf.read_shc(ppigrf.ppigrf.shc_fn)
    k = list(zip(c.n.tolist(), c.m.tolist(), strict=True)).index((3, 2))
    assert c.g_nT[:, k] == pytest.approx(g[(3, 2)].to_numpy())
    assert c.h_nT[:, k] == pytest.approx(h[(3, 2)].to_numpy())
    assert c.radius_km == ppigrf.ppigrf.RE
    assert len(c.n) == 104 and c.n.max() == 13


def test_single_thread_limits_blas_and_restores_it():
    # from two threads (the test run itself keeps BLAS at one: tests/conftest.py), so a restore is visible
    with blas._controller().limit(limits=2, user_api="blas"):
        before = blas.blas_threads()
        assert before and all(k == 2 for k in before)
        with blas.single_thread():
            assert all(k == 1 for k in blas.blas_threads())
        assert blas.blas_threads() == before
