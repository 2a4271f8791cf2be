"""What the field, temperature and currents really are, as functions of time.

Truth generators (bench coil programs, orbits) implement :class:`TruthSource`; chip
models and the error model consume it. Field in uT in the body frame, temperature
in degC, currents in A, time in seconds of the simulation clock's monotonic time.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class TruthSource(Protocol):
    def field_uT(self, t_s: float) -> np.ndarray:
        """True field vector (3,) at ``t_s``."""

    def temp_c(self, t_s: float) -> float:
        """True sensor temperature at ``t_s``."""

    def currents_A(self, t_s: float) -> Mapping[str, float]:
        """Named interfering currents at ``t_s`` (empty if none)."""

    def session(self, t_s: float) -> int:
        """Power-cycle / run id in force at ``t_s``."""


class StaticTruth:
    """A constant field and temperature; settable by tests."""

    def __init__(self, b_uT=(20.0, -5.0, 40.0), temp_c: float = 25.0, currents_A: Mapping[str, float] | None = None):
        self.b_uT = np.asarray(b_uT, dtype=float)
        self.temperature_c = float(temp_c)
        self.currents = dict(currents_A or {})

    def field_uT(self, t_s: float) -> np.ndarray:
        return self.b_uT.copy()

    def temp_c(self, t_s: float) -> float:
        return self.temperature_c

    def currents_A(self, t_s: float) -> Mapping[str, float]:
        return dict(self.currents)

    def session(self, t_s: float) -> int:
        return 0


class SeriesTruth:
    """Mixin: the scalar :class:`TruthSource` methods and power-cycle sessions from the vectorised ones.

    A subclass provides ``field_series_uT``, ``temp_series_c``, ``currents_series_A`` and the attributes
    ``duration_s`` (s) and ``sessions`` (equal power cycles over the run)."""

    duration_s: float
    sessions: int

    def session_series(self, t_s) -> np.ndarray:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        idx = np.floor(np.clip(t, 0.0, self.duration_s) / self.duration_s * self.sessions).astype(np.int64)
        return np.minimum(idx, self.sessions - 1)

    def field_uT(self, t_s: float) -> np.ndarray:
        return self.field_series_uT(np.array([t_s]))[0]

    def temp_c(self, t_s: float) -> float:
        return float(self.temp_series_c(np.array([t_s]))[0])

    def currents_A(self, t_s: float) -> dict[str, float]:
        return {k: float(v[0]) for k, v in self.currents_series_A(np.array([t_s])).items()}

    def session(self, t_s: float) -> int:
        return int(self.session_series(np.array([t_s]))[0])
