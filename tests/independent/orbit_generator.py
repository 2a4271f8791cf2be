"""An orbit telemetry generator that shares no code with magstack (the independent check of the orbit diagnosis).

Circular 97.4 deg orbit at 520 km in GCRS; the Earth-fixed position by ERFA's celestial-to-terrestrial matrix
(IAU 2006/2000A, UT1 = UTC, no polar motion); geodetic coordinates by ERFA; the field by ppigrf (IGRF, one date
for the whole pass) in north-east-down, turned to Earth-fixed and back to GCRS; the body attitude a steady
tumble about a fixed axis (0.8 deg/s); the sensor: a gain matrix, an offset, a sensitivity that falls with
temperature (optional), white noise; the temperature a sine over the orbit. Written as a telemetry file without
reference columns (docs/refit.md columns), currents absent.
"""
from __future__ import annotations

import datetime as dt

import erfa
import numpy as np
import ppigrf
from scipy.spatial.transform import Rotation

T0 = dt.datetime(2026, 3, 1, tzinfo=dt.UTC)


def orbit_telemetry(path, seconds=11400.0, rate_hz=0.5, tempco=0.0, seed=0, noise_uT=0.03):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    r_km, inc = 6378.137 + 520.0, np.deg2rad(97.4)
    u = 2 * np.pi * t / (2 * np.pi * np.sqrt(r_km ** 3 / 398600.4418))
    p_gcrs = r_km * np.column_stack([np.cos(u), np.sin(u) * np.cos(inc), np.sin(u) * np.sin(inc)])
    jd = 2440587.5 + (T0.timestamp() + t) / 86400.0
    tt = jd + 69.184 / 86400.0
    c2t = erfa.c2t06a(np.full(t.size, 2400000.5), tt - 2400000.5, np.full(t.size, 2400000.5), jd - 2400000.5,
                      np.zeros(t.size), np.zeros(t.size))
    p_ecef = np.einsum("nij,nj->ni", c2t, p_gcrs)
    elon, phi, height = erfa.gc2gd(1, p_ecef * 1e3)
    be, bn, bu = ppigrf.igrf(np.rad2deg(elon), np.rad2deg(phi), height / 1e3, T0.replace(tzinfo=None))
    be, bn, bu = (np.asarray(x, dtype=float).reshape(-1) for x in (be, bn, bu))
    sl, cl, sp, cp = np.sin(elon), np.cos(elon), np.sin(phi), np.cos(phi)
    east = np.column_stack([-sl, cl, np.zeros_like(sl)])
    north = np.column_stack([-sp * cl, -sp * sl, cp])
    up = np.column_stack([cp * cl, cp * sl, sp])
    b_ecef = (be[:, None] * east + bn[:, None] * north + bu[:, None] * up) / 1e3      # uT
    b_gcrs = np.einsum("nji,nj->ni", c2t, b_ecef)
    axis = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    att = Rotation.from_rotvec(np.outer(np.deg2rad(0.8) * t, axis))
    b_body = att.apply(b_gcrs)
    q = att.as_quat()                                   # x, y, z, w
    temp = 20.0 + 15.0 * np.sin(2 * np.pi * t / 5700.0)
    G = np.array([[1.08, 0.03, -0.02], [0.02, 1.12, 0.01], [-0.03, 0.02, 1.10]])
    dut = (b_body @ G.T) * (1.0 + tempco * (temp - 25.0))[:, None] + np.array([0.4, -0.2, 0.3])
    dut = dut + rng.standard_normal(dut.shape) * noise_uT
    cols = ["t_s", "dut_x_uT", "dut_y_uT", "dut_z_uT", "temp_c", "session", "pos_ecef_x_km", "pos_ecef_y_km",
            "pos_ecef_z_km", "q_body_eci_w", "q_body_eci_x", "q_body_eci_y", "q_body_eci_z"]
    data = np.column_stack([T0.timestamp() + t, dut, temp, (t // (seconds / 3)).astype(int), p_ecef,
                            q[:, 3], q[:, 0], q[:, 1], q[:, 2]])
    with open(path, "w") as fh:
        fh.write("# magstack-session: 1\n# dut_chip: hmc1053\n# source: independent orbit generator\n")
        fh.write(",".join(cols) + "\n")
        for row in data:
            fh.write(",".join(f"{v:.6f}" if i != 5 else str(int(v)) for i, v in enumerate(row)) + "\n")
    return path
