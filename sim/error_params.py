"""Parameters of the sensor error model: one group of fields per effect, validated, with a JSON form.

:class:`ErrorParams` is the schema of :class:`magstack.sim.error_model.ErrorModel`. Stack units:
field in uT, temperature in degC, time in s, currents in A, angles in rad. Defaults are *neutral*
(identity gain, zero offsets, no noise, infinite range, no quantisation), so ``ErrorParams()`` with
every effect on reproduces truth exactly. Each stage of the pipeline
(:mod:`magstack.sim.error_stages`) reads the fields of its own effect.
"""
from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType
from typing import Any

import numpy as np

from magstack.drivers.errors import ConfigurationError

__all__ = ["ErrorParams", "CROSS_AXIS_MODES"]

#: Set/reset state assumed by the ``cross_axis`` effect: ``set`` or ``reset`` (single polarity,
#: first-order error) or ``set_reset`` (the difference of a set and a reset reading, leaving the
#: second-order term only; hardware-facts 5.3/5.4).
CROSS_AXIS_MODES = ("set", "reset", "set_reset")

_CURRENT_NAME_RE = re.compile(r"^[A-Za-z0-9_]+$")
#: Smallest quantisation step accepted (uT): 1 fT, far below any magnetometer's resolution.
_MIN_LSB_uT = 1e-9


def _vec3(name: str, value: Any, *, allow_inf: bool = False, nonneg: bool = False) -> np.ndarray:
    arr = np.array(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(3, float(arr))
    if arr.shape != (3,):
        raise ConfigurationError(f"{name} must be a scalar or a 3-vector, got shape {arr.shape}")
    _check_values(name, arr, allow_inf=allow_inf, nonneg=nonneg)
    arr.setflags(write=False)
    return arr


def _check_values(name: str, arr: np.ndarray, *, allow_inf: bool = False, nonneg: bool = False) -> None:
    if np.isnan(arr).any() or (not allow_inf and np.isinf(arr).any()):
        raise ConfigurationError(f"{name} must be finite, got {arr.tolist()}")
    if nonneg and (arr < 0).any():
        raise ConfigurationError(f"{name} must be >= 0, got {arr.tolist()}")


def _mat3(name: str, value: Any) -> np.ndarray:
    arr = np.array(value, dtype=float)
    if arr.shape != (3, 3):
        raise ConfigurationError(f"{name} must be a 3x3 matrix, got shape {arr.shape}")
    _check_values(name, arr)
    arr.setflags(write=False)
    return arr


def _scalar(name: str, value: Any, *, allow_inf: bool = False, positive: bool = False, nonneg: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigurationError(f"{name} must be a number, got {value!r}") from None
    if math.isnan(v) or (not allow_inf and math.isinf(v)):
        raise ConfigurationError(f"{name} must be finite, got {v}")
    if positive and not v > 0:
        raise ConfigurationError(f"{name} must be > 0, got {v}")
    if nonneg and v < 0:
        raise ConfigurationError(f"{name} must be >= 0, got {v}")
    return v


@dataclass(frozen=True, eq=False)
class ErrorParams:
    """Parameters of every effect, in stack units. Defaults are neutral (truth in = truth out).

    Vectors are per sensor axis (x, y, z); matrices map body-frame input (columns) to sensor
    axes (rows). Values are validated and frozen on construction (``ConfigurationError``, a
    ``ValueError``, names the bad field). Use :func:`dataclasses.replace` to derive variants.
    """

    # time_skew: axis i is sampled at t + axis_delay_s[i] (s); sequential conversion.
    axis_delay_s: Any = (0.0, 0.0, 0.0)
    # interference: field added at the sensor per named current, uT/A, body frame (3,).
    interference_uT_per_A: Mapping[str, Any] = field(default_factory=dict)
    # mount_rotation: session id -> rotation vector (3,) rad of the sensor mount in that session
    # relative to the frame mount; the sensor senses R_s^T b_body (R_s = error_stages.rotvec_matrix, active:
    # the mounted triad is the frame triad turned by +rotvec). Sessions not listed: unrotated.
    mount_rotation_rad: Mapping[int, Any] = field(default_factory=dict)
    # misalignment: non-orthogonality angles (a_xy, a_xz, a_yz) in rad (deviation from 90 deg
    # between the named pair of sensor axes) and a rotation vector (rad): b_sensor = W R b_body with
    # R = error_stages.rotvec_matrix(rotation_rad) applied actively (the sensor triad is the body triad
    # turned by -rotation_rad); see magstack.sim.error_stages.misalignment_matrix.
    misalignment_rad: Any = (0.0, 0.0, 0.0)
    rotation_rad: Any = (0.0, 0.0, 0.0)
    # gain: 3x3 scale and soft-iron coupling, b_axis = G @ b (rows: affected axis, cols: incident).
    gain_matrix: Any = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    # cross_axis: AMR anisotropy field H0 (uT; inf = no effect), the easy (magnetisation) axis of
    # each bridge (index of the body axis whose field is the "cross field"), set/reset mode.
    cross_axis_h0_uT: float = math.inf
    cross_axis_easy_axis: tuple[int, int, int] = (1, 0, 0)
    cross_axis_mode: str = "set_reset"
    # nonlinearity: b_i += cubic_per_uT2[i] * b_i**3 (1/uT^2).
    cubic_per_uT2: Any = (0.0, 0.0, 0.0)
    # temperature_gain: b <- (I + K_S dT + diag(k_s2) dT^2) b, dT = T - temp_ref_c.
    k_s_per_c: Any = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    k_s2_per_c2: Any = (0.0, 0.0, 0.0)
    temp_ref_c: float = 25.0
    # thermal_lag: the temperature effects see the die temperature, a first-order lag of the truth (board)
    # temperature with this time constant (s; 0 = no lag).
    thermal_lag_tau_s: float = 0.0
    # hysteresis: remanent offset (uT, per axis) after |b_i| >= threshold, signed by the excursion.
    hysteresis_uT: Any = (0.0, 0.0, 0.0)
    hysteresis_threshold_uT: float = math.inf
    # remanence sign per axis before the first excursion of a run (-1, 0 or +1): 0 is a demagnetised
    # (degaussed) part; a part that has ever seen a large field holds +-1 that no file records.
    hysteresis_initial_state: Any = (0.0, 0.0, 0.0)
    # offset (uT) and temperature_offset (uT/degC, about temp_ref_c).
    offset_uT: Any = (0.0, 0.0, 0.0)
    k_o_uT_per_c: Any = (0.0, 0.0, 0.0)
    # drift: linear rate (uT/s) from drift_t0_s plus a random walk (uT/sqrt(s)).
    drift_uT_per_s: Any = (0.0, 0.0, 0.0)
    drift_walk_uT_per_sqrt_s: Any = (0.0, 0.0, 0.0)
    drift_t0_s: float = 0.0
    # session_offset: each session id draws a Gaussian offset with this sigma (uT), fixed per seed.
    session_offset_sigma_uT: Any = (0.0, 0.0, 0.0)
    # noise: per-sample white sigma (uT) and total 1/f sigma (uT) over noise_pink_band_hz.
    noise_white_uT: Any = (0.0, 0.0, 0.0)
    noise_pink_uT: Any = (0.0, 0.0, 0.0)
    noise_pink_band_hz: tuple[float, float] = (1e-3, 10.0)
    # saturation: |b_i| clipped to range_uT (inf = none); quantization: step lsb_uT (0 = none).
    range_uT: float = math.inf
    lsb_uT: Any = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        s = object.__setattr__
        s(self, "axis_delay_s", _vec3("axis_delay_s", self.axis_delay_s))
        if not isinstance(self.interference_uT_per_A, Mapping):
            raise ConfigurationError("interference_uT_per_A must be a mapping name -> (3,) uT/A")
        interf = {}
        for name, vec in self.interference_uT_per_A.items():
            if not isinstance(name, str) or not _CURRENT_NAME_RE.match(name):
                raise ConfigurationError(f"current name {name!r} must match [A-Za-z0-9_]+")
            interf[name] = _vec3(f"interference_uT_per_A[{name!r}]", vec)
        s(self, "interference_uT_per_A", MappingProxyType(dict(sorted(interf.items()))))
        if not isinstance(self.mount_rotation_rad, Mapping):
            raise ConfigurationError("mount_rotation_rad must be a mapping session id -> (3,) rad")
        mounts = {}
        for key, vec in self.mount_rotation_rad.items():
            try:
                sid = int(key)
            except (TypeError, ValueError):
                raise ConfigurationError(f"mount_rotation_rad: session id {key!r} is not an integer") from None
            if isinstance(key, float) and key != sid:
                raise ConfigurationError(f"mount_rotation_rad: session id {key!r} is not an integer")
            rv = _vec3(f"mount_rotation_rad[{sid}]", vec)
            if np.linalg.norm(rv) >= math.pi / 4:
                raise ConfigurationError(f"mount_rotation_rad[{sid}] must be a small rotation (< pi/4 rad), got {rv}")
            mounts[sid] = rv
        s(self, "mount_rotation_rad", MappingProxyType(dict(sorted(mounts.items()))))
        s(self, "misalignment_rad", _vec3("misalignment_rad", self.misalignment_rad))
        if (np.abs(self.misalignment_rad) >= math.pi / 4).any():
            raise ConfigurationError(f"misalignment_rad must be < pi/4 in magnitude, got {self.misalignment_rad}")
        s(self, "rotation_rad", _vec3("rotation_rad", self.rotation_rad))
        s(self, "gain_matrix", _mat3("gain_matrix", self.gain_matrix))
        s(self, "cross_axis_h0_uT", _scalar("cross_axis_h0_uT", self.cross_axis_h0_uT, allow_inf=True, positive=True))
        easy = tuple(self.cross_axis_easy_axis)
        if len(easy) != 3 or any(not isinstance(e, (int, np.integer)) or isinstance(e, bool) or e not in (0, 1, 2)
                                 for e in easy) or any(easy[i] == i for i in range(3)):
            raise ConfigurationError(f"cross_axis_easy_axis must be 3 axis indices (0..2), none its own axis, "
                                     f"got {self.cross_axis_easy_axis!r}")
        s(self, "cross_axis_easy_axis", tuple(int(e) for e in easy))
        if self.cross_axis_mode not in CROSS_AXIS_MODES:
            raise ConfigurationError(f"cross_axis_mode {self.cross_axis_mode!r}; valid: {', '.join(CROSS_AXIS_MODES)}")
        s(self, "cubic_per_uT2", _vec3("cubic_per_uT2", self.cubic_per_uT2))
        s(self, "k_s_per_c", _mat3("k_s_per_c", self.k_s_per_c))
        s(self, "k_s2_per_c2", _vec3("k_s2_per_c2", self.k_s2_per_c2))
        s(self, "temp_ref_c", _scalar("temp_ref_c", self.temp_ref_c))
        tau = _scalar("thermal_lag_tau_s", self.thermal_lag_tau_s)
        if tau < 0:
            raise ConfigurationError(f"thermal_lag_tau_s must be >= 0 s, got {tau!r}")
        s(self, "thermal_lag_tau_s", tau)
        s(self, "hysteresis_uT", _vec3("hysteresis_uT", self.hysteresis_uT))
        s(self, "hysteresis_threshold_uT",
          _scalar("hysteresis_threshold_uT", self.hysteresis_threshold_uT, allow_inf=True, positive=True))
        h0 = _vec3("hysteresis_initial_state", self.hysteresis_initial_state)
        if not np.isin(h0, (-1.0, 0.0, 1.0)).all():
            raise ConfigurationError(f"hysteresis_initial_state must be -1, 0 or +1 per axis, got {h0.tolist()}")
        s(self, "hysteresis_initial_state", h0)
        s(self, "offset_uT", _vec3("offset_uT", self.offset_uT))
        s(self, "k_o_uT_per_c", _vec3("k_o_uT_per_c", self.k_o_uT_per_c))
        s(self, "drift_uT_per_s", _vec3("drift_uT_per_s", self.drift_uT_per_s))
        s(self, "drift_walk_uT_per_sqrt_s", _vec3("drift_walk_uT_per_sqrt_s", self.drift_walk_uT_per_sqrt_s,
                                                  nonneg=True))
        s(self, "drift_t0_s", _scalar("drift_t0_s", self.drift_t0_s))
        s(self, "session_offset_sigma_uT", _vec3("session_offset_sigma_uT", self.session_offset_sigma_uT,
                                                 nonneg=True))
        s(self, "noise_white_uT", _vec3("noise_white_uT", self.noise_white_uT, nonneg=True))
        s(self, "noise_pink_uT", _vec3("noise_pink_uT", self.noise_pink_uT, nonneg=True))
        band = tuple(self.noise_pink_band_hz)
        if len(band) != 2:
            raise ConfigurationError(f"noise_pink_band_hz must be (f_lo, f_hi), got {self.noise_pink_band_hz!r}")
        f_lo = _scalar("noise_pink_band_hz[0]", band[0], positive=True)
        f_hi = _scalar("noise_pink_band_hz[1]", band[1], positive=True)
        if not f_hi > f_lo:
            raise ConfigurationError(f"noise_pink_band_hz needs f_lo < f_hi, got {band!r}")
        s(self, "noise_pink_band_hz", (f_lo, f_hi))
        s(self, "range_uT", _scalar("range_uT", self.range_uT, allow_inf=True, positive=True))
        s(self, "lsb_uT", _vec3("lsb_uT", self.lsb_uT, nonneg=True))
        if ((self.lsb_uT > 0) & (self.lsb_uT < _MIN_LSB_uT)).any():
            raise ConfigurationError(f"lsb_uT must be 0 (no quantisation) or >= {_MIN_LSB_uT} uT, got {self.lsb_uT}")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ErrorParams):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None  # type: ignore[assignment]

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable plain dict (lists, floats; inf as the string 'inf')."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, Mapping):   # JSON object keys are strings (session ids are read back as ints)
                v = {str(k): np.asarray(x).tolist() for k, x in v.items()}
            elif isinstance(v, np.ndarray):
                v = v.tolist()
            elif isinstance(v, tuple):
                v = list(v)
            out[f.name] = _json_inf(v)
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ErrorParams:
        """Inverse of :meth:`to_dict`; unknown keys raise ConfigurationError naming the valid ones."""
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ConfigurationError(f"unknown ErrorParams field(s) {sorted(unknown)}; "
                                     f"valid: {', '.join(sorted(names))}")
        kw = {k: _unjson_inf(v) for k, v in d.items()}
        for k in ("cross_axis_easy_axis",):
            if k in kw:
                kw[k] = tuple(kw[k])
        if "noise_pink_band_hz" in kw:
            kw["noise_pink_band_hz"] = tuple(kw["noise_pink_band_hz"])
        return cls(**kw)


def _json_inf(v: Any) -> Any:
    if isinstance(v, float) and math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if isinstance(v, list):
        return [_json_inf(x) for x in v]
    if isinstance(v, dict):
        return {k: _json_inf(x) for k, x in v.items()}
    return v


def _unjson_inf(v: Any) -> Any:
    if v in ("inf", "-inf"):
        return float(v)
    if isinstance(v, list):
        return [_unjson_inf(x) for x in v]
    if isinstance(v, dict):
        return {k: _unjson_inf(x) for k, x in v.items()}
    return v

