"""Truth generators: bench coil programs (field, temperature, named currents, power cycles).

Every program is a :class:`ProgramTruth`, which implements :class:`magstack.sim.truth_source.TruthSource`
(scalar ``field_uT(t)``, ``temp_c(t)``, ``currents_A(t)``, ``session(t)``) and the optional
vectorised companions the error model uses when present (``field_series_uT(t)`` (N,3),
``temp_series_c(t)`` (N,), ``currents_series_A(t)`` {name: (N,)}, ``session_series(t)`` (N,)).

A program is built from three independent parts so they combine freely:

* a field profile ``t_s (N,) -> b_uT (N,3)`` (steps, sweeps, rotations, excursions, zero field),
* a temperature profile ``t_s -> temp_c`` (constant, heating then cooling, cycling),
* named current profiles ``t_s -> I_A`` (square, pulse trains),

plus the number of power cycles: the run is split into ``sessions`` equal parts numbered 0, 1, ...
Outside [0, duration_s] every profile holds its end value. Time is simulation time in s.

Other generators plug in beside these by implementing the same TruthSource protocol (and optionally
the series methods) and registering a builder with :func:`register_program`, which makes them available
to ``magstack simulate --program`` and ``magstack run --sim --sim-program``. The orbit programmes
(:mod:`magstack.sim.orbit_truth`) are registered here by name; their builder imports the orbit generator
(IGRF and the celestial frames: the ``ground`` extra's libraries) only when one is built.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from magstack.drivers.errors import ConfigurationError
from magstack.sim.truth_source import SeriesTruth

__all__ = [
    "ProgramTruth", "ProgramSpec", "PROGRAMS", "program", "program_names", "register_program",
    "steps_profile", "sweep_profile", "rotation_profile", "spiral_rotation", "excursion_profile", "constant_field",
    "piecewise_linear", "constant_temp", "heating_profile", "cycling_temp", "square_current",
    "pulse_current", "STEP_LEVELS_uT", "STEP_SLEW_S",
]

Profile = Callable[[np.ndarray], np.ndarray]

#: Plateau levels of a per-axis step program, uT: 0 -> +50 -> -50 -> 0 in 10 uT steps, like the
#: real bench's +-50 uT step tests (realdata/av-mageval tests 5-7, belsten sec. 2.3.2).
STEP_LEVELS_uT = tuple(float(v) for v in [0, 10, 20, 30, 40, 50, 40, 30, 20, 10, 0, -10, -20, -30, -40, -50,
                                           -40, -30, -20, -10, 0])
#: Time a coil takes to move between plateaus (s); a linear ramp so rates of change stay finite.
STEP_SLEW_S = 0.5


def _t(t_s) -> np.ndarray:
    t = np.asarray(t_s, dtype=float)
    if not np.isfinite(t).all():
        raise ConfigurationError("truth time t_s must be finite")
    return t


def _num(name: str, value, *, positive: bool = False, nonneg: bool = False) -> float:
    """``value`` as a finite float (optionally > 0 / >= 0); ConfigurationError naming ``name`` otherwise."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigurationError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or (positive and not v > 0) or (nonneg and v < 0):
        need = " and > 0" if positive else (" and >= 0" if nonneg else "")
        raise ConfigurationError(f"{name} must be finite{need}, got {value!r}")
    return v


def _vec3(name: str, value) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ConfigurationError(f"{name} must be 3 finite values (uT), got {value!r}")
    return v


def _axes(axes: str) -> list[int]:
    if not isinstance(axes, str) or not axes:
        raise ConfigurationError(f"axes must be a non-empty string of x, y, z; got {axes!r}")
    return [_axis_index(a) for a in axes]


def piecewise_linear(t_knots, values) -> Profile:
    """Linear interpolation through knots (held constant outside). ``values`` (M,) or (M,k)."""
    tk = np.asarray(t_knots, dtype=float)
    v = np.asarray(values, dtype=float)
    if tk.ndim != 1 or tk.size < 1 or v.shape[0] != tk.size:
        raise ConfigurationError(f"piecewise_linear needs M knots and M values, got {tk.shape} and {v.shape}")
    if (np.diff(tk) < 0).any() or not np.isfinite(tk).all() or not np.isfinite(v).all():
        raise ConfigurationError("piecewise_linear knots must be finite and non-decreasing")

    def f(t_s: np.ndarray) -> np.ndarray:
        t = _t(t_s)
        if v.ndim == 1:
            return np.interp(t, tk, v)
        return np.stack([np.interp(t, tk, v[:, j]) for j in range(v.shape[1])], axis=-1)

    return f


def _plateaus(levels_uT: np.ndarray, duration_s: float, slew_s: float) -> Profile:
    """Hold each row of ``levels_uT`` (M,3) for an equal time, ramping ``slew_s`` between them."""
    m = levels_uT.shape[0]
    hold = duration_s / m
    slew = min(slew_s, 0.25 * hold)
    knots_t, knots_v = [], []
    for i in range(m):
        start = i * hold + (slew if i > 0 else 0.0)
        knots_t += [start, (i + 1) * hold]
        knots_v += [levels_uT[i], levels_uT[i]]
    return piecewise_linear(knots_t, np.array(knots_v))


def _axis_index(axis: str) -> int:
    try:
        return "xyz".index(axis)
    except ValueError:
        raise ConfigurationError(f"axis must be one of x, y, z; got {axis!r}") from None


def constant_field(b_uT=(0.0, 0.0, 0.0)) -> Profile:
    """A constant field vector (uT)."""
    b = _vec3("b_uT", b_uT)

    def f(t_s):
        t = _t(t_s)
        return np.broadcast_to(b, t.shape + (3,)).copy()

    return f


def steps_profile(axes: str, duration_s: float, levels_uT=STEP_LEVELS_uT, slew_s: float = STEP_SLEW_S,
                  background_uT=(0.0, 0.0, 0.0)) -> Profile:
    """Plateaus along each axis in ``axes`` in turn (each axis gets an equal share of the time)."""
    idx = _axes(axes)
    _num("duration_s", duration_s, positive=True)
    _num("slew_s", slew_s, nonneg=True)
    bg = _vec3("background_uT", background_uT)
    lv = np.asarray(levels_uT, dtype=float).reshape(-1)
    if lv.size == 0 or not np.isfinite(lv).all():
        raise ConfigurationError(f"levels_uT must be one or more finite values, got {levels_uT!r}")
    rows = []
    for i in idx:
        for v in lv:
            r = bg.copy()
            r[i] += v
            rows.append(r)
    return _plateaus(np.array(rows), duration_s, slew_s)


def sweep_profile(axes: str, duration_s: float, amplitude_uT: float = 50.0,
                  background_uT=(0.0, 0.0, 0.0)) -> Profile:
    """Triangle sweeps 0 -> +A -> -A -> 0 along each axis in ``axes`` in turn (constant |dB/dt|)."""
    idx = _axes(axes)
    seg = _num("duration_s", duration_s, positive=True) / len(idx)
    _num("amplitude_uT", amplitude_uT)
    bg = _vec3("background_uT", background_uT)
    tk, vk = [], []
    for k, i in enumerate(idx):
        base = bg.copy()
        for frac, lvl in ((0.0, 0.0), (0.25, amplitude_uT), (0.75, -amplitude_uT), (1.0, 0.0)):
            r = base.copy()
            r[i] += lvl
            tk.append(k * seg + frac * seg)
            vk.append(r)
    return piecewise_linear(tk, np.array(vk))


def rotation_profile(duration_s: float, magnitude_uT: float = 50.0, turns: float = 4.0) -> Profile:
    """A field of constant magnitude whose direction spirals over the whole sphere.

    ``b_body_uT(t) = R(t) @ (0, 0, magnitude_uT)`` with the active rotation
    ``R(t) = Rz(phi) Ry(theta)`` (:func:`spiral_rotation`): the polar angle theta goes 0 -> pi over
    the run while the azimuth phi makes ``turns`` turns, like a 3-axis coil tracing the sphere
    (or a sensor turned through every attitude in a constant field).
    """
    _num("duration_s", duration_s, positive=True)
    _num("magnitude_uT", magnitude_uT)
    _num("turns", turns)
    rot_body_from_spiral = spiral_rotation(duration_s, turns)
    b_spiral_uT = np.array([0.0, 0.0, magnitude_uT])  # the field is fixed along z of the turning frame

    def f(t_s):
        t = _t(t_s)
        if t.size == 0:
            return np.zeros(t.shape + (3,))
        return (rot_body_from_spiral(t) @ b_spiral_uT).reshape(t.shape + (3,))

    return f


def spiral_rotation(duration_s: float, turns: float = 4.0) -> Callable[[np.ndarray], np.ndarray]:
    """``t_s (N,) -> R(t) (N, 3, 3)``: the turning frame of :func:`rotation_profile` relative to the body frame.

    ``R = Rz(phi) @ Ry(theta)`` (intrinsic Z then Y Euler angles, scipy's ``Rotation.from_euler("ZY",
    [phi, theta])``), an active rotation: ``R @ v_spiral`` gives body-frame coordinates of a vector fixed
    in the turning frame (the columns of R are the turning frame's axes in the body frame).
    theta = pi * u, phi = 2 pi turns u, u = t / duration_s clipped to [0, 1].
    """
    _num("duration_s", duration_s, positive=True)
    _num("turns", turns)

    def rot_body_from_spiral(t_s) -> np.ndarray:
        u = np.clip(_t(t_s), 0.0, duration_s).reshape(-1) / duration_s
        phi, theta = 2.0 * math.pi * turns * u, math.pi * u
        cp, sp, ct, st = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta)
        zero = np.zeros_like(u)
        return np.stack([np.stack([cp * ct, -sp, cp * st], axis=-1),
                         np.stack([sp * ct, cp, sp * st], axis=-1),
                         np.stack([-st, zero, ct], axis=-1)], axis=-2)

    return rot_body_from_spiral


def excursion_profile(axes: str, duration_s: float, peak_uT: float = 150.0, probe_uT: float = 0.0,
                      slew_s: float = 2.0) -> Profile:
    """Large-field excursions per axis: 0, +peak, 0, -peak, 0 (belsten sec. 2.3.4: +-150 uT).

    The zero plateaus after each excursion show the remanent (hysteresis) offset.
    """
    idx = _axes(axes)
    _num("duration_s", duration_s, positive=True)
    _num("peak_uT", peak_uT)
    _num("probe_uT", probe_uT)
    _num("slew_s", slew_s, nonneg=True)
    rows = []
    for i in idx:
        for lvl in (probe_uT, peak_uT, probe_uT, -peak_uT, probe_uT):
            r = np.zeros(3)
            r[i] = lvl
            rows.append(r)
    return _plateaus(np.array(rows), duration_s, slew_s)


def constant_temp(temp_c: float = 25.0) -> Profile:
    """Constant temperature (degC)."""
    _num("temp_c", temp_c)

    def f(t_s):
        return np.full(np.shape(_t(t_s)), float(temp_c))

    return f


def heating_profile(duration_s: float, start_c: float = 25.0, peak_c: float = 65.0,
                    heat_fraction: float = 0.2, cool_tau_fraction: float = 0.25) -> Profile:
    """Heat linearly from ``start_c`` to ``peak_c`` then cool exponentially back toward ``start_c``.

    Belsten sec. 2.3.3: board heated to about 65 degC and left to cool (about 30 degC range).
    """
    for name, v in (("start_c", start_c), ("peak_c", peak_c)):
        _num(name, v)
    _num("duration_s", duration_s, positive=True)
    if not 0.0 <= _num("heat_fraction", heat_fraction) <= 1.0:
        raise ConfigurationError(f"heat_fraction must be in [0, 1], got {heat_fraction!r}")
    _num("cool_tau_fraction", cool_tau_fraction, positive=True)
    t_heat = heat_fraction * duration_s
    tau = cool_tau_fraction * duration_s

    def f(t_s):
        t = np.clip(_t(t_s), 0.0, duration_s)
        up = start_c + (peak_c - start_c) * np.clip(t / t_heat, 0.0, 1.0) if t_heat > 0 else np.full(t.shape, peak_c)
        down = start_c + (peak_c - start_c) * np.exp(-(t - t_heat) / tau)
        return np.where(t <= t_heat, up, down)

    return f


def cycling_temp(duration_s: float, mean_c: float = 20.0, amplitude_c: float = 40.0, cycles: float = 2.0) -> Profile:
    """Sinusoidal thermal cycling (degC), e.g. orbit-like -20..60 degC."""
    _num("duration_s", duration_s, positive=True)
    for name, v in (("mean_c", mean_c), ("amplitude_c", amplitude_c), ("cycles", cycles)):
        _num(name, v)

    def f(t_s):
        t = np.clip(_t(t_s), 0.0, duration_s)
        return mean_c + amplitude_c * np.sin(2.0 * math.pi * cycles * t / duration_s)

    return f


def square_current(amplitude_A: float, period_s: float, duty: float = 0.5, offset_A: float = 0.0) -> Profile:
    """A square wave: ``offset_A + amplitude_A`` during the first ``duty`` of each period (A)."""
    _num("amplitude_A", amplitude_A)
    _num("offset_A", offset_A)
    if not (math.isfinite(period_s) and period_s > 0) or not 0.0 <= duty <= 1.0:
        raise ConfigurationError(f"square_current needs period_s > 0 and 0 <= duty <= 1, got {period_s}, {duty}")

    def f(t_s):
        t = _t(t_s)
        phase = np.mod(t, period_s) / period_s
        return offset_A + amplitude_A * (phase < duty)

    return f


def pulse_current(amplitude_A: float, period_s: float, width_s: float, start_s: float = 0.0) -> Profile:
    """Short pulses of ``amplitude_A`` lasting ``width_s`` every ``period_s`` from ``start_s`` (A)."""
    _num("amplitude_A", amplitude_A)
    _num("start_s", start_s)
    if not (math.isfinite(period_s) and period_s > 0) or not 0 < width_s <= period_s:
        raise ConfigurationError(f"pulse_current needs 0 < width_s <= period_s, got {width_s}, {period_s}")

    def f(t_s):
        t = _t(t_s)
        phase = np.mod(t - start_s, period_s)
        return np.where((t >= start_s) & (phase < width_s), amplitude_A, 0.0)

    return f


@dataclass
class ProgramTruth(SeriesTruth):
    """A TruthSource built from a field profile, a temperature profile, named currents, sessions."""

    name: str
    duration_s: float
    field_fn: Profile
    temp_fn: Profile = field(default_factory=constant_temp)
    current_fns: Mapping[str, Profile] = field(default_factory=dict)
    sessions: int = 1
    description: str = ""

    def __post_init__(self) -> None:
        if not (self.duration_s > 0 and math.isfinite(self.duration_s)):
            raise ConfigurationError(f"duration_s must be > 0 and finite, got {self.duration_s}")
        if int(self.sessions) != self.sessions or self.sessions < 1:
            raise ConfigurationError(f"sessions must be an int >= 1, got {self.sessions}")
        self.sessions = int(self.sessions)
        self.current_fns = dict(sorted(self.current_fns.items()))

    # vectorised
    def field_series_uT(self, t_s) -> np.ndarray:
        t = _t(t_s).reshape(-1)
        return np.asarray(self.field_fn(t), dtype=float).reshape(t.size, 3)

    def temp_series_c(self, t_s) -> np.ndarray:
        t = _t(t_s).reshape(-1)
        return np.asarray(self.temp_fn(t), dtype=float).reshape(t.size)

    def currents_series_A(self, t_s) -> dict[str, np.ndarray]:
        t = _t(t_s).reshape(-1)
        return {k: np.asarray(f(t), dtype=float).reshape(t.size) for k, f in self.current_fns.items()}

    # session_series and the scalar TruthSource protocol: SeriesTruth

    def session_starts_s(self) -> np.ndarray:
        """Start time (s) of each power cycle."""
        return np.arange(self.sessions) * self.duration_s / self.sessions


@dataclass(frozen=True)
class ProgramSpec:
    """A named program builder: ``build(duration_s, sessions) -> TruthSource``."""

    name: str
    build: Callable[[float, int], ProgramTruth]
    default_duration_s: float
    help: str


PROGRAMS: dict[str, ProgramSpec] = {}


def register_program(name: str, build: Callable[[float, int], object], default_duration_s: float, help: str) -> None:
    """Add a program (e.g. an orbit generator) under ``name``; a duplicate name raises ValueError."""
    if name in PROGRAMS:
        raise ValueError(f"program {name!r} already registered")
    PROGRAMS[name] = ProgramSpec(name, build, float(default_duration_s), help)


def program_names() -> tuple[str, ...]:
    return tuple(PROGRAMS)


def program(name: str, duration_s: float | None = None, sessions: int = 3):
    """Build program ``name`` (unknown names raise ValueError naming the valid ones)."""
    spec = PROGRAMS.get(name)
    if spec is None:
        raise ValueError(f"unknown program {name!r}; valid: {', '.join(PROGRAMS)}")
    d = spec.default_duration_s if duration_s is None else float(duration_s)
    if not (d > 0 and math.isfinite(d)):
        raise ConfigurationError(f"duration must be > 0 s, got {d}")
    return spec.build(d, sessions)


def _reg(name: str, default_s: float, help: str):
    def deco(fn):
        register_program(name, fn, default_s, help)
        return fn
    return deco


# ---------------------------------------------------------------- the bench programs
for _ax in "xyz":
    register_program(f"steps_{_ax}", (lambda a: lambda d, s: ProgramTruth(
        f"steps_{a}", d, steps_profile(a, d), sessions=s,
        description=f"{a.upper()}-axis plateaus 0..+50..-50..0 uT in 10 uT steps"))(_ax), 420.0,
        f"{_ax.upper()}-axis steps 0 -> +50 -> -50 -> 0 uT (10 uT plateaus), 25 degC")
    register_program(f"sweep_{_ax}", (lambda a: lambda d, s: ProgramTruth(
        f"sweep_{a}", d, sweep_profile(a, d), sessions=s,
        description=f"{a.upper()}-axis triangle sweep +-50 uT"))(_ax), 200.0,
        f"{_ax.upper()}-axis triangle sweep 0 -> +50 -> -50 -> 0 uT, 25 degC")


@_reg("steps_xyz", 1260.0, "steps on X, then Y, then Z (+-50 uT, 10 uT plateaus), 25 degC")
def _steps_xyz(d, s):
    return ProgramTruth("steps_xyz", d, steps_profile("xyz", d), sessions=s,
                        description="X, Y, Z plateaus 0..+50..-50..0 uT in turn")


@_reg("sweeps", 600.0, "triangle sweeps +-50 uT on X, Y, Z in turn, 25 degC")
def _sweeps(d, s):
    return ProgramTruth("sweeps", d, sweep_profile("xyz", d), sessions=s, description="X, Y, Z triangle sweeps")


@_reg("rotation", 600.0, "50 uT field rotating over the whole sphere (4 azimuth turns), 25 degC")
def _rotation(d, s):
    return ProgramTruth("rotation", d, rotation_profile(d), sessions=s, description="spiral over the sphere")


@_reg("zero_field", 120.0, "near-zero field (coil nulls the ambient), 25 degC (belsten Table 1 run)")
def _zero(d, s):
    return ProgramTruth("zero_field", d, constant_field(), sessions=s, description="zero field")


@_reg("large_field", 300.0, "excursions 0, +150, 0, -150, 0 uT on X, Y, Z (hysteresis screen, belsten 2.3.4)")
def _large(d, s):
    return ProgramTruth("large_field", d, excursion_profile("xyz", d), sessions=s,
                        description="+-150 uT excursions per axis")


@_reg("heating", 1800.0, "constant 50 uT on X, board heated 25 -> 65 degC then cooling (belsten 2.3.3)")
def _heating(d, s):
    return ProgramTruth("heating", d, constant_field((50.0, 0.0, 0.0)), heating_profile(d), sessions=s,
                        description="50 uT on X, heat to 65 degC and cool")


@_reg("temp_cycling", 2400.0, "50 uT rotating field while temperature cycles -20 .. 60 degC twice")
def _cycling(d, s):
    return ProgramTruth("temp_cycling", d, rotation_profile(d, turns=8.0), cycling_temp(d), sessions=s,
                        description="rotation with thermal cycling")


@_reg("currents", 600.0, "constant field with named currents: solar square wave, torquer pulses")
def _currents(d, s):
    return ProgramTruth("currents", d, constant_field((20.0, -5.0, 40.0)),
                        current_fns={"solar": square_current(0.5, 60.0, 0.5),
                                     "torquer": pulse_current(0.1, 20.0, 2.0, start_s=5.0)},
                        sessions=s, description="solar 0/0.5 A square (60 s), torquer 0.1 A pulses")


@_reg("full", 3600.0, "steps, sweeps, rotation and excursions with thermal cycling and named currents")
def _full(d, s):
    return _full_program(d, s, "full", 150.0)


#: Excursion peak of ``full_in_range`` (uT): inside an FVM400 reference's +-100 uT range with margin.
IN_RANGE_PEAK_UT = 90.0


@_reg("full_in_range", 3600.0, "as full, excursions to +-90 uT: every reference value inside an FVM400's +-100 uT")
def _full_in_range(d, s):
    return _full_program(d, s, "full_in_range", IN_RANGE_PEAK_UT)


def _full_program(d, s, name: str, peak_uT: float):
    q = d / 4.0
    parts = [steps_profile("xyz", q), sweep_profile("xyz", q), rotation_profile(q),
             excursion_profile("xyz", q, peak_uT=peak_uT)]

    def fld(t_s):
        t = _t(t_s)
        k = np.clip(np.floor(t / q), 0, 3).astype(int)
        out = np.empty(t.shape + (3,))
        for i, p in enumerate(parts):
            m = k == i
            if m.any():
                out[m] = p(t[m] - i * q)
        return out

    return ProgramTruth(name, d, fld, cycling_temp(d, mean_c=30.0, amplitude_c=25.0, cycles=1.0),
                        current_fns={"solar": square_current(0.5, 90.0, 0.5),
                                     "torquer": pulse_current(0.1, 30.0, 3.0, start_s=10.0)},
                        sessions=s, description="all bench patterns, thermal cycle, currents")


#: Orbit programmes (:mod:`magstack.sim.orbit_truth`): name -> (attitude, help). Built on demand: the orbit
#: generator needs IGRF and the celestial frames (the ``ground`` extra), a bench program does not.
ORBIT_PROGRAMS = {
    "orbit_nadir": ("nadir", "500 km SSO, nadir pointing, eclipse thermal cycle, torquer/solar/battery currents"),
    "orbit_inertial": ("inertial", "500 km SSO, inertially fixed attitude, eclipse thermal cycle, currents"),
    "orbit_tumbling": ("tumbling", "500 km SSO, tumbling (1.1 and 0.37 deg/s), eclipse thermal cycle, currents"),
    "orbit_spinning": ("spinning", "500 km SSO, 6 deg/s spin about body z, spin axis precessing on a 20 deg cone"),
}


def _orbit_builder(name: str) -> Callable[[float, int], object]:
    def build(d, s):
        from magstack.sim.orbit_truth import orbit_program

        return orbit_program(name, d, s)
    return build


for _name, (_, _help) in ORBIT_PROGRAMS.items():
    register_program(_name, _orbit_builder(_name), 5700.0, _help)
