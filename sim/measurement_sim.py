"""Measurement-level bench simulation: DUT (error model) and reference (FVM400-like) against truth.

Produces the arrays of a session (see data/session.py) without importing hil: rows at the
DUT's sample instants; ``ref_uT`` = truth + the reference instrument's own white noise, rounded to
its 1 nT resolution; ``dut_uT`` = :class:`magstack.sim.error_model.ErrorModel` output. The reference sees
the true field at the row instant (its own skew is not modelled).

Frames: ``truth_uT`` and ``ref_uT`` are in the body (coil) frame, the reference's axes taken as the
body axes; ``dut_uT`` is on the DUT's sensor axes (the error model's ``misalignment`` maps body ->
sensor).
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from magstack.drivers.errors import ConfigurationError
from magstack.sim.error_model import ErrorModel, ErrorParams, sample_truth

__all__ = ["SimulatedRun", "simulate_measurement", "simulate_measurement_blocks", "FVM400_NOISE_uT",
           "FVM400_LSB_uT"]

#: Reference (FVM400) white noise per axis, uT: measured on realdata/av-mageval test1/ref1.csv
#: (near-zero field, 499 samples at 4.1 Hz) as std(first difference)/sqrt(2) = (0.63, 0.78, 6.2) nT,
#: less the 1 nT quantisation (Sheppard, q^2/12). The z value includes ambient disturbance.
FVM400_NOISE_uT = (0.00056, 0.00073, 0.0062)
#: FVM400 resolution in the bench files: 1 nT (hardware-facts 6.3).
FVM400_LSB_uT = 0.001


@dataclass
class SimulatedRun:
    """Arrays of one simulated bench run (N rows). Field in uT, time in s, temperature in degC."""

    t_s: np.ndarray
    truth_uT: np.ndarray
    ref_uT: np.ndarray
    dut_uT: np.ndarray
    temp_c: np.ndarray
    session: np.ndarray
    currents_A: dict[str, np.ndarray] = field(default_factory=dict)
    effects: tuple[str, ...] = ()
    seed: int = 0


def _check_run(rate_hz: float, duration_s: float, ref_lsb_uT: float, t_start_s: float) -> None:
    """ConfigurationError for a run that cannot be sampled (shared by both simulate functions)."""
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise ConfigurationError(f"rate_hz must be > 0, got {rate_hz}")
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise ConfigurationError(f"duration_s must be > 0, got {duration_s}")
    if not (math.isfinite(ref_lsb_uT) and ref_lsb_uT >= 0):
        raise ConfigurationError(f"ref_lsb_uT must be finite and >= 0 (0 = no rounding), got {ref_lsb_uT}")
    if not math.isfinite(t_start_s):
        raise ConfigurationError(f"t_start_s must be finite, got {t_start_s}")


def simulate_measurement(params: ErrorParams, truth, *, duration_s: float, rate_hz: float, seed: int = 0,
                         effects: Iterable[str] | None = None, ref_noise_uT=FVM400_NOISE_uT,
                         ref_lsb_uT: float = FVM400_LSB_uT, t_start_s: float = 0.0) -> SimulatedRun:
    """Sample ``truth`` at ``rate_hz`` for ``duration_s`` and return DUT, reference and truth arrays.

    Deterministic in ``seed``: the DUT model uses ``seed``; the reference noise uses an independent
    stream derived from it. ``effects`` as for :class:`ErrorModel` (None = all).
    """
    _check_run(rate_hz, duration_s, ref_lsb_uT, t_start_s)
    n = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    t = t_start_s + np.arange(n) / rate_hz
    model = ErrorModel(params, seed=seed, effects=effects)
    dut_sensor_uT = model.sense_series(t, truth)
    ts = sample_truth(truth, t)
    b_body_uT = ts.b_uT
    noise = np.asarray(ref_noise_uT, dtype=float).reshape(3)
    if (noise < 0).any() or not np.isfinite(noise).all():
        raise ConfigurationError(f"ref_noise_uT must be finite and >= 0, got {noise}")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xF7A400]))
    ref_body_uT = b_body_uT + rng.standard_normal((n, 3)) * noise
    if ref_lsb_uT > 0:
        ref_body_uT = np.round(ref_body_uT / ref_lsb_uT) * ref_lsb_uT + 0.0  # + 0.0: no negative zeros
    effects_on = tuple(e for e in _ordered(model.enabled))
    return SimulatedRun(t, b_body_uT, ref_body_uT, dut_sensor_uT, ts.temp_c, ts.session, ts.currents_A, effects_on,
                        seed)


def simulate_measurement_blocks(params: ErrorParams, truth, *, duration_s: float, rate_hz: float, seed: int = 0,
                                effects: Iterable[str] | None = None, ref_noise_uT=FVM400_NOISE_uT,
                                ref_lsb_uT: float = FVM400_LSB_uT, t_start_s: float = 0.0,
                                block_rows: int = 20000) -> Iterator[SimulatedRun]:
    """The run of :func:`simulate_measurement` in consecutive blocks of at most ``block_rows`` rows.

    The model state and both random streams continue from block to block, so a writer can stream
    rows to disk while they are generated (a killed run keeps every block written). The rows equal
    those of :func:`simulate_measurement` up to floating-point rounding of the noise-filter state
    (deterministic in ``seed`` and ``block_rows``).
    """
    _check_run(rate_hz, duration_s, ref_lsb_uT, t_start_s)
    if int(block_rows) < 1:
        raise ConfigurationError(f"block_rows must be >= 1, got {block_rows}")
    noise = np.asarray(ref_noise_uT, dtype=float).reshape(3)
    if (noise < 0).any() or not np.isfinite(noise).all():
        raise ConfigurationError(f"ref_noise_uT must be finite and >= 0, got {noise}")
    n = measurement_rows(duration_s, rate_hz)
    model = ErrorModel(params, seed=seed, effects=effects)
    effects_on = tuple(_ordered(model.enabled))
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xF7A400]))
    for i0 in range(0, n, int(block_rows)):
        t = t_start_s + np.arange(i0, min(n, i0 + int(block_rows))) / rate_hz
        dut = model.sense_series(t, truth)
        ts = sample_truth(truth, t)
        ref = ts.b_uT + rng.standard_normal((t.size, 3)) * noise
        if ref_lsb_uT > 0:
            ref = np.round(ref / ref_lsb_uT) * ref_lsb_uT + 0.0  # + 0.0: no negative zeros
        yield SimulatedRun(t, ts.b_uT, ref, dut, ts.temp_c, ts.session, ts.currents_A, effects_on, seed)


def measurement_rows(duration_s: float, rate_hz: float) -> int:
    """Rows of a run of ``duration_s`` at ``rate_hz`` (both ends included)."""
    return int(math.floor(duration_s * rate_hz + 1e-9)) + 1


def _ordered(names) -> list[str]:
    from magstack.firmware.effects import EFFECT_NAMES
    return [e for e in EFFECT_NAMES if e in names]
