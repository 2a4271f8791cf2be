"""On-board corrector: the active calibration table applied by the integer (fixed-point) applier.

The float reading crosses into integers once, at the boundary (uT -> int nT, degC -> int
centi-degC, A -> int mA), the applier runs on integers only, and its Q23.8 nT output is
published in uT. A sample is published as calibrated only when every input is finite and
inside the table's validity box (field per axis, temperature range, current ranges) and the
output did not saturate; otherwise :class:`Correction` says why and carries no field.
"""
from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from magstack.firmware.cal_table import CalTableStore
from magstack.firmware.fixed_point import OUT_FRAC, B_LIMIT_nT, I_LIMIT_mA, T_LIMIT_cdeg
from magstack.firmware.float_applier import ApplyFlag

#: Why a sample was not calibrated (the ``status`` of a :class:`Correction`).
STATUSES = ("ok", "no_table", "bad_input", "no_temperature", "no_currents", "out_of_validity", "saturated")
_OUT_SCALE = float(2 ** OUT_FRAC) * 1e3     # Q23.8 nT -> uT


@dataclass(frozen=True)
class Correction:
    b_uT: tuple[float, float, float] | None     # None unless status == "ok"
    status: str
    table_crc32: int | None = None


class TableCorrector:
    """Corrects samples with ``store``'s active fixed-point table; ``status`` counts each outcome."""

    def __init__(self, store: CalTableStore, current_names: Sequence[str] = ()) -> None:
        self.store = store
        self.current_names = tuple(current_names)
        self.status: Counter = Counter()

    def _result(self, status: str, crc: int | None, b=None) -> Correction:
        self.status[status] += 1
        return Correction(b, status, crc)

    def correct(self, b_uT: Sequence[float], temp_c: float | None,
                currents_A: Mapping[str, float] | None = None) -> Correction:
        table, fx = self.store.active, self.store.active_fixed
        if table is None or fx is None:
            return self._result("no_table", None)
        crc = table.crc32
        # bound every input before converting (1e308 or NaN must not reach int())
        if len(b_uT) != 3 or not all(math.isfinite(v) and abs(v) * 1e3 < B_LIMIT_nT for v in b_uT):
            return self._result("bad_input", crc)
        if temp_c is None or not math.isfinite(temp_c) or abs(temp_c) * 100.0 >= T_LIMIT_cdeg:
            if fx.temp_range_cdeg is not None:
                return self._result("no_temperature", crc)
            t_cdeg = fx.t0_cdeg
        else:
            t_cdeg = int(round(temp_c * 100.0))
        cur_mA = []
        for name in table.currents:
            v = (currents_A or {}).get(name)
            if v is None or not math.isfinite(v) or abs(v) * 1e3 >= I_LIMIT_mA:
                return self._result("no_currents", crc)
            cur_mA.append(int(round(v * 1e3)))
        q, flags = fx.apply_sample([int(round(v * 1e3)) for v in b_uT], t_cdeg, cur_mA)
        if flags & ApplyFlag.SATURATED:
            return self._result("saturated", crc)
        if flags & ApplyFlag.OUT_OF_VALIDITY:
            return self._result("out_of_validity", crc)
        return self._result("ok", crc, (q[0] / _OUT_SCALE, q[1] / _OUT_SCALE, q[2] / _OUT_SCALE))
