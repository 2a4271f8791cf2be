"""Alignment: clock offset, per-axis skew, axis map with uncertainties; refusal; real bench data."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from magstack.cli.main import main
from magstack.ground.alignment import (
    align_streams,
    estimate_axis_map,
    estimate_clock_offset,
    interp_no_extrapolation,
    linear_fit_rmse_uT,
)
from magstack.ground.errors import AlignmentError
from magstack.ground.mageval_import import (
    AUTHORS_AXIS_MAP,
    AUTHORS_OFFSET_S,
    apply_axis_map,
    read_mageval_data,
    read_mageval_ref,
)

DATA = Path(__file__).parent / "data" / "av-mageval"


T0 = 1.0e9  # reference-clock epoch of the synthetic sessions (s)


def _field(t_s: np.ndarray, seed: int, duration_s: float = 200.0) -> np.ndarray:
    """Steps on every axis plus a slow sweep: a field that determines offset, skew and map (uT)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((t_s.size, 3))
    for ax in range(3):
        edges = np.sort(rng.uniform(T0, T0 + duration_s, 12))
        levels = rng.uniform(-40, 40, edges.size + 1)
        out[:, ax] = levels[np.searchsorted(edges, t_s)] + 5 * np.sin(2 * np.pi * t_s / (37.0 + 11 * ax))
    return out


def _pair(offset_s=3600.3, perm=(1, 0, 2), sign=(1, 1, -1), skew=(0.0, 0.1, 0.2), noise_uT=0.02, seed=0,
          duration_s=200.0):
    """Synthetic DUT/reference streams. Reference in its own clock (t_ref = t_dut - offset)."""
    rng = np.random.default_rng(seed)
    t_ref = np.cumsum(rng.uniform(0.225, 0.265, int(duration_s / 0.245))) + T0
    b_ref = _field(t_ref, seed, duration_s) + rng.normal(0, 0.001, (t_ref.size, 3))  # its own clock
    t_dut = np.cumsum(rng.uniform(0.45, 0.48, int(duration_s / 0.46))) + T0 + offset_s + 5
    b = np.zeros((t_dut.size, 3))
    gains = np.array([1.09, 1.12, 1.11])
    for i in range(3):
        # DUT axis i sees reference axis perm[i] at (DUT time + skew_i) -> reference clock time - offset
        ref_axis = _field(t_dut + skew[i] - offset_s, seed, duration_s)[:, perm[i]]
        b[:, i] = sign[i] * ref_axis / gains[i] + 0.3 * (i + 1) + rng.normal(0, noise_uT, t_dut.size)
    return t_dut, b, t_ref, b_ref


def test_interp_never_extrapolates_and_marks_gaps():
    t = np.array([0.0, 1.0, 2.0, 5.0, 6.0])
    y = np.array([0.0, 10.0, 20.0, 50.0, 60.0])
    q = np.array([-0.1, 0.0, 0.5, 1.999, 3.0, 5.5, 6.0, 6.01])
    v, ok = interp_no_extrapolation(t, y, q, max_gap_s=1.5)
    assert ok.tolist() == [False, True, True, True, False, True, True, False]
    assert np.allclose(v[ok], [0.0, 5.0, 19.99, 55.0, 60.0])
    assert np.isnan(v[~ok]).all()


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=30), st.floats(-2, 40))
def test_interp_stays_within_bracketing_samples(vals, q):
    t = np.arange(len(vals), dtype=float)
    y = np.asarray(vals)
    v, ok = interp_no_extrapolation(t, y, np.array([q]))
    if not (0 <= q <= len(vals) - 1):
        assert not ok[0] and np.isnan(v[0])
    else:
        lo, hi = int(np.floor(q)), int(np.ceil(q))
        assert min(y[lo], y[hi]) - 1e-9 <= v[0] <= max(y[lo], y[hi]) + 1e-9


def test_recovers_offset_skew_and_axis_map_with_uncertainty():
    t_dut, dut, t_ref, ref = _pair()
    rep = align_streams(t_dut, dut, t_ref, ref)
    assert 0 < rep.offset.sigma_s < 0.1
    assert all(e.determined for e in rep.skew_s)
    # a common shift of all axes is the clock offset, so the joint offset lies among the per-axis
    # ones; what the data determine is each axis's effective offset (offset - skew_i)
    for i, true_skew in enumerate((0.0, 0.1, 0.2)):
        e = rep.skew_s[i]
        assert rep.offset.offset_s - e.value == pytest.approx(3600.3 - true_skew, abs=max(0.01, 4 * e.sigma))
    assert 3600.1 < rep.offset.offset_s < 3600.3
    assert rep.axis_map.perm == (1, 0, 2) and rep.axis_map.sign == (1, 1, -1)
    assert all(rep.axis_map.determined)
    y, ok = interp_no_extrapolation(t_ref, ref, t_dut - rep.offset.offset_s - 0.5)
    assert rep.rmse_uT["vector"] < linear_fit_rmse_uT(y[ok], dut[ok])["vector"] / 2


@settings(max_examples=8, deadline=None)
@given(st.floats(-300.0, 300.0), st.permutations([0, 1, 2]), st.tuples(*[st.sampled_from([1, -1])] * 3),
       st.integers(0, 10_000))
# hypothesis-found: steps faster than the 0.245 s / 0.46 s sampling give offset errors of ~0.01-0.07 s,
# which the curvature-only uncertainty (~0.003 s) did not cover (seed 6) and, where a few rows at
# the steps carry the offset, neither did the block jackknife (seeds 1057, 4096: 7x and 5x);
# seed 9734 has a jackknife sigma of ~0.1 s
@example(offset_s=0.0, perm=[0, 1, 2], sign=(1, 1, 1), seed=6)
@example(offset_s=0.0, perm=[0, 1, 2], sign=(1, 1, 1), seed=9734)
@example(offset_s=0.0, perm=[0, 1, 2], sign=(1, 1, 1), seed=1057)
@example(offset_s=0.0, perm=[0, 1, 2], sign=(1, 1, 1), seed=4096)
def test_offset_and_map_property(offset_s, perm, sign, seed):
    t_dut, dut, t_ref, ref = _pair(offset_s=offset_s, perm=tuple(perm), sign=sign, skew=(0, 0, 0), seed=seed)
    off = estimate_clock_offset(t_dut, dut, t_ref, ref)
    assert off.offset_s == pytest.approx(offset_s, abs=max(0.01, 4 * off.sigma_s))
    assert off.sigma_s < 0.2  # jackknife: ~0.03 s typical for 12 steps per axis sampled at 4 Hz
    y, ok = interp_no_extrapolation(t_ref, ref, t_dut - off.offset_s)
    amap = estimate_axis_map(dut[ok], y[ok])
    assert amap.perm == tuple(perm) and amap.sign == tuple(sign)


def test_static_field_is_refused():
    rng = np.random.default_rng(1)
    t_ref = np.arange(0, 200, 0.245)
    t_dut = np.arange(3, 200, 0.46) + 100.0
    ref = np.array([20.0, -5.0, 40.0]) + rng.normal(0, 0.02, (t_ref.size, 3))
    dut = np.array([21.0, -4.0, 41.0]) + rng.normal(0, 0.02, (t_dut.size, 3))
    with pytest.raises(AlignmentError, match="do not determine the clock offset"):
        estimate_clock_offset(t_dut, dut, t_ref, ref)


def test_no_overlap_is_refused():
    t_dut, dut, t_ref, ref = _pair()
    with pytest.raises(AlignmentError, match="overlap"):
        estimate_clock_offset(t_dut, dut, t_ref, ref, prior_s=1e6, search_halfwidth_s=10.0)


@pytest.mark.parametrize("kw, match", [
    ({"min_r2": float("nan")}, "min_r2"), ({"prior_s": float("nan"), "search_halfwidth_s": 10.0}, "prior_s"),
    ({"prior_s": 0.0, "search_halfwidth_s": -1.0}, "search_halfwidth_s"), ({"max_gap_s": float("nan")}, "max_gap_s"),
])
def test_bad_search_parameters_are_named(kw, match):
    t_dut, dut, t_ref, ref = _pair()
    with pytest.raises(AlignmentError, match=match):
        estimate_clock_offset(t_dut, dut, t_ref, ref, **kw)


def test_periodic_field_is_ambiguous():
    t_ref = np.arange(0, 300, 0.245)
    t_dut = np.arange(0, 300, 0.46) + 0.3
    period = 20.0

    def f(t):
        ph = np.mod(t, period) < period / 2
        return np.column_stack([np.where(ph, 30.0, -30.0), np.zeros_like(t), np.ones_like(t)])

    rng = np.random.default_rng(0)
    ref = f(t_ref) + rng.normal(0, 0.01, (t_ref.size, 3))
    dut = f(t_dut - 0.3) + rng.normal(0, 0.01, (t_dut.size, 3))
    with pytest.raises(AlignmentError, match="ambiguous"):
        estimate_clock_offset(t_dut, dut, t_ref, ref)


def test_bad_shapes_and_too_few_samples():
    with pytest.raises(AlignmentError, match="expected"):
        estimate_clock_offset(np.arange(20.0), np.zeros((20, 2)), np.arange(20.0), np.zeros((20, 3)))
    with pytest.raises(AlignmentError, match="finite samples"):
        estimate_clock_offset(np.arange(5.0), np.zeros((5, 3)), np.arange(20.0), np.zeros((20, 3)))


def _real(data: int, ref: int | None = None):
    cols, _ = read_mageval_data(DATA / f"data{data}.csv")
    t_ref, ref_raw, _ = read_mageval_ref(DATA / f"ref{data if ref is None else ref}.csv")
    dut = np.column_stack([cols["x_test"], cols["y_test"], cols["z_test"]])
    return cols["time"], dut, t_ref, ref_raw


@pytest.mark.parametrize("test,swept", [(5, 0), (6, 1), (7, 2)])
def test_real_bench_no_worse_than_authors(test, swept):
    t_dut, dut, t_ref, ref_raw = _real(test)
    rep = align_streams(t_dut, dut, t_ref, ref_raw, prior_s=AUTHORS_OFFSET_S)
    o = rep.offset
    assert abs(o.offset_s - AUTHORS_OFFSET_S) < 1.0 and o.sigma_s < 0.05 and o.r2 > 0.999
    # the swept axis's map is determined and equals the authors' hand-written map
    perm, sign = AUTHORS_AXIS_MAP[swept]
    assert rep.axis_map.determined[swept]
    assert (rep.axis_map.perm[swept], rep.axis_map.sign[swept]) == (perm, sign)
    # residual of the linear fit: ours vs the authors' manual correction on the same rows
    ours_ref, ok1 = interp_no_extrapolation(t_ref + o.offset_s, ref_raw, t_dut)
    auth_ref, ok2 = interp_no_extrapolation(t_ref + AUTHORS_OFFSET_S, ref_raw, t_dut)
    ok = ok1 & ok2
    ours = linear_fit_rmse_uT(ours_ref[ok], dut[ok])["vector"]
    theirs = linear_fit_rmse_uT(auth_ref[ok], dut[ok])["vector"]
    assert ours <= theirs


def test_real_static_test_is_refused_and_cli_exit_code(capsys):
    t_dut, dut, t_ref, ref_raw = _real(3, 4)
    with pytest.raises(AlignmentError, match="do not determine"):
        align_streams(t_dut, dut, t_ref, apply_axis_map(ref_raw, AUTHORS_AXIS_MAP))
    assert main(["align", str(DATA / "data3.csv"), str(DATA / "ref4.csv")]) == 3   # bad input data
    assert "do not determine the clock offset" in capsys.readouterr().err


def test_cli_align_reports_all_estimates(capsys, tmp_path):
    assert main(["align", str(DATA / "data5.csv"), str(DATA / "ref5.csv")]) == 0
    out = capsys.readouterr().out
    assert "clock offset: 14399.5" in out and "skew z" in out and "axis map: dut_x = +ref_y" in out
    assert main(["align", "--json", str(DATA / "data6.csv"), str(DATA / "ref6.csv")]) == 0
    import json

    rep = json.loads(capsys.readouterr().out)
    assert rep["axis_map"]["perm"][1] == 0 and rep["axis_map"]["determined"][1]
    # a session file works as input too (reference already on the DUT clock: offset ~ 0)
    out_csv = tmp_path / "s7.csv"
    assert main(["import-mageval", str(DATA / "data7.csv"), str(DATA / "ref7.csv"), "--out", str(out_csv)]) == 0
    capsys.readouterr()
    assert main(["align", "--json", str(out_csv)]) == 0
    assert abs(json.loads(capsys.readouterr().out)["offset_s"]) < 0.05


def test_aligned_session_pairs_raw_bench_rows_and_corrects_skew(tmp_path, capsys):
    from magstack.data.session import read_session
    from magstack.ground.alignment import aligned_session
    from magstack.hil.bench import build_sim_bench, run_bench

    sb = build_sim_bench("hmc1053", program="sweep_y", seconds=60.0, instrument_name="t_al")
    raw_path = tmp_path / "raw.csv"
    run_bench(sb.dut, sb.ref, sb.clock, raw_path, seconds=60.0, ref_clock=sb.ref_clock)
    raw = read_session(raw_path)
    t_dut, dut, t_ref, ref = (raw.t_s[np.isfinite(raw.dut_uT[:, 0])], raw.dut_uT[np.isfinite(raw.dut_uT[:, 0])],
                              raw.t_s[np.isfinite(raw.ref_uT[:, 0])], raw.ref_uT[np.isfinite(raw.ref_uT[:, 0])])
    rep = align_streams(t_dut, dut, t_ref, ref, prior_s=0.0, search_halfwidth_s=5.0)
    paired = aligned_session(raw, rep, correct_skew=True, gaps="drop")
    assert np.all(np.isfinite(paired.ref_uT)) and np.all(np.isfinite(paired.dut_uT))
    assert len(paired) >= len(t_dut) - 4 and "clock offset" in paired.metadata["alignment_applied"]
    # after applying offset and skews the data show none left
    again = align_streams(paired.t_s, paired.dut_uT, paired.t_s, paired.ref_uT, prior_s=0.0, search_halfwidth_s=2.0)
    assert abs(again.offset.offset_s) < max(0.005, 4 * again.offset.sigma_s)
    assert all(abs(e.value) < max(0.01, 4 * e.sigma) for e in again.skew_s if e.determined)
    # the CLI does the same
    out = tmp_path / "paired.csv"
    assert main(["align", str(raw_path), "--out", str(out), "--drop-gaps"]) == 0
    assert "paired rows" in capsys.readouterr().out and len(read_session(out)) >= len(t_dut) - 4
    with pytest.raises(AlignmentError, match="nothing to pair"):
        aligned_session(paired.select(np.zeros(len(paired), bool)), rep)


def test_pooled_sweeps_determine_the_full_authors_axis_map():
    """Each single-axis sweep determines one axis; pooled after alignment, all three are."""
    duts, refs = [], []
    for test in (5, 6, 7):
        t_dut, dut, t_ref, ref_raw = _real(test)
        off = estimate_clock_offset(t_dut, dut, t_ref, ref_raw)
        y, ok = interp_no_extrapolation(t_ref + off.offset_s, ref_raw, t_dut)
        duts.append(dut[ok])
        refs.append(y[ok])
    amap = estimate_axis_map(np.vstack(duts), np.vstack(refs))
    assert all(amap.determined)
    assert tuple(zip(amap.perm, amap.sign, strict=True)) == AUTHORS_AXIS_MAP
