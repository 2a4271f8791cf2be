"""Fixed-point on-board applier vs the float64 reference."""
from __future__ import annotations

import ast
import inspect
import textwrap

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.firmware import fixed_point as fp
from magstack.firmware.cal_table import CalTable, validate
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.float_applier import ApplyFlag, apply_float

EQ4 = ("gain_matrix", "temperature_gain", "offset", "temperature_offset", "currents")


def _table(S, K_S, O, K_O, D=(), field=100.0, temps=(-40.0, 85.0), currents_range=(-5.0, 5.0), t0=25.0,
           K_S2=None):
    terms = EQ4 if D else EQ4[:4]
    if K_S2 is not None:
        terms = terms[:2] + ("temperature_gain2",) + terms[2:]
    return CalTable(device_id="dev", terms=terms, S=S, K_S=K_S, O=O, K_O=K_O,
                    K_S2=np.zeros(3) if K_S2 is None else K_S2,
                    D=tuple((f"i{k}", d) for k, d in enumerate(D)), t0_c=t0, validity_temp_c=temps,
                    validity_field_uT=field,
                    validity_currents_A=tuple((f"i{k}", currents_range) for k in range(len(D))))


def test_q_formats_are_pinned():
    assert (fp.S_FRAC, fp.K_S_FRAC, fp.O_FRAC, fp.K_O_FRAC, fp.D_FRAC, fp.OUT_FRAC) == (27, 34, 8, 16, 20, 8)
    t = _table(np.eye(3) * 1.5, np.full((3, 3), 0.001), [1.0, -2.0, 0.5], [0.1, 0, 0], D=[[1.0, 0, 0]])
    f = fp.FixedPointTable.from_table(t)
    assert f.S[0][0] == 3 * 2 ** 26 and f.S[0][1] == 0
    assert f.K_S[0][0] == round(0.001 * 2 ** 34)
    assert f.O == (1000 * 256, -2000 * 256, 500 * 256)
    assert f.K_O[0] == 100 * 2 ** 16
    assert f.D[0] == (2 ** 20, 0, 0)
    assert f.t0_cdeg == 2500
    assert f.K_S2 == (0, 0, 0)
    assert fp.K_S2_FRAC == 40
    f2 = fp.FixedPointTable.from_table(_table(np.eye(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3),
                                              K_S2=[7.3e-6, -1e-6, 0.0]))
    assert f2.K_S2 == (round(7.3e-6 * 2 ** 40), round(-1e-6 * 2 ** 40), 0)
    # 1 uT on x at 10 degC above t0 with K_S2 = 2**-20 /degC^2: gain 1 + 100 * 2**-20 exactly
    f3 = fp.FixedPointTable.from_table(_table(np.eye(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3),
                                              K_S2=[2.0 ** -20, 0.0, 0.0]))
    out, _ = f3.apply_sample((1000, 0, 0), 3500)
    assert out[0] == fp.rshift_round((2 ** 27 + fp.rdiv(fp.rdiv(2 ** 20 * 1000, 100) * 1000, 819200)) * 1000, 19)
    # identity table: 12345 nT in -> 12345 * 256 out, exactly
    ident = fp.FixedPointTable.from_table(_table(np.eye(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3)))
    out, status = ident.apply_sample((12345, -7, 0), 2500)
    assert out == (12345 * 256, -7 * 256, 0) and status == 0


def test_rounding_is_half_away_from_zero():
    assert [fp.rdiv(a, 4) for a in (6, -6, 5, -5, 7, -7)] == [2, -2, 1, -1, 2, -2]
    assert [fp.rshift_round(a, 1) for a in (3, -3, 1, -1, 2)] == [2, -2, 1, -1, 1]


def test_per_sample_path_has_no_floats():
    for fn in (fp.FixedPointTable.apply_sample, fp.rdiv, fp.rshift_round, fp._clip):
        tree = ast.parse(textwrap.dedent(inspect.getsource(fn)))
        for node in ast.walk(tree):
            assert not (isinstance(node, ast.Constant) and isinstance(node.value, float)), fn.__name__
            assert not (isinstance(node, ast.Name) and node.id == "float"), fn.__name__
            assert not isinstance(node, ast.Div), f"true division in {fn.__name__}"
    f = fp.FixedPointTable.from_table(_table(np.eye(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3)))
    out, status = f.apply_sample((1, 2, 3), 100)
    assert all(type(v) is int for v in out) and type(status) is int


def _random_valid_table(data):
    fl = lambda lo, hi: st.floats(lo, hi, allow_nan=False, allow_infinity=False)  # noqa: E731
    diag = data.draw(st.lists(fl(0.5, 3.0), min_size=3, max_size=3))
    off = data.draw(st.lists(fl(-0.5, 0.5), min_size=9, max_size=9))
    S = np.array(off).reshape(3, 3)
    np.fill_diagonal(S, diag)
    K = np.array(data.draw(st.lists(fl(-0.02, 0.02), min_size=9, max_size=9))).reshape(3, 3)
    O = data.draw(st.lists(fl(-500, 500), min_size=3, max_size=3))
    KO = data.draw(st.lists(fl(-5, 5), min_size=3, max_size=3))
    nD = data.draw(st.integers(0, 2))
    D = [data.draw(st.lists(fl(-200, 200), min_size=3, max_size=3)) for _ in range(nD)]
    t0 = data.draw(st.integers(-2000, 6000)) / 100
    K2 = data.draw(st.one_of(st.none(), st.lists(fl(-1e-4, 1e-4), min_size=3, max_size=3)))
    return _table(S, K, O, KO, D, t0=t0, K_S2=K2, field=data.draw(st.sampled_from((300.0, 1000.0))))


@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_property_fixed_point_within_half_nT_of_float(data):
    table = _random_valid_table(data)
    res = validate(table)
    if not res.ok:  # an ill-conditioned draw or one without output headroom is refused: nothing to compare
        assert any("condition" in p or "would saturate" in p for p in res.problems), res.problems
        return
    f = fp.FixedPointTable.from_table(table)
    rng = np.random.default_rng(data.draw(st.integers(0, 2 ** 32 - 1)))
    n = 200
    b_nT = rng.integers(-100_000, 100_001, size=(n, 3))
    b_nT[:8] = np.array([[s1, s2, s3] for s1 in (-1, 1) for s2 in (-1, 1) for s3 in (-1, 1)]) * 100_000
    t_cdeg = rng.integers(-4000, 8501, size=n)
    t_cdeg[:4] = [-4000, 8500, -4000, 8500]
    nd = len(table.D)
    i_mA = rng.integers(-5000, 5001, size=(n, nd))
    q, status = f.apply_block(b_nT, t_cdeg, i_mA)
    ref, ref_flags = apply_float(table, b_nT / 1e3, t_cdeg / 100, {f"i{k}": i_mA[:, k] / 1e3 for k in range(nd)})
    err_nT = np.abs(fp.output_to_uT(q) - ref) * 1e3
    assert err_nT.max() <= 0.5, err_nT.max()
    # validity is judged on the calibrated output: both appliers agree except within 1 nT of the field limit
    near = np.any(np.abs(np.abs(ref) - table.validity_field_uT) * 1e3 <= 1.0, axis=1)
    assert np.array_equal(status[~near], ref_flags[~near])
    assert np.all(status[np.all(np.abs(ref) < table.validity_field_uT - 1e-3, axis=1)] == 0)
    for k in range(0, n, 23):  # the per-sample integer path is bit-identical to the vectorised one
        out, s = f.apply_sample(tuple(int(x) for x in b_nT[k]), int(t_cdeg[k]), tuple(int(x) for x in i_mA[k]))
        assert out == tuple(int(x) for x in q[k]) and s == status[k]


@settings(max_examples=60, deadline=None)
@given(scale=st.floats(1.0, 60.0), field=st.floats(100.0, 2000.0), offset=st.floats(-1000, 1000))
def test_property_overflowing_tables_are_refused(scale, field, offset):
    S = np.full((3, 3), 0.3 * scale / 10)
    np.fill_diagonal(S, min(scale, 10.0))
    table = _table(S, np.zeros((3, 3)), [offset] * 3, np.zeros(3), field=field)
    res = validate(table)
    worst = table.S.__abs__().sum(axis=1).max() * field + abs(offset)
    corner = np.full((1, 3), int(field * 1e3))
    if worst > fp.OUT_LIMIT_uT or abs(S).max() >= 16:
        assert not res.ok
    if res.ok:
        q, status = fp.FixedPointTable.from_table(table).apply_block(corner, np.array([2500]))
        assert status[0] & ApplyFlag.SATURATED == 0
    elif any("saturate" in p for p in res.problems):
        # the refusal is not hypothetical: that corner of the validity box really saturates
        f = fp.FixedPointTable.from_table(table)
        sign = 1 if offset >= 0 else -1
        q, status = f.apply_block(corner * sign, np.array([2500]))
        assert status[0] & ApplyFlag.SATURATED
        assert np.all(q == (fp.INT32_MAX if sign > 0 else fp.INT32_MIN))   # saturated, never wrapped


def test_second_order_tempco_beyond_its_fixed_point_limit_is_refused():
    with pytest.raises(CalTableInvalid, match="K_S2"):
        fp.FixedPointTable.from_table(_table(np.eye(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3),
                                             K_S2=[3e-4, 0.0, 0.0]))
    res = validate(_table(np.eye(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3), K_S2=[3e-4, 0.0, 0.0]))
    assert not res.ok and any("K_S2" in p for p in res.problems)


def test_saturates_never_wraps_and_clips_inputs():
    S = np.eye(3) * 9.0
    t = _table(S, np.zeros((3, 3)), [900.0, -900.0, 0.0], np.zeros(3), field=2000.0)
    f = fp.FixedPointTable.from_table(t)   # coefficients fit; the worst case output does not
    out, status = f.apply_sample((2_000_000, -2_000_000, 0), 2500)
    assert out[0] == fp.INT32_MAX and out[1] == fp.INT32_MIN and status & ApplyFlag.SATURATED
    out, status = f.apply_sample((2 ** 30, 0, 0), 2500)   # input beyond the clip
    assert status & ApplyFlag.SATURATED and out[0] == fp.INT32_MAX
    q, st_ = f.apply_block(np.array([[2 ** 30, 0, 0], [-(2 ** 40), 0, 0]]), np.array([2500, 2500]))
    assert q[0, 0] == fp.INT32_MAX and q[1, 0] == fp.INT32_MIN and np.all(st_ & ApplyFlag.SATURATED)


def test_out_of_validity_is_flagged_but_calibrated():
    t = _table(np.eye(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3), field=50.0, temps=(0.0, 40.0))
    f = fp.FixedPointTable.from_table(t)
    out, status = f.apply_sample((60_000, 0, 0), 2500)
    assert status == ApplyFlag.OUT_OF_VALIDITY and out[0] == 60_000 * 256
    _, status = f.apply_sample((0, 0, 0), 4500)
    assert status == ApplyFlag.OUT_OF_VALIDITY


def test_unsupported_terms_and_bad_inputs():
    t = CalTable(device_id="d", terms=("gain_matrix", "cubic"), S=np.eye(3), validity_field_uT=100.0)
    with pytest.raises(CalTableInvalid, match="not supported by the fixed-point"):
        fp.FixedPointTable.from_table(t)
    with pytest.raises(CalTableInvalid, match="Q format"):
        fp.FixedPointTable.from_table(_table(np.eye(3) * 20, np.zeros((3, 3)), np.zeros(3), np.zeros(3)))
    f = fp.FixedPointTable.from_table(_table(np.eye(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3)))
    with pytest.raises(TypeError):
        f.apply_block(np.zeros((2, 3)))
    with pytest.raises(ValueError):
        f.apply_sample((0, 0, 0), 0, (5,))
    assert not f.uses_temperature and f.apply_block(np.zeros((1, 3), np.int64))[1].tolist() == [0]
    ft = fp.FixedPointTable.from_table(_table(np.eye(3), np.full((3, 3), 1e-3), np.zeros(3), np.zeros(3)))
    with pytest.raises(ValueError, match="temp_cdeg is required"):   # never a silent t0 for a thermal table
        ft.apply_block(np.zeros((1, 3), np.int64))
    bi, ti, ci, bad = fp.to_fixed_inputs([[1.0, np.nan, 0], [0.0015, 0, 0]], [20.0, 21.005])
    assert bad.tolist() == [True, False] and bi[1, 0] == 2 and ti[1] == 2100
