"""Orbit truth: a circular LEO with IGRF-14 along it, attitude modes, eclipse thermal cycle, currents.

:class:`OrbitTruth` implements :class:`magstack.sim.truth_source.TruthSource` and the vectorised
series methods (``field_series_uT`` etc.), so it feeds the error model like a coil program. Time
``t_s`` is simulation time (s) from ``epoch_unix_s``; it also exposes what telemetry carries
(``pos_ecef_series_km``, ``q_body_eci_series``) and the eclipse flag.

* Orbit: circular, altitude ``altitude_km``; ``inclination_deg=None`` gives the sun-synchronous
  inclination (J2); the node starts at local time ``ltan_h`` and precesses with J2 (0.9856 deg/day
  for SSO). Position in GCRS, then Earth-fixed through :mod:`magstack.firmware.reference.frames`.
* Field: IGRF-14 (:mod:`magstack.firmware.reference.geomag`) at the Earth-fixed position, rotated
  to GCRS and into the body frame by the attitude (sensor frame = body frame).
* Attitude (rotation GCRS -> body): ``inertial`` (fixed), ``nadir`` (z to nadir, y to minus orbit
  normal, x about along velocity), ``tumbling`` (two incommensurate rotations, covers the sphere),
  ``spinning`` (spin about body z at ``spin_rate_deg_s``; the spin axis precesses on a cone of
  ``cone_deg`` about an inertial axis with period ``precession_s``).
* Temperature: first order towards ``temp_sun_c`` in sunlight and ``temp_eclipse_c`` in eclipse
  (time constant ``thermal_tau_s``), integrated exactly on a 10 s grid and interpolated.
* Currents (A): ``torquer`` (alternating +-pulses), ``solar`` (array current: illuminated cosine
  of the Sun on body +x, zero in eclipse), ``battery`` (solar minus bus load; a heater cycle and the
  torquer draw make the load vary, so battery is not a copy of solar). ``housekeeping_period_s``
  says how often telemetry samples each (``magstack simulate`` leaves the other rows empty).
  ``default_interference_uT_per_A`` is the field per amp at the sensor the simulator adds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from magstack.drivers.errors import ConfigurationError
from magstack.firmware.reference import frames, geomag
from magstack.sim.coil_programs import ORBIT_PROGRAMS
from magstack.sim.truth_source import SeriesTruth

MU_KM3_S2 = 398600.4418
J2 = 1.08262668e-3
#: Sun-synchronous node rate, rad/s (360 deg per tropical year).
SSO_RATE = 2 * math.pi / (365.2422 * 86400.0)
ATTITUDES = ("inertial", "nadir", "tumbling", "spinning")
#: Default epoch of orbit programs (Unix s): 2026-06-01 00:00:00 UTC.
DEFAULT_EPOCH_S = 1780272000.0
_THERMAL_GRID_S = 10.0


def sso_inclination_deg(altitude_km: float) -> float:
    """Sun-synchronous inclination of a circular orbit (J2), deg."""
    a = frames.R_EARTH_KM + altitude_km
    n = math.sqrt(MU_KM3_S2 / a ** 3)
    cos_i = -SSO_RATE / (1.5 * n * J2 * (frames.R_EARTH_KM / a) ** 2)
    if abs(cos_i) > 1:
        raise ConfigurationError(f"no sun-synchronous orbit at {altitude_km} km")
    return math.degrees(math.acos(cos_i))


@dataclass
class OrbitTruth(SeriesTruth):
    name: str = "orbit"
    duration_s: float = 86400.0
    epoch_unix_s: float = DEFAULT_EPOCH_S
    altitude_km: float = 500.0
    inclination_deg: float | None = None
    ltan_h: float = 10.5
    arg_lat0_deg: float = 0.0
    attitude: str = "nadir"
    inertial_q_wxyz: tuple = (0.9238795, 0.0, 0.3826834, 0.0)
    tumble_rates_deg_s: tuple = (1.1, 0.37)
    spin_rate_deg_s: float = 6.0
    cone_deg: float = 20.0
    precession_s: float = 20000.0
    spin_axis_gcrs: tuple = (0.3, -0.5, 0.81)
    temp_sun_c: float = 35.0
    temp_eclipse_c: float = -5.0
    thermal_tau_s: float = 900.0
    torquer_A: float = 0.08
    torquer_period_s: float = 120.0
    torquer_width_s: float = 20.0
    solar_max_A: float = 1.2
    load_A: float = 0.35
    heater_A: float = 0.25
    heater_period_s: float = 1500.0
    heater_duty: float = 0.3
    sessions: int = 1
    housekeeping_period_s: dict = field(default_factory=lambda: {"torquer": 0.0, "solar": 10.0, "battery": 10.0})
    default_interference_uT_per_A: dict = field(default_factory=lambda: {
        "torquer": (4.0, -2.5, 1.5), "solar": (0.35, 0.2, -0.5), "battery": (-0.3, 0.45, 0.25)})
    description: str = ""

    def __post_init__(self) -> None:
        if self.attitude not in ATTITUDES:
            raise ConfigurationError(f"attitude must be one of {ATTITUDES}, got {self.attitude!r}")
        if not (self.duration_s > 0 and math.isfinite(self.duration_s)):
            raise ConfigurationError(f"duration_s must be > 0, got {self.duration_s}")
        if not 150.0 <= self.altitude_km <= 40000.0:
            raise ConfigurationError(f"altitude_km must be 150..40000, got {self.altitude_km}")
        if int(self.sessions) != self.sessions or self.sessions < 1:
            raise ConfigurationError(f"sessions must be an int >= 1, got {self.sessions}")
        self.sessions = int(self.sessions)
        self.a_km = frames.R_EARTH_KM + self.altitude_km
        self.n_rad_s = math.sqrt(MU_KM3_S2 / self.a_km ** 3)
        inc = sso_inclination_deg(self.altitude_km) if self.inclination_deg is None else self.inclination_deg
        self.inc_rad = math.radians(inc)
        self.raan_rate = -1.5 * self.n_rad_s * J2 * (frames.R_EARTH_KM / self.a_km) ** 2 * math.cos(self.inc_rad)
        sun = frames.sun_direction_gcrs(np.array([self.epoch_unix_s]))[0]
        sun_ra = math.atan2(sun[1], sun[0])
        self.raan0 = sun_ra + math.radians(15.0 * (self.ltan_h - 12.0))
        self._thermal_grid()

    def at_epoch(self, epoch_unix_s: float) -> OrbitTruth:
        """The same orbit programme starting at another Unix time."""
        return replace(self, epoch_unix_s=float(epoch_unix_s))

    # ------------------------------------------------------------------ geometry
    def _abs(self, t_s) -> np.ndarray:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if not np.all(np.isfinite(t)):
            raise ConfigurationError("truth time t_s must be finite")
        return self.epoch_unix_s + t

    def pos_vel_gcrs_km(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) position (km) and velocity (km/s), GCRS."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        u = math.radians(self.arg_lat0_deg) + self.n_rad_s * t
        om = self.raan0 + self.raan_rate * t
        ci, si = math.cos(self.inc_rad), math.sin(self.inc_rad)
        cu, su, co, so = np.cos(u), np.sin(u), np.cos(om), np.sin(om)
        p = np.column_stack([co * cu - so * su * ci, so * cu + co * su * ci, su * si])
        v = np.column_stack([-co * su - so * cu * ci, -so * su + co * cu * ci, cu * si])
        return self.a_km * p, self.a_km * self.n_rad_s * v

    def pos_ecef_series_km(self, t_s) -> np.ndarray:
        return frames.gcrs_to_itrs(self._abs(t_s), self.pos_vel_gcrs_km(t_s)[0])

    def attitude_series(self, t_s) -> Rotation:
        """Rotation GCRS -> body at each instant."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if self.attitude == "inertial":
            q = np.asarray(self.inertial_q_wxyz, dtype=float)
            return Rotation.from_quat(np.tile(q[[1, 2, 3, 0]] / np.linalg.norm(q), (t.size, 1)))
        if self.attitude == "nadir":
            r, v = self.pos_vel_gcrs_km(t)
            z = -r / np.linalg.norm(r, axis=1, keepdims=True)
            h = np.cross(r, v)
            y = -h / np.linalg.norm(h, axis=1, keepdims=True)
            x = np.cross(y, z)
            return Rotation.from_matrix(np.stack([x, y, z], axis=1))   # rows: body axes in GCRS
        if self.attitude == "tumbling":
            w1, w2 = (math.radians(w) for w in self.tumble_rates_deg_s)
            a = Rotation.from_rotvec(np.outer(w1 * t, [0.36, 0.48, 0.8]))
            b = Rotation.from_rotvec(np.outer(w2 * t, [1.0, 0.0, 0.0]))
            return b * a    # body <- gcrs
        # spinning: gcrs <- body = B * Rz(psi) * Rx(cone) * Rz(phi)
        c = np.asarray(self.spin_axis_gcrs, dtype=float)
        c = c / np.linalg.norm(c)
        base, _ = Rotation.align_vectors([c], [[0.0, 0.0, 1.0]])
        psi = 2 * math.pi * t / self.precession_s
        phi = math.radians(self.spin_rate_deg_s) * t
        a = (base * Rotation.from_euler("z", psi[:, None]) * Rotation.from_euler("x", math.radians(self.cone_deg))
             * Rotation.from_euler("z", phi[:, None]))
        return a.inv()

    def q_body_eci_series(self, t_s) -> np.ndarray:
        """(N, 4) scalar-first quaternions (w, x, y, z), GCRS -> body, w >= 0."""
        q = self.attitude_series(t_s).as_quat()[:, [3, 0, 1, 2]]
        return np.where(q[:, :1] < 0, -q, q)

    def eclipse_series(self, t_s) -> np.ndarray:
        return frames.in_eclipse(self._abs(t_s), self.pos_vel_gcrs_km(t_s)[0])

    # ------------------------------------------------------------------ TruthSource (vectorised)
    def field_series_uT(self, t_s) -> np.ndarray:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        ta = self._abs(t)
        r = self.pos_vel_gcrs_km(t)[0]
        b_itrs = geomag.igrf_ecef_nT(ta, frames.gcrs_to_itrs(ta, r))
        return self.attitude_series(t).apply(frames.itrs_to_gcrs(ta, b_itrs)).reshape(-1, 3) / 1e3

    def _thermal_grid(self) -> None:
        g = np.arange(0.0, self.duration_s + 2 * _THERMAL_GRID_S, _THERMAL_GRID_S)
        ecl = self.eclipse_series(g)
        target = np.where(ecl, self.temp_eclipse_c, self.temp_sun_c)
        k = math.exp(-_THERMAL_GRID_S / self.thermal_tau_s)
        temp = np.empty(g.size)
        temp[0] = 0.5 * (self.temp_sun_c + self.temp_eclipse_c)
        for i in range(1, g.size):
            temp[i] = target[i - 1] + (temp[i - 1] - target[i - 1]) * k
        self._tgrid, self._temp = g, temp

    def temp_series_c(self, t_s) -> np.ndarray:
        return np.interp(np.asarray(t_s, dtype=float).reshape(-1), self._tgrid, self._temp)

    def currents_series_A(self, t_s) -> dict[str, np.ndarray]:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        k = np.floor(t / self.torquer_period_s)
        on = np.mod(t, self.torquer_period_s) < self.torquer_width_s
        torquer = np.where(on, self.torquer_A * np.where(np.mod(k, 2) == 0, 1.0, -1.0), 0.0)
        ecl = self.eclipse_series(t)
        sun_body = self.attitude_series(t).apply(frames.sun_direction_gcrs(self._abs(t))).reshape(-1, 3)
        solar = np.where(ecl, 0.0, self.solar_max_A * np.clip(sun_body[:, 0], 0.0, None))
        heater = np.mod(t, self.heater_period_s) < self.heater_duty * self.heater_period_s
        battery = solar - self.load_A - self.heater_A * heater - np.abs(torquer)
        return {"battery": battery, "solar": solar, "torquer": torquer}

    # session_series and the scalar TruthSource protocol: SeriesTruth


def orbit_program(name: str, duration_s: float, sessions: int) -> OrbitTruth:
    """The orbit programme ``name`` of :data:`magstack.sim.coil_programs.ORBIT_PROGRAMS` (registered there)."""
    attitude, help_ = ORBIT_PROGRAMS[name]
    return OrbitTruth(name=name, duration_s=duration_s, attitude=attitude, sessions=sessions, description=help_)
