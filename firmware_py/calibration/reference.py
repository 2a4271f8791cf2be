"""Reference instruments' measuring ranges and the saturation guard of the fit.

A reference pinned at (or read beyond) its range while the DUT reads the real, larger field
teaches the fit a wrong gain: one such stretch took the joint fit from ~120 to ~1,985 nT on a
real bench. The fit therefore flags rows where any reference component is at or beyond
``(1 - margin)`` of the reference's range and, by default, excludes them (counted, with a
warning); ``FitOptions.include_saturated`` keeps them.

Ranges come from each reference's driver table (``magstack.drivers.fvm400.NOMINAL_RANGE_NT``);
the session metadata key ``reference`` (written by ``magstack bench`` and ``import-mageval``)
names the instrument.
"""
from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

import numpy as np

from magstack.drivers import fvm400

#: Reference name (session metadata ``reference``) -> nominal range per component, uT.
REFERENCE_RANGES_UT: Mapping[str, float] = MappingProxyType({
    "fvm400": fvm400.NOMINAL_RANGE_NT / 1000.0,
    "igrf": float("inf"),      # a field model (orbit telemetry: IGRF at the position, rotated by the attitude)
})
#: Reference assumed when a session does not name one (the project's bench reference).
DEFAULT_REFERENCE = "fvm400"
#: A row counts as saturated when a reference component reaches this fraction of the range
#: short of it (1 %: the FVM400 resolves 1 nT, so a pinned reading sits within ~1 uT of the limit).
SATURATION_MARGIN = 0.01


def reference_range(metadata: Mapping[str, str]) -> tuple[str, float, str | None]:
    """``(name, range_uT, note)`` for a session's reference; the note says when the default
    was assumed (reference unknown or not named)."""
    name = str(metadata.get("reference", "") or "").strip().lower()
    if name in REFERENCE_RANGES_UT:
        return name, REFERENCE_RANGES_UT[name], None
    what = f"reference {name!r} has no range table" if name else "session metadata names no reference"
    return (DEFAULT_REFERENCE, REFERENCE_RANGES_UT[DEFAULT_REFERENCE],
            f"{what}: assuming {DEFAULT_REFERENCE.upper()} (+-{REFERENCE_RANGES_UT[DEFAULT_REFERENCE]:g} uT)")


def saturated_rows(b_ref_uT: np.ndarray, range_uT: float, margin: float = SATURATION_MARGIN) -> np.ndarray:
    """(N,) bool: any reference component with ``|B| >= (1 - margin) * range_uT`` (NaN: False)."""
    b = np.abs(np.asarray(b_ref_uT, dtype=float).reshape(-1, 3))
    with np.errstate(invalid="ignore"):
        return np.any(b >= (1.0 - margin) * float(range_uT), axis=1)
