"""192 equal-area attitude bins (Archer et al. 2015) with a temperature dimension."""
from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.firmware.calibration.coverage_bins import (
    N_BANDS,
    N_BINS,
    N_SECTORS,
    AttitudeCoverage,
    bin_center,
    bin_index,
)


def test_192_bins_of_equal_area():
    assert N_BINS == 192
    # zone area is 2 pi * height (Archimedes); every band has height 2/12, every sector 1/16 of it
    areas = np.full(N_BINS, 2 * math.pi * (2 / N_BANDS) / N_SECTORS)
    assert np.allclose(areas, 4 * math.pi / 192)
    # directions uniform on the sphere land uniformly: chi-square against equal areas
    v = np.random.default_rng(11).normal(size=(192_000, 3))
    c = np.bincount(bin_index(v), minlength=N_BINS)
    chi2 = np.sum((c - 1000.0) ** 2 / 1000.0)
    assert chi2 < 191 + 5 * math.sqrt(2 * 191)


#: components (no subnormals: halving one flushes it to zero, a different direction)
_coord = st.floats(-1e3, 1e3).map(lambda v: 0.0 if abs(v) < 1e-100 else v)


@settings(max_examples=300, deadline=None)
@given(x=_coord, y=_coord, z=_coord, k=st.integers(-20, 20))
def test_bin_contains_the_direction_and_ignores_length(x, y, z, k):
    v = np.array([[x, y, z]])
    n = np.linalg.norm(v)
    if n == 0:
        assert bin_index(v)[0] == -1
        return
    b = bin_index(v)[0]
    assert 0 <= b < N_BINS
    assert bin_index(v * 2.0 ** k)[0] == b            # power-of-two scaling is exact in floating point
    c = bin_center([b])[0]
    assert abs(z / n - c[2]) <= 1 / N_BANDS + 1e-12  # half a band height (2/12) around the centre
    dlon = abs((math.atan2(y, x) - math.atan2(c[1], c[0]) + math.pi) % (2 * math.pi) - math.pi)
    assert dlon <= math.pi / N_SECTORS + 1e-9 or abs(z / n) > 1 - 1e-12


def test_bin_centres_fall_in_their_bins():
    assert np.array_equal(bin_index(bin_center(np.arange(N_BINS))), np.arange(N_BINS))


def test_coverage_counts_merge_and_temperature_bands():
    a, b = AttitudeCoverage(), AttitudeCoverage()
    d = bin_center(np.arange(N_BINS))
    a.update(d[:100], np.full(100, -10.0))
    b.update(d[50:], np.full(142, 40.0))
    m = a.merge(b)
    assert m.bins_filled == 192 and m.fraction == 1.0
    assert m.bins_in_temp(-12, -8) == 100 and m.bins_in_temp(38, 42) == 142
    assert [(lo, k) for lo, _, k in m.per_temp_band()] == [(-10.0, 100), (40.0, 142)]
