"""A straightforward vectorised fixed-point applier, frozen as a reference (validity judged on the input field).

``apply_block(table, ...)`` with the table passed explicitly: the reference that
tests/test_fixed_point_vectorised.py holds the applier's integers and saturation bits to (bit for bit) and the
baseline of benchmarks/bench_calibration.py. Not used by magstack itself.
"""
from __future__ import annotations

import numpy as np

from magstack.firmware.fixed_point import (
    ACC_FRAC,
    D_FRAC,
    INT32_MAX,
    INT32_MIN,
    K_O_FRAC,
    O_FRAC,
    OUT_FRAC,
    B_LIMIT_nT,
    I_LIMIT_mA,
    T_LIMIT_cdeg,
)
from magstack.firmware.float_applier import ApplyFlag


def apply_block(self, b_nT, temp_cdeg=None, currents_mA=None) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) int nT, (N,) centi-degC, (N,k) mA -> ((N,3) int64 nT*2**8, (N,) flags).
    Bit-identical to :meth:`apply_sample`; int64 throughout (no overflow, see module doc)."""
    b = np.asarray(b_nT)
    if not np.issubdtype(b.dtype, np.integer):
        raise TypeError("b_nT must be an integer array")
    b = b.astype(np.int64).reshape(-1, 3)
    n = b.shape[0]
    if temp_cdeg is None and self.uses_temperature:
        raise ValueError("table has temperature terms: temp_cdeg is required")
    t = np.zeros(n, np.int64) + self.t0_cdeg if temp_cdeg is None else np.asarray(temp_cdeg)
    if not np.issubdtype(t.dtype, np.integer):
        raise TypeError("temp_cdeg must be an integer array")
    t = t.astype(np.int64).reshape(n)
    cur = np.zeros((n, 0), np.int64) if currents_mA is None else np.asarray(currents_mA)
    if cur.size and not np.issubdtype(cur.dtype, np.integer):
        raise TypeError("currents_mA must be an integer array")
    cur = cur.astype(np.int64).reshape(n, -1)
    if cur.shape[1] != len(self.D):
        raise ValueError(f"expected {len(self.D)} currents, got {cur.shape[1]}")
    status = np.zeros(n, np.int64)
    bc = np.clip(b, -B_LIMIT_nT, B_LIMIT_nT)
    tc = np.clip(t, -T_LIMIT_cdeg, T_LIMIT_cdeg)
    cc = np.clip(cur, -I_LIMIT_mA, I_LIMIT_mA)
    sat = np.any(bc != b, axis=1) | (tc != t) | np.any(cc != cur, axis=1)
    status[sat] |= int(ApplyFlag.SATURATED)
    oov = np.any(np.abs(bc) > self.field_limit_nT, axis=1)
    if self.temp_range_cdeg is not None:
        oov |= (tc < self.temp_range_cdeg[0]) | (tc > self.temp_range_cdeg[1])
    for k, (lo, hi) in enumerate(self.current_ranges_mA):
        oov |= (cc[:, k] < lo) | (cc[:, k] > hi)
    status[oov] |= int(ApplyFlag.OUT_OF_VALIDITY)
    dtc = tc - self.t0_cdeg
    S = np.array(self.S, np.int64)
    K = np.array(self.K_S, np.int64)
    out = np.empty((n, 3), np.int64)
    for i in range(3):
        acc = np.zeros(n, np.int64)
        for j in range(3):
            acc += (S[i, j] + _rdiv_v(K[i, j] * dtc, 12800)) * bc[:, j]
        acc += np.int64(self.O[i]) << (ACC_FRAC - O_FRAC)
        acc += _rdiv_v((np.int64(self.K_O[i]) * dtc) << (ACC_FRAC - K_O_FRAC), 100)
        for k in range(cc.shape[1]):
            acc += (np.int64(self.D[k][i]) * cc[:, k]) << (ACC_FRAC - D_FRAC)
        o = _rshift_round_v(acc, ACC_FRAC - OUT_FRAC)
        hit = (o > INT32_MAX) | (o < INT32_MIN)
        status[hit] |= int(ApplyFlag.SATURATED)
        out[:, i] = np.clip(o, INT32_MIN, INT32_MAX)
    return out, status


def _rdiv_v(a: np.ndarray, d: int) -> np.ndarray:
    q = (np.abs(a) + d // 2) // d
    return np.where(a >= 0, q, -q)


def _rshift_round_v(a: np.ndarray, n: int) -> np.ndarray:
    q = (np.abs(a) + (np.int64(1) << (n - 1))) >> n
    return np.where(a >= 0, q, -q)
