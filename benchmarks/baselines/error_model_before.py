# FROZEN BASELINE - FOR MEASUREMENT ONLY. Do not import from library code, do not edit, do not fix.
#
# A verbatim copy of the single-function implementation of sim/error_model.py (the model before it was split
# into one stage per effect, sim/error_stages.py; the git history holds it). benchmarks/bench_error_model.py times its
# single-sample ``sense()`` beside the current one in the same process, and
# tests/test_error_model_refactor.py checks the restructured model against it. Only this header
# was added; its imports (magstack.drivers.errors, magstack.firmware.effects) resolve unchanged.
# Delete this file (and that test) once an effect's physics is changed on purpose.
"""Forward sensor error model: true field -> what a magnetometer reports, effect by effect.

One ordered pipeline (the order and names come from :mod:`magstack.firmware.effects`, the single
catalogue) applied to a :class:`~magstack.sim.truth_source.TruthSource`::

    time_skew -> interference -> misalignment -> gain -> cross_axis -> nonlinearity
    -> temperature_gain -> hysteresis -> offset -> temperature_offset -> drift
    -> session_offset -> noise -> saturation -> quantization

All quantities are in stack units: field in uT (sensor frame), temperature in degC, time in s,
currents in A. The parameter object :class:`ErrorParams` has one group of fields per effect;
its defaults are *neutral* (identity gain, zero offsets, no noise, infinite range, no
quantisation), so ``ErrorParams()`` with every effect on reproduces truth exactly.

Each effect is switchable: ``ErrorModel(params, effects={...})``. Switching an effect off
removes its contribution exactly (the stage is skipped; random streams of the other effects
are unchanged because every random effect draws from its own seeded stream).

``quantization`` and ``saturation`` use ``params.lsb_uT`` / ``params.range_uT``, so a
measurement-level simulation (``magstack simulate``) gets them from the preset. Register-level
chip models that quantise to their own LSB and clip to their own code range should switch
both off (``effects=without("quantization", "saturation")``) and do it themselves.

The model is stateful (random streams, hysteresis state, 1/f noise state, drift random walk):
calling :meth:`ErrorModel.sense` at t0, t1, ... gives exactly the same values as one
:meth:`ErrorModel.sense_series` call over the same instants with a fresh model of the same seed.
"""
from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType
from typing import Any

import numpy as np

from magstack.drivers.errors import ConfigurationError
from magstack.firmware.effects import EFFECT_NAMES, effect

__all__ = ["ErrorParams", "ErrorModel", "TruthSamples", "sample_truth", "without", "CROSS_AXIS_MODES"]

#: Set/reset state assumed by the ``cross_axis`` effect: ``set`` or ``reset`` (single polarity,
#: first-order error) or ``set_reset`` (the difference of a set and a reset reading, leaving the
#: second-order term only; hardware-facts 5.3/5.4).
CROSS_AXIS_MODES = ("set", "reset", "set_reset")

_CURRENT_NAME_RE = re.compile(r"^[A-Za-z0-9_]+$")
#: The cross field is limited to this fraction of H0 in the cross-axis formula (the AMR model
#: diverges at |B_c| = H0, far outside every supported range; beyond it the bridge would flip).
_CROSS_AXIS_CLAMP = 0.9
#: Smallest quantisation step accepted (uT): 1 fT, far below any magnetometer's resolution.
_MIN_LSB_uT = 1e-9
#: Uniformly spaced runs at least this long use scipy's lfilter for the 1/f state; shorter ones a loop.
_PINK_LFILTER_MIN = 32
#: Number of first-order (Lorentzian) processes per decade synthesising 1/f noise.
_PINK_POLES_PER_DECADE = 2.0
#: Normal deviates drawn per refill of a stream's buffer (the single-sample path takes them from it).
_NORMAL_BLOCK = 4096


class _NormalStream:
    """Standard-normal deviates of one seeded stream, drawn from the generator in blocks.

    Taking ``n`` values gives exactly the next ``n`` values of ``rng.standard_normal`` whatever
    the chunking (numpy draws them one after another), so the per-sample and vectorised paths
    consume one identical sequence; blocks only amortise the per-call numpy overhead.
    """

    __slots__ = ("_rng", "_buf", "_i")

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._buf: list[float] = []
        self._i = 0

    def take(self, n: int) -> list[float]:
        """The next ``n`` deviates as a list of floats."""
        i = self._i
        j = i + n
        if j <= len(self._buf):
            self._i = j
            return self._buf[i:j]
        head = self._buf[i:]
        need = n - len(head)
        if need > _NORMAL_BLOCK:
            self._buf, self._i = [], 0
            return head + self._rng.standard_normal(need).tolist()
        self._buf = self._rng.standard_normal(_NORMAL_BLOCK).tolist()
        self._i = need
        return head + self._buf[:need]

    def take_array(self, n: int) -> np.ndarray:
        """The next ``n`` deviates as an array (n,)."""
        rest = len(self._buf) - self._i
        if n <= rest:
            return np.array(self.take(n), dtype=float)
        head = np.array(self._buf[self._i:], dtype=float)
        self._buf, self._i = [], 0
        return np.concatenate([head, self._rng.standard_normal(n - rest)])


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
    # misalignment: non-orthogonality angles (a_xy, a_xz, a_yz) in rad (deviation from 90 deg
    # between the named pair of sensor axes) and a small rotation vector (rad) of the sensor frame.
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
    # hysteresis: remanent offset (uT, per axis) after |b_i| >= threshold, signed by the excursion.
    hysteresis_uT: Any = (0.0, 0.0, 0.0)
    hysteresis_threshold_uT: float = math.inf
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
        s(self, "hysteresis_uT", _vec3("hysteresis_uT", self.hysteresis_uT))
        s(self, "hysteresis_threshold_uT",
          _scalar("hysteresis_threshold_uT", self.hysteresis_threshold_uT, allow_inf=True, positive=True))
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
            if isinstance(v, Mapping):
                v = {k: np.asarray(x).tolist() for k, x in v.items()}
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


def without(*names: str) -> tuple[str, ...]:
    """Every catalogue effect except ``names`` (each must be a known effect name)."""
    for n in names:
        effect(n)
    return tuple(n for n in EFFECT_NAMES if n not in names)


@dataclass
class TruthSamples:
    """Truth sampled at N instants: b_uT (N,3), temp_c (N,), currents_A name->(N,), session (N,) int."""

    b_uT: np.ndarray
    temp_c: np.ndarray
    currents_A: dict[str, np.ndarray]
    session: np.ndarray


def sample_truth(truth: Any, t_s: np.ndarray) -> TruthSamples:
    """Sample a TruthSource at the instants ``t_s`` (N,).

    Uses the optional vectorised methods ``field_series_uT``, ``temp_series_c``,
    ``currents_series_A`` and ``session_series`` when the source has them (see
    :mod:`magstack.sim.coil_programs`), otherwise loops over the scalar protocol. Non-finite truth raises
    ConfigurationError naming the instant.
    """
    t = np.asarray(t_s, dtype=float).reshape(-1)
    n = t.size
    if hasattr(truth, "field_series_uT"):
        b = np.asarray(truth.field_series_uT(t), dtype=float).reshape(n, 3)
    else:
        b = np.array([np.asarray(truth.field_uT(float(x)), dtype=float).reshape(3) for x in t]).reshape(n, 3)
    if hasattr(truth, "temp_series_c"):
        temp = np.asarray(truth.temp_series_c(t), dtype=float).reshape(n)
    else:
        temp = np.array([float(truth.temp_c(float(x))) for x in t], dtype=float).reshape(n)
    if hasattr(truth, "currents_series_A"):
        cur = {k: np.asarray(v, dtype=float).reshape(n) for k, v in truth.currents_series_A(t).items()}
    else:
        per = [truth.currents_A(float(x)) for x in t]
        keys = sorted({k for p in per for k in p})
        cur = {k: np.array([float(p.get(k, 0.0)) for p in per], dtype=float) for k in keys}
    if hasattr(truth, "session_series"):
        sess = np.asarray(truth.session_series(t)).reshape(n).astype(np.int64)
    else:
        sess = np.array([int(truth.session(float(x))) for x in t], dtype=np.int64)
    for name, arr in (("field_uT", b), ("temp_c", temp), *((f"currents_A[{k!r}]", v) for k, v in cur.items())):
        bad = ~np.isfinite(arr)
        if bad.any():
            idx = np.argwhere(bad)[0][0]
            raise ConfigurationError(f"truth source returned non-finite {name} at t_s={t[idx]!r}")
    return TruthSamples(b, temp, cur, sess)


def _max_code(range_uT: float, lsb_uT: np.ndarray) -> np.ndarray:
    """Largest code k per axis with ``k * lsb <= range`` in floating point (saturated output).

    ``floor(range / lsb)`` alone can be one too many when ``range / lsb`` rounds up to an
    integer (range 11 uT, lsb 1e-5 uT: 1100000 * 1e-5 = 11.000000000000002 > 11).
    """
    lim = np.floor(range_uT / lsb_uT)
    return np.where(lim * lsb_uT > range_uT, lim - 1.0, lim)


def _rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues rotation matrix for a rotation vector (rad)."""
    theta = float(np.linalg.norm(rotvec))
    if theta == 0.0:
        return np.eye(3)
    k = rotvec / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * kx + (1.0 - math.cos(theta)) * (kx @ kx)


def misalignment_matrix(misalignment_rad: np.ndarray, rotation_rad: np.ndarray) -> np.ndarray:
    """M = W @ R: rows of W are the sensor axes' unit vectors (non-orthogonal frame), R a rotation.

    With angles (a_xy, a_xz, a_yz): e_x = (1,0,0); e_y = (sin a_xy, cos a_xy, 0); e_z a unit
    vector with e_x.e_z = sin a_xz and e_y.e_z = sin a_yz. So the angle between sensor axes i and j
    is exactly 90 deg - a_ij (lower-triangular frame, x along body x, y in the body x-y plane).
    """
    a_xy, a_xz, a_yz = (float(a) for a in misalignment_rad)
    sz = math.sin(a_xz)
    cz = (math.sin(a_yz) - math.sin(a_xy) * sz) / math.cos(a_xy)
    w = np.array([[1.0, 0.0, 0.0],
                  [math.sin(a_xy), math.cos(a_xy), 0.0],
                  [sz, cz, math.sqrt(max(0.0, 1.0 - sz * sz - cz * cz))]])
    return w @ _rotation_matrix(np.asarray(rotation_rad, dtype=float))


class ErrorModel:
    """Stateful forward model: ``sense(t, truth)`` -> (3,) uT as the sensor reports it.

    ``effects=None`` turns every catalogue effect on; otherwise only the named ones (unknown
    names raise ValueError listing the valid ones). ``seed`` (int >= 0) fixes every random
    stream: white noise, 1/f noise, drift random walk and the per-session offsets (each drawn
    from its own stream, so switching one random effect off leaves the others' draws unchanged).
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
        self.params = params
        self.seed = int(seed)
        self.enabled: frozenset[str] = enabled
        m = misalignment_matrix(params.misalignment_rad, params.rotation_rad)
        self._misalign = m
        # pink-noise synthesis: K first-order processes with log-spaced corners of equal variance
        f_lo, f_hi = params.noise_pink_band_hz
        k = max(1, int(math.ceil(math.log10(f_hi / f_lo) * _PINK_POLES_PER_DECADE)) + 1)
        self._pink_fc = np.geomspace(f_lo, f_hi, k)
        self._pink_sigma = params.noise_pink_uT[None, :] / math.sqrt(k)  # (1,3) per pole
        self._fast: _FastPlan | None = None  # plain-float constants for sense(), built on first use
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget all state (random streams restart from the seed, hysteresis and 1/f state cleared)."""
        ss = np.random.SeedSequence(self.seed)
        white, pink, walk = ss.spawn(3)
        self._white = _NormalStream(np.random.default_rng(white))
        self._pink_z = _NormalStream(np.random.default_rng(pink))
        self._walk_z = _NormalStream(np.random.default_rng(walk))
        self._last_t: float | None = None
        # state as plain floats (shared by the vectorised and the single-sample path)
        self._pink_state: list[float] = [0.0] * (3 * self._pink_fc.size)  # (K,3) row-major
        self._walk_state: list[float] = [0.0, 0.0, 0.0]
        self._hyst_state: list[float] = [0.0, 0.0, 0.0]  # -1, 0, +1 per axis
        self._session_offsets: dict[int, np.ndarray] = {}
        self._session_offsets_f: dict[int, list[float]] = {}

    def session_offset_uT(self, session: int) -> np.ndarray:
        """The offset (3,) uT drawn for ``session`` (deterministic in seed and session id)."""
        session = int(session)
        off = self._session_offsets.get(session)
        if off is None:
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x5E55, session % (1 << 63)]))
            off = rng.standard_normal(3) * self.params.session_offset_sigma_uT
            self._session_offsets[session] = off
        return off

    # ------------------------------------------------------------------ public
    def sense(self, t_s: float, truth: Any) -> np.ndarray:
        """One vector sample (3,) uT at ``t_s`` (s, non-decreasing between calls).

        A plain-float implementation of the same pipeline as :meth:`sense_series` (same draws
        from the same streams, same state), for register-level simulators that convert one
        sample at a time; it agrees with the vectorised path to rounding (~1e-15 relative).
        """
        t = float(t_s)
        if not math.isfinite(t) or (self._last_t is not None and t < self._last_t):
            return self._run(np.array([t]), truth)[0]  # raises the typed error
        plan = self._fast
        if plan is None or plan.params is not self.params or plan.enabled is not self.enabled:
            plan = self._fast = _FastPlan(self)
        y = plan.sense(self, t, truth)
        if y is None:  # non-finite truth: the vectorised path raises the typed error
            return self._run(np.array([t]), truth)[0]
        return y

    def sense_series(self, t_s: np.ndarray, truth: Any) -> np.ndarray:
        """Samples (N,3) uT at the non-decreasing instants ``t_s`` (N,); continues the model state."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if t.size == 0:
            return np.zeros((0, 3))
        return self._run(t, truth)

    # ------------------------------------------------------------------ pipeline
    def _run(self, t: np.ndarray, truth: Any) -> np.ndarray:
        p = self.params
        on = self.enabled
        if not np.isfinite(t).all():
            raise ConfigurationError("t_s must be finite")
        if t.size > 1 and (np.diff(t) < 0).any():
            raise ConfigurationError("t_s must be non-decreasing")
        if self._last_t is not None and t[0] < self._last_t:
            raise ConfigurationError(f"t_s={t[0]!r} is before the previous sample at {self._last_t!r}")
        n = t.size
        delays = p.axis_delay_s if "time_skew" in on else np.zeros(3)

        # truth at each axis' own instant: (N, K, ...) with K = 1 (no skew) or 3; one truth call
        if np.all(delays == 0.0):
            ts = sample_truth(truth, t)
            b = ts.b_uT[:, None, :]
            temp = np.repeat(ts.temp_c[:, None], 3, axis=1)
            currents = {k: v[:, None] for k, v in ts.currents_A.items()}
            session = ts.session
        else:
            ts = sample_truth(truth, np.concatenate([t + d for d in delays] + [t]))
            b = ts.b_uT[:3 * n].reshape(3, n, 3).transpose(1, 0, 2)
            temp = ts.temp_c[:3 * n].reshape(3, n).T
            currents = {k: v[:3 * n].reshape(3, n).T for k, v in ts.currents_A.items()}
            session = ts.session[3 * n:]
        b = b.copy()

        if "interference" in on:
            for name, d in p.interference_uT_per_A.items():
                cur = currents.get(name)
                if cur is not None:  # a named current absent from the truth carries 0 A
                    b = b + cur[..., None] * d
        if "misalignment" in on:
            b = b @ self._misalign.T
        if "gain" in on:
            b = b @ p.gain_matrix.T
        if "cross_axis" in on and math.isfinite(p.cross_axis_h0_uT):
            h0 = p.cross_axis_h0_uT
            bc = np.clip(b[..., list(p.cross_axis_easy_axis)], -_CROSS_AXIS_CLAMP * h0, _CROSS_AXIS_CLAMP * h0)
            if p.cross_axis_mode == "set":
                factor = h0 / (h0 + bc)
            elif p.cross_axis_mode == "reset":
                factor = h0 / (h0 - bc)
            else:
                factor = h0 * h0 / (h0 * h0 - bc * bc)
            b = b * factor
        if "nonlinearity" in on:
            b = b + p.cubic_per_uT2 * b ** 3
        d_t = temp - p.temp_ref_c  # (N, 3) per axis instant
        if "temperature_gain" in on:
            # b_k <- b_k + dT_k * (K_S @ b_k) + k_s2 * dT_k^2 * b_k, per instant k
            b = (b + d_t[:, :, None] * (b @ p.k_s_per_c.T)
                 + p.k_s2_per_c2 * (d_t[:, :, None] ** 2) * b)
        # each axis takes its own instant's reading
        if b.shape[1] == 1:
            y = b[:, 0, :].copy()
        else:
            y = np.stack([b[:, i, i] for i in range(3)], axis=1)

        if "hysteresis" in on:
            y = y + self._hysteresis(y) * p.hysteresis_uT
        if "offset" in on:
            y = y + p.offset_uT
        if "temperature_offset" in on:
            y = y + p.k_o_uT_per_c * d_t
        prev_t = self._last_t
        if "drift" in on:
            y = y + p.drift_uT_per_s * (t - p.drift_t0_s)[:, None] + self._walk(t, prev_t)
        if "session_offset" in on:
            offs = np.array([self.session_offset_uT(s) for s in np.unique(session)]).reshape(-1, 3)
            idx = np.searchsorted(np.unique(session), session)
            y = y + offs[idx]
        if "noise" in on:
            y = y + self._white.take_array(3 * n).reshape(n, 3) * p.noise_white_uT
            y = y + self._pink(t, prev_t)
        if "saturation" in on and math.isfinite(p.range_uT):
            y = np.clip(y, -p.range_uT, p.range_uT)
        if "quantization" in on:
            lsb = p.lsb_uT
            q = lsb > 0
            if q.any():
                codes = np.round(y[:, q] / lsb[q])
                if "saturation" in on and math.isfinite(p.range_uT):
                    lim = _max_code(p.range_uT, lsb[q])
                    codes = np.clip(codes, -lim, lim)
                y[:, q] = codes * lsb[q] + 0.0  # + 0.0: no negative zeros
        self._last_t = float(t[-1])
        return y

    def _hysteresis(self, y: np.ndarray) -> np.ndarray:
        """Per-axis remanence sign (-1/0/+1) after each sample; updates the state."""
        thr = self.params.hysteresis_threshold_uT
        n = y.shape[0]
        out = np.empty_like(y)
        events = np.where(np.abs(y) >= thr, np.sign(y), 0.0)
        ar = np.arange(n)
        for i in range(3):
            e = events[:, i]
            last = np.maximum.accumulate(np.where(e != 0, ar, -1))
            out[:, i] = np.where(last >= 0, e[np.maximum(last, 0)], self._hyst_state[i])
        self._hyst_state = out[-1].tolist()
        return out

    def _walk(self, t: np.ndarray, prev_t: float | None) -> np.ndarray:
        sig = self.params.drift_walk_uT_per_sqrt_s
        if not (sig > 0).any():  # no walk: no draws (the stream is this effect's own)
            return np.zeros((t.size, 3))
        z = self._walk_z.take_array(3 * t.size).reshape(t.size, 3)
        dt = np.diff(t, prepend=t[0] if prev_t is None else prev_t)
        steps = z * np.sqrt(dt)[:, None] * sig
        w = np.array(self._walk_state) + np.cumsum(steps, axis=0)
        self._walk_state = w[-1].tolist()
        return w

    def _pink(self, t: np.ndarray, prev_t: float | None) -> np.ndarray:
        """Sum of K Ornstein-Uhlenbeck processes (exact discretisation for any dt): ~1/f in band."""
        sig = self._pink_sigma  # (1,3)
        k = self._pink_fc.size
        if not (self.params.noise_pink_uT > 0).any():  # no 1/f noise: no draws (own stream)
            return np.zeros((t.size, 3))
        z = self._pink_z.take_array(3 * k * t.size).reshape(t.size, k, 3)
        tau = 1.0 / (2.0 * math.pi * self._pink_fc)  # (K,)
        x = np.array(self._pink_state, dtype=float).reshape(k, 3)
        out = np.empty((t.size, 3))
        start = 0
        if prev_t is None:  # stationary start
            x = z[0] * sig
            out[0] = x.sum(axis=0)
            start = 1
            prev = t[0]
        else:
            prev = prev_t
        dts = np.diff(np.concatenate([[prev], t[start:]]))
        if dts.size:
            if dts.size >= _PINK_LFILTER_MIN and np.allclose(dts, dts[0], rtol=1e-9, atol=0.0):
                from scipy.signal import lfilter
                phi = np.exp(-dts[0] / tau)  # (K,)
                gain = np.sqrt(1.0 - phi ** 2)
                for j in range(k):
                    e = z[start:, j, :] * sig[0] * gain[j]
                    xs, _ = lfilter([1.0], [1.0, -phi[j]], e, axis=0, zi=(phi[j] * x[j])[None, :])
                    if j == 0:
                        acc = xs.copy()
                    else:
                        acc += xs
                    x[j] = xs[-1]
                out[start:] = acc
            else:
                for i, dt in enumerate(dts):
                    phi = np.exp(-dt / tau)[:, None]
                    x = phi * x + np.sqrt(1.0 - phi ** 2) * sig * z[start + i]
                    out[start + i] = x.sum(axis=0)
        self._pink_state = np.asarray(x, dtype=float).ravel().tolist()
        return out


def _sample_truth_floats(truth: Any, ts: list[float]):
    """:func:`sample_truth` at a few instants as plain floats: (b rows, temps, currents, sessions).

    Calls the truth source exactly as :func:`sample_truth` does (series methods when present, in
    the same order); returns None when any value is non-finite (the caller then raises).
    """
    if (hasattr(truth, "field_series_uT") or hasattr(truth, "temp_series_c")
            or hasattr(truth, "currents_series_A") or hasattr(truth, "session_series")):
        try:
            s = sample_truth(truth, np.array(ts))
        except ConfigurationError:
            return None
        return (s.b_uT.tolist(), s.temp_c.tolist(), {k: v.tolist() for k, v in s.currents_A.items()},
                s.session.tolist())
    isfinite = math.isfinite
    bs = []
    for x in ts:
        b = np.asarray(truth.field_uT(x), dtype=float).reshape(3).tolist()
        if not (isfinite(b[0]) and isfinite(b[1]) and isfinite(b[2])):
            return None
        bs.append(b)
    temps = [float(truth.temp_c(x)) for x in ts]
    per = [truth.currents_A(x) for x in ts]
    if len(per) == 1:
        cur = {k: [float(v)] for k, v in per[0].items()}
    else:
        cur = {k: [float(q.get(k, 0.0)) for q in per] for k in sorted({k for q in per for k in q})}
    sessions = [int(truth.session(x)) for x in ts]
    for v in temps:
        if not isfinite(v):
            return None
    for vs in cur.values():
        for v in vs:
            if not isfinite(v):
                return None
    return bs, temps, cur, sessions


class _FastPlan:
    """One model's pipeline constants as plain floats, for the single-sample :meth:`ErrorModel.sense`.

    Follows :meth:`ErrorModel._run` stage by stage with the same operation order, the same
    random draws (from the same buffered streams) and the same state, so one ``sense()`` per
    instant reproduces ``sense_series`` over those instants (to rounding of the 3x3 products).
    """

    def __init__(self, m: ErrorModel) -> None:
        p, on = m.params, m.enabled
        self.params, self.enabled = p, on
        delays = [float(d) for d in p.axis_delay_s] if "time_skew" in on else [0.0, 0.0, 0.0]
        self.delays = None if all(d == 0.0 for d in delays) else delays
        self.interf = ([(name, d.tolist()) for name, d in p.interference_uT_per_A.items()]
                       if "interference" in on else [])
        self.misalign = m._misalign.tolist() if "misalignment" in on else None
        self.gain = p.gain_matrix.tolist() if "gain" in on else None
        self.cross = None
        if "cross_axis" in on and math.isfinite(p.cross_axis_h0_uT):
            h0 = p.cross_axis_h0_uT
            self.cross = (h0, -_CROSS_AXIS_CLAMP * h0, _CROSS_AXIS_CLAMP * h0, p.cross_axis_easy_axis,
                          p.cross_axis_mode)
        self.cubic = p.cubic_per_uT2.tolist() if "nonlinearity" in on else None
        self.temp_gain = (p.k_s_per_c.tolist(), p.k_s2_per_c2.tolist()) if "temperature_gain" in on else None
        self.temp_ref = p.temp_ref_c
        self.hyst = (p.hysteresis_threshold_uT, p.hysteresis_uT.tolist()) if "hysteresis" in on else None
        self.offset = p.offset_uT.tolist() if "offset" in on else None
        self.temp_off = p.k_o_uT_per_c.tolist() if "temperature_offset" in on else None
        self.drift = None
        if "drift" in on:
            walk = p.drift_walk_uT_per_sqrt_s
            self.drift = (p.drift_uT_per_s.tolist(), p.drift_t0_s, walk.tolist(), bool((walk > 0).any()))
        self.session = "session_offset" in on
        self.noise = None
        if "noise" in on:
            k = m._pink_fc.size
            pink_on = bool((p.noise_pink_uT > 0).any())
            self.noise = (p.noise_white_uT.tolist(), pink_on, k, (m._pink_sigma[0].tolist()) * k)
        self.tau = 1.0 / (2.0 * math.pi * m._pink_fc)  # (K,), exactly as in ErrorModel._pink
        self.sigma = m._pink_sigma
        self.pink_coef: dict[float, tuple[list[float], list[float]]] = {}  # dt -> (phi, gain*sigma) (K*3,)
        sat = "saturation" in on and math.isfinite(p.range_uT)
        self.sat = p.range_uT if sat else None
        self.quant = []
        if "quantization" in on:
            for i, lsb in enumerate(p.lsb_uT.tolist()):
                if lsb > 0:
                    lim = float(_max_code(p.range_uT, np.array([lsb]))[0]) if sat else None
                    self.quant.append((i, lsb, lim))

    def _pink_step(self, dt: float) -> tuple[list[float], list[float]]:
        coef = self.pink_coef.get(dt)
        if coef is None:
            if len(self.pink_coef) >= 256:  # uniform sampling gives a handful of distinct dt values
                self.pink_coef.clear()
            phi = np.exp(-dt / self.tau)[:, None]  # as ErrorModel._pink's general loop
            g = np.sqrt(1.0 - phi ** 2) * self.sigma
            coef = self.pink_coef[dt] = (np.repeat(phi, 3, axis=1).ravel().tolist(), g.ravel().tolist())
        return coef

    def _front(self, b: list[float], d_t: float, cur: dict[str, float]) -> list[float]:
        """interference .. temperature_gain on one instant's body-frame field (3 floats)."""
        x, y, z = b
        for name, d in self.interf:
            c = cur.get(name)
            if c is not None:
                x, y, z = x + c * d[0], y + c * d[1], z + c * d[2]
        for mat in (self.misalign, self.gain):
            if mat is not None:
                r0, r1, r2 = mat
                x, y, z = (x * r0[0] + y * r0[1] + z * r0[2], x * r1[0] + y * r1[1] + z * r1[2],
                           x * r2[0] + y * r2[1] + z * r2[2])
        if self.cross is not None:
            h0, lo, hi, (e0, e1, e2), mode = self.cross
            v = (x, y, z)
            c0, c1, c2 = v[e0], v[e1], v[e2]
            c0 = lo if c0 < lo else (hi if c0 > hi else c0)
            c1 = lo if c1 < lo else (hi if c1 > hi else c1)
            c2 = lo if c2 < lo else (hi if c2 > hi else c2)
            if mode == "set":
                x, y, z = x * (h0 / (h0 + c0)), y * (h0 / (h0 + c1)), z * (h0 / (h0 + c2))
            elif mode == "reset":
                x, y, z = x * (h0 / (h0 - c0)), y * (h0 / (h0 - c1)), z * (h0 / (h0 - c2))
            else:
                hh = h0 * h0
                x, y, z = x * (hh / (hh - c0 * c0)), y * (hh / (hh - c1 * c1)), z * (hh / (hh - c2 * c2))
        if self.cubic is not None:
            c = self.cubic
            x, y, z = x + c[0] * x ** 3, y + c[1] * y ** 3, z + c[2] * z ** 3
        if self.temp_gain is not None:
            (k0, k1, k2), s2 = self.temp_gain
            d2 = d_t * d_t
            x, y, z = (x + d_t * (x * k0[0] + y * k0[1] + z * k0[2]) + s2[0] * d2 * x,
                       y + d_t * (x * k1[0] + y * k1[1] + z * k1[2]) + s2[1] * d2 * y,
                       z + d_t * (x * k2[0] + y * k2[1] + z * k2[2]) + s2[2] * d2 * z)
        return [x, y, z]

    def sense(self, m: ErrorModel, t: float, truth: Any) -> np.ndarray | None:
        """One sample (3,) uT at ``t`` (already checked finite and not before the last sample)."""
        tr = self.temp_ref
        if self.delays is None:
            got = _sample_truth_floats(truth, [t])
            if got is None:
                return None
            bs, temps, cur, sessions = got
            d_t = temps[0] - tr
            y = self._front(bs[0], d_t, {k: v[0] for k, v in cur.items()})
            dts = (d_t, d_t, d_t)
        else:
            got = _sample_truth_floats(truth, [t + d for d in self.delays] + [t])
            if got is None:
                return None
            bs, temps, cur, sessions = got
            dts = tuple(temps[i] - tr for i in range(3))
            y = [self._front(bs[i], dts[i], {k: v[i] for k, v in cur.items()})[i] for i in range(3)]
        session = sessions[-1]
        if self.hyst is not None:
            thr, h = self.hyst
            st = m._hyst_state
            for i in range(3):
                v = y[i]
                if abs(v) >= thr and v != 0.0:
                    st[i] = 1.0 if v > 0 else -1.0
                y[i] = v + st[i] * h[i]
        if self.offset is not None:
            o = self.offset
            y = [y[0] + o[0], y[1] + o[1], y[2] + o[2]]
        if self.temp_off is not None:
            k = self.temp_off
            y = [y[0] + k[0] * dts[0], y[1] + k[1] * dts[1], y[2] + k[2] * dts[2]]
        prev_t = m._last_t
        if self.drift is not None:
            rate, t0, sig, walk_on = self.drift
            w = m._walk_state
            if walk_on:
                z = m._walk_z.take(3)
                sq = math.sqrt(0.0 if prev_t is None else t - prev_t)
                w = [w[0] + z[0] * sq * sig[0], w[1] + z[1] * sq * sig[1], w[2] + z[2] * sq * sig[2]]
                m._walk_state = w
            else:
                w = [0.0, 0.0, 0.0]
            dt0 = t - t0
            y = [y[0] + rate[0] * dt0 + w[0], y[1] + rate[1] * dt0 + w[1], y[2] + rate[2] * dt0 + w[2]]
        if self.session:
            off = m._session_offsets_f.get(session)
            if off is None:
                off = m._session_offsets_f[session] = m.session_offset_uT(session).tolist()
            y = [y[0] + off[0], y[1] + off[1], y[2] + off[2]]
        if self.noise is not None:
            white, pink_on, k, sig3 = self.noise
            z = m._white.take(3)
            y = [y[0] + z[0] * white[0], y[1] + z[1] * white[1], y[2] + z[2] * white[2]]
            if pink_on:
                zs = m._pink_z.take(3 * k)
                if prev_t is None:  # stationary start
                    x = [a * b for a, b in zip(zs, sig3, strict=True)]
                else:
                    phi, g = self._pink_step(t - prev_t)
                    x = [ph * xv + gv * zv for ph, xv, gv, zv in zip(phi, m._pink_state, g, zs, strict=True)]
                m._pink_state = x
                s0, s1, s2 = x[0], x[1], x[2]
                for j in range(3, 3 * k, 3):
                    s0 += x[j]
                    s1 += x[j + 1]
                    s2 += x[j + 2]
                y = [y[0] + s0, y[1] + s1, y[2] + s2]
            else:
                y = [y[0] + 0.0, y[1] + 0.0, y[2] + 0.0]
        if self.sat is not None:
            r = self.sat
            y = [-r if v < -r else (r if v > r else v) for v in y]
        for i, lsb, lim in self.quant:
            c = float(round(y[i] / lsb))
            if lim is not None:
                c = -lim if c < -lim else (lim if c > lim else c)
            y[i] = c * lsb + 0.0
        m._last_t = t
        return np.array(y)
