"""The plain refit pipeline: the baseline of ``bench_refit.py --part plain``.

What a refit of one telemetry file needs, written straight: pandas reads the whole file; currents
by ``np.interp`` from their samples; the vectorised IGRF evaluation (``baselines/igrf_numpy.py``);
ITRS -> GCRS by ERFA (``frames.gcrs_to_itrs_matrix``); attitude by scipy; Eq. 3 + currents design
(3 gains, 3 temperature gains, offset, temperature offset, one column per current, per axis); the
same held-out blocks as refit; ``np.linalg.lstsq``, then 4 Huber passes (k = 1.345, scale 1.4826 x
median |residual|, row weight the smallest axis weight) each another ``lstsq``. No coverage bins,
holds, validation or report. Not used by magstack itself.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from magstack.data.telemetry import DUT_COLUMNS, POS_COLUMNS, QUAT_COLUMNS
from magstack.firmware.reference import frames, geomag

from . import igrf_numpy


def plain_refit(path: str, t0_c: float = 25.0, passes: int = 4, holdout_block_s: float = 600.0,
                holdout_every: int = 5) -> np.ndarray:
    """(3, p) coefficients per axis (fit rows only)."""
    df = pd.read_csv(path, comment="#")
    t = df["t_s"].to_numpy()
    b = df[list(DUT_COLUMNS)].to_numpy()
    p = df[list(POS_COLUMNS)].to_numpy()
    q = df[list(QUAT_COLUMNS)].to_numpy()
    dtc = df["temp_c"].to_numpy() - t0_c
    cur = []
    for c in [c for c in df.columns if c.startswith("current_")]:
        x = df[c].to_numpy()
        ok = np.isfinite(x)
        cur.append(np.interp(t, t[ok], x[ok]))
    r = np.linalg.norm(p, axis=1)
    th = np.arccos(p[:, 2] / r)
    ph = np.arctan2(p[:, 1], p[:, 0])
    ep = geomag.igrf_epochs_s()
    s = int(np.searchsorted(ep, t[0], side="right") - 1)
    w = (t - ep[s]) / (ep[s + 1] - ep[s])
    b_itrs = geomag.spherical_to_ecef(th, ph, *igrf_numpy.igrf_spherical_nT(r, th, ph, s, w))
    b_gcrs = np.einsum("nji,nj->ni", frames.gcrs_to_itrs_matrix(t), b_itrs)
    y = Rotation.from_quat(q[:, [1, 2, 3, 0]]).apply(b_gcrs) / 1e3
    x = np.column_stack([b, b * dtc[:, None], np.ones_like(dtc), dtc, *cur])
    fit = np.floor(t / holdout_block_s).astype(np.int64) % holdout_every != 0
    x, y = x[fit], y[fit]
    coef = np.linalg.lstsq(x, y, rcond=None)[0]
    for _ in range(passes):
        res = y - x @ coef
        scale = 1.4826 * np.median(np.abs(res), axis=0)
        u = np.abs(res) / (1.345 * scale)
        wt = np.sqrt(np.min(np.where(u <= 1, 1.0, 1.0 / u), axis=1))
        coef = np.linalg.lstsq(x * wt[:, None], y * wt[:, None], rcond=None)[0]
    return coef.T
