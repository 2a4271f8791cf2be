"""``fit`` memory in rows ("memory flat in rows"): what each added row costs the fit beyond its inputs.

The fit with held-out figures runs in 64k-row blocks (:mod:`magstack.firmware.calibration.crossfit`); the
figures that need every residual (noise floor and step threshold medians, step split, RMSE) are streamed
(:mod:`magstack.firmware.calibration.residual_figures`). Measured by tracemalloc (deterministic, not a timing)
between two lengths, the input arrays built before tracing starts.
"""
from __future__ import annotations

import gc
import tracemalloc

import numpy as np
import pytest

from magstack.firmware.calibration import FitOptions, fit
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.sim.synthetic_calibration import make_data, random_theta

#: Bytes per added row allowed: measured -0.3 to 1.0 B/row here (the one per-row array is the 1-byte mask of
#: usable rows; the peak itself is set by fixed per-block buffers); whole-array figures would cost ~91 B/row
#: (N x 3 residuals, fold and piece ids, the noise floor's index pairs and differences, the step split's arrays).
MAX_BYTES_PER_ROW = 8
CURRENTS = ("solar", "heater")


def _data(n: int, nan_fraction: float = 0.0):
    rng = np.random.default_rng(0)
    model = CalModel(resolve_terms("eq3", currents=CURRENTS), CURRENTS, (), 25.0, 0.0)
    d = make_data(model, random_theta(model, rng), n, rng, noise_uT=0.03, t0_s=0.0)
    d.b_meas_uT[rng.random(n) < nan_fraction, 1] = np.nan       # excluded rows (kept rows are not copied)
    return d


def _peak_bytes(n: int, nan_fraction: float = 0.0) -> tuple[int, np.ndarray]:
    d = _data(n, nan_fraction)
    gc.collect()
    tracemalloc.start()
    try:
        res = fit(d, "eq3", currents=CURRENTS, options=FitOptions())
        return tracemalloc.get_traced_memory()[1], res.noise_floor_uT
    finally:
        tracemalloc.stop()


@pytest.mark.slow
@pytest.mark.parametrize("nan_fraction", [0.0, 0.01])
def test_fit_memory_per_added_row_is_flat(nan_fraction):
    """Also with 1 % of the rows excluded (NaN): copying the kept rows would cost ~88 B/row."""
    n1, n2 = 6 * 65536 + 100, 12 * 65536 + 200
    p1, nf1 = _peak_bytes(n1, nan_fraction)
    p2, nf2 = _peak_bytes(n2, nan_fraction)
    np.testing.assert_allclose(nf1, 0.03, rtol=0.1)     # the figures are there (white noise of 30 nT)
    np.testing.assert_allclose(nf2, 0.03, rtol=0.1)
    per_row = (p2 - p1) / (n2 - n1)
    assert per_row < MAX_BYTES_PER_ROW, f"{per_row:.1f} B per added row"
