"""Reference field (IGRF-14 via ppigrf), frames (ERFA) and the attitude convention."""
from __future__ import annotations

import datetime as dt
import math

import erfa
import numpy as np
import ppigrf
import pytest
from scipy.spatial.transform import Rotation

from magstack.firmware.errors import InputDataError
from magstack.firmware.reference import frames, geomag

T2026 = dt.datetime(2026, 3, 1, tzinfo=dt.UTC).timestamp()


def test_pinned_model_is_igrf14():
    # IGRF-14 coefficient table (IAGA V-MOD, 2024 release): g(1,0) of DGRF 2020 = -29403.41 nT,
    # IGRF 2025 = -29350.0 nT, secular variation 2025-2030 = +12.6 nT/yr (-> -29287.0 nT in 2030)
    g, h = ppigrf.ppigrf.read_shc(ppigrf.ppigrf.shc_fn)
    g10 = g[(1, 0)]
    assert g10.loc["2020-01-01"] == pytest.approx(-29403.41)
    assert g10.loc["2025-01-01"] == pytest.approx(-29350.0)
    assert g10.loc["2030-01-01"] == pytest.approx(-29350.0 + 5 * 12.6)
    assert geomag.igrf_epochs_s()[-1] == dt.datetime(2030, 1, 1, tzinfo=dt.UTC).timestamp()


@pytest.mark.parametrize("height_km, xyz_nT", [(0.0, (27455.6, -1924.6, -15996.8)),
                                               (500.0, (21550.0, -1684.8, -10816.4))])
def test_published_calculator_values(height_km, xyz_nT):
    # NOAA NCEI magnetic field calculator, IGRF model, at decimal year 2025.03288, geodetic latitude 0,
    # longitude 0 (north, east, down, printed to 0.1 nT), as quoted in a public pyIGRF check script
    t = dt.datetime(2025, 1, 1, tzinfo=dt.UTC).timestamp() + 0.03288 * 365 * 86400
    got = geomag.igrf_geodetic_nT(np.array([t]), 0.0, 0.0, height_km)[0]
    assert np.max(np.abs(got - np.array(xyz_nT))) < 0.5


def test_agrees_with_independent_implementation_pyIGRF14():
    pyIGRF14 = pytest.importorskip("pyIGRF14")
    rng = np.random.default_rng(7)
    n = 40
    lat = rng.uniform(-85, 85, n)
    lon = rng.uniform(-180, 180, n)
    h = rng.uniform(0, 800, n)
    years = rng.uniform(2020.2, 2029.8, n)
    t = np.array([dt.datetime(int(y), 1, 1, tzinfo=dt.UTC).timestamp()
                  + (y - int(y)) * (366 if int(y) % 4 == 0 else 365) * 86400 for y in years])
    ours = np.vstack([geomag.igrf_geodetic_nT(t[k:k + 1], lat[k], lon[k], h[k]) for k in range(n)])
    theirs = np.array([pyIGRF14.igrf_value(lat[k], lon[k], h[k], years[k])[3:6] for k in range(n)])
    # pyIGRF14 interpolates in decimal years, ppigrf in time: same model to well under 1 nT
    assert np.max(np.abs(ours - theirs)) < 1.0


def test_two_epoch_evaluation_equals_direct_ppigrf_call_at_the_date():
    rng = np.random.default_rng(3)
    n = 500
    t = T2026 + rng.uniform(0, 3 * 365 * 86400, n)
    p = rng.normal(size=(n, 3))
    p *= (6878.0 / np.linalg.norm(p, axis=1))[:, None]
    ours = geomag.igrf_ecef_nT(t, p)
    for k in range(0, n, 97):
        r = np.linalg.norm(p[k])
        th = math.acos(p[k, 2] / r)
        ph = math.atan2(p[k, 1], p[k, 0])
        d = dt.datetime.fromtimestamp(t[k], dt.UTC).replace(tzinfo=None)
        br, bt, bp = (x.ravel()[0] for x in ppigrf.igrf_gc(r, math.degrees(th), math.degrees(ph), d))
        direct = geomag.spherical_to_ecef(np.array([th]), np.array([ph]), br, bt, bp)[0]
        assert np.allclose(ours[k], direct, atol=1e-6)


def test_degree_one_is_the_closed_form_dipole(monkeypatch):
    monkeypatch.setattr(geomag, "MAX_DEGREE", 1)
    g, h = ppigrf.ppigrf.read_shc(ppigrf.ppigrf.shc_fn)
    m = np.array([g[(1, 1)].loc["2025-01-01"], h[(1, 1)].loc["2025-01-01"], g[(1, 0)].loc["2025-01-01"]])
    t = np.full(3, dt.datetime(2025, 1, 1, tzinfo=dt.UTC).timestamp())
    p = np.array([[7000.0, 0.0, 0.0], [0.0, -6800.0, 1000.0], [1000.0, 2000.0, -6500.0]])
    b = geomag.igrf_ecef_nT(t, p)
    a = 6371.2
    for k in range(3):
        r = np.linalg.norm(p[k])
        u = p[k] / r
        expect = (a / r) ** 3 * (3 * np.dot(m, u) * u - m)   # B = -grad(a^3 m.r / r^3)
        assert np.allclose(b[k], expect, atol=1e-6)


def test_bad_inputs_raise_typed_errors():
    with pytest.raises(InputDataError, match="IGRF-14 covers"):
        geomag.igrf_ecef_nT([dt.datetime(2031, 1, 1, tzinfo=dt.UTC).timestamp()], [[7000.0, 0, 0]])
    with pytest.raises(InputDataError, match="6300..100000 km"):
        geomag.igrf_ecef_nT([T2026], [[7000e3, 0, 0]])
    with pytest.raises(InputDataError, match="not unit"):
        geomag.attitude([[2.0, 0, 0, 0]])


def test_itrs_gcrs_round_trip_and_agreement_with_erfa_per_sample_transform():
    rng = np.random.default_rng(1)
    t = T2026 + np.sort(rng.uniform(0, 2 * 86400, 300))
    v = rng.normal(size=(300, 3))
    back = frames.gcrs_to_itrs(t, frames.itrs_to_gcrs(t, v))
    assert np.allclose(back, v, atol=1e-12)
    m = frames.gcrs_to_itrs_matrix(t)
    u1, u2 = frames.utc_jd(t)
    tt1, tt2 = frames.tt_jd(t)
    exact = erfa.c2t06a(tt1, tt2, *erfa.utcut1(u1, u2, 0.0), 0.0, 0.0)   # per-sample IAU 2006/2000A
    ang = Rotation.from_matrix(np.einsum("nij,nkj->nik", m, exact)).magnitude()
    assert ang.max() < 1e-9


def test_earth_rotation_angle_known_values():
    # IERS Conventions (2010) eq. 5.15: ERA(Tu) = 2 pi (0.7790572732640 + 1.00273781191135448 Tu),
    # Tu = JD(UT1) - 2451545.0; at J2000.0 (2000-01-01 12:00 UT1) ERA = 280.46061837504 deg
    t_j2000 = dt.datetime(2000, 1, 1, 12, tzinfo=dt.UTC).timestamp()
    assert math.degrees(frames.earth_rotation_angle_rad([t_j2000], dut1_s=0.0)[0]) == pytest.approx(
        280.46061837504, abs=1e-9)
    t = T2026
    tu = (t / 86400.0 + 2440587.5) - 2451545.0
    want = 2 * math.pi * ((0.7790572732640 + 1.00273781191135448 * tu) % 1.0)
    assert frames.earth_rotation_angle_rad([t])[0] == pytest.approx(want, abs=1e-9)


def test_precession_nutation_is_not_neglected():
    # A GMST-only Earth-fixed -> inertial rotation misses precession since J2000: about 0.36 deg by
    # 2026 (50.3 arcsec/yr x 26 yr, in right ascension), plus the pole's 20 arcsec/yr (0.146 deg)
    t = np.array([T2026])
    m = frames.gcrs_to_itrs_matrix(t)[0]
    tt = frames.tt_jd(t)
    gmst = erfa.gmst06(*frames.ut1_jd(t), *tt)[0]
    gmst_only = Rotation.from_euler("z", -gmst).as_matrix()   # v_tod = R3(GMST)^T v_itrs
    err = math.degrees(Rotation.from_matrix(gmst_only @ m.T).magnitude())
    assert 0.33 < err < 0.45
    pole = math.degrees(math.acos(np.clip((m.T @ [0, 0, 1.0])[2], -1, 1)))   # ITRS z in GCRS
    assert 0.13 < pole < 0.16


def test_attitude_convention_scalar_first_gcrs_to_body():
    # q_body_eci = (cos 45, 0, 0, sin 45): the rotation by +90 deg about z applied to GCRS components
    # gives body components: inertial x has body components (0, 1, 0)
    q = np.array([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]])
    assert np.allclose(geomag.attitude(q).apply([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0])
    assert np.allclose(Rotation.from_quat(q[0, [1, 2, 3, 0]]).apply([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0])
    t = np.array([T2026])
    p = np.array([[0.0, 0.0, 6878.0]])
    b_gcrs = frames.itrs_to_gcrs(t, geomag.igrf_ecef_nT(t, p)) / 1e3
    b_body = geomag.body_field_uT(t, p, q)
    assert np.allclose(b_body[0], [-b_gcrs[0, 1], b_gcrs[0, 0], b_gcrs[0, 2]])
    assert np.linalg.norm(b_body) == pytest.approx(np.linalg.norm(b_gcrs))


def test_sun_direction_and_eclipse():
    # March equinox 2026: 2026-03-20 14:46 UTC, the Sun crosses the true equator of date at the true
    # equinox of date; in GCRS (J2000 axes) it is then about 0.36 deg away from +x (precession)
    t = np.array([dt.datetime(2026, 3, 20, 14, 46, tzinfo=dt.UTC).timestamp()])
    s = frames.sun_direction_gcrs(t)[0]
    s_tod = erfa.pnm06a(*frames.tt_jd(t))[0] @ s
    assert math.degrees(math.acos(s_tod[0])) < 0.03
    assert 0.3 < math.degrees(math.acos(s[0])) < 0.42
    behind = -s * 6878.0
    beside = np.cross(s, [0, 0, 1.0]) * 6878.0 / np.linalg.norm(np.cross(s, [0, 0, 1.0]))
    assert frames.in_eclipse(np.r_[t, t, t], np.vstack([behind, beside, -behind])).tolist() == [True, False, False]


def test_geodetic_round_trip():
    p = frames.geodetic_to_ecef_km([10.0, -45.0], [20.0, 170.0], [500.0, 0.0])
    lat, lon, h = frames.ecef_to_geodetic(p)
    assert np.allclose(lat, [10.0, -45.0]) and np.allclose(lon, [20.0, 170.0]) and np.allclose(h, [500.0, 0.0])


def test_sparse_samples_years_apart_use_a_grid_around_each_sample():
    t = np.array([dt.datetime(2021, 5, 1, tzinfo=dt.UTC).timestamp(), T2026, T2026 + 1800.0,
                  dt.datetime(2029, 9, 1, tzinfo=dt.UTC).timestamp()])
    m = frames.gcrs_to_itrs_matrix(t)
    exact = erfa.c2t06a(*frames.tt_jd(t), *frames.ut1_jd(t), 0.0, 0.0)
    assert Rotation.from_matrix(np.einsum("nij,nkj->nik", m, exact)).magnitude().max() < 1e-9
    assert frames._grid_around(t, frames.Q_GRID_S).size <= 2 * t.size


def test_batch_spanning_an_igrf_epoch_is_continuous_and_exact():
    t25 = dt.datetime(2025, 1, 1, tzinfo=dt.UTC).timestamp()
    t = t25 + np.array([-3600.0, -1.0, 0.0, 1.0, 3600.0])
    p = np.tile([[3000.0, -4000.0, 4500.0]], (5, 1))
    b = geomag.igrf_ecef_nT(t, p)
    assert np.max(np.abs(np.diff(b, axis=0))) < 0.1          # secular variation: ~0.01 nT per hour
    r = np.linalg.norm(p[0])
    th, ph = math.acos(p[0, 2] / r), math.atan2(p[0, 1], p[0, 0])
    for k in (0, 4):
        d = dt.datetime.fromtimestamp(t[k], dt.UTC).replace(tzinfo=None)
        br, bt, bp = (x.ravel()[0] for x in ppigrf.igrf_gc(r, math.degrees(th), math.degrees(ph), d))
        assert np.allclose(b[k], geomag.spherical_to_ecef(np.array([th]), np.array([ph]), br, bt, bp)[0],
                           atol=1e-6)
