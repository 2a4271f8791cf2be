"""Plain vectorised degree-13 IGRF evaluation: the baseline of benchmarks/bench_igrf.py.

The textbook form, no tuning: one loop over (n, m) on full-length arrays, Schmidt semi-normalised
Legendre functions by the standard recursion, each sample's coefficients ``g_a + w (g_b - g_a)``.
Same coefficients and reference radius as ``magstack.firmware.reference.geomag`` (read from
ppigrf's file). Not used by magstack itself.
"""
from __future__ import annotations

import math

import numpy as np

from magstack.firmware.reference import geomag


def igrf_spherical_nT(r_km, theta_rad, phi_rad, seg: int, w) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B_r, B_theta, B_phi) nT on epoch segment ``seg`` at weights ``w`` (N,)."""
    c = geomag.coefficients()
    coef = {(int(a), int(b)): k for k, (a, b) in enumerate(zip(c.n, c.m, strict=True))}
    ga, ha = c.g_nT[seg], c.h_nT[seg]
    dg, dh = c.g_nT[seg + 1] - ga, c.h_nT[seg + 1] - ha
    st, ct = np.sin(theta_rad), np.cos(theta_rad)
    ar = c.radius_km / r_km
    cosm = [np.cos(m * phi_rad) for m in range(14)]
    sinm = [np.sin(m * phi_rad) for m in range(14)]
    p = {(0, 0): np.ones_like(st)}
    dp = {(0, 0): np.zeros_like(st)}
    br = np.zeros_like(st)
    bt = np.zeros_like(st)
    bp = np.zeros_like(st)
    for n in range(1, 14):
        arn = ar ** (n + 2)
        for m in range(n + 1):
            if n == m:   # Schmidt semi-normalised recursion
                f = math.sqrt(1.0 - 1.0 / (2 * n)) if n > 1 else 1.0
                p[n, m] = f * st * p[n - 1, m - 1]
                dp[n, m] = f * (st * dp[n - 1, m - 1] + ct * p[n - 1, m - 1])
            else:
                a1 = (2 * n - 1) / math.sqrt(n * n - m * m)
                a2 = math.sqrt(((n - 1) ** 2 - m * m) / (n * n - m * m))
                p[n, m] = a1 * ct * p[n - 1, m]
                dp[n, m] = a1 * (ct * dp[n - 1, m] - st * p[n - 1, m])
                if n > 1 and m <= n - 2:
                    p[n, m] = p[n, m] - a2 * p[n - 2, m]
                    dp[n, m] = dp[n, m] - a2 * dp[n - 2, m]
            k = coef[n, m]
            g = ga[k] + w * dg[k]
            h = ha[k] + w * dh[k]
            gc = g * cosm[m] + h * sinm[m]
            br += (n + 1) * arn * p[n, m] * gc
            bt -= arn * dp[n, m] * gc
            bp += m * arn * p[n, m] * (g * sinm[m] - h * cosm[m])
    return br, bt, bp / st
