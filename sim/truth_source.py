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
