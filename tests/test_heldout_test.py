"""The paired held-out test that decides between two models (fit's optional terms, refit's candidate vs the active
table): its level under the null, its power on large uneven improvements, and the parts rule for few blocks."""
from __future__ import annotations

import numpy as np

from magstack.firmware.calibration.heldout_test import (
    ALPHA,
    MIN_BATCHES,
    PARTS_PER_BLOCK,
    paired_block_test,
    paired_test_over_parts,
)


def _sse(rng, scale, n_blocks, rows=60):
    """Per block the sum of squares of ``rows`` normal residuals with per-block sd ``scale``."""
    return {(0, k): float(np.sum((scale[k] * rng.standard_normal(rows)) ** 2)) for k in range(n_blocks)}


def test_two_equally_good_models_are_rarely_called_different():
    # the null: both models' errors have the same distribution; blocks differ in scale (an orbit's attitude)
    rng = np.random.default_rng(0)
    hits = {False: 0, True: 0}
    trials = 400
    for _ in range(trials):
        scale = rng.uniform(0.02, 0.5, 30)
        a, b = _sse(rng, scale, 30), _sse(rng, scale, 30)
        for sf in (False, True):
            t = paired_block_test(a, b, scale_free=sf)
            hits[sf] += t.p <= ALPHA
    # one-sided level ALPHA; Bonferroni keeps the combined test at or below it (binomial sd ~0.005 here)
    assert hits[False] / trials <= ALPHA + 0.015
    assert hits[True] / trials <= ALPHA + 0.015


def test_a_large_uneven_improvement_over_few_blocks_is_significant_scale_free():
    # five blocks, the active table's error 0.5-5 uT depending on the block, the candidate's 50 nT everywhere
    rng = np.random.default_rng(1)
    act = _sse(rng, np.array([5.0, 0.5, 2.0, 1.0, 3.0]), 5)
    cand = _sse(rng, np.full(5, 0.05), 5)
    plain, free = paired_block_test(act, cand), paired_block_test(act, cand, scale_free=True)
    assert plain.gain > 0.99 and free.gain == plain.gain
    assert plain.p > ALPHA and not plain.significant        # the differences are dominated by the largest block
    assert free.p <= ALPHA and free.significant
    assert "log ratios" in free.describe() and "log ratios" not in plain.describe()


def test_few_blocks_are_tested_over_their_parts_and_say_so():
    rng = np.random.default_rng(2)
    parts = 2 * PARTS_PER_BLOCK                              # two held-out blocks, scored in parts
    act = _sse(rng, np.full(parts, 4.0), parts)
    cand = _sse(rng, np.full(parts, 0.05), parts)
    t = paired_test_over_parts(act, cand, scale_free=True)
    assert t.parts_of == 2 and t.blocks == parts and t.significant
    assert f"{parts} parts of 2 time blocks" in t.describe()
    # two blocks' worth of data without the parts: no test at all
    whole = {(0, k): sum(v for (s, p), v in act.items() if p // PARTS_PER_BLOCK == k) for k in range(2)}
    whole_c = {(0, k): sum(v for (s, p), v in cand.items() if p // PARTS_PER_BLOCK == k) for k in range(2)}
    assert not paired_block_test(whole, whole_c, scale_free=True).significant


def test_enough_blocks_are_tested_as_whole_blocks():
    rng = np.random.default_rng(3)
    n = MIN_BATCHES * PARTS_PER_BLOCK
    act = _sse(rng, np.full(n, 0.06), n)
    cand = _sse(rng, np.full(n, 0.06), n)
    t = paired_test_over_parts(act, cand, scale_free=True)
    assert t.parts_of == 0 and t.blocks == MIN_BATCHES and "parts" not in t.describe()
    assert not t.significant


def test_block_sse_sums_per_block_in_any_row_order():
    """Squared residuals summed per (session, block): rows in key order (runs) or shuffled (grouped) alike, and
    over several calls."""
    from magstack.firmware.calibration.heldout_test import BlockSSE

    rng = np.random.default_rng(3)
    sess = np.repeat([0, 0, 1, 2], 50)
    blk = np.sort(rng.integers(0, 7, sess.size)) + 10 * (sess == 2)
    order = np.lexsort((blk, sess))
    sess, blk = sess[order], blk[order]
    sq = rng.random(sess.size)
    want: dict = {}
    for s, b, v in zip(sess.tolist(), blk.tolist(), sq.tolist(), strict=True):
        want[s, b] = want.get((s, b), 0.0) + v
    in_order, shuffled = BlockSSE(), BlockSSE()
    half = sess.size // 2
    in_order.add(sess[:half], blk[:half], sq[:half])
    in_order.add(sess[half:], blk[half:], sq[half:])
    p = rng.permutation(sess.size)
    assert BlockSSE.group(sess[p], blk[p])[1] is None            # out of order: grouped by key
    shuffled.add(sess[p], blk[p], sq[p])
    for got in (in_order.sse, shuffled.sse):
        assert sorted(got) == sorted(want)
        np.testing.assert_allclose([got[k] for k in sorted(want)], [want[k] for k in sorted(want)], rtol=1e-12)
