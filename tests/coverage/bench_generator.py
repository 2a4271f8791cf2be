"""Independent bench generator for the calibration coverage harness: plain numpy, seeded.

An HMC1053-like 3-axis AMR sensor on a coil bench with a perfect reference. Written from the physics
below, without magstack's simulator or calibration code. Per bridge (output axis) ``i``::

    dut_i = (1 + a_i dT) sum_j M_ij B_j + O_i + k_o_i dT + w_i(t) + rw_i(t),      dT = T - 25 degC

* ``B`` the true field (uT) from the coil programme; ``T`` the board thermistor (the die follows it).
* ``a_i``: sensitivity tempco, -2.7e-3/degC +- 10 % per axis (HMC1053 datasheet: -2700 ppm/degC typ). The
  sensitivity falls with temperature, so the calibration needs ``1 / (1 + a dT)``: not linear in dT.
* ``M = I + gain error (+-0.05 on the diagonal) + misalignment (+-0.01 off the diagonal)``.
* ``O_i`` +- 0.5 uT; ``k_o_i`` offset tempco 5-30 nT/degC either sign (``big_offset_tempco``: -140 nT/degC on
  X, the slope Belsten et al. sec. 2.3.3 report on a real HMC1053 board at a constant X field).
* ``w_i`` white noise, 40-70 nT per axis; ``rw_i`` a random walk from 0 at each session's start, scaled so
  that its excursion (max - min) over the session is 20-50 nT per axis.

The control shape ``eq3_control`` has no random walk and a tempco exactly linear in the calibration
direction (belsten Eq. 3 is then the truth)::

    dut_i = (sum_j M_ij B_j + O_i + k_o_i dT) / (1 - a_i dT) + w_i(t)

so that ``B = M^-1 [(1 - a dT) dut - O - k_o dT]`` exactly (same first-order tempco as the other shapes).

Bench shapes (``SHAPES``), each a coil programme with a temperature profile:

* ``wide_sweeps``: full sweeps (each axis -50..50 uT in 10 uT steps, then a tumbling 50 uT field), the
  temperature heated and cooled over a 30-40 degC span;
* ``two_plateaus``: the same sweeps at two temperature plateaus 16-25 degC apart (one session each);
* ``narrow_sweeps``: the sweeps over a 5-8 degC span;
* ``room``: the sweeps at room temperature with ~2 degC of drift;
* ``sweeps_thermal``: sweeps at room temperature (session 1), then a one-field thermal run over 30-40 degC
  (session 2, 40-50 uT along one axis);
* ``thermal_only``: a one-field thermal run only (X ~44 uT, cooling 80 -> 38 degC);
* ``eq3_control``: ``wide_sweeps`` with the control sensor above.

Held-out data: :func:`realise` the same programme again (new noise and walk, same sensor), and
:func:`box_grid` (points over -40..125 degC and 0..600 uT in many directions).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

T_REF_C = 25.0
SHAPES = ("wide_sweeps", "two_plateaus", "narrow_sweeps", "room", "sweeps_thermal", "thermal_only", "eq3_control")
#: The bench index (within a shape) whose sensor gets the -140 nT/degC offset tempco on X.
BIG_TEMPCO_INDEX = 3
BIG_TEMPCO_UT_PER_C = -0.140
#: Box grid: the part's operating range and full scale (HMC1053 datasheet: -40..125 degC, +-6 G).
GRID_TEMP_C = (-40.0, 125.0)
GRID_FIELD_UT = 600.0


@dataclass(frozen=True)
class Sensor:
    """True parameters of one simulated part (see the module docstring for the equation)."""

    m: np.ndarray                 # (3, 3) gain and misalignment
    a_per_c: np.ndarray           # (3,) sensitivity tempco, 1/degC
    offset_uT: np.ndarray         # (3,)
    k_o_uT_per_c: np.ndarray      # (3,) offset tempco
    noise_uT: np.ndarray          # (3,) white-noise sd
    walk_uT: np.ndarray           # (3,) random-walk excursion over a session (0: none)
    eq3_exact: bool = False       # control form: calibration exactly linear in dT


@dataclass(frozen=True)
class Programme:
    """What the bench applies: time (s), true field (N, 3) uT, temperature (N,) degC, session id (N,)."""

    t_s: np.ndarray
    b_uT: np.ndarray
    temp_c: np.ndarray
    session: np.ndarray


def draw_sensor(rng: np.random.Generator, *, control: bool = False, big_offset_tempco: bool = False) -> Sensor:
    """A part drawn within the ranges of the module docstring."""
    m = np.eye(3) + np.diag(rng.uniform(-0.05, 0.05, 3))
    m += (1 - np.eye(3)) * rng.uniform(-0.01, 0.01, (3, 3))
    a = -2.7e-3 * rng.uniform(0.9, 1.1, 3)
    k_o = rng.uniform(0.005, 0.030, 3) * rng.choice([-1.0, 1.0], 3)
    if big_offset_tempco:
        k_o[0] = BIG_TEMPCO_UT_PER_C
    walk = np.zeros(3) if control else rng.uniform(0.020, 0.050, 3)
    return Sensor(m=m, a_per_c=a, offset_uT=rng.uniform(-0.5, 0.5, 3), k_o_uT_per_c=k_o,
                  noise_uT=rng.uniform(0.040, 0.070, 3), walk_uT=walk, eq3_exact=control)


def true_reading_uT(s: Sensor, b_uT: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
    """(N, 3) noise-free sensor reading (no white noise, no random walk)."""
    dT = (np.asarray(temp_c, float) - T_REF_C)[:, None]
    mb = np.asarray(b_uT, float) @ s.m.T
    off = s.offset_uT + s.k_o_uT_per_c * dT
    if s.eq3_exact:
        return (mb + off) / (1.0 - s.a_per_c * dT)
    return (1.0 + s.a_per_c * dT) * mb + off


def random_walk_uT(rng: np.random.Generator, t_s: np.ndarray, session: np.ndarray,
                   excursion_uT: np.ndarray) -> np.ndarray:
    """(N, 3) a Brownian walk per session and axis, 0 at the session's start, excursion scaled to ``excursion_uT``."""
    out = np.zeros((t_s.size, 3))
    for sid in np.unique(session):
        rows = np.flatnonzero(session == sid)
        dt = np.diff(t_s[rows], prepend=t_s[rows[0]])
        w = np.cumsum(rng.standard_normal((rows.size, 3)) * np.sqrt(dt)[:, None], axis=0)
        w -= w[0]
        span = np.ptp(w, axis=0)
        out[rows] = w * np.divide(excursion_uT, span, out=np.zeros(3), where=span > 0)
    return out


def realise(s: Sensor, p: Programme, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) one noisy realisation of the sensor's reading over a programme."""
    noise = rng.standard_normal((p.t_s.size, 3)) * s.noise_uT
    return true_reading_uT(s, p.b_uT, p.temp_c) + noise + random_walk_uT(rng, p.t_s, p.session, s.walk_uT)


# ------------------------------------------------------------------------------------ coil programmes

def _sweep_cycle(rng: np.random.Generator, rate_hz: float) -> np.ndarray:
    """(n, 3) one full sweep: each axis -50..50 uT in 10 uT steps (4-8 s dwell), then 60-120 s of a tumbling
    field of 50 uT whose direction covers the sphere."""
    dwell = int(round(rng.uniform(4.0, 8.0) * rate_hz))
    parts = []
    for ax in range(3):
        lev = np.repeat(np.arange(-50.0, 50.1, 10.0), dwell)
        blk = np.zeros((lev.size, 3))
        blk[:, ax] = lev
        parts.append(blk)
    n = int(round(rng.uniform(60.0, 120.0) * rate_hz))
    t = np.arange(n) / rate_hz
    w1, w2 = rng.uniform(0.15, 0.35), rng.uniform(0.04, 0.09)      # rad/s
    ph1, ph2 = rng.uniform(0, 2 * np.pi, 2)
    u = np.column_stack([np.cos(w1 * t + ph1) * np.sin(w2 * t + ph2), np.sin(w1 * t + ph1) * np.sin(w2 * t + ph2),
                         np.cos(w2 * t + ph2)])
    parts.append(50.0 * u)
    return np.concatenate(parts)


def _sweeps(rng: np.random.Generator, rate_hz: float, duration_s: float) -> np.ndarray:
    """(round(duration * rate), 3) sweep cycles repeated over the duration."""
    n = int(round(duration_s * rate_hz))
    cycles = []
    while sum(len(c) for c in cycles) < n:
        cycles.append(_sweep_cycle(rng, rate_hz))
    return np.concatenate(cycles)[:n]


def _heat_cool(n: int, lo_c: float, span_c: float) -> np.ndarray:
    """Heated from lo to lo + span and cooled back (raised cosine)."""
    return lo_c + span_c * 0.5 * (1.0 - np.cos(2.0 * np.pi * np.arange(n) / max(n - 1, 1)))


def _cooling(n: int, start_c: float, end_c: float, tau_frac: float) -> np.ndarray:
    """Exponential cooling from start to end (exactly) over n rows, time constant tau_frac of the run."""
    x = np.arange(n) / max(n - 1, 1)
    e = (np.exp(-x / tau_frac) - np.exp(-1.0 / tau_frac)) / (1.0 - np.exp(-1.0 / tau_frac))
    return end_c + (start_c - end_c) * e


def _one_field(n: int, b_uT: np.ndarray) -> np.ndarray:
    return np.tile(np.asarray(b_uT, float), (n, 1))


def make_programme(shape: str, rng: np.random.Generator) -> Programme:
    """The coil and temperature programme of one bench of ``shape`` (parameters drawn from ``rng``)."""
    segs: list[tuple[np.ndarray, np.ndarray, float]] = []      # (b, temp, rate) per session
    if shape in ("wide_sweeps", "eq3_control"):
        rate = rng.uniform(2.0, 3.0)
        b = _sweeps(rng, rate, rng.uniform(50.0, 65.0) * 60)
        segs.append((b, _heat_cool(len(b), rng.uniform(12.0, 20.0), rng.uniform(30.0, 40.0)), rate))
    elif shape == "two_plateaus":
        rate = rng.uniform(3.0, 5.0)
        t1 = rng.uniform(18.0, 25.0)
        for tp in (t1, t1 + rng.uniform(16.0, 25.0)):
            b = _sweeps(rng, rate, rng.uniform(12.0, 18.0) * 60)
            segs.append((b, tp + np.linspace(0.0, rng.uniform(-0.5, 0.5), len(b)), rate))
    elif shape == "narrow_sweeps":
        rate = rng.uniform(3.0, 6.0)
        b = _sweeps(rng, rate, rng.uniform(25.0, 40.0) * 60)
        segs.append((b, _heat_cool(len(b), rng.uniform(20.0, 26.0), rng.uniform(5.0, 8.0)), rate))
    elif shape == "room":
        rate = rng.uniform(5.0, 10.0)
        b = _sweeps(rng, rate, rng.uniform(10.0, 20.0) * 60)
        t0 = rng.uniform(21.0, 25.0)
        segs.append((b, t0 + np.linspace(0.0, rng.uniform(1.5, 2.5), len(b)), rate))
    elif shape == "sweeps_thermal":
        rate = rng.uniform(2.0, 4.0)
        b = _sweeps(rng, rate, rng.uniform(12.0, 18.0) * 60)
        t0 = rng.uniform(21.0, 25.0)
        segs.append((b, t0 + np.linspace(0.0, rng.uniform(0.5, 1.0), len(b)), rate))
        n = int(round(rng.uniform(35.0, 50.0) * 60 * rate))
        field = np.zeros(3)
        field[rng.integers(3)] = rng.choice([-1.0, 1.0]) * rng.uniform(40.0, 50.0)
        segs.append((_one_field(n, field), _heat_cool(n, t0, rng.uniform(30.0, 40.0)), rate))
    elif shape == "thermal_only":
        rate = rng.uniform(2.0, 3.0)
        n = int(round(rng.uniform(40.0, 60.0) * 60 * rate))
        b = _one_field(n, [rng.uniform(42.0, 46.0), 0.0, 0.0])
        segs.append((b, _cooling(n, rng.uniform(78.0, 82.0), rng.uniform(36.0, 40.0), rng.uniform(0.3, 0.6)), rate))
    else:
        raise ValueError(f"unknown bench shape {shape!r}; known: {', '.join(SHAPES)}")
    t_parts, s_parts = [], []
    t_next = 1.7e9 + rng.uniform(0.0, 1e7)
    for sid, (b, _temp, rate) in enumerate(segs, start=1):
        t_parts.append(t_next + np.arange(len(b)) / rate)
        s_parts.append(np.full(len(b), sid))
        t_next = t_parts[-1][-1] + 600.0
    return Programme(np.concatenate(t_parts), np.concatenate([s[0] for s in segs]),
                     np.concatenate([s[1] for s in segs]), np.concatenate(s_parts))


def box_grid(rng: np.random.Generator, near_temp_c: tuple[float, float], near_field_uT: float,
             n_far: int = 6000, n_near: int = 6000) -> tuple[Programme, np.ndarray]:
    """Held-out points over the part's range, and the weight of each that makes shares volume shares.

    Two uniform samples in (temperature, |B|): ``n_far`` over -40..125 degC x 0..600 uT, and ``n_near`` over
    ``near_temp_c`` x 0..``near_field_uT`` (where a table's box usually is, so a narrow box still holds
    hundreds of points). Directions: a quarter along +-x, +-y, +-z, the rest uniform on the sphere. The
    weight is 1 / (the two samples' summed density at the point), so a weighted share over any region is
    the share of that region's (temperature x |B|) area. Returns (programme with session 99, weights)."""
    (tlo, thi), flo, fhi = GRID_TEMP_C, 0.0, GRID_FIELD_UT
    nlo, nhi = max(near_temp_c[0], tlo), min(near_temp_c[1], thi)
    nf = min(near_field_uT, fhi)
    temp = np.concatenate([rng.uniform(tlo, thi, n_far), rng.uniform(nlo, nhi, n_near)])
    mag = np.concatenate([rng.uniform(flo, fhi, n_far), rng.uniform(0.0, nf, n_near)])
    n = temp.size
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    axis_rows = rng.random(n) < 0.25
    k = rng.integers(3, size=n)
    u[axis_rows] = 0.0
    u[axis_rows, k[axis_rows]] = rng.choice([-1.0, 1.0], axis_rows.sum())
    dens = n_far / ((thi - tlo) * (fhi - flo)) + np.where((temp >= nlo) & (temp <= nhi) & (mag <= nf),
                                                          n_near / ((nhi - nlo) * nf), 0.0)
    t = 1.8e9 + np.arange(n, dtype=float)
    return Programme(t, mag[:, None] * u, temp, np.full(n, 99)), 1.0 / dens


@dataclass(frozen=True)
class Bench:
    """One bench: its part, the fit session's programme and reading, and the held-out sets (noisy and
    noise-free readings of the same points)."""

    shape: str
    seed: tuple[int, ...]
    sensor: Sensor
    fit: Programme
    fit_dut_uT: np.ndarray
    again: Programme                 # fresh realisation: the same programme
    again_dut_uT: np.ndarray
    again_clean_uT: np.ndarray
    grid: Programme
    grid_weight: np.ndarray
    grid_dut_uT: np.ndarray
    grid_clean_uT: np.ndarray


def make_bench(shape: str, index: int, seed: int = 0) -> Bench:
    """Bench ``index`` of ``shape`` for a base ``seed`` (every random choice from one SeedSequence)."""
    key = (int(seed), SHAPES.index(shape), int(index))
    r_part, r_prog, r_fit, r_again, r_grid = (np.random.default_rng(s) for s in np.random.SeedSequence(key).spawn(5))
    sensor = draw_sensor(r_part, control=shape == "eq3_control",
                         big_offset_tempco=index == BIG_TEMPCO_INDEX and shape != "eq3_control")
    prog = make_programme(shape, r_prog)
    tlo, thi = float(prog.temp_c.min()), float(prog.temp_c.max())
    fmax = float(np.max(np.linalg.norm(prog.b_uT, axis=1)))
    grid, weight = box_grid(r_grid, (tlo - 15.0, thi + 15.0), 1.5 * fmax)
    return Bench(shape=shape, seed=key, sensor=sensor, fit=prog, fit_dut_uT=realise(sensor, prog, r_fit),
                 again=prog, again_dut_uT=realise(sensor, prog, r_again),
                 again_clean_uT=true_reading_uT(sensor, prog.b_uT, prog.temp_c),
                 grid=grid, grid_weight=weight, grid_dut_uT=realise(sensor, grid, r_grid),
                 grid_clean_uT=true_reading_uT(sensor, grid.b_uT, grid.temp_c))
