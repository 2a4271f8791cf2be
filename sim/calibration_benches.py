"""Simulated benches for the calibration's identifiability and mount-rotation checks (tests, benchmarks).

* :func:`thermal_bench`: sweeps of each axis at room temperature (session 1), then heat-and-cool
  runs at constant fields (session 2) -- one field level reproduces belsten's degenerate
  ``K_S``/``K_O`` pair, two or more separate them. The reference is generated through the
  calibration model (Eq. 3) with known parameters.
* :func:`remount_bench`: the HMC1053 error model (gain, misalignment, offset, noise from its
  preset) sensing a field that tumbles over the sphere in every session, the DUT remounted with
  a known small rotation per session (the error model's ``mount_rotation`` stage).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from magstack.firmware.calibration.fit import FitData
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.sim.coil_programs import ProgramTruth, rotation_profile, sweep_profile
from magstack.sim.error_model import ErrorModel
from magstack.sim.presets import preset

#: Eq. 3 parameters of the thermal bench (rows: output axis), calibration direction. The sensitivity of
#: input axis j falls with temperature by ``alpha_j`` (HMC1053 datasheet -2700 ppm/degC typ, here -2600 /
#: -2900 / -2500 ppm/degC: not the prior's mean), so the calibration gain rises: K_S[:, j] = -alpha_j S[:, j].
#: K_O a few nT/degC (set/reset part).
THERMAL_S = np.array([[1.026, -0.02, 0.01], [0.03, 1.07, 0.02], [-0.01, 0.015, 1.05]])
THERMAL_ALPHA_PER_C = np.array([-2.6e-3, -2.9e-3, -2.5e-3])
THERMAL_K_S = -THERMAL_S * THERMAL_ALPHA_PER_C[None, :]
THERMAL_O = np.array([0.33, 0.03, -0.47])
THERMAL_K_O = np.array([0.004, -0.003, 0.005])


def thermal_theta(model: CalModel) -> np.ndarray:
    """(3, p) the thermal bench's parameters laid out for ``model`` (eq3 columns)."""
    th = model.prior()
    for c, col in enumerate(model.columns):
        if col.param == "S":
            th[:, c] = THERMAL_S[:, col.index]
        elif col.param == "K_S":
            th[:, c] = THERMAL_K_S[:, col.index]
        elif col.param == "O":
            th[:, c] = THERMAL_O
        elif col.param == "K_O":
            th[:, c] = THERMAL_K_O
    return th


def thermal_bench(levels_uT: Sequence[Sequence[float]], rng: np.random.Generator, *, noise_uT: float = 0.02,
                  rows_per_level: int = 2000, peak_rise_c: float = 40.0, with_sweeps: bool = True,
                  t0_s: float = 1.6e9) -> tuple[CalModel, np.ndarray, FitData]:
    """``(model, theta, data)``: room-temperature sweeps (session 1, +-50 uT steps on each axis) and
    one heat-and-cool run (25 -> 25 + ~peak_rise_c degC, 0.25 s rows) per constant field in
    ``levels_uT`` (session 2)."""
    m = CalModel(resolve_terms("eq3"))
    th = thermal_theta(m)
    parts = []
    if with_sweeps:
        steps = np.repeat(np.linspace(-50.0, 50.0, 11), 40)
        for j in range(3):
            b = np.zeros((steps.size, 3))
            b[:, j] = steps
            parts.append((b, 25.0 + rng.normal(0, 0.05, steps.size), 1))
    k = np.arange(rows_per_level)
    heat = 25.0 + peak_rise_c * 1.2 * np.exp(-k / (rows_per_level / 3.3)) * (1 - np.exp(-k / (rows_per_level / 40)))
    for lev in levels_uT:
        parts.append((np.tile(np.asarray(lev, dtype=float), (rows_per_level, 1)), heat.copy(), 2))
    B = np.vstack([p[0] for p in parts]) + rng.normal(0, 0.01, (sum(len(p[1]) for p in parts), 3))
    T = np.concatenate([p[1] for p in parts])
    S = np.concatenate([np.full(len(p[1]), p[2]) for p in parts])
    ref = m.predict(th, m.design(B, T)) + rng.normal(0, noise_uT, B.shape)
    return m, th, FitData(B, ref, T, t0_s + 0.25 * np.arange(T.size), S)


def remount_bench(rotvec_rad: Mapping[int, Sequence[float]], *, sessions: int = 4, seconds_per_session: float = 600.0,
                  rate_hz: float = 4.0, magnitude_uT: float = 50.0, ref_noise_uT: float = 0.01,
                  seed: int = 0) -> FitData:
    """Paired rows of a bench whose DUT (HMC1053 preset: gain, misalignment, offset, noise) is
    remounted with ``rotvec_rad[s]`` (rad) in session ``s`` (0 .. sessions-1); each session's
    field tumbles over the whole sphere (``rotation_profile``) at ``magnitude_uT``."""
    seg = float(seconds_per_session)
    tumble = rotation_profile(seg, magnitude_uT, turns=6.0)
    truth = ProgramTruth("remount", seg * sessions, lambda t: tumble(np.mod(np.asarray(t, dtype=float), seg)),
                         sessions=sessions)
    t = np.arange(0.0, seg * sessions, 1.0 / rate_hz)
    params = dataclasses.replace(preset("hmc1053"), mount_rotation_rad=dict(rotvec_rad))
    dut = ErrorModel(params, seed=seed, effects=("mount_rotation", "misalignment", "gain", "offset", "noise")) \
        .sense_series(t, truth)
    rng = np.random.default_rng(seed + 1)
    ref = truth.field_series_uT(t) + rng.normal(0, ref_noise_uT, (t.size, 3))
    return FitData(dut, ref, np.full(t.size, 25.0), 1.6e9 + t, truth.session_series(t))


def sweep_sessions_bench(axes: Sequence[str], rotvec_rad: Mapping[int, Sequence[float]], *,
                         seconds_per_session: float = 200.0, amplitude_uT: float = 50.0,
                         ambient_uT: Sequence[float] = (0.3, 0.4, -0.2), rate_hz: float = 4.0,
                         ref_noise_uT: float = 0.01, seed: int = 0) -> FitData:
    """A bench like AV-MagEval's: session k sweeps the single axis ``axes[k]`` (``""``: near-zero
    field) to +-``amplitude_uT`` over a small ambient field; the DUT (HMC1053 preset) is remounted
    with ``rotvec_rad[k]`` (rad). Repeating an axis in several sessions is what makes the
    remounts determinable (relative to one another)."""
    seg = float(seconds_per_session)
    profiles = [sweep_profile(a, seg, amplitude_uT) if a else None for a in axes]
    amb = np.asarray(ambient_uT, dtype=float)

    def field(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        k = np.clip((t // seg).astype(int), 0, len(axes) - 1)
        out = np.tile(amb, (t.size, 1))
        for j, prof in enumerate(profiles):
            m = k == j
            if prof is not None and m.any():
                out[m] += np.asarray(prof(t[m] - j * seg)).reshape(-1, 3)
        return out

    truth = ProgramTruth("sweeps", seg * len(axes), field, sessions=len(axes))
    t = np.arange(0.0, seg * len(axes), 1.0 / rate_hz)
    params = dataclasses.replace(preset("hmc1053"), mount_rotation_rad=dict(rotvec_rad))
    dut = ErrorModel(params, seed=seed, effects=("mount_rotation", "misalignment", "gain", "offset", "noise")) \
        .sense_series(t, truth)
    rng = np.random.default_rng(seed + 1)
    ref = truth.field_series_uT(t) + rng.normal(0, ref_noise_uT, (t.size, 3))
    return FitData(dut, ref, np.full(t.size, 25.0), 1.6e9 + t, truth.session_series(t))


def preset_thermal_bench(*, seed: int = 0, level_uT: Sequence[float] = (44.0, 0.0, 0.0),
                         cool_c: tuple[float, float] = (80.0, 38.0), rate_hz: float = 2.0,
                         sweep_s: float = 40.0, cool_s: float = 3000.0, tau_s: float = 900.0,
                         ref_noise_uT: float = 0.01, effects: Sequence[str] | None = None) -> FitData:
    """The HMC1053 *error model* (its preset, every effect unless ``effects`` names some) on a bench like
    the real thermal check: session 1 steps each axis through -50..+50 uT (11 levels, ``sweep_s`` each)
    at 25 degC; session 2 holds ``level_uT`` while the unit cools exponentially from ``cool_c[0]`` to
    ``cool_c[1]`` degC (time constant ``tau_s``). The reference is the truth plus white noise."""
    levels = np.linspace(-50.0, 50.0, 11)
    seg1 = 3 * levels.size * sweep_s
    lev = np.asarray(level_uT, dtype=float)
    hot, cold = cool_c

    def field(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        out = np.tile(lev, (t.size, 1))
        k = (t // sweep_s).astype(int)
        first = t < seg1
        axis, step = k[first] // levels.size, k[first] % levels.size
        b = np.zeros((int(first.sum()), 3))
        b[np.arange(b.shape[0]), axis] = levels[step]
        out[first] = b
        return out

    def temp(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        cool = cold + (hot - cold) * np.exp(-np.maximum(t - seg1, 0.0) / tau_s)
        return np.where(t < seg1, 25.0, cool)

    duration = seg1 + cool_s
    truth = ProgramTruth("preset-thermal", duration, field, temp, sessions=1)
    t = np.arange(0.0, duration, 1.0 / rate_hz)
    params = preset("hmc1053")
    model = ErrorModel(params, seed=seed) if effects is None else ErrorModel(params, seed=seed, effects=tuple(effects))
    dut = model.sense_series(t, truth)
    rng = np.random.default_rng(seed + 1)
    ref = truth.field_series_uT(t) + rng.normal(0, ref_noise_uT, (t.size, 3))
    session = np.where(t < seg1, 1, 2)
    return FitData(dut, ref, truth.temp_series_c(t), 1.6e9 + t, session)
