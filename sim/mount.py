"""Simulated bench remounts: effect ``mount_rotation`` of the catalogue, as a truth wrapper.

Between bench sessions the DUT is taken off and put back, a little rotated each time. The
sensor then senses ``R_s^T B`` instead of ``B`` in session ``s`` (``R_s`` a small rotation; the
reference, fixed to the coil, still reads ``B``). :class:`MountedTruth` wraps any
:class:`~magstack.sim.truth_source.TruthSource` and rotates its field per session, so the error
model, chip models and ``magstack simulate`` produce the effect without knowing about it:
feed the DUT's error model the wrapped truth and the reference the original.

Rotation vectors are in rad (sensor mount relative to the frame mount); a session without an
entry is unrotated. Rotations use :class:`scipy.spatial.transform.Rotation`.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from magstack.drivers.errors import ConfigurationError
from magstack.firmware.effects import effect

#: The catalogue entry this module produces.
EFFECT = effect("mount_rotation")


class MountedTruth:
    """A TruthSource whose field is ``R_s^T B(t)`` for ``s = truth.session(t)``.

    ``rotvec_rad``: session id -> rotation vector (3,) rad. Temperature, currents and session
    pass through unchanged. Vectorised methods are provided whenever the wrapped source has them.
    """

    def __init__(self, truth, rotvec_rad: Mapping[int, object]) -> None:
        self.truth = truth
        self.rotvec_rad: dict[int, np.ndarray] = {}
        for k, v in rotvec_rad.items():
            rv = np.asarray(v, dtype=float).reshape(-1)
            if rv.size != 3 or not np.all(np.isfinite(rv)):
                raise ConfigurationError(f"mount rotation of session {k} must be 3 finite angles (rad), got {v!r}")
            self.rotvec_rad[int(k)] = rv
        self._inv = {k: Rotation.from_rotvec(v).inv() for k, v in self.rotvec_rad.items()}

    def _rotate(self, b: np.ndarray, sessions: np.ndarray) -> np.ndarray:
        out = np.array(b, dtype=float, copy=True).reshape(-1, 3)
        for k, inv in self._inv.items():
            m = sessions == k
            if m.any():
                out[m] = inv.apply(out[m])
        return out

    # vectorised (used by the error model when present)
    def field_series_uT(self, t_s) -> np.ndarray:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if hasattr(self.truth, "field_series_uT"):
            b = np.asarray(self.truth.field_series_uT(t), dtype=float).reshape(t.size, 3)
        else:
            b = np.array([self.truth.field_uT(float(x)) for x in t], dtype=float).reshape(t.size, 3)
        return self._rotate(b, self.session_series(t))

    def session_series(self, t_s) -> np.ndarray:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if hasattr(self.truth, "session_series"):
            return np.asarray(self.truth.session_series(t)).astype(np.int64).reshape(t.size)
        return np.array([int(self.truth.session(float(x))) for x in t], dtype=np.int64)

    def __getattr__(self, name: str):
        # temp_series_c / currents_series_A pass through when the wrapped source has them
        if name in ("temp_series_c", "currents_series_A"):
            return getattr(self.truth, name)
        raise AttributeError(name)

    # scalar TruthSource protocol
    def field_uT(self, t_s: float) -> np.ndarray:
        return self.field_series_uT(np.array([t_s]))[0]

    def temp_c(self, t_s: float) -> float:
        return self.truth.temp_c(t_s)

    def currents_A(self, t_s: float) -> Mapping[str, float]:
        return self.truth.currents_A(t_s)

    def session(self, t_s: float) -> int:
        return int(self.truth.session(t_s))
