"""The error-model pipeline: one stage per catalogue effect, its vector and single-sample forms side by side.

Each effect of :mod:`magstack.firmware.effects` is one :class:`Stage` subclass here, registered under
the effect's name with :func:`stage` and listed in catalogue order. A stage has two forms of the
same arithmetic, written next to each other:

* ``vector(b, at)``: many samples as numpy arrays (used by ``ErrorModel.sense_series``);
* ``single(b, at)``: one sample as plain floats (used by ``ErrorModel.sense``; on one sample
  7-12x faster than the vector form, measured on the four presets).

Both forms perform the same IEEE operations in the same order (3x3 products as explicit sums, not
``@``), draw from the same seeded streams and share the stage's state, so the two paths give
bit-identical samples.

Four kinds of stage, in this order along the catalogue:

* ``temperature`` (``thermal_lag``): maps the truth (board) temperature at the sample times to the
  temperature the later stages see (``die(t, temp)``; every sampling instant of a sample sees its value);
* ``sampling`` (``time_skew``): chooses the instants at which truth is sampled (one per axis) and
  picks each axis' reading from its own instant;
* ``field``: acts on the 3-vector field at one sampling instant, ``b`` (M,3) / 3 floats, with the
  instant's temperature, currents and session in :class:`FieldInputs`. Interference acts in the
  body frame, ``misalignment`` maps body -> sensor axes, later field stages act on sensor axes;
* ``reading``: acts on the per-axis reading ``y`` (N,3) / 3 floats, with the sample time, the
  previous sample time, per-axis temperature and session in :class:`ReadingInputs`.

Adding an effect: add it to the catalogue, add its parameters to
:class:`~magstack.sim.error_params.ErrorParams` (neutral defaults), and write one stage class here
with both forms (docs/error-model.md, "Adding an effect"). Rotations are active 3x3 matrices
(:func:`rotvec_matrix`: ``R @ v`` turns ``v``); ``rot_a_from_b`` maps coordinates in frame b to frame a.
"""
from __future__ import annotations

import math
from collections.abc import Collection
from typing import Any, ClassVar

import numpy as np

from magstack.firmware.effects import EFFECT_NAMES, effect
from magstack.sim.error_params import ErrorParams
from magstack.sim.error_random import SESSION_OFFSET_TAG, normal_stream, session_rng

__all__ = ["Stage", "FieldInputs", "ReadingInputs", "STAGES", "stage", "build_stages", "misalignment_matrix",
           "rotvec_matrix",
           "TEMPERATURE", "SAMPLING", "FIELD", "READING"]

TEMPERATURE, SAMPLING, FIELD, READING = "temperature", "sampling", "field", "reading"
_KIND_RANK = {TEMPERATURE: 0, SAMPLING: 1, FIELD: 2, READING: 3}

#: The cross field is limited to this fraction of H0 in the cross-axis formula (the AMR model
#: diverges at |B_c| = H0, far outside every supported range; beyond it the bridge would flip).
_CROSS_AXIS_CLAMP = 0.9
#: Runs of one held step at least this long use scipy's lfilter for the 1/f state (the vector form of long
#: runs: ``magstack simulate``); shorter ones, and the single-sample form, a loop.
_PINK_LFILTER_MIN = 32
#: A step within this relative distance of the held step keeps it (1/f coefficients; see Noise).
_HELD_STEP_RTOL = 1e-9
#: Number of first-order (Lorentzian) processes per decade synthesising 1/f noise.
_PINK_POLES_PER_DECADE = 2.0
#: Distinct step lengths whose 1/f coefficients the single-sample path keeps (uniform sampling needs a few).
_PINK_COEF_CACHE = 256


class FieldInputs:
    """What a field stage sees besides the field, per sampling instant.

    ``d_temp_c``: temperature minus ``temp_ref_c`` (degC); ``currents_A``: {name: A}; ``session``:
    power-cycle id. Arrays (M,) in the vector path, one float / int each in the single-sample path.
    """

    __slots__ = ("d_temp_c", "currents_A", "session")

    def __init__(self, d_temp_c: Any, currents_A: dict[str, Any], session: Any) -> None:
        self.d_temp_c, self.currents_A, self.session = d_temp_c, currents_A, session


class ReadingInputs:
    """What a reading stage sees besides the reading.

    ``t_s``: sample time(s) (N,) / float; ``prev_t_s``: the previous sample's time (None before the
    first); ``d_temp_c``: per-axis temperature minus ``temp_ref_c`` at each axis' instant, (N,3) / 3
    floats; ``session``: power-cycle id at the sample time, (N,) / int.
    """

    __slots__ = ("t_s", "prev_t_s", "d_temp_c", "session")

    def __init__(self, t_s: Any, prev_t_s: float | None, d_temp_c: Any, session: Any) -> None:
        self.t_s, self.prev_t_s, self.d_temp_c, self.session = t_s, prev_t_s, d_temp_c, session


class Stage:
    """One effect. Subclasses set ``name`` (a catalogue effect) and ``kind``, and write both forms.

    ``active`` is False when the parameters make the stage an identity (neutral values: zero
    offsets, identity matrix, infinite range, ...; exact except that a -0.0 may stay -0.0); both
    paths then skip it. ``reset()`` restarts the stage's random streams and state.
    """

    name: ClassVar[str]
    kind: ClassVar[str]

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        self.params = params
        self.seed = seed
        self.active = True

    def reset(self) -> None:
        """Forget state and restart random streams (stateless stages: nothing to do)."""


#: effect name -> stage class, filled by :func:`stage` in catalogue order.
STAGES: dict[str, type[Stage]] = {}


def stage(cls: type[Stage]) -> type[Stage]:
    """Class decorator registering the one stage of effect ``cls.name``."""
    effect(cls.name)  # a catalogue effect (ValueError listing the valid names otherwise)
    if cls.name in STAGES:
        raise ValueError(f"effect {cls.name!r} already has a stage ({STAGES[cls.name].__name__})")
    if cls.kind not in _KIND_RANK:
        raise ValueError(f"stage kind {cls.kind!r}; valid: {', '.join(_KIND_RANK)}")
    STAGES[cls.name] = cls
    return cls


def build_stages(params: ErrorParams, seed: int, enabled: Collection[str]) -> dict[str, Stage]:
    """One stage object per catalogue effect, in catalogue order (also those switched off).

    Raises RuntimeError when the catalogue names an effect without a stage or orders the kinds other than
    temperature, sampling, field, reading (the pipeline cannot run them in another order).
    """
    missing = [n for n in EFFECT_NAMES if n not in STAGES]
    if missing:
        raise RuntimeError(f"effect(s) {missing} are in the catalogue (magstack.firmware.effects) but have no stage "
                           f"in magstack.sim.error_stages")
    ranks = [_KIND_RANK[STAGES[n].kind] for n in EFFECT_NAMES]
    if ranks != sorted(ranks):
        raise RuntimeError("catalogue order must put the temperature stage first, then the sampling stage, "
                           "field stages, then reading stages; "
                           f"got {[(n, STAGES[n].kind) for n in EFFECT_NAMES]}")
    return {n: STAGES[n](params, seed, enabled) for n in EFFECT_NAMES}


# ---------------------------------------------------------------- helpers shared by both forms
def _matvec_series(m: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rows of ``b`` (M,3) mapped by the 3x3 ``m``: b_i' = (m_i0 b_0 + m_i1 b_1) + m_i2 b_2, as :func:`_matvec_one`."""
    return b[:, 0:1] * m[:, 0] + b[:, 1:2] * m[:, 1] + b[:, 2:3] * m[:, 2]


def _matvec_one(rows: list[list[float]], x: float, y: float, z: float) -> list[float]:
    """``rows`` (3x3 as lists) times (x, y, z), summed in the order of :func:`_matvec_series`."""
    r0, r1, r2 = rows
    return [x * r0[0] + y * r0[1] + z * r0[2], x * r1[0] + y * r1[1] + z * r1[2], x * r2[0] + y * r2[1] + z * r2[2]]


def rotvec_matrix(rotvec_rad) -> np.ndarray:
    """The active rotation by the rotation vector ``rotvec_rad`` (axis times angle, rad) as a 3x3 matrix.

    Through the unit quaternion (v sin(a/2)/a, cos(a/2)), a = |v| (a Taylor series of sin(a/2)/a below
    1e-3 rad), as scipy's ``Rotation.from_rotvec(v).as_matrix()`` computes it, to the last bit."""
    v = np.array(rotvec_rad, dtype=float).reshape(3)
    a = math.sqrt(float(v @ v))
    a2 = a * a
    scale = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0 if a <= 1e-3 else math.sin(a / 2.0) / a
    x, y, z = (float(c) * scale for c in v)
    w = math.cos(a / 2.0)
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([[x2 - y2 - z2 + w2, 2.0 * (xy - zw), 2.0 * (xz + yw)],
                     [2.0 * (xy + zw), -x2 + y2 - z2 + w2, 2.0 * (yz - xw)],
                     [2.0 * (xz - yw), 2.0 * (yz + xw), -x2 - y2 + z2 + w2]])


def misalignment_matrix(misalignment_rad: np.ndarray, rotation_rad: np.ndarray) -> np.ndarray:
    """M = W @ R mapping a body-frame field to the sensor axes: b_sensor = M b_body.

    R = :func:`rotvec_matrix` ``(rotation_rad)`` (active; i.e. the orthogonal sensor triad
    is the body triad turned by -rotation_rad). Rows of W are the sensor axes' unit vectors in that
    orthogonal triad (a non-orthogonal frame, not a rotation): with angles (a_xy, a_xz, a_yz),
    e_x = (1,0,0); e_y = (sin a_xy, cos a_xy, 0); e_z a unit vector with e_x.e_z = sin a_xz and
    e_y.e_z = sin a_yz. So the angle between sensor axes i and j is exactly 90 deg - a_ij.
    """
    a_xy, a_xz, a_yz = (float(a) for a in misalignment_rad)
    sz = math.sin(a_xz)
    cz = (math.sin(a_yz) - math.sin(a_xy) * sz) / math.cos(a_xy)
    w = np.array([[1.0, 0.0, 0.0],
                  [math.sin(a_xy), math.cos(a_xy), 0.0],
                  [sz, cz, math.sqrt(max(0.0, 1.0 - sz * sz - cz * cz))]])
    return w @ rotvec_matrix(rotation_rad)


# ---------------------------------------------------------------- the stages, in catalogue order
@stage
class ThermalLag(Stage):
    """``thermal_lag``: T_die(t_k) = a_k T_die(t_(k-1)) + (1 - a_k) T_board(t_k), a_k = exp(-(t_k - t_(k-1))/tau);
    the first sample (and the first after ``reset``) starts in equilibrium, T_die = T_board.

    State: the last sample time and die temperature, shared by both forms. Both run the same float
    recursion (``math.exp``, one sample after the other), so they agree bit for bit.
    """

    name, kind = "thermal_lag", TEMPERATURE

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._tau = float(params.thermal_lag_tau_s)
        self.active = self._tau > 0.0
        self.reset()

    def reset(self) -> None:
        self._last: tuple[float, float] | None = None

    def vector(self, t_s: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
        """Die temperatures (N,) at the sample times ``t_s`` (N,) from the board temperatures ``temp_c``."""
        single = self.single
        return np.array([single(t, x) for t, x in zip(t_s.tolist(), temp_c.tolist(), strict=True)])

    def single(self, t_s: float, temp_c: float) -> float:
        last = self._last
        if last is None:
            die = temp_c
        else:
            a = math.exp(-(t_s - last[0]) / self._tau)
            die = a * last[1] + (1.0 - a) * temp_c
        self._last = (t_s, die)
        return die


@stage
class TimeSkew(Stage):
    """``time_skew``: axis i is the whole field part of the pipeline evaluated at t + axis_delay_s[i]."""

    name, kind = "time_skew", SAMPLING

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._delays = params.axis_delay_s
        self._delays_f = [float(d) for d in params.axis_delay_s]
        self.active = any(d != 0.0 for d in self._delays_f)

    def instants(self, t_s: np.ndarray) -> np.ndarray:
        """Truth instants (4N,): t + d_x, t + d_y, t + d_z (one block per axis), then t itself."""
        return np.concatenate([t_s + d for d in self._delays] + [t_s])

    def instants_one(self, t_s: float) -> list[float]:
        return [t_s + d for d in self._delays_f] + [t_s]

    def select(self, b_uT: np.ndarray, n: int) -> np.ndarray:
        """Axis i of block i: (3N,3) evaluated fields -> (N,3) readings."""
        return np.stack([b_uT[i * n:(i + 1) * n, i] for i in range(3)], axis=1)

    def select_one(self, rows: list[list[float]]) -> list[float]:
        return [rows[0][0], rows[1][1], rows[2][2]]


@stage
class Interference(Stage):
    """``interference``: b_body += D_k I_k for each named current (a current absent from the truth carries 0 A)."""

    name, kind = "interference", FIELD

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._coef = list(params.interference_uT_per_A.items())
        self._coef_f = [(k, d.tolist()) for k, d in self._coef]
        self.active = any((d != 0).any() for _, d in self._coef)

    def vector(self, b_body_uT: np.ndarray, at: FieldInputs) -> np.ndarray:
        for name, d in self._coef:
            cur = at.currents_A.get(name)
            if cur is not None:
                b_body_uT = b_body_uT + cur[:, None] * d
        return b_body_uT

    def single(self, b_body_uT: list[float], at: FieldInputs) -> list[float]:
        x, y, z = b_body_uT
        for name, d in self._coef_f:
            c = at.currents_A.get(name)
            if c is not None:
                x, y, z = x + c * d[0], y + c * d[1], z + c * d[2]
        return [x, y, z]


@stage
class MountRotation(Stage):
    """``mount_rotation``: in session s the sensor is mounted turned by R_s, so it senses R_s^T b_body
    (``params.mount_rotation_rad[s]``, rad; sessions not listed are unrotated)."""

    name, kind = "mount_rotation", FIELD

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        # rot_mount_from_frame^T as a matrix per session: b_mounted = R_s^T b_body
        self._m = {k: rotvec_matrix(v).T
                   for k, v in params.mount_rotation_rad.items() if np.any(v != 0)}
        self._rows = {k: m.tolist() for k, m in self._m.items()}
        self.active = bool(self._m)

    def vector(self, b_body_uT: np.ndarray, at: FieldInputs) -> np.ndarray:
        out = b_body_uT.copy()
        ses = np.asarray(at.session)
        for k, m in self._m.items():
            rows = ses == k
            if rows.any():
                out[rows] = _matvec_series(m, b_body_uT[rows])
        return out

    def single(self, b_body_uT: list[float], at: FieldInputs) -> list[float]:
        rows = self._rows.get(int(at.session))
        return b_body_uT if rows is None else _matvec_one(rows, *b_body_uT)


@stage
class Misalignment(Stage):
    """``misalignment``: body frame -> sensor axes, b_sensor = W R b_body (:func:`misalignment_matrix`)."""

    name, kind = "misalignment", FIELD

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self.matrix = misalignment_matrix(params.misalignment_rad, params.rotation_rad)
        self._rows = self.matrix.tolist()
        self.active = not (self.matrix == np.eye(3)).all()

    def vector(self, b_body_uT: np.ndarray, at: FieldInputs) -> np.ndarray:
        return _matvec_series(self.matrix, b_body_uT)

    def single(self, b_body_uT: list[float], at: FieldInputs) -> list[float]:
        return _matvec_one(self._rows, *b_body_uT)


@stage
class Gain(Stage):
    """``gain``: b_sensor <- G b_sensor (rows: affected axis, columns: incident axis)."""

    name, kind = "gain", FIELD

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._g = params.gain_matrix
        self._rows = params.gain_matrix.tolist()
        self.active = not (params.gain_matrix == np.eye(3)).all()

    def vector(self, b_sensor_uT: np.ndarray, at: FieldInputs) -> np.ndarray:
        return _matvec_series(self._g, b_sensor_uT)

    def single(self, b_sensor_uT: list[float], at: FieldInputs) -> list[float]:
        return _matvec_one(self._rows, *b_sensor_uT)


@stage
class CrossAxis(Stage):
    """``cross_axis``: b_i *= H0/(H0 + B_c) (set), H0/(H0 - B_c) (reset), H0^2/(H0^2 - B_c^2) (set/reset).

    B_c = the field on bridge i's easy axis, clamped to +-0.9 H0.
    """

    name, kind = "cross_axis", FIELD

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        h0 = params.cross_axis_h0_uT
        self.active = math.isfinite(h0)
        self._h0, self._lo, self._hi = h0, -_CROSS_AXIS_CLAMP * h0, _CROSS_AXIS_CLAMP * h0
        self._easy = params.cross_axis_easy_axis
        self._mode = params.cross_axis_mode

    def vector(self, b_sensor_uT: np.ndarray, at: FieldInputs) -> np.ndarray:
        h0 = self._h0
        bc = np.clip(b_sensor_uT[:, list(self._easy)], self._lo, self._hi)
        if self._mode == "set":
            factor = h0 / (h0 + bc)
        elif self._mode == "reset":
            factor = h0 / (h0 - bc)
        else:
            factor = h0 * h0 / (h0 * h0 - bc * bc)
        return b_sensor_uT * factor

    def single(self, b_sensor_uT: list[float], at: FieldInputs) -> list[float]:
        h0, lo, hi = self._h0, self._lo, self._hi
        e0, e1, e2 = self._easy
        x, y, z = b_sensor_uT
        c0, c1, c2 = b_sensor_uT[e0], b_sensor_uT[e1], b_sensor_uT[e2]
        c0 = lo if c0 < lo else (hi if c0 > hi else c0)
        c1 = lo if c1 < lo else (hi if c1 > hi else c1)
        c2 = lo if c2 < lo else (hi if c2 > hi else c2)
        if self._mode == "set":
            return [x * (h0 / (h0 + c0)), y * (h0 / (h0 + c1)), z * (h0 / (h0 + c2))]
        if self._mode == "reset":
            return [x * (h0 / (h0 - c0)), y * (h0 / (h0 - c1)), z * (h0 / (h0 - c2))]
        hh = h0 * h0
        return [x * (hh / (hh - c0 * c0)), y * (hh / (hh - c1 * c1)), z * (hh / (hh - c2 * c2))]


@stage
class Nonlinearity(Stage):
    """``nonlinearity``: b_i += c3_i b_i^3."""

    name, kind = "nonlinearity", FIELD

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._c3 = params.cubic_per_uT2
        self._c3_f = params.cubic_per_uT2.tolist()
        self.active = bool((params.cubic_per_uT2 != 0).any())

    def vector(self, b_sensor_uT: np.ndarray, at: FieldInputs) -> np.ndarray:
        b = b_sensor_uT
        return b + self._c3 * (b * b * b)  # b * b * b, not b ** 3: numpy's power and libm's pow round differently

    def single(self, b_sensor_uT: list[float], at: FieldInputs) -> list[float]:
        c = self._c3_f
        x, y, z = b_sensor_uT
        return [x + c[0] * (x * x * x), y + c[1] * (y * y * y), z + c[2] * (z * z * z)]


@stage
class TemperatureGain(Stage):
    """``temperature_gain``: b <- b + dT (K_S b) + (k_s2 dT^2) b, dT = T - temp_ref_c at the instant."""

    name, kind = "temperature_gain", FIELD

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._ks, self._ks2 = params.k_s_per_c, params.k_s2_per_c2
        self._ks_rows, self._ks2_f = params.k_s_per_c.tolist(), params.k_s2_per_c2.tolist()
        self.active = bool((params.k_s_per_c != 0).any() or (params.k_s2_per_c2 != 0).any())

    def vector(self, b_sensor_uT: np.ndarray, at: FieldInputs) -> np.ndarray:
        d = at.d_temp_c[:, None]
        return b_sensor_uT + d * _matvec_series(self._ks, b_sensor_uT) + self._ks2 * (d * d) * b_sensor_uT

    def single(self, b_sensor_uT: list[float], at: FieldInputs) -> list[float]:
        d = at.d_temp_c
        d2 = d * d
        s2 = self._ks2_f
        x, y, z = b_sensor_uT
        k0, k1, k2 = _matvec_one(self._ks_rows, x, y, z)
        return [x + d * k0 + s2[0] * d2 * x, y + d * k1 + s2[1] * d2 * y, z + d * k2 + s2[2] * d2 * z]


@stage
class Hysteresis(Stage):
    """``hysteresis``: once |y_i| >= threshold, y_i += +-h_i signed by that excursion, until an opposite one.

    State: the last excursion sign per axis (-1, 0, +1), carried across calls and shared by both forms;
    before the first excursion (and after ``reset``) ``hysteresis_initial_state``.
    """

    name, kind = "hysteresis", READING

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._thr = params.hysteresis_threshold_uT
        self._s0 = params.hysteresis_initial_state.tolist()
        self._h, self._h_f = params.hysteresis_uT, params.hysteresis_uT.tolist()
        self.active = bool((params.hysteresis_uT != 0).any()) and math.isfinite(self._thr)
        self.reset()

    def reset(self) -> None:
        self._state = list(self._s0)

    def vector(self, y_uT: np.ndarray, at: ReadingInputs) -> np.ndarray:
        n = y_uT.shape[0]
        sign = np.empty_like(y_uT)
        events = np.where(np.abs(y_uT) >= self._thr, np.sign(y_uT), 0.0)
        ar = np.arange(n)
        for i in range(3):
            e = events[:, i]
            last = np.maximum.accumulate(np.where(e != 0, ar, -1))
            sign[:, i] = np.where(last >= 0, e[np.maximum(last, 0)], self._state[i])
        self._state = sign[-1].tolist()
        return y_uT + sign * self._h

    def single(self, y_uT: list[float], at: ReadingInputs) -> list[float]:
        thr, h, st = self._thr, self._h_f, self._state
        out = []
        for i in range(3):
            v = y_uT[i]
            if abs(v) >= thr and v != 0.0:
                st[i] = 1.0 if v > 0 else -1.0
            out.append(v + st[i] * h[i])
        return out


@stage
class Offset(Stage):
    """``offset``: y += O."""

    name, kind = "offset", READING

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._o, self._o_f = params.offset_uT, params.offset_uT.tolist()
        self.active = bool((params.offset_uT != 0).any())

    def vector(self, y_uT: np.ndarray, at: ReadingInputs) -> np.ndarray:
        return y_uT + self._o

    def single(self, y_uT: list[float], at: ReadingInputs) -> list[float]:
        o = self._o_f
        return [y_uT[0] + o[0], y_uT[1] + o[1], y_uT[2] + o[2]]


@stage
class TemperatureOffset(Stage):
    """``temperature_offset``: y_i += K_O,i dT_i (dT at axis i's instant)."""

    name, kind = "temperature_offset", READING

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._k, self._k_f = params.k_o_uT_per_c, params.k_o_uT_per_c.tolist()
        self.active = bool((params.k_o_uT_per_c != 0).any())

    def vector(self, y_uT: np.ndarray, at: ReadingInputs) -> np.ndarray:
        return y_uT + self._k * at.d_temp_c

    def single(self, y_uT: list[float], at: ReadingInputs) -> list[float]:
        k, d = self._k_f, at.d_temp_c
        return [y_uT[0] + k[0] * d[0], y_uT[1] + k[1] * d[1], y_uT[2] + k[2] * d[2]]


@stage
class Drift(Stage):
    """``drift``: y += r (t - t0) + w(t), w a random walk (sigma sqrt(dt) per step, 0 at the first sample).

    State: the walk's value; draws: the ``walk`` stream (only when some sigma > 0).
    """

    name, kind = "drift", READING

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._rate, self._rate_f = params.drift_uT_per_s, params.drift_uT_per_s.tolist()
        self._t0 = params.drift_t0_s
        self._sig, self._sig_f = params.drift_walk_uT_per_sqrt_s, params.drift_walk_uT_per_sqrt_s.tolist()
        self._walk_on = bool((params.drift_walk_uT_per_sqrt_s > 0).any())
        self.active = self._walk_on or bool((params.drift_uT_per_s != 0).any())
        self.reset()

    def reset(self) -> None:
        self._z = normal_stream(self.seed, "walk")
        self._walk = [0.0, 0.0, 0.0]

    def vector(self, y_uT: np.ndarray, at: ReadingInputs) -> np.ndarray:
        t = at.t_s
        n = t.size
        if self._walk_on:
            z = self._z.take_array(3 * n).reshape(n, 3)
            dt = np.diff(t, prepend=t[0] if at.prev_t_s is None else at.prev_t_s)
            steps = z * np.sqrt(dt)[:, None] * self._sig
            w = np.cumsum(np.vstack([self._walk, steps]), axis=0)[1:]  # sequential, as single()
            self._walk = w[-1].tolist()
        else:  # no walk: no draws (the stream is this effect's own)
            w = np.zeros((n, 3))
        return y_uT + self._rate * (t - self._t0)[:, None] + w

    def single(self, y_uT: list[float], at: ReadingInputs) -> list[float]:
        rate, t = self._rate_f, at.t_s
        if self._walk_on:
            z = self._z.take(3)
            sq = math.sqrt(0.0 if at.prev_t_s is None else t - at.prev_t_s)
            sig, w = self._sig_f, self._walk
            w = self._walk = [w[0] + z[0] * sq * sig[0], w[1] + z[1] * sq * sig[1], w[2] + z[2] * sq * sig[2]]
        else:
            w = [0.0, 0.0, 0.0]
        dt0 = t - self._t0
        return [y_uT[0] + rate[0] * dt0 + w[0], y_uT[1] + rate[1] * dt0 + w[1], y_uT[2] + rate[2] * dt0 + w[2]]


@stage
class SessionOffset(Stage):
    """``session_offset``: y += N(0, sigma) drawn per session id, fixed for (seed, id) whatever the visiting order."""

    name, kind = "session_offset", READING

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._sigma = params.session_offset_sigma_uT
        self.active = bool((params.session_offset_sigma_uT != 0).any())
        self.reset()

    def reset(self) -> None:
        self._offsets: dict[int, np.ndarray] = {}
        self._offsets_f: dict[int, list[float]] = {}

    def offset_uT(self, session: int) -> np.ndarray:
        """The offset (3,) uT of ``session``."""
        session = int(session)
        off = self._offsets.get(session)
        if off is None:
            off = self._offsets[session] = (session_rng(self.seed, SESSION_OFFSET_TAG, session).standard_normal(3)
                                             * self._sigma)
        return off

    def vector(self, y_uT: np.ndarray, at: ReadingInputs) -> np.ndarray:
        ids = np.unique(at.session)
        offs = np.array([self.offset_uT(s) for s in ids]).reshape(-1, 3)
        return y_uT + offs[np.searchsorted(ids, at.session)]

    def single(self, y_uT: list[float], at: ReadingInputs) -> list[float]:
        off = self._offsets_f.get(at.session)
        if off is None:
            off = self._offsets_f[at.session] = self.offset_uT(at.session).tolist()
        return [y_uT[0] + off[0], y_uT[1] + off[1], y_uT[2] + off[2]]


@stage
class Noise(Stage):
    """``noise``: white Gaussian per sample plus 1/f noise (sum of K Ornstein-Uhlenbeck processes).

    The 1/f part: K first-order processes with log-spaced corners across ``noise_pink_band_hz``
    (2 per decade), equal variance, exact update x <- phi x + sqrt(1 - phi^2) sigma z for any step,
    phi = exp(-dt/tau); stationary start at the first sample. Draws: the ``white`` and ``pink``
    streams. State: the K x 3 process values and the held step (below).

    Held step: the coefficients come from a step length that is held while each new step stays
    within 1e-9 relative of it (timestamps t0 + k/rate differ in their last bits). A uniformly
    sampled run is then one filter pass (scipy lfilter) in the vector form, and both forms use the
    same coefficients at every step, whatever the split into calls.
    """

    name, kind = "noise", READING

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._white, self._white_f = params.noise_white_uT, params.noise_white_uT.tolist()
        f_lo, f_hi = params.noise_pink_band_hz
        k = max(1, int(math.ceil(math.log10(f_hi / f_lo) * _PINK_POLES_PER_DECADE)) + 1)
        self._k = k
        self._tau = 1.0 / (2.0 * math.pi * np.geomspace(f_lo, f_hi, k))  # (K,) s
        self._sig = params.noise_pink_uT[None, :] / math.sqrt(k)  # (1,3) per process
        self._sig_f = self._sig[0].tolist() * k  # (K*3,) row-major
        self._pink_on = bool((params.noise_pink_uT > 0).any())
        self.active = self._pink_on or bool((params.noise_white_uT != 0).any())
        self._coef_f: dict[float, tuple[list[float], list[float]]] = {}  # held step -> (phi, g) (K*3,)
        self.reset()

    def reset(self) -> None:
        self._zw = normal_stream(self.seed, "white")
        self._zp = normal_stream(self.seed, "pink")
        self._x = [0.0] * (3 * self._k)  # (K,3) row-major
        self._step: float | None = None  # held step length (s)

    def _coef(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """phi (K,) and g = sqrt(1 - phi^2) sigma (K,3) of one step dt (s)."""
        phi = np.exp(-dt / self._tau)
        return phi, np.sqrt(1.0 - phi[:, None] ** 2) * self._sig

    def _held_steps(self, dts: np.ndarray) -> np.ndarray:
        """The held step length for each step (N,), updating the held step as single() does."""
        c = self._step if self._step is not None else float(dts[0])
        if (np.abs(dts - c) <= _HELD_STEP_RTOL * c).all():  # the usual case: one uniform run
            self._step = c
            return np.full(dts.size, c)
        out = np.empty(dts.size)
        for i, dt in enumerate(dts.tolist()):
            if not abs(dt - c) <= _HELD_STEP_RTOL * c:
                c = dt
            out[i] = c
        self._step = c
        return out

    @staticmethod
    def _sum_rows(x: np.ndarray) -> np.ndarray:
        """Sum of the K process rows, added one after another (as single())."""
        s = x[0].copy()
        for j in range(1, x.shape[0]):
            s += x[j]
        return s

    def _pink(self, t: np.ndarray, prev_t: float | None) -> np.ndarray:
        n, k = t.size, self._k
        if not self._pink_on:  # no 1/f noise: no draws (own stream)
            return np.zeros((n, 3))
        z = self._zp.take_array(3 * k * n).reshape(n, k, 3)
        x = np.array(self._x, dtype=float).reshape(k, 3)
        out = np.empty((n, 3))
        start = 0
        if prev_t is None:  # stationary start
            x = z[0] * self._sig
            out[0] = self._sum_rows(x)
            start, prev_t = 1, t[0]
        dts = np.diff(np.concatenate([[prev_t], t[start:]]))
        if dts.size:
            steps = self._held_steps(dts)
            cuts = [0, *(np.flatnonzero(steps[1:] != steps[:-1]) + 1).tolist(), dts.size]
            for a, b in zip(cuts[:-1], cuts[1:], strict=True):  # runs of one held step
                phi, g = self._coef(steps[a])
                if b - a >= _PINK_LFILTER_MIN:  # x_n = phi x_{n-1} + g z_n per process: a one-pole filter
                    from scipy.signal import lfilter  # the ground extra: bulk simulation only

                    acc = np.zeros((b - a, 3))
                    for j in range(k):
                        xs, _ = lfilter([1.0], [1.0, -phi[j]], z[start + a:start + b, j, :] * g[j], axis=0,
                                        zi=(phi[j] * x[j])[None, :])
                        acc = xs.copy() if j == 0 else acc + xs
                        x[j] = xs[-1]
                    out[start + a:start + b] = acc
                else:
                    for i in range(start + a, start + b):
                        x = phi[:, None] * x + g * z[i]
                        out[i] = self._sum_rows(x)
        self._x = x.ravel().tolist()
        return out

    def vector(self, y_uT: np.ndarray, at: ReadingInputs) -> np.ndarray:
        n = y_uT.shape[0]
        y_uT = y_uT + self._zw.take_array(3 * n).reshape(n, 3) * self._white
        return y_uT + self._pink(at.t_s, at.prev_t_s)

    def single(self, y_uT: list[float], at: ReadingInputs) -> list[float]:
        w, z = self._white_f, self._zw.take(3)
        y0, y1, y2 = y_uT[0] + z[0] * w[0], y_uT[1] + z[1] * w[1], y_uT[2] + z[2] * w[2]
        if not self._pink_on:
            return [y0 + 0.0, y1 + 0.0, y2 + 0.0]  # as vector(): + zeros (no negative zeros)
        zs = self._zp.take(3 * self._k)
        if at.prev_t_s is None:  # stationary start
            x = [a * b for a, b in zip(zs, self._sig_f, strict=True)]
        else:
            dt = at.t_s - at.prev_t_s
            c = self._step
            if c is None or not abs(dt - c) <= _HELD_STEP_RTOL * c:
                c = self._step = dt
            coef = self._coef_f.get(c)
            if coef is None:
                if len(self._coef_f) >= _PINK_COEF_CACHE:
                    self._coef_f.clear()
                phi, g = self._coef(c)
                coef = self._coef_f[c] = (np.repeat(phi, 3).tolist(), g.ravel().tolist())
            phi_f, g_f = coef
            x = [ph * xv + gv * zv for ph, xv, gv, zv in zip(phi_f, self._x, g_f, zs, strict=True)]
        self._x = x
        s0, s1, s2 = x[0], x[1], x[2]
        for j in range(3, len(x), 3):
            s0 += x[j]
            s1 += x[j + 1]
            s2 += x[j + 2]
        return [y0 + s0, y1 + s1, y2 + s2]


@stage
class Saturation(Stage):
    """``saturation``: y_i clipped to +-range_uT (inactive when the range is infinite)."""

    name, kind = "saturation", READING

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        self._r = params.range_uT
        self.active = math.isfinite(params.range_uT)

    def vector(self, y_uT: np.ndarray, at: ReadingInputs) -> np.ndarray:
        return np.clip(y_uT, -self._r, self._r)

    def single(self, y_uT: list[float], at: ReadingInputs) -> list[float]:
        r = self._r
        return [-r if v < -r else (r if v > r else v) for v in y_uT]


def _max_code(range_uT: float, lsb_uT: np.ndarray) -> np.ndarray:
    """Largest code k per axis with ``k * lsb <= range`` in floating point (saturated output).

    ``floor(range / lsb)`` alone can be one too many when ``range / lsb`` rounds up to an
    integer (range 11 uT, lsb 1e-5 uT: 1100000 * 1e-5 = 11.000000000000002 > 11).
    """
    lim = np.floor(range_uT / lsb_uT)
    return np.where(lim * lsb_uT > range_uT, lim - 1.0, lim)


@stage
class Quantization(Stage):
    """``quantization``: y_i rounded to a multiple of lsb_uT[i] (0 = none).

    With ``saturation`` on (and a finite range) codes are limited to :func:`_max_code`, so the output
    never leaves the range.
    """

    name, kind = "quantization", READING

    def __init__(self, params: ErrorParams, seed: int, enabled: Collection[str]) -> None:
        super().__init__(params, seed, enabled)
        lsb = params.lsb_uT
        self._q = lsb > 0
        self.active = bool(self._q.any())
        self._lsb = lsb[self._q]
        clip = "saturation" in enabled and math.isfinite(params.range_uT)
        self._lim = _max_code(params.range_uT, self._lsb) if clip and self.active else None
        lims = [None] * self._lsb.size if self._lim is None else self._lim.tolist()
        self._axes_f = list(zip(np.flatnonzero(self._q).tolist(), self._lsb.tolist(), lims, strict=True))

    def vector(self, y_uT: np.ndarray, at: ReadingInputs) -> np.ndarray:
        y_uT = y_uT.copy()
        codes = np.round(y_uT[:, self._q] / self._lsb)
        if self._lim is not None:
            codes = np.clip(codes, -self._lim, self._lim)
        y_uT[:, self._q] = codes * self._lsb + 0.0  # + 0.0: no negative zeros
        return y_uT

    def single(self, y_uT: list[float], at: ReadingInputs) -> list[float]:
        y_uT = list(y_uT)
        for i, lsb, lim in self._axes_f:
            c = float(round(y_uT[i] / lsb))
            if lim is not None:
                c = -lim if c < -lim else (lim if c > lim else c)
            y_uT[i] = c * lsb + 0.0
        return y_uT
