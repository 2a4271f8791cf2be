"""Forward sensor error model: true field -> what a magnetometer reports, effect by effect.

One ordered pipeline (the order and names come from :mod:`magstack.firmware.effects`, the single
catalogue) applied to a :class:`~magstack.sim.truth_source.TruthSource`::

    time_skew -> interference -> mount_rotation -> misalignment -> gain -> cross_axis -> nonlinearity
    -> temperature_gain -> hysteresis -> offset -> temperature_offset -> drift
    -> session_offset -> noise -> saturation -> quantization

Each effect is written once, as a stage of :mod:`magstack.sim.error_stages` holding its vector
form (``sense_series``) and its single-sample form (``sense``) side by side; this module only runs
the stages. Parameters: :class:`~magstack.sim.error_params.ErrorParams` (neutral defaults, so
``ErrorParams()`` with every effect on reproduces truth exactly). Truth sampling:
:mod:`magstack.sim.error_truth`. Random streams: :mod:`magstack.sim.error_random`.

All quantities are in stack units: field in uT (body frame in the truth, sensor axes after
``misalignment``), temperature in degC, time in s, currents in A.

Each effect is switchable: ``ErrorModel(params, effects={...})``. Switching an effect off
removes its contribution exactly (the stage is skipped; random streams of the other effects
are unchanged because every random effect draws from its own seeded stream).

``quantization`` and ``saturation`` use ``params.lsb_uT`` / ``params.range_uT``, so a
measurement-level simulation (``magstack simulate``) gets them from the preset. Register-level
chip models that quantise to their own LSB and clip to their own code range should switch
both off (``effects=without("quantization", "saturation")``) and do it themselves.

The model is stateful (random streams, hysteresis state, 1/f noise state, drift random walk):
calling :meth:`ErrorModel.sense` at t0, t1, ... gives the same values as one
:meth:`ErrorModel.sense_series` call over the same instants with a fresh model of the same seed,
bit for bit; both calls continue one state and may be interleaved.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from magstack.drivers.errors import ConfigurationError
from magstack.firmware.effects import EFFECT_NAMES, effect
from magstack.sim.error_params import CROSS_AXIS_MODES, ErrorParams
from magstack.sim.error_stages import FIELD, READING, FieldInputs, ReadingInputs, build_stages, misalignment_matrix
from magstack.sim.error_truth import TruthSamples, sample_truth, sample_truth_floats

__all__ = ["ErrorParams", "ErrorModel", "TruthSamples", "sample_truth", "without", "CROSS_AXIS_MODES",
           "misalignment_matrix"]

_NO_CURRENTS: dict[str, float] = {}


def without(*names: str) -> tuple[str, ...]:
    """Every catalogue effect except ``names`` (each must be a known effect name)."""
    for n in names:
        effect(n)
    return tuple(n for n in EFFECT_NAMES if n not in names)


class ErrorModel:
    """Stateful forward model: ``sense(t, truth)`` -> (3,) uT as the sensor reports it.

    ``effects=None`` turns every catalogue effect on; otherwise only the named ones (unknown
    names raise ValueError listing the valid ones). ``seed`` (int >= 0) fixes every random
    stream: white noise, 1/f noise, drift random walk and the per-session offsets (each drawn
    from its own stream, so switching one random effect off leaves the others' draws unchanged).
    ``params``, ``seed`` and ``enabled`` are fixed at construction.
    """

    def __init__(self, params: ErrorParams, *, seed: int = 0, effects: Iterable[str] | None = None) -> None:
        if not isinstance(params, ErrorParams):
            raise TypeError(f"params must be ErrorParams, got {type(params).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigurationError(f"seed must be an int >= 0, got {seed!r}")
        if effects is None:
            enabled = frozenset(EFFECT_NAMES)
        else:
            if isinstance(effects, str):
                effects = [effects]
            names = list(effects)
            for n in names:
                effect(n)  # raises ValueError listing the valid names
            enabled = frozenset(names)
        self._params = params
        self._seed = int(seed)
        self._enabled: frozenset[str] = enabled
        self._stages = build_stages(params, self._seed, enabled)
        on = [s for name, s in self._stages.items() if name in enabled and s.active]
        skew = self._stages["time_skew"]
        self._skew = skew if skew in on else None
        lag = self._stages["thermal_lag"]
        self._lag = lag if lag in on else None
        self._field = [s for s in on if s.kind == FIELD]
        self._reading = [s for s in on if s.kind == READING]
        self._field_single = [s.single for s in self._field]
        self._reading_single = [s.single for s in self._reading]
        self._temp_ref_c = params.temp_ref_c
        self._last_t: float | None = None
        # inputs of the single-sample path, refilled per sample (no allocation per call)
        self._at_field = FieldInputs(0.0, {}, 0)
        self._at_reading = ReadingInputs(0.0, None, (0.0, 0.0, 0.0), 0)

    @property
    def params(self) -> ErrorParams:
        return self._params

    @property
    def seed(self) -> int:
        return self._seed

    @property
    def enabled(self) -> frozenset[str]:
        """Names of the effects switched on."""
        return self._enabled

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget all state (random streams restart from the seed, hysteresis back to its initial state, walk
        and 1/f state cleared)."""
        for s in self._stages.values():
            s.reset()
        self._last_t = None

    def session_offset_uT(self, session: int) -> np.ndarray:
        """The offset (3,) uT drawn for ``session`` (deterministic in seed and session id)."""
        return self._stages["session_offset"].offset_uT(session)

    # ------------------------------------------------------------------ public
    def sense(self, t_s: float, truth: Any) -> np.ndarray:
        """One vector sample (3,) uT at ``t_s`` (s, non-decreasing between calls).

        Runs each stage's single-sample form on plain floats (for register-level simulators that
        convert one sample at a time); same draws, same state and same values as :meth:`sense_series`.
        """
        t = float(t_s)
        last = self._last_t
        if not math.isfinite(t) or (last is not None and t < last):
            return self._run(np.array([t]), truth)[0]  # raises the typed error
        skew = self._skew
        got = sample_truth_floats(truth, [t] if skew is None else skew.instants_one(t))
        if got is None:  # non-finite truth: the vector path raises the typed error
            return self._run(np.array([t]), truth)[0]
        bs, temps, cur, sessions = got
        if self._lag is not None:   # every instant of this sample sees the die temperature at t
            temps = [self._lag.single(t, temps[-1])] * len(temps)
        ref = self._temp_ref_c
        at = self._at_field
        if skew is None:
            d = at.d_temp_c = temps[0] - ref
            at.currents_A = {k: v[0] for k, v in cur.items()} if cur else _NO_CURRENTS
            at.session = sessions[0]
            y = bs[0]
            for f in self._field_single:
                y = f(y, at)
            d_temp = (d, d, d)
        else:  # the field part once per axis instant; each axis keeps its own
            rows = []
            for i in range(3):
                at.d_temp_c = temps[i] - ref
                at.currents_A = {k: v[i] for k, v in cur.items()} if cur else _NO_CURRENTS
                at.session = sessions[i]
                b = bs[i]
                for f in self._field_single:
                    b = f(b, at)
                rows.append(b)
            y = skew.select_one(rows)
            d_temp = (temps[0] - ref, temps[1] - ref, temps[2] - ref)
        at_reading = self._at_reading
        at_reading.t_s, at_reading.prev_t_s, at_reading.d_temp_c, at_reading.session = t, last, d_temp, sessions[-1]
        for f in self._reading_single:
            y = f(y, at_reading)
        self._last_t = t
        return np.array(y)

    def prefetch(self, t_s: list[float], truth: Any) -> None:
        """Hand the truth instants that samples at ``t_s`` will need to a memoising truth source (one
        vectorised evaluation instead of one per sample); nothing for any other source."""
        ahead = getattr(truth, "prefetch", None)
        if ahead is not None:
            skew = self._skew
            ahead(t_s if skew is None else [x for t in t_s for x in skew.instants_one(t)])

    def sense_series(self, t_s: np.ndarray, truth: Any) -> np.ndarray:
        """Samples (N,3) uT at the non-decreasing instants ``t_s`` (N,); continues the model state."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if t.size == 0:
            return np.zeros((0, 3))
        return self._run(t, truth)

    # ------------------------------------------------------------------ vector path
    def _run(self, t: np.ndarray, truth: Any) -> np.ndarray:
        if not np.isfinite(t).all():
            raise ConfigurationError("t_s must be finite")
        if t.size > 1 and (np.diff(t) < 0).any():
            raise ConfigurationError("t_s must be non-decreasing")
        if self._last_t is not None and t[0] < self._last_t:
            raise ConfigurationError(f"t_s={t[0]!r} is before the previous sample at {self._last_t!r}")
        n = t.size
        skew = self._skew
        ref = self._temp_ref_c
        # truth at every sampling instant in one call: N instants, or 3N (one block per axis) + N
        if self._lag is not None:   # the die temperature at the sample times, seen at every instant
            ts0 = sample_truth(truth, t if skew is None else skew.instants(t))
            die = self._lag.vector(t, ts0.temp_c[-n:])
            ts0 = dataclasses.replace(ts0, temp_c=np.tile(die, ts0.temp_c.size // n))
        if skew is None:
            ts = ts0 if self._lag is not None else sample_truth(truth, t)
            b = ts.b_uT.copy()
            d_inst = ts.temp_c - ref
            at = FieldInputs(d_inst, ts.currents_A, ts.session)
            session = ts.session
        else:
            ts = ts0 if self._lag is not None else sample_truth(truth, skew.instants(t))
            m = 3 * n
            b = ts.b_uT[:m].copy()
            d_inst = ts.temp_c[:m] - ref
            at = FieldInputs(d_inst, {k: v[:m] for k, v in ts.currents_A.items()}, ts.session[:m])
            session = ts.session[m:]
        for s in self._field:
            b = s.vector(b, at)
        if skew is None:
            y = b
            d_temp = np.repeat(d_inst[:, None], 3, axis=1)
        else:
            y = skew.select(b, n)
            d_temp = d_inst.reshape(3, n).T
        at_reading = ReadingInputs(t, self._last_t, d_temp, session)
        for s in self._reading:
            y = s.vector(y, at_reading)
        self._last_t = float(t[-1])
        return y
