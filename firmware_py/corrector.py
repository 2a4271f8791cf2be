"""On-board corrector: the sampling loop's calibration step, backed by the active fixed-point table.

:class:`FixedPointCorrector` implements :class:`magstack.firmware.sampling_loop.Corrector`. Each
call takes the table that is active *now* in a :class:`~magstack.firmware.cal_table.CalTableStore`
(so a table swapped in at ``cycle_boundary()`` applies from the next cycle), converts the float
reading once at the boundary (uT -> int nT, degC -> int centi-degC), runs the integer applier
(:meth:`~magstack.firmware.fixed_point.FixedPointTable.apply_sample`) and returns its Q.8 nT
output in uT.

It returns None - the loop then publishes the sample as uncalibrated - and counts why in
``status`` when: no table is active or the table needs current inputs this loop does not measure
(``not_applied``); the reading or temperature is not finite once scaled (``bad_input``: e.g.
NaN, or 1e308 uT, which overflows to inf in nT); the table needs a temperature and the sample
has none (``no_temperature``); the
sample lies outside the table's validity box (``out_of_validity``: a table is never applied
where it was not fitted); the applier saturated (``saturated``). ``ok`` counts calibrated samples.
It never raises on a reading.
"""
from __future__ import annotations

import math
from collections import Counter

from magstack.firmware.fixed_point import OUT_FRAC
from magstack.firmware.float_applier import ApplyFlag

__all__ = ["FixedPointCorrector", "STATUS_KEYS"]

#: Keys of :attr:`FixedPointCorrector.status` (every key is present, starting at 0).
STATUS_KEYS = ("ok", "not_applied", "bad_input", "no_temperature", "out_of_validity", "saturated")
_OUT_SCALE = float(2 ** OUT_FRAC) * 1e3   # Q.8 nT -> uT


class FixedPointCorrector:
    """Sampling-loop corrector using ``store.active_fixed`` (see the module docstring)."""

    def __init__(self, store) -> None:
        self.store = store
        self.status: Counter = Counter({k: 0 for k in STATUS_KEYS})

    def __call__(self, sample) -> tuple[float, float, float] | None:
        fx = self.store.active_fixed
        if fx is None or fx.D:
            self.status["not_applied"] += 1
            return None
        b_nT = _to_int(sample.b_uT, 1e3)
        if b_nT is None:
            self.status["bad_input"] += 1
            return None
        if sample.temp_c is None or not math.isfinite(sample.temp_c):
            if fx.temp_range_cdeg is not None:
                self.status["no_temperature"] += 1
                return None
            t_cdeg = fx.t0_cdeg
        else:
            t = _to_int((sample.temp_c,), 100.0)
            if t is None:
                self.status["bad_input"] += 1
                return None
            t_cdeg = t[0]
        q, flags = fx.apply_sample(b_nT, t_cdeg)
        if flags & ApplyFlag.SATURATED:
            self.status["saturated"] += 1
            return None
        if flags & ApplyFlag.OUT_OF_VALIDITY:
            self.status["out_of_validity"] += 1
            return None
        self.status["ok"] += 1
        return (q[0] / _OUT_SCALE, q[1] / _OUT_SCALE, q[2] / _OUT_SCALE)


def _to_int(values, scale: float) -> list[int] | None:
    """``round(v * scale)`` for each value, or None when one is not finite after scaling (finite
    values beyond the applier's input range are clipped and flagged SATURATED by the applier)."""
    out = []
    for v in values:
        try:
            x = float(v) * scale
        except (TypeError, ValueError):
            return None
        if not math.isfinite(x):
            return None
        out.append(int(round(x)))
    return out
