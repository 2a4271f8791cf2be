"""Attitude coverage: 192 equal-area bins of field direction (Archer et al. 2015), per temperature band.

Bins: 12 bands of equal height in z (a sphere's zone area is proportional to its height,
Archimedes) times 16 equal longitude sectors, so every bin has area 4 pi / 192 sr exactly. (Not
HEALPix nside=4, which has the same count and equal areas with other shapes; this scheme needs no
extra package on a flight computer.) A sample's direction is its reference field's unit vector in
the sensor frame: that is what the gain matrix sees. Coverage also keeps a temperature dimension
(bands of ``TEMP_BAND_C``, belsten sec. 3.3), so "which directions were seen while cold / warm"
is answerable. Counts are integers and add, so coverage from separate blocks or machines merges.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

N_BANDS = 12
N_SECTORS = 16
N_BINS = N_BANDS * N_SECTORS   # 192
#: Temperature band width (degC) and the range the bands cover (outside: first / last band).
TEMP_BAND_C = 5.0
TEMP_RANGE_C = (-60.0, 130.0)
N_TEMP = int(round((TEMP_RANGE_C[1] - TEMP_RANGE_C[0]) / TEMP_BAND_C))


def bin_index(direction) -> np.ndarray:
    """(N,) bin 0..191 of each (N, 3) direction (need not be unit length; zero vectors -> -1)."""
    v = np.asarray(direction, dtype=float).reshape(-1, 3)
    n = np.linalg.norm(v, axis=1)
    ok = np.isfinite(n) & (n > 0)
    z = np.divide(v[:, 2], n, out=np.zeros_like(n), where=ok)
    band = np.clip(np.floor((z + 1.0) / 2.0 * N_BANDS), 0, N_BANDS - 1).astype(np.int64)
    lon = np.mod(np.arctan2(v[:, 1], v[:, 0]), 2 * math.pi)
    sector = np.clip(np.floor(lon / (2 * math.pi) * N_SECTORS), 0, N_SECTORS - 1).astype(np.int64)
    return np.where(ok, band * N_SECTORS + sector, -1)


def bin_center(k) -> np.ndarray:
    """(N, 3) unit vector at the centre (mid z, mid longitude) of bins ``k``."""
    k = np.asarray(k, dtype=np.int64).reshape(-1)
    z = -1.0 + (k // N_SECTORS + 0.5) * 2.0 / N_BANDS
    lon = (k % N_SECTORS + 0.5) * 2 * math.pi / N_SECTORS
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(lon), r * np.sin(lon), z])


def temp_band(temp_c) -> np.ndarray:
    t = np.asarray(temp_c, dtype=float).reshape(-1)
    return np.clip(np.floor((t - TEMP_RANGE_C[0]) / TEMP_BAND_C), 0, N_TEMP - 1).astype(np.int64)


@dataclass
class AttitudeCoverage:
    """Sample counts per (temperature band, direction bin)."""

    counts: np.ndarray = field(default_factory=lambda: np.zeros((N_TEMP, N_BINS), dtype=np.int64))

    def update(self, b_sensor_uT, temp_c) -> None:
        k = bin_index(b_sensor_uT)
        tb = temp_band(temp_c)
        ok = (k >= 0) & np.isfinite(np.asarray(temp_c, dtype=float).reshape(-1))
        np.add.at(self.counts, (tb[ok], k[ok]), 1)

    def merge(self, other: AttitudeCoverage) -> AttitudeCoverage:
        return AttitudeCoverage(self.counts + other.counts)

    @property
    def bins_filled(self) -> int:
        return int(np.count_nonzero(self.counts.sum(axis=0)))

    @property
    def fraction(self) -> float:
        """Fraction of the 192 direction bins holding data (any temperature)."""
        return self.bins_filled / N_BINS

    def bins_in_temp(self, lo_c: float, hi_c: float) -> int:
        """Direction bins holding data from temperature bands overlapping [lo_c, hi_c]."""
        a, b = temp_band([lo_c])[0], temp_band([hi_c])[0]
        return int(np.count_nonzero(self.counts[a:b + 1].sum(axis=0)))

    def per_temp_band(self) -> list[tuple[float, float, int]]:
        """(band lo degC, band hi degC, bins filled) for every band holding data."""
        out = []
        for j in np.flatnonzero(self.counts.sum(axis=1)):
            lo = TEMP_RANGE_C[0] + j * TEMP_BAND_C
            out.append((lo, lo + TEMP_BAND_C, int(np.count_nonzero(self.counts[j]))))
        return out
