"""IGRF-14 main field at time-tagged positions through ppigrf, rotated into the body frame.

ppigrf (pinned in pyproject; IGRF-14 coefficients ship in the package, no network) evaluates an
outer product of dates x coordinates and re-reads its coefficient file on every call, so a
one-call-per-sample loop is slow and one call with every sample's date is quadratic. IGRF's
coefficients are linear in time between consecutive epochs (5-year models, then the secular
variation to the last epoch), so at a fixed position the field is linear in time on each
segment: ``B(t) = (1 - w) B(t_a) + w B(t_b)``, ``w = (t - t_a) / (t_b - t_a)``. Each batch is
split by segment and evaluated with the two epoch dates only, in chunks of ``CHUNK`` coordinates
(ppigrf builds (chunk x 208) matrices); the result is IGRF at every sample's own time exactly.

Units: positions km, field nT (IGRF) or uT (``*_uT``), time Unix s UTC.
"""
from __future__ import annotations

import datetime as _dt
import functools
import math

import numpy as np
from scipy.spatial.transform import Rotation

from magstack.firmware.errors import InputDataError
from magstack.firmware.reference import frames

#: Coordinates per ppigrf call (measured in benchmarks/bench_refit.py).
CHUNK = 8192
#: IGRF degree used (full IGRF-14 main field).
MAX_DEGREE = 13
#: Colatitude kept this far from the poles (rad), where ppigrf's B_phi is 0/0.
POLE_EPS_RAD = 1e-9


@functools.cache
def igrf_epochs_s() -> np.ndarray:
    """Epochs of the coefficient file as Unix seconds (1900, 1905, ..., 2030)."""
    g, _ = _ppigrf().ppigrf.read_shc(_ppigrf().ppigrf.shc_fn)
    return np.array([_dt.datetime(d.year, d.month, d.day, tzinfo=_dt.UTC).timestamp() for d in g.index])


def _ppigrf():
    """ppigrf, imported on first use (it imports pandas: keeps ``magstack --help`` fast)."""
    import ppigrf

    return ppigrf


def _date(t_s: float) -> _dt.datetime:
    return _dt.datetime.fromtimestamp(t_s, _dt.UTC).replace(tzinfo=None)


def spherical_to_ecef(theta_rad, phi_rad, b_r, b_theta, b_phi) -> np.ndarray:
    """(N, 3) ECEF components from local spherical components (r up, theta south, phi east)."""
    st, ct, sp, cp = np.sin(theta_rad), np.cos(theta_rad), np.sin(phi_rad), np.cos(phi_rad)
    return np.column_stack([
        b_r * st * cp + b_theta * ct * cp - b_phi * sp,
        b_r * st * sp + b_theta * ct * sp + b_phi * cp,
        b_r * ct - b_theta * st])


def igrf_ecef_nT(t_s, pos_ecef_km) -> np.ndarray:
    """(N, 3) IGRF-14 field, ECEF (ITRS) components, nT, at each sample's own time and position."""
    t = frames._t(t_s)
    p = np.asarray(pos_ecef_km, dtype=float).reshape(-1, 3)
    if p.shape[0] != t.size:
        raise InputDataError(f"{t.size} times but {p.shape[0]} positions")
    if not np.all(np.isfinite(p)):
        raise InputDataError("positions must be finite (drop or flag rows without a GPS fix)")
    r = np.linalg.norm(p, axis=1)
    if np.any(r < 6300.0) or np.any(r > 100_000.0):
        raise InputDataError(f"|position| must be 6300..100000 km (ECEF km), got {r.min():.1f}..{r.max():.1f}")
    ep = igrf_epochs_s()
    igrf_gc = _ppigrf().igrf_gc
    if t.size and (t.min() < ep[0] or t.max() > ep[-1]):
        raise InputDataError(f"IGRF-14 covers {_date(ep[0]).date()}..{_date(ep[-1]).date()}; "
                             f"data spans {_date(t.min())}..{_date(t.max())}")
    # ppigrf divides by sin(theta): keep theta 1e-9 rad (6 mm at LEO) off the geographic poles
    theta = np.clip(np.arccos(np.clip(p[:, 2] / r, -1.0, 1.0)), POLE_EPS_RAD, math.pi - POLE_EPS_RAD)
    phi = np.arctan2(p[:, 1], p[:, 0])
    seg = np.clip(np.searchsorted(ep, t, side="right") - 1, 0, ep.size - 2)
    out = np.empty((t.size, 3))
    for s in np.unique(seg):
        idx = np.flatnonzero(seg == s)
        ta, tb = ep[s], ep[s + 1]
        w = (t[idx] - ta) / (tb - ta)
        for k in range(0, idx.size, CHUNK):
            j = idx[k:k + CHUNK]
            br, bt, bp = igrf_gc(r[j], np.degrees(theta[j]), np.degrees(phi[j]),
                                        [_date(ta), _date(tb)], max_degree=MAX_DEGREE)
            wj = w[k:k + CHUNK]
            comb = [(1.0 - wj) * c[0] + wj * c[1] for c in (br, bt, bp)]
            out[j] = spherical_to_ecef(theta[j], phi[j], *comb)
    return out


def igrf_geodetic_nT(t_s, lat_deg, lon_deg, height_km) -> np.ndarray:
    """(N, 3) IGRF-14 field at WGS84 geodetic positions, local (north, east, down) components, nT."""
    pos = frames.geodetic_to_ecef_km(lat_deg, lon_deg, height_km)
    b = igrf_ecef_nT(t_s, pos)
    lat = np.radians(np.broadcast_to(np.asarray(lat_deg, float), (pos.shape[0],)))
    lon = np.radians(np.broadcast_to(np.asarray(lon_deg, float), (pos.shape[0],)))
    north = np.column_stack([-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)])
    east = np.column_stack([-np.sin(lon), np.cos(lon), np.zeros_like(lon)])
    up = np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    return np.column_stack([np.sum(b * north, 1), np.sum(b * east, 1), -np.sum(b * up, 1)])


def attitude(q_body_eci_wxyz) -> Rotation:
    """The rotation taking GCRS components to body components, from scalar-first quaternions
    ``(w, x, y, z)`` (telemetry ``q_body_eci_w,x,y,z``); scipy takes scalar-last ``[x, y, z, w]``."""
    q = np.asarray(q_body_eci_wxyz, dtype=float).reshape(-1, 4)
    if not np.all(np.isfinite(q)):
        raise InputDataError("attitude quaternions must be finite")
    nrm = np.linalg.norm(q, axis=1)
    if np.any(np.abs(nrm - 1.0) > 1e-3):
        k = int(np.argmax(np.abs(nrm - 1.0)))
        raise InputDataError(f"attitude quaternion row {k} has norm {nrm[k]:.6f}, not unit (scalar first?)")
    return Rotation.from_quat(q[:, [1, 2, 3, 0]])


def body_field_uT(t_s, pos_ecef_km, q_body_eci_wxyz, dut1_s: float = 0.0) -> np.ndarray:
    """(N, 3) IGRF-14 field in the body frame, uT: ECEF field -> GCRS -> ``attitude(q).apply``."""
    t = frames._t(t_s)
    b_itrs = igrf_ecef_nT(t, pos_ecef_km)
    b_gcrs = frames.itrs_to_gcrs(t, b_itrs, dut1_s)
    return attitude(q_body_eci_wxyz).apply(b_gcrs) / 1e3
