"""``diagnose --sim PARAMS.json``: the project's error model, parameters fixed, as "the simulator".

PARAMS.json is what ``magstack simulate --save-params`` writes::

    {"format": "magstack-error-params", "version": 1, "chip": "hmc1053",
     "effects": ["time_skew", ...], "params": {ErrorParams.to_dict()}}

(a bare ``ErrorParams.to_dict()`` object is accepted too, with every effect on). The prediction for
a session is the error model run on the session's own reference field (as truth), temperature,
currents and sessions, with the random parts left out (white/1-f noise, the drift random walk, the
per-session offset draws): the gap is ``dut - prediction`` in sensor units. Per-session offsets the
simulator draws at random are fitted as nuisance (effect-coded, so the mean offset stays fixed).

An effect counts as modelled when it is switched on *and* its parameters differ from the neutral
defaults; this module (with validate.py) is the only part of the diagnosis that imports the error model.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from magstack.data.errors import SessionFileError
from magstack.data.session import Session
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.effects import EFFECT_NAMES
from magstack.ground.diagnose.gap import Gap, fixed_gap, kept_rows
from magstack.sim.error_model import ErrorModel, ErrorParams

FORMAT = "magstack-error-params"

#: ErrorParams fields that carry each effect's strength (neutral = the dataclass default).
_FIELDS = {
    "thermal_lag": ("thermal_lag_tau_s",), "time_skew": ("axis_delay_s",), "interference": ("interference_uT_per_A",),
    "misalignment": ("misalignment_rad", "rotation_rad"), "gain": ("gain_matrix",),
    "cross_axis": ("cross_axis_h0_uT",), "nonlinearity": ("cubic_per_uT2",),
    "temperature_gain": ("k_s_per_c", "k_s2_per_c2"), "hysteresis": ("hysteresis_uT",),
    "offset": ("offset_uT",), "temperature_offset": ("k_o_uT_per_c",),
    "drift": ("drift_uT_per_s", "drift_walk_uT_per_sqrt_s"), "session_offset": ("session_offset_sigma_uT",),
    "noise": ("noise_white_uT", "noise_pink_uT"), "saturation": ("range_uT",), "quantization": ("lsb_uT",),
}
#: Random parts left out of the prediction.
RANDOM_EFFECTS = ("noise", "session_offset")


def params_document(params: ErrorParams, effects, chip: str = "") -> dict:
    return {"format": FORMAT, "version": 1, "chip": chip, "effects": [e for e in EFFECT_NAMES if e in set(effects)],
            "params": params.to_dict()}


def load_params(path) -> tuple[ErrorParams, tuple[str, ...]]:
    """ErrorParams and enabled effects from PARAMS.json; bad files raise SessionFileError naming them."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SessionFileError(f"{path}: no such parameter file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionFileError(f"{path}: cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise SessionFileError(f"{path}: line {exc.lineno}: column {exc.colno}: not JSON ({exc.msg})") from None
    if not isinstance(doc, dict):
        raise SessionFileError(f"{path}: expected a JSON object")
    if doc.get("format") == FORMAT:
        p, effects = doc.get("params"), doc.get("effects", list(EFFECT_NAMES))
    else:
        p, effects = doc, list(EFFECT_NAMES)
    if not isinstance(p, dict) or not isinstance(effects, list):
        raise SessionFileError(f"{path}: 'params' must be an object and 'effects' a list")
    bad = [e for e in effects if e not in EFFECT_NAMES]
    if bad:
        raise SessionFileError(f"{path}: unknown effect(s) {bad}")
    try:
        params = ErrorParams.from_dict(p)
    except (ConfigurationError, TypeError, ValueError) as exc:
        raise SessionFileError(f"{path}: bad error-model parameters: {exc}") from None
    return params, tuple(effects)


def modelled_effects(params: ErrorParams, effects) -> tuple[str, ...]:
    """Effects switched on whose parameters are not neutral."""
    neutral = ErrorParams()
    out = []
    for e in effects:
        fields = _FIELDS.get(e)
        if fields is None:
            out.append(e)   # an effect this adapter does not know: trust the switch
            continue
        if any(json.dumps(ErrorParams.to_dict(params)[f], sort_keys=True) !=
               json.dumps(neutral.to_dict()[f], sort_keys=True) for f in fields):
            out.append(e)
    return tuple(e for e in EFFECT_NAMES if e in out)


class SessionTruth:
    """A session's reference field, temperature, currents and session ids as a TruthSource (series
    methods; linear interpolation in time, ends held)."""

    def __init__(self, s: Session) -> None:
        self.s = s

    def field_series_uT(self, t):
        return np.column_stack([np.interp(t, self.s.t_s, self.s.ref_uT[:, j]) for j in range(3)])

    def temp_series_c(self, t):
        ok = np.isfinite(self.s.temp_c)
        if not ok.any():
            return np.full(np.shape(t), 25.0)
        return np.interp(t, self.s.t_s[ok], self.s.temp_c[ok])

    def currents_series_A(self, t):
        return {k: np.interp(t, self.s.t_s, v) for k, v in self.s.currents_A.items()}

    def session_series(self, t):
        idx = np.clip(np.searchsorted(self.s.t_s, t, side="right") - 1, 0, len(self.s) - 1)
        return self.s.session[idx]

    def field_uT(self, t):
        return self.field_series_uT(np.array([t]))[0]

    def temp_c(self, t):
        return float(self.temp_series_c(np.array([t]))[0])

    def currents_A(self, t):
        return {k: float(v[0]) for k, v in self.currents_series_A(np.array([t])).items()}

    def session(self, t):
        return int(self.session_series(np.array([t]))[0])


def predict_dut(s: Session, params: ErrorParams, effects) -> np.ndarray:
    """(N,3) uT: the error model's deterministic prediction of the DUT reading for session ``s``
    (rows sorted by session and time), each session run as its own record in time order."""
    p = dataclasses.replace(params, drift_walk_uT_per_sqrt_s=(0.0, 0.0, 0.0))
    on = [e for e in effects if e not in RANDOM_EFFECTS]
    out = np.full((len(s), 3), np.nan)
    if np.all(np.diff(s.t_s) >= 0):   # one record: hysteresis state carries across power cycles
        return ErrorModel(p, seed=0, effects=on).sense_series(s.t_s, SessionTruth(s))
    for k in np.unique(s.session):
        idx = np.flatnonzero(s.session == k)
        sub = s.select(idx)
        if not np.all(np.diff(sub.t_s) >= 0):
            raise SessionFileError("time stamps are not increasing within a session: cannot run the simulator")
        out[idx] = ErrorModel(p, seed=0, effects=on).sense_series(sub.t_s, SessionTruth(sub))
    return out


def sim_gap(full: Session, keep: np.ndarray, params_path, t0_c: float | None = None) -> Gap:
    """Mode (b) gap from PARAMS.json on the rows ``keep`` of ``full``: ``dut - prediction`` (sensor
    units); features from the reference. The simulator runs on every usable row (``full``), so its
    truth is interpolated only between neighbouring samples."""
    params, effects = load_params(params_path)
    pred = predict_dut(full, params, effects)[keep]
    s = kept_rows(full, keep)
    modelled = modelled_effects(params, effects)
    nuisance = ("session_offset",) if ("session_offset" in modelled and len(np.unique(s.session)) > 1) else ()
    t0 = params.temp_ref_c if t0_c is None else t0_c
    t0 = round(t0 * 100) / 100 if math.isfinite(t0) else 25.0
    g = fixed_gap(s, s.dut_uT - pred, s.ref_uT, modelled, f"--sim {params_path}", nuisance, t0)
    g.deskew_J = -np.eye(3)
    g.forward = True
    return g
