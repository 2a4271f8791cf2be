"""Rows a fit keeps, not copied (fit memory flat in rows when rows are excluded).

``FitData.kept`` numbers the usable rows without copying them (:mod:`magstack.firmware.calibration.kept_rows`);
what it returns must index exactly as the copied rows do, and a fit through it must equal the fit of the
copied rows.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.firmware.calibration import FitData, FitOptions, fit
from magstack.firmware.calibration import kept_rows as kr
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.sim.synthetic_calibration import make_data, random_theta


@settings(max_examples=80, deadline=None)
@given(st.integers(1, 120), st.floats(0.0, 1.0), st.integers(0, 2 ** 31), st.sampled_from([1, 3, 7, 64]))
def test_kept_columns_index_as_the_copied_rows(n, p_keep, seed, block):
    keep_block = kr.BLOCK_ROWS
    kr.BLOCK_ROWS = block                      # many blocks: ranges cross their edges
    try:
        rng = np.random.default_rng(seed)
        mask = rng.random(n) < p_keep
        base = rng.standard_normal((n, 3))
        sess = np.sort(rng.integers(0, 4, n))
        rows = kr.KeptRows(mask)
        col, scol = kr.KeptColumn(rows, base), kr.KeptColumn(rows, sess)
        want, swant = base[mask], sess[mask]
        m = int(mask.sum())
        assert len(col) == m and col.shape == (m, 3) and rows.n == m
        np.testing.assert_array_equal(np.asarray(col), want)
        for _ in range(6):
            a, b = sorted(rng.integers(0, m + 1, 2))
            np.testing.assert_array_equal(col[a:b], want[a:b])
            np.testing.assert_array_equal(col[a:b, 1], want[a:b, 1])
            if m:
                idx = rng.integers(-m, m, int(rng.integers(1, 9)))
                np.testing.assert_array_equal(col[idx], want[idx])
                i = int(rng.integers(0, m))
                np.testing.assert_array_equal(col[i], want[i])
        np.testing.assert_array_equal(col[::3], want[::3])
        for v in range(-1, 5):
            for side in ("left", "right"):
                assert scol.searchsorted(v, side=side) == np.searchsorted(swant, v, side=side)
        if m:
            with pytest.raises(IndexError):
                col[np.array([m])]
    finally:
        kr.BLOCK_ROWS = keep_block


CURRENTS = ("solar", "heater")


def _data(n: int, seed: int = 0) -> FitData:
    rng = np.random.default_rng(seed)
    model = CalModel(resolve_terms("eq3", currents=CURRENTS), CURRENTS, (), 25.0, 0.0)
    d = make_data(model, random_theta(model, rng), n, rng, noise_uT=0.03, t0_s=0.0)
    d.session = (np.arange(n) * 3 // n).astype(np.int64)       # three sessions, rows in (session, time) order
    return d


@pytest.mark.parametrize("how", ["nan", "flag", "weight", "current"])
def test_a_fit_through_kept_rows_equals_the_fit_of_the_copied_rows(how, monkeypatch):
    d = _data(70_000 + 123)                    # more than one 65,536-row block
    rng = np.random.default_rng(5)
    bad = rng.random(len(d)) < 0.02
    bad[65530:65545] = True                    # a run across the block edge
    if how == "nan":
        d.b_meas_uT[bad, 2] = np.nan
    elif how == "flag":
        d.flag = np.where(bad, 1 << 30, 0)     # a disqualifying flag bit (not informational)
    elif how == "weight":
        d.weights = np.where(bad, 0.0, 1.0)
    else:
        d.currents_A["heater"][bad] = np.nan
    before = {k: v.copy() for k, v in (("meas", d.b_meas_uT), ("ref", d.b_ref_uT), ("t", d.t_s))}
    opts = FitOptions()
    with monkeypatch.context() as m:           # the fit must not copy the kept rows
        m.setattr(FitData, "select", lambda self, mask: pytest.fail("kept rows copied"))
        res = fit(d, "eq3", currents=CURRENTS, options=opts)
    ok = d.usable(res.model.terms, CURRENTS)
    assert res.n_excluded == int((~ok).sum()) > 0
    ref = fit(d.select(ok), "eq3", currents=CURRENTS, options=opts)
    assert res.n_used == ref.n_used
    np.testing.assert_allclose(res.theta, ref.theta, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(res.se, ref.se, rtol=1e-12)
    for k in ("rmse_uT", "raw_rmse_uT", "noise_floor_uT", "holdout_blocks_uT", "holdout_sessions_uT"):
        np.testing.assert_allclose(getattr(res, k), getattr(ref, k), rtol=1e-12, err_msg=k)
    for k, v in before.items():                # the input is not modified
        np.testing.assert_array_equal(v, {"meas": d.b_meas_uT, "ref": d.b_ref_uT, "t": d.t_s}[k])


def test_rows_out_of_order_with_excluded_rows_fall_back_to_the_copy(monkeypatch):
    d = _data(5000)
    d.b_meas_uT[::50, 0] = np.nan
    o = np.random.default_rng(1).permutation(len(d))
    shuffled = FitData(d.b_meas_uT[o], d.b_ref_uT[o], d.temp_c[o], d.t_s[o], d.session[o],
                       {k: v[o] for k, v in d.currents_A.items()})
    copies = []
    select = FitData.select
    monkeypatch.setattr(FitData, "select", lambda self, mask: copies.append(1) or select(self, mask))
    a = fit(shuffled, "eq3", currents=CURRENTS, options=FitOptions())
    assert copies                              # out of (session, time) order: the whole-array path, copied
    b = fit(d, "eq3", currents=CURRENTS, options=FitOptions())
    np.testing.assert_allclose(a.theta, b.theta, rtol=1e-9, atol=1e-12)
    assert a.n_excluded == b.n_excluded == 100
