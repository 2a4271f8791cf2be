"""The vectorised fixed-point applier is bit-identical to a frozen straightforward implementation.

The frozen reference is ``benchmarks/baselines/fixed_point_before.py``. Its field validity rule is on the input
field; the applier's is on the calibrated output (per axis and magnitude, whole nT), so :func:`_frozen` runs the
frozen code without a field limit and adds the output rule.
"""
from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.firmware import fixed_point as fp

_spec = importlib.util.spec_from_file_location(
    "fixed_point_before", Path(__file__).resolve().parent.parent / "benchmarks" / "baselines" / "fixed_point_before.py")
before = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(before)

I32 = st.integers(fp.INT32_MIN, fp.INT32_MAX)


def _frozen(table, b, t=None, c=None):
    """The frozen applier's (outputs, status), its field rule replaced by the calibrated-field one: OUT_OF_VALIDITY
    when an output's whole nT (rounded half away from zero) exceeds its axis' limit, or their squares' sum the
    magnitude limit's square."""
    args = () if t is None else (t, c)
    q, s = before.apply_block(dataclasses.replace(table, field_limit_nT=2 ** 62), b, *args)
    nt = (np.abs(q) + 128) >> 8
    oov = np.any(nt > np.array(table.axis_limits_nT, np.int64), axis=1)
    if table.field_norm_nT is not None:
        oov |= (nt ** 2).sum(axis=1) > table.field_norm_nT ** 2
    return q, s | np.where(oov, 2, 0)


def _tables(n_currents: int):
    return st.builds(
        fp.FixedPointTable,
        S=st.tuples(*[st.tuples(I32, I32, I32)] * 3), K_S=st.tuples(*[st.tuples(I32, I32, I32)] * 3),
        O=st.tuples(I32, I32, I32), K_O=st.tuples(I32, I32, I32),
        D=st.tuples(*[st.tuples(I32, I32, I32)] * n_currents),
        t0_cdeg=st.integers(-30_000, 30_000), field_limit_nT=st.integers(0, 2 ** 25),
        field_limits_nT=st.one_of(st.none(), st.tuples(*[st.integers(0, 2 ** 24)] * 3)),
        field_norm_nT=st.one_of(st.none(), st.integers(0, fp.B_NORM_LIMIT_nT)),
        temp_range_cdeg=st.one_of(st.none(), st.tuples(st.integers(-40_000, 0), st.integers(0, 40_000))),
        current_ranges_mA=st.tuples(*[st.tuples(st.integers(-2 ** 21, 0), st.integers(0, 2 ** 21))] * n_currents))


@st.composite
def _cases(draw):
    k = draw(st.integers(0, fp.MAX_CURRENTS))
    table = draw(_tables(k))
    n = draw(st.integers(1, 60))
    seed = draw(st.integers(0, 2 ** 32 - 1))
    rng = np.random.default_rng(seed)
    span = draw(st.sampled_from([0, 1, 50, 5000, 2 ** 17]))     # one temperature ... wider than the clip
    mid = draw(st.integers(-40_000, 40_000))
    b_lim = draw(st.sampled_from([1000, 100_000, 2 ** 24, 2 ** 31]))
    b = rng.integers(-b_lim, b_lim + 1, size=(n, 3))
    t = mid + rng.integers(-span, span + 1, size=n)
    c = rng.integers(-(2 ** 21), 2 ** 21 + 1, size=(n, k))
    b[0] = [2 ** 24, -(2 ** 24) - 1, 0]      # exactly at / past the input clips
    return table, b, t, c


@settings(max_examples=300, deadline=None)
@given(case=_cases())
def test_bit_identical_to_the_frozen_applier(case):
    table, b, t, c = case
    q_new, s_new = table.apply_block(b, t, c)
    q_old, s_old = _frozen(table, b, t, c)
    assert q_new.dtype == q_old.dtype and s_new.dtype == s_old.dtype
    assert np.array_equal(q_new, q_old)
    assert np.array_equal(s_new, s_old)


I28 = st.integers(-fp.K_S2_INT_LIMIT, fp.K_S2_INT_LIMIT)


@settings(max_examples=200, deadline=None)
@given(case=_cases(), k2=st.tuples(I28, I28, I28))
def test_second_order_tempco_block_equals_sample(case, k2):
    """With K_S2 (which the frozen applier lacks) the block path equals the per-sample integer path."""
    table, b, t, c = case
    table = fp.FixedPointTable(**{**table.__dict__, "K_S2": k2})
    q, s = table.apply_block(b, t, c)
    for k in range(b.shape[0]):
        out, st_k = table.apply_sample(tuple(int(x) for x in b[k]), int(t[k]), tuple(int(x) for x in c[k]))
        assert out == tuple(int(x) for x in q[k]) and st_k == s[k]


def test_bit_identical_on_the_shipped_vector_shapes():
    rng = np.random.default_rng(0)
    S = ((2 ** 27, 1234, -999), (-5, 2 ** 27 + 77, 3), (0, 1, 2 ** 27 - 4))
    K = ((12345, -678, 9), (0, 4444, -1), (7, 7, -99999))
    table = fp.FixedPointTable(S, K, (256_000, -512_000, 13), (6_553_600, -123, 0), ((2 ** 20, -77, 5),), 2500,
                               100_000, (-4000, 8500), ((-5000, 5000),))
    b = rng.integers(-120_000, 120_001, size=(10_000, 3))
    for t in (np.full(10_000, 2500), rng.integers(-4000, 8501, size=10_000), rng.integers(-40_000, 40_000, 10_000)):
        c = rng.integers(-6000, 6001, size=(10_000, 1))
        q_new, s_new = table.apply_block(b, t, c)
        q_old, s_old = _frozen(table, b, t, c)
        assert np.array_equal(q_new, q_old) and np.array_equal(s_new, s_old)
        assert np.any(s_new & 2) and not np.all(s_new & 2)
    # no temperature given, table without temperature terms
    flat = fp.FixedPointTable(S, ((0, 0, 0),) * 3, (1, 2, 3), (0, 0, 0), (), 2500, 100_000, None, ())
    assert np.array_equal(flat.apply_block(b)[0], before.apply_block(flat, b)[0])
