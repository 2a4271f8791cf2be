"""The calibration model's terms and how each is used: on board (fixed point and float), float only, or
ground only. Taken from the effect catalogue (:mod:`magstack.firmware.effects`); a module of its own so the
table and the flight corrector need not import the fit (and its SciPy dependencies)."""
from __future__ import annotations

from magstack.firmware.effects import EFFECTS

#: Every calibration term, in catalogue (pipeline) order, taken from the effect catalogue.
CAL_TERMS: tuple[str, ...] = tuple(dict.fromkeys(
    t for e in EFFECTS.values() if e.cal_term for t in (e.cal_term, *e.cal_terms_extra)))

#: Terms carried to the on-board applier (fixed point and float).
FLIGHT_TERMS: tuple[str, ...] = ("gain_matrix", "temperature_gain", "temperature_gain2", "offset", "temperature_offset",
                                  "currents")
#: Terms whose inputs include the temperature.
TEMPERATURE_TERMS: tuple[str, ...] = ("temperature_gain", "temperature_gain2", "temperature_offset")
#: Terms the float64 applier can also apply (not the fixed-point one).
FLOAT_ONLY_TERMS: tuple[str, ...] = ("cubic", "cross_products")
#: Terms that explain the fit data (nuisance) but are not applied to new data:
#: time skew needs dB/dt, session offsets are unknown for a new power cycle, drift would extrapolate,
#: a mount rotation belongs to the bench, not to the sensor.
GROUND_ONLY_TERMS: tuple[str, ...] = ("time_skew", "session_offset", "drift", "mount_rotation")
#: Terms without design-matrix columns: fitted by their own solver (``mount_rotation``: the
#: per-session angles couple the output axes; :mod:`magstack.firmware.calibration.mount`).
JOINT_TERMS: tuple[str, ...] = ("mount_rotation",)

assert set(FLIGHT_TERMS + FLOAT_ONLY_TERMS + GROUND_ONLY_TERMS) == set(CAL_TERMS), \
    "effects catalogue cal_term set changed: update firmware.cal_terms"
