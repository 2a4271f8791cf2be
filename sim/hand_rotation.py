"""Hand-rotation truth: a person turning a board with a magnetometer through the local geomagnetic field.

:class:`HandRotationTruth` implements :class:`magstack.sim.truth_source.TruthSource` and the vectorised
series methods, like the coil programmes (:mod:`magstack.sim.coil_programs`), for a bench without a coil:

* **Field at the site**: the IGRF-14 main field (:mod:`magstack.firmware.reference.geomag`) at
  ``site`` (lat deg, lon deg, height km) and ``epoch_unix_s``, in local north-east-down components
  (the world frame here). Constant over the run: only its direction in the board frame changes.
* **Attitude** (``rot_world_from_body``, scipy, active): the board starts level (body x north, y east,
  z down) and follows a script of moves, each with a minimum-jerk profile (the smooth speed curve of
  human reaching movements), rates drawn between ``rate_deg_s`` limits and pauses between moves:

  - ``guided`` (default): the sequence the live view of ``magstack calibrate`` asks for: a full turn
    about the vertical with the board level, then upside down, on each side and on each end (a full
    turn about the vertical in each), then free tumbling until the run ends;
  - ``flat``: level turns about the vertical only, with +-10 deg of wobble (the poor-coverage case:
    the field's vertical component never changes sign in the board frame).

  Hand tremor is added on top: per body axis a sum of sinusoids at 8-12 Hz (physiological tremor,
  ``tremor_deg`` rms) and a slow wander at 0.1-0.7 Hz (``wander_deg`` rms), random phases.
* **Board iron** (truth, not sensor error: the field really is there): ``soft_iron`` (3x3, field at
  the sensor = ``soft_iron @ ambient``) and ``hard_iron_uT`` (body frame).
* **Disturbance**: a laptop modelled as a point dipole (``laptop_moment_Am2`` in the world frame) at
  ``laptop_pos_m`` from the board's mean position, present between ``laptop_on_s`` and ``laptop_off_s``;
  the board wanders by a few cm in the hand (``hand_travel_m``), so the dipole's field at the sensor
  changes with the board's position as well as with its attitude.
* **Temperature**: ``temp_start_c`` approaching ``temp_end_c`` with time constant ``temp_tau_s``
  (a board warming in the hand or from the Raspberry Pi under it); equal values give a constant.

What a perfect calibration should output is :meth:`HandRotationTruth.earth_body_series_uT` (the site's
field in the board frame, no board iron, no laptop). :meth:`disturbed_series` marks the rows with the
laptop present, :meth:`level_turn_series` the rows of the level turn about the vertical (body z
vertical). Units: uT, degC, s, m, A m^2.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from magstack.drivers.errors import ConfigurationError
from magstack.sim.truth_source import SeriesTruth

#: Default site: Delft (52.0 N, 4.36 E, sea level), 2026-06-01 00:00 UTC.
DEFAULT_SITE = (52.0, 4.36, 0.0)
DEFAULT_EPOCH_S = 1780272000.0
SCRIPTS = ("guided", "flat")
#: Attitude knots per second (the scripted motion between knots is interpolated by Slerp).
KNOT_HZ = 100.0
_MU0_4PI = 1e-7


def site_field_ned_uT(site=DEFAULT_SITE, epoch_unix_s: float = DEFAULT_EPOCH_S) -> np.ndarray:
    """IGRF-14 field (north, east, down) uT at ``site`` = (lat deg, lon deg, height km) and time."""
    from magstack.firmware.reference.geomag import igrf_geodetic_nT

    lat, lon, h = (float(x) for x in site)
    return igrf_geodetic_nT(np.array([epoch_unix_s]), lat, lon, h)[0] / 1e3


def _min_jerk(tau: np.ndarray) -> np.ndarray:
    """Minimum-jerk position profile 10 t^3 - 15 t^4 + 6 t^5 on [0, 1]."""
    t = np.clip(tau, 0.0, 1.0)
    return t ** 3 * (10.0 - 15.0 * t + 6.0 * t * t)


@dataclass
class _Move:
    """One scripted move: rotate ``angle_deg`` about ``axis`` (in the world frame if ``world`` else the
    body frame) over ``duration_s``, then rest ``pause_s``; ``level`` marks a level turn about the vertical."""

    axis: tuple[float, float, float]
    angle_deg: float
    duration_s: float
    pause_s: float
    world: bool
    level: bool = False


@dataclass
class HandRotationTruth(SeriesTruth):
    """A board turned by hand through the local field (module docstring)."""

    name: str = "hand"
    duration_s: float = 120.0
    script: str = "guided"
    seed: int = 0
    site: tuple[float, float, float] = DEFAULT_SITE
    epoch_unix_s: float = DEFAULT_EPOCH_S
    rate_deg_s: tuple[float, float] = (45.0, 110.0)
    pause_s: tuple[float, float] = (0.4, 1.8)
    tremor_deg: float = 0.3
    wander_deg: float = 1.5
    hard_iron_uT: tuple[float, float, float] | None = None
    soft_iron: np.ndarray | None = None
    laptop_moment_Am2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    laptop_pos_m: tuple[float, float, float] = (0.0, 0.25, 0.0)
    laptop_on_s: float = math.inf
    laptop_off_s: float = math.inf
    hand_travel_m: float = 0.04
    temp_start_c: float = 22.0
    temp_end_c: float = 22.0
    temp_tau_s: float = 200.0
    sessions: int = 1
    description: str = ""
    field_world_uT: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not (self.duration_s > 0 and math.isfinite(self.duration_s)):
            raise ConfigurationError(f"duration_s must be > 0 and finite, got {self.duration_s}")
        if self.script not in SCRIPTS:
            raise ConfigurationError(f"unknown hand script {self.script!r}; valid: {', '.join(SCRIPTS)}")
        lo, hi = self.rate_deg_s
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise ConfigurationError(f"rate_deg_s must be 0 < lo <= hi, got {self.rate_deg_s}")
        if not (self.temp_tau_s > 0):
            raise ConfigurationError(f"temp_tau_s must be > 0, got {self.temp_tau_s}")
        rng = np.random.default_rng(np.random.SeedSequence([int(self.seed), 0x4A2D]))
        if self.hard_iron_uT is None:
            self.hard_iron_uT = tuple(rng.uniform(-12.0, 12.0, 3))
        if self.soft_iron is None:
            a = rng.normal(0.0, 0.015, (3, 3))
            self.soft_iron = np.eye(3) + 0.5 * (a + a.T)
        self.soft_iron = np.asarray(self.soft_iron, dtype=float).reshape(3, 3)
        self.hard_iron_uT = tuple(float(x) for x in self.hard_iron_uT)
        self.field_world_uT = site_field_ned_uT(self.site, self.epoch_unix_s)
        self._build_attitude(rng)
        # tremor: 4 sinusoids per axis at 8-12 Hz, and 3 slow ones (0.1-0.7 Hz) of wander
        self._tremor_f = rng.uniform(8.0, 12.0, (3, 4))
        self._tremor_p = rng.uniform(0, 2 * np.pi, (3, 4))
        self._wander_f = rng.uniform(0.1, 0.7, (3, 3))
        self._wander_p = rng.uniform(0, 2 * np.pi, (3, 3))
        self._travel_f = rng.uniform(0.05, 0.4, (3, 2))
        self._travel_p = rng.uniform(0, 2 * np.pi, (3, 2))

    # ------------------------------------------------------------------ the script
    def _moves(self, rng: np.random.Generator) -> list[_Move]:
        lo, hi = self.rate_deg_s

        def dur(angle: float) -> float:
            # a minimum-jerk move peaks at 1.875x its mean rate: draw the mean rate, scale the time
            return abs(angle) / rng.uniform(lo, hi)

        def pause() -> float:
            return float(rng.uniform(*self.pause_s))

        down = (0.0, 0.0, 1.0)
        moves: list[_Move] = []
        if self.script == "flat":
            t = 0.0
            while t < self.duration_s:
                ang = float(rng.choice([-1.0, 1.0]) * 360.0)
                d = dur(ang)
                moves.append(_Move(down, ang, d, pause(), True, level=True))
                # wobble: a small tilt about a random horizontal axis and back
                tilt = rng.uniform(-10.0, 10.0)
                ax = rng.normal(size=2)
                ax = tuple(np.r_[ax / np.linalg.norm(ax), 0.0])
                moves += [_Move(ax, tilt, 0.8, 0.2, True), _Move(ax, -tilt, 0.8, pause(), True)]
                t += d + 2.0 + 2 * self.pause_s[1]
            return moves
        # guided: level turn, then each face down with a turn about the vertical, then tumbling
        flips = [((1.0, 0.0, 0.0), 180.0), ((1.0, 0.0, 0.0), 90.0), ((1.0, 0.0, 0.0), 180.0),
                 ((1.0, 0.0, 0.0), 90.0), ((0.0, 1.0, 0.0), 90.0), ((0.0, 1.0, 0.0), 180.0)]
        turn = float(rng.choice([-1.0, 1.0]) * 360.0)
        moves.append(_Move(down, turn, dur(turn), pause(), True, level=True))
        for ax, ang in flips:
            moves.append(_Move(ax, ang, dur(ang), pause(), False))
            turn = float(rng.choice([-1.0, 1.0]) * 360.0)
            moves.append(_Move(down, turn, dur(turn), pause(), True))
        t = sum(m.duration_s + m.pause_s for m in moves)
        while t < self.duration_s:
            ax = rng.normal(size=3)
            ang = float(rng.uniform(60.0, 200.0) * rng.choice([-1.0, 1.0]))
            m = _Move(tuple(ax / np.linalg.norm(ax)), ang, dur(ang), pause(), False)
            moves.append(m)
            t += m.duration_s + m.pause_s
        return moves

    def _build_attitude(self, rng: np.random.Generator) -> None:
        moves = self._moves(rng)
        dt = 1.0 / KNOT_HZ
        times, rots, level = [0.0], [Rotation.identity()], []
        t = 0.0
        current = Rotation.identity()
        for m in moves:
            n = max(2, int(math.ceil(m.duration_s / dt)))
            tau = np.arange(1, n + 1) / n
            ang = np.radians(m.angle_deg) * _min_jerk(tau)
            steps = Rotation.from_rotvec(np.outer(ang, np.asarray(m.axis, dtype=float)))
            path = steps * current if m.world else current * steps
            times += list(t + tau * m.duration_s)
            rots.append(path)
            if m.world and abs(current.inv().apply(np.asarray(m.axis, dtype=float))[2]) > 0.99:
                level.append((t, t + m.duration_s))      # a turn about the vertical with body z vertical
            t += m.duration_s
            current = path[-1]
            if m.pause_s > 0:
                times.append(t + m.pause_s)
                rots.append(current)
                t += m.pause_s
        self._knot_t = np.asarray(times)
        self._slerp = Slerp(self._knot_t, Rotation.concatenate(rots))
        self._level = level
        self.script_end_s = float(t)

    # ------------------------------------------------------------------ series
    def rot_world_from_body(self, t_s) -> Rotation:
        """Board attitude at ``t_s`` (s): scripted motion plus tremor and wander (body-frame rotation)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float)).reshape(-1)
        base = self._slerp(np.clip(t, self._knot_t[0], self._knot_t[-1]))
        tr = np.radians(self.tremor_deg) * np.sqrt(2.0 / 4.0) * np.sum(
            np.sin(2 * np.pi * self._tremor_f[None] * t[:, None, None] + self._tremor_p[None]), axis=2)
        wa = np.radians(self.wander_deg) * np.sqrt(2.0 / 3.0) * np.sum(
            np.sin(2 * np.pi * self._wander_f[None] * t[:, None, None] + self._wander_p[None]), axis=2)
        hand = ~self.level_turn_series(t)             # a level turn is made on the table: no tremor there
        return base * Rotation.from_rotvec((tr + wa) * hand[:, None])

    def position_series_m(self, t_s) -> np.ndarray:
        """(N, 3) board position (world frame, m) about its mean: the hand's travel."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float)).reshape(-1)
        return self.hand_travel_m * np.sqrt(2.0 / 2.0) * np.sum(
            np.sin(2 * np.pi * self._travel_f[None] * t[:, None, None] + self._travel_p[None]), axis=2)

    def laptop_world_uT(self, t_s) -> np.ndarray:
        """(N, 3) the laptop dipole's field at the board (world frame, uT); 0 while it is away."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float)).reshape(-1)
        out = np.zeros((t.size, 3))
        m = np.asarray(self.laptop_moment_Am2, dtype=float)
        on = (t >= self.laptop_on_s) & (t < self.laptop_off_s)
        if not on.any() or not m.any():
            return out
        r = self.position_series_m(t[on]) - np.asarray(self.laptop_pos_m, dtype=float)
        d = np.linalg.norm(r, axis=1, keepdims=True)
        u = r / d
        out[on] = _MU0_4PI * (3.0 * u * (u @ m)[:, None] - m) / d ** 3 * 1e6
        return out

    def earth_body_series_uT(self, t_s) -> np.ndarray:
        """(N, 3) the site's field in the board frame (what a perfect calibration outputs), uT."""
        return self.rot_world_from_body(t_s).inv().apply(self.field_world_uT)

    def field_series_uT(self, t_s) -> np.ndarray:
        rot = self.rot_world_from_body(t_s)
        t = np.atleast_1d(np.asarray(t_s, dtype=float)).reshape(-1)
        ambient = rot.inv().apply(self.field_world_uT + self.laptop_world_uT(t))
        return ambient @ self.soft_iron.T + np.asarray(self.hard_iron_uT)

    def temp_series_c(self, t_s) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=float)).reshape(-1)
        decay = np.exp(-np.clip(t, 0.0, None) / self.temp_tau_s)
        return self.temp_end_c + (self.temp_start_c - self.temp_end_c) * decay

    def currents_series_A(self, t_s) -> dict[str, np.ndarray]:
        return {}

    def disturbed_series(self, t_s) -> np.ndarray:
        """(N,) bool: the laptop is near (its field is in the truth)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float)).reshape(-1)
        return (t >= self.laptop_on_s) & (t < self.laptop_off_s) & bool(np.any(self.laptop_moment_Am2))

    def level_turn_series(self, t_s) -> np.ndarray:
        """(N,) bool: rows inside a level turn about the vertical (board z vertical)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float)).reshape(-1)
        out = np.zeros(t.size, dtype=bool)
        for a, b in self._level:
            out |= (t >= a) & (t <= b)
        return out


def exact_calibration(params, truth: HandRotationTruth, dut_uT, temp_c) -> np.ndarray:
    """(N, 3) the site's field in the board frame recovered from sensor readings ``dut_uT`` with the true
    parameters: the error model's misalignment, gain, temperature gain (first and second order), offset and
    offset tempco (``params``: :class:`~magstack.sim.error_params.ErrorParams`), then the board's iron,
    inverted exactly. What remains is the sensor's noise and quantisation (and any laptop field): the
    floor no calibration can go below."""
    from magstack.sim.error_stages import misalignment_matrix

    y = np.asarray(dut_uT, dtype=float).reshape(-1, 3)
    d = np.asarray(temp_c, dtype=float).reshape(-1) - params.temp_ref_c
    y = y - params.offset_uT - d[:, None] * params.k_o_uT_per_c
    out = np.empty_like(y)
    G = params.gain_matrix @ misalignment_matrix(params.misalignment_rad, params.rotation_rad)
    for k in np.unique(d):
        m = d == k
        T = np.eye(3) + k * params.k_s_per_c + np.diag(params.k_s2_per_c2 * k * k)
        out[m] = np.linalg.solve(T @ G, y[m].T).T
    ambient = np.linalg.solve(truth.soft_iron, (out - np.asarray(truth.hard_iron_uT)).T).T
    return ambient


# ---------------------------------------------------------------------- registered programmes
HAND_PROGRAMS = {
    "hand": (120.0, "board turned by hand through the local field (guided sequence, then tumbling), 22 degC",
             {}),
    "hand_flat": (60.0, "board turned by hand flat on a table only (level turns, +-10 deg wobble): poor coverage",
                  {"script": "flat"}),
    "hand_warm": (180.0, "guided hand rotations while the board warms 22 -> 37 degC (tau 200 s)",
                  {"temp_start_c": 22.0, "temp_end_c": 37.0, "temp_tau_s": 200.0}),
    "hand_laptop": (120.0, "guided hand rotations with a laptop (0.3 A m^2 dipole) 25 cm away for a third of the run",
                    {"laptop_moment_Am2": (0.1, 0.25, -0.12)}),
}


def hand_program(name: str, duration_s: float, sessions: int = 1, seed: int = 0, **kw) -> HandRotationTruth:
    """Build registered hand programme ``name`` (see :data:`HAND_PROGRAMS`), ``kw`` overriding its settings."""
    _, help_, extra = HAND_PROGRAMS[name]
    args = dict(extra)
    if name == "hand_laptop":
        args.setdefault("laptop_on_s", 0.4 * duration_s)
        args.setdefault("laptop_off_s", 0.7 * duration_s)
    args.update(kw)
    return HandRotationTruth(name=name, duration_s=duration_s, seed=seed, sessions=sessions, description=help_,
                             **args)


def register_hand_programs() -> None:
    """Register the hand programmes with the coil-program registry (idempotent)."""
    from magstack.sim.coil_programs import PROGRAMS, register_program

    for name, (default_s, help_, _) in HAND_PROGRAMS.items():
        if name not in PROGRAMS:
            register_program(name, (lambda n: lambda d, s: hand_program(n, d, s))(name), default_s, help_)


register_hand_programs()
