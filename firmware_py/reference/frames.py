"""Time scales and frames: Unix UTC -> ERFA two-part Julian dates, ITRS (ECEF) -> GCRS, Sun, eclipse.

Frames (docs/refit.md):

* ITRS: Earth-fixed ("ECEF", WGS84 realises it to centimetres); telemetry ``pos_ecef_*_km``.
* GCRS: geocentric inertial (J2000/EME2000 matches it to well under an arcsecond); ``q_body_eci``
  rotates GCRS components into body components.

ITRS -> GCRS is the IAU 2006/2000A CIO-based transform: ``v_gcrs = (W R3(ERA) Q)^T v_itrs`` with
Q the bias-precession-nutation matrix (``erfa.c2i06a``), ERA the Earth rotation angle from UT1
(``erfa.era00``), W polar motion (taken as identity: |xp|, |yp| < 0.6 arcsec, under 0.15 nT at
50 uT). Q moves by under 0.03 arcsec per hour, so it is evaluated on a grid (``q_grid_s``, default
1 h) and interpolated linearly per matrix element (interpolation error below 1e-9 rad, tested
against per-sample ``erfa.c2t06a``); ERA is evaluated per sample. UT1 = UTC + ``dut1_s``: IERS keeps
|UT1 - UTC| < 0.9 s, which as an Earth-rotation angle is under 13.5 arcsec (about 3 nT at 50 uT);
pass the IERS Bulletin A value when that matters.

Time: ``t_s`` is Unix seconds (UTC, POSIX: no leap seconds counted). A sample inside a leap
second is not representable; every other instant maps exactly.
"""
from __future__ import annotations

import warnings

import erfa
import numpy as np

from magstack.firmware.errors import InputDataError

#: Unix epoch as a Julian date.
UNIX_EPOCH_JD = 2440587.5
#: Equatorial radius of the Earth (WGS84), km: used for the cylindrical Earth shadow.
R_EARTH_KM = 6378.137
#: Default grid step for the precession-nutation matrix, s.
Q_GRID_S = 3600.0


def _t(t_s) -> np.ndarray:
    t = np.asarray(t_s, dtype=float).reshape(-1)
    if not np.all(np.isfinite(t)):
        raise InputDataError("time t_s must be finite Unix seconds")
    return t


def _grid_around(t: np.ndarray, step_s: float) -> np.ndarray:
    """Grid nodes (s) bracketing every sample: for each sample the nodes just below and above it on a
    ``step_s`` grid (so sparse data spanning years costs no more nodes than it has samples)."""
    lo = float(t.min())
    k = np.floor((t - lo) / step_s)
    nodes = np.unique(np.concatenate([k, k + 1]))
    return lo + nodes * step_s


def utc_jd(t_s) -> tuple[np.ndarray, np.ndarray]:
    """Unix seconds -> ERFA UTC two-part quasi Julian date (day number, fraction of day)."""
    t = _t(t_s)
    day = np.floor(t / 86400.0)
    return UNIX_EPOCH_JD + day, (t - day * 86400.0) / 86400.0


def tt_jd(t_s) -> tuple[np.ndarray, np.ndarray]:
    """Unix seconds (UTC) -> TT two-part Julian date (leap seconds from ERFA's table; past the
    table's end ERFA holds the last TAI-UTC and flags a "dubious year", which is silenced here:
    correct unless a new leap second is announced)."""
    u1, u2 = utc_jd(t_s)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", erfa.ErfaWarning)
        a1, a2 = erfa.utctai(u1, u2)
    return erfa.taitt(a1, a2)


def ut1_jd(t_s, dut1_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Unix seconds (UTC) -> UT1 two-part Julian date, UT1 = UTC + dut1_s."""
    u1, u2 = utc_jd(t_s)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", erfa.ErfaWarning)
        return erfa.utcut1(u1, u2, float(dut1_s))


def earth_rotation_angle_rad(t_s, dut1_s: float = 0.0) -> np.ndarray:
    """IAU 2000 Earth rotation angle (rad, 0..2pi)."""
    return erfa.era00(*ut1_jd(t_s, dut1_s))


def gcrs_to_itrs_matrix(t_s, dut1_s: float = 0.0, q_grid_s: float = Q_GRID_S) -> np.ndarray:
    """(N, 3, 3) matrices M with ``v_itrs = M @ v_gcrs`` (transpose for ITRS -> GCRS)."""
    t = _t(t_s)
    if t.size == 0:
        return np.zeros((0, 3, 3))
    grid = _grid_around(t, q_grid_s)
    q_grid = erfa.c2i06a(*tt_jd(grid)).reshape(grid.size, 9)
    q = np.empty((t.size, 9))
    for k in range(9):
        q[:, k] = np.interp(t, grid, q_grid[:, k])
    era = earth_rotation_angle_rad(t, dut1_s)
    return erfa.c2tcio(q.reshape(-1, 3, 3), era, np.eye(3))


def itrs_to_gcrs(t_s, v_itrs, dut1_s: float = 0.0) -> np.ndarray:
    """(N, 3) Earth-fixed components -> GCRS components (any unit)."""
    v = np.asarray(v_itrs, dtype=float).reshape(-1, 3)
    m = gcrs_to_itrs_matrix(t_s, dut1_s)
    return np.einsum("nji,nj->ni", m, v)


def gcrs_to_itrs(t_s, v_gcrs, dut1_s: float = 0.0) -> np.ndarray:
    """(N, 3) GCRS components -> Earth-fixed components (any unit)."""
    v = np.asarray(v_gcrs, dtype=float).reshape(-1, 3)
    m = gcrs_to_itrs_matrix(t_s, dut1_s)
    return np.einsum("nij,nj->ni", m, v)


def geodetic_to_ecef_km(lat_deg, lon_deg, height_km) -> np.ndarray:
    """WGS84 geodetic latitude/longitude (deg) and height (km) -> (N, 3) ECEF km."""
    lat, lon, h = np.broadcast_arrays(np.asarray(lat_deg, float), np.asarray(lon_deg, float),
                                      np.asarray(height_km, float))
    xyz = erfa.gd2gc(1, np.radians(lon).reshape(-1), np.radians(lat).reshape(-1), h.reshape(-1) * 1e3)
    return np.asarray(xyz).reshape(-1, 3) / 1e3


def ecef_to_geodetic(pos_ecef_km) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) ECEF km -> WGS84 geodetic latitude (deg), longitude (deg), height (km)."""
    p = np.asarray(pos_ecef_km, dtype=float).reshape(-1, 3)
    if not np.all(np.isfinite(p)) or np.any(np.linalg.norm(p, axis=1) < 100.0):
        raise InputDataError("ECEF positions must be finite and away from the geocentre (km, not m?)")
    lon, lat, h = erfa.gc2gd(1, p * 1e3)
    return np.degrees(lat), np.degrees(lon), h / 1e3


#: Grid step for the Sun direction, s (it moves about 0.007 deg in 10 min; linear interpolation).
SUN_GRID_S = 600.0


def sun_direction_gcrs(t_s, grid_s: float = SUN_GRID_S) -> np.ndarray:
    """(N, 3) unit vector from the Earth's centre to the Sun, GCRS axes (geometric, no aberration:
    20 arcsec, irrelevant for eclipse). ``erfa.epv00`` on a ``grid_s`` grid, interpolated."""
    t = _t(t_s)
    if t.size == 0:
        return np.zeros((0, 3))
    grid = _grid_around(t, grid_s)
    pvh, _ = erfa.epv00(*tt_jd(grid))
    sg = -np.asarray(pvh["p"]).reshape(-1, 3)
    s = np.column_stack([np.interp(t, grid, sg[:, k]) for k in range(3)])
    return s / np.linalg.norm(s, axis=1, keepdims=True)


def in_eclipse(t_s, pos_gcrs_km) -> np.ndarray:
    """(N,) bool: inside the Earth's cylindrical shadow (behind the Earth, within R_EARTH_KM of the
    Earth-Sun line). Penumbra (about 10 s per pass at LEO) counts as sunlit."""
    r = np.asarray(pos_gcrs_km, dtype=float).reshape(-1, 3)
    s = sun_direction_gcrs(t_s)
    along = np.sum(r * s, axis=1)
    perp = np.linalg.norm(r - along[:, None] * s, axis=1)
    return (along < 0) & (perp < R_EARTH_KM)
