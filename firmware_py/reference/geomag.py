"""IGRF-14 main field at time-tagged positions (vectorised spherical harmonics), rotated into the body frame.

The Gauss coefficients are those ppigrf ships (pinned in pyproject; its ``IGRF14.shc`` is read once
through ``ppigrf.read_shc``: no number is copied here), and the field is the degree-13
spherical-harmonic sum ppigrf's ``igrf_gc`` evaluates, in geocentric spherical coordinates with
ppigrf's reference radius: Schmidt semi-normalised associated Legendre functions by the same
recursion, ``B = -grad V``. ppigrf builds pandas frames and re-reads its file on every call; here
the evaluation is plain numpy on blocks of ``CHUNK`` positions (tests hold it to ppigrf at 1e-6 nT;
``benchmarks/bench_igrf.py`` times both).

Time: IGRF's coefficients are linear in time between consecutive epochs (5-year models, then the
secular variation to the last epoch), as ppigrf interpolates them (pandas "time" interpolation of
the coefficient table), so every sample gets ``g(t) = g_a + w (g_b - g_a)``, ``w = (t - t_a) /
(t_b - t_a)``: the field at each sample's own time exactly.

Units: positions km, field nT (IGRF) or uT (``*_uT``), time Unix s UTC.
"""
from __future__ import annotations

import datetime as _dt
import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from magstack.firmware import blas
from magstack.firmware.errors import InputDataError
from magstack.firmware.reference import frames

#: Positions per evaluation block: the (terms x CHUNK) work arrays stay cache-sized (benchmarks/bench_igrf.py).
CHUNK = 1024
#: IGRF degree used (full IGRF-14 main field).
MAX_DEGREE = 13
#: Colatitude kept this far from the poles (rad), where B_phi is 0/0 (as in ppigrf).
POLE_EPS_RAD = 1e-9


def _ppigrf():
    """ppigrf, imported on first use (it imports pandas: keeps ``magstack --help`` fast)."""
    import ppigrf

    return ppigrf


@dataclass(frozen=True)
class Coefficients:
    """Gauss coefficients, terms ordered by degree then order (n >= 1, 0 <= m <= n): ``g_nT``,
    ``h_nT`` (epochs, terms) nT; ``epochs_s`` Unix s; ``radius_km`` the expansion's reference radius."""

    epochs_s: np.ndarray
    n: np.ndarray
    m: np.ndarray
    g_nT: np.ndarray
    h_nT: np.ndarray
    radius_km: float


@functools.cache
def coefficients() -> Coefficients:
    """IGRF-14 as read from the installed ppigrf package's ``.shc`` file (once per process)."""
    pp = _ppigrf().ppigrf
    g, h = pp.read_shc(pp.shc_fn)
    keys = sorted(g.columns)
    epochs = np.array([_dt.datetime(d.year, d.month, d.day, tzinfo=_dt.UTC).timestamp() for d in g.index])
    return Coefficients(epochs, np.array([k[0] for k in keys]), np.array([k[1] for k in keys]),
                        g[keys].to_numpy(float), h[keys].to_numpy(float), float(pp.RE))


def igrf_epochs_s() -> np.ndarray:
    """Epochs of the coefficient file as Unix seconds (1900, 1905, ..., 2030)."""
    return coefficients().epochs_s


def _date(t_s: float) -> _dt.datetime:
    return _dt.datetime.fromtimestamp(t_s, _dt.UTC).replace(tzinfo=None)


def _row(n: int) -> int:
    """Row of P_n0 in the packed (n, m) order 00, 10, 11, 20, 21, 22, ... (P_nm is row ``_row(n) + m``)."""
    return n * (n + 1) // 2


@functools.cache
def _recursion(max_degree: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple]:
    """(n, m, Schmidt factors S_nm of the terms n = 1..max_degree, per-degree K_nm vectors) for the
    recursion of ppigrf's ``get_legendre`` on Gauss-normalised P_nm (``P_nm = S_nm * Gauss P_nm``)."""
    n = np.concatenate([np.full(a + 1, a) for a in range(1, max_degree + 1)])
    m = np.concatenate([np.arange(a + 1) for a in range(1, max_degree + 1)])
    schmidt = {(0, 0): 1.0}
    for a in range(1, max_degree + 1):
        for b in range(a + 1):
            schmidt[a, b] = (schmidt[a - 1, 0] * (2.0 * a - 1) / a if b == 0
                             else schmidt[a, b - 1] * math.sqrt((a - b + 1) * (int(b == 1) + 1.0) / (a + b)))
    snm = np.array([schmidt[a, b] for a, b in zip(n.tolist(), m.tolist(), strict=True)])
    c = coefficients()
    if not (np.array_equal(c.n[:n.size], n) and np.array_equal(c.m[:n.size], m)):
        raise RuntimeError("ppigrf's coefficient file is not ordered by degree and order up to the degree used")
    knm = tuple(np.array([((a - 1) ** 2 - b ** 2) / ((2 * a - 1) * (2 * a - 3)) for b in range(a - 1)])[:, None]
                if a > 1 else None for a in range(max_degree + 1))
    return n, m, snm, knm


def _legendre(theta_rad: np.ndarray, max_degree: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, N) Gauss-normalised P_nm(cos theta) and dP_nm/dtheta, packed as :func:`_row`, n = 0..max_degree.
    Each degree is one vectorised step over its orders: ``P_nm = cos P_n-1,m - K_nm P_n-2,m``
    (``dP`` likewise, ``- sin P_n-1,m``), and the diagonal ``P_nn = sin P_n-1,n-1``."""
    knm = _recursion(max_degree)[3]
    st, ct = np.sin(theta_rad), np.cos(theta_rad)
    p = np.empty((_row(max_degree + 1), theta_rad.size))
    dp = np.empty_like(p)
    p[0], dp[0] = 1.0, 0.0
    for a in range(1, max_degree + 1):
        cur, prev = _row(a), _row(a - 1)
        pn, dpn, pp, dpp = p[cur:cur + a + 1], dp[cur:cur + a + 1], p[prev:prev + a], dp[prev:prev + a]
        np.multiply(ct, pp, out=pn[:a])
        np.multiply(ct, dpp, out=dpn[:a])
        dpn[:a] -= st * pp
        np.multiply(st, pp[a - 1], out=pn[a])
        np.multiply(st, dpp[a - 1], out=dpn[a])
        dpn[a] += ct * pp[a - 1]
        if a > 1:
            old = _row(a - 2)
            pn[:a - 1] -= knm[a] * p[old:old + a - 1]
            dpn[:a - 1] -= knm[a] * dp[old:old + a - 1]
    return p, dp


def igrf_spherical_nT(r_km, theta_rad, phi_rad, g_nT, h_nT, dg_nT=None, dh_nT=None, w=None,
                      max_degree: int | None = None) -> np.ndarray:
    """(3, N) field (B_r, B_theta, B_phi) nT, geocentric spherical components (up, south, east), at
    radius ``r_km``, colatitude ``theta_rad`` and longitude ``phi_rad`` (N,), for the coefficients
    ``g + w dg``, ``h + w dh`` (terms as :func:`coefficients`; without ``w`` just ``g``, ``h``)."""
    deg = MAX_DEGREE if max_degree is None else int(max_degree)
    n, m, snm, _ = _recursion(deg)
    k = n.size
    sets = [(g_nT, h_nT)] + ([(dg_nT, dh_nT)] if w is not None else [])
    # With Schmidt P = S * (Gauss P) and X = (a/r)^(n+2) * Gauss P:
    #   B_r = sum (n+1) S X (g cos + h sin),  B_theta = -sum S dX (g cos + h sin),
    #   B_phi sin(theta) = sum m S X (g sin - h cos):
    # coefficient rows against the bases [X cos(m phi); X sin(m phi)] and [dX cos; dX sin].
    c_p, c_dp = [], []
    for g, h in sets:
        g, h = snm * np.asarray(g, float)[:k], snm * np.asarray(h, float)[:k]
        c_p += [np.r_[(n + 1) * g, (n + 1) * h], np.r_[-m * h, m * g]]
        c_dp.append(np.r_[-g, -h])
    c_p, c_dp = np.array(c_p), np.array(c_dp)
    a = coefficients().radius_km
    r = np.asarray(r_km, float).reshape(-1)
    th = np.asarray(theta_rad, float).reshape(-1)
    ph = np.asarray(phi_rad, float).reshape(-1)
    ws = None if w is None else np.broadcast_to(np.asarray(w, float).reshape(-1), r.shape)
    out = np.empty((3, r.size))
    for k0 in range(0, r.size, CHUNK):
        sl = slice(k0, k0 + CHUNK)
        nc = th[sl].size
        p, dp = _legendre(th[sl], deg)
        ar = a / r[sl]
        rad = ar * ar                                       # (a/r)^(n+2), n = 1.. in the loop
        e_phi = np.exp(1j * ph[sl])
        z = np.empty((deg + 1, nc), complex)                # exp(i m phi), m = 0..deg
        z[0] = 1.0
        for j in range(1, deg + 1):
            np.multiply(z[j - 1], e_phi, out=z[j])
        cos_m, sin_m = z.real, z.imag
        basis = np.empty((2 * k, nc))
        dbasis = np.empty((2 * k, nc))
        for d in range(1, deg + 1):
            rad = rad * ar
            src, dst = slice(_row(d), _row(d) + d + 1), slice(_row(d) - 1, _row(d) + d)
            x, dx = p[src] * rad, dp[src] * rad
            np.multiply(x, cos_m[:d + 1], out=basis[dst])
            np.multiply(x, sin_m[:d + 1], out=basis[k + dst.start:k + dst.stop])
            np.multiply(dx, cos_m[:d + 1], out=dbasis[dst])
            np.multiply(dx, sin_m[:d + 1], out=dbasis[k + dst.start:k + dst.stop])
        bp = c_p @ basis                                     # rows: (B_r, B_phi sin(theta)) per set
        bd = c_dp @ dbasis                                   # rows: B_theta per set
        bp[1::2] /= np.sin(th[sl])
        if ws is None:
            out[0, sl], out[2, sl], out[1, sl] = bp[0], bp[1], bd[0]
        else:
            wk = ws[sl]
            out[0, sl] = bp[0] + wk * bp[2]
            out[2, sl] = bp[1] + wk * bp[3]
            out[1, sl] = bd[0] + wk * bd[1]
    return out


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
    c = coefficients()
    ep = c.epochs_s
    if t.size and (t.min() < ep[0] or t.max() > ep[-1]):
        raise InputDataError(f"IGRF-14 covers {_date(ep[0]).date()}..{_date(ep[-1]).date()}; "
                             f"data spans {_date(t.min())}..{_date(t.max())}")
    # B_phi divides by sin(theta): keep theta 1e-9 rad (6 mm at LEO) off the geographic poles
    theta = np.clip(np.arccos(np.clip(p[:, 2] / r, -1.0, 1.0)), POLE_EPS_RAD, math.pi - POLE_EPS_RAD)
    phi = np.arctan2(p[:, 1], p[:, 0])
    seg = np.clip(np.searchsorted(ep, t, side="right") - 1, 0, ep.size - 2)
    out = np.empty((t.size, 3))
    segments = np.unique(seg)
    with blas.single_thread():        # (6 x 208) x (208 x CHUNK) products: threads only wait
        for s in segments:
            idx = slice(None) if segments.size == 1 else np.flatnonzero(seg == s)
            w = (t[idx] - ep[s]) / (ep[s + 1] - ep[s])
            b = igrf_spherical_nT(r[idx], theta[idx], phi[idx], c.g_nT[s], c.h_nT[s],
                                  c.g_nT[s + 1] - c.g_nT[s], c.h_nT[s + 1] - c.h_nT[s], w)
            out[idx] = spherical_to_ecef(theta[idx], phi[idx], *b)
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
