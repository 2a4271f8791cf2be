"""Synthetic paired data for tests and benchmarks (not flight code).

The reference is generated *through the calibration model itself* from a smooth random
DUT trajectory, so a correct fit recovers the generating parameters to the noise level.
"""
from __future__ import annotations

import numpy as np

from magstack.firmware.calibration.fit import FitData
from magstack.firmware.calibration.model import CalModel


def random_theta(model: CalModel, rng: np.random.Generator) -> np.ndarray:
    """(3, p) plausible parameters: S near identity, temperature terms of belsten's size."""
    th = np.zeros((3, model.n_columns))
    for c, col in enumerate(model.columns):
        for i in range(3):
            if not col.axes[i]:
                continue
            if col.param == "S":
                th[i, c] = (1.0 if i == col.index else 0.0) + rng.normal(0, 0.05)
            elif col.param == "K_S":
                th[i, c] = rng.normal(0, 3e-3)
            elif col.param == "O":
                th[i, c] = rng.normal(0, 1.0)
            elif col.param == "K_O":
                th[i, c] = rng.normal(0, 0.1)
            elif col.term == "currents":
                th[i, c] = rng.normal(0, 20.0)
            elif col.param == "c3":
                th[i, c] = rng.normal(0, 1e-6)
            elif col.param == "P":
                th[i, c] = rng.normal(0, 1e-4)
            elif col.param == "tau":
                th[i, c] = rng.normal(0, 0.05)
            elif col.term == "session_offset":
                th[i, c] = rng.normal(0, 0.2)
            elif col.param == "r":
                th[i, c] = rng.normal(0, 1e-5)
    return th


def make_data(model: CalModel, theta: np.ndarray, n: int, rng: np.random.Generator, *,
              noise_uT: float = 0.02, field_uT: float = 60.0, temp_span_c: tuple[float, float] = (-20.0, 60.0),
              dt_s: float = 0.25, t0_s: float = 1.6e9) -> FitData:
    """``n`` rows: smooth 3-axis DUT field (uT), temperature ramp (degC), currents (A),
    sessions split in equal time runs, reference = model + white noise (uT rms)."""
    t = t0_s + np.arange(n) * dt_s
    k = np.arange(n)
    b = np.column_stack([field_uT * np.sin(2 * np.pi * k / (n / (3.1 + 0.7 * j)) + j) for j in range(3)])
    b += rng.normal(0, 0.05, size=(n, 3))
    lo, hi = temp_span_c
    temp = lo + (hi - lo) * 0.5 * (1 - np.cos(2 * np.pi * k / n * 1.3))
    cur = {name: 0.5 + 0.5 * np.sign(np.sin(2 * np.pi * k / (n / (7 + 2 * q)))) * rng.uniform(0.2, 1.0, n)
           for q, name in enumerate(model.currents)}
    sess = np.zeros(n, dtype=np.int64)
    if model.sessions:
        sess = np.asarray(model.sessions)[np.minimum(k * len(model.sessions) // n, len(model.sessions) - 1)]
    X = model.design(b, temp, cur, sess, t)
    ref = model.predict(theta, X) + rng.normal(0, noise_uT, size=(n, 3))
    return FitData(b, ref, temp, t, sess, cur)
