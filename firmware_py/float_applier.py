"""float64 reference applier of a calibration table (vectorised numpy).

    B_cal = (S + K_S dT) B_meas + K_S2 dT^2 B_meas + O + K_O dT + sum_k D_k I_k + c3 * B_meas^3
            + P @ (BxBy, BxBz, ByBz)

with ``dT = temp_c - t0_c``. Inputs uT, degC, A; output uT. Ground-only terms of the
table (time skew, session offsets, drift) are not applied. This is the reference the
fixed-point applier is tested against and what ground tools use.
"""
from __future__ import annotations

from collections.abc import Mapping
from enum import IntFlag

import numpy as np

from magstack.firmware.cal_terms import TEMPERATURE_TERMS


class ApplyFlag(IntFlag):
    """Per-row status bits written to a session's ``flag`` column by ``magstack apply``."""

    OK = 0
    MISSING_INPUT = 1        # a needed input was NaN: output NaN, row kept
    OUT_OF_VALIDITY = 2      # temperature, field or current outside the table's validity range
    SATURATED = 4            # fixed-point input clipped or output saturated


def _needs_temp(table) -> bool:
    return bool(set(TEMPERATURE_TERMS) & set(table.terms))


def apply_float(table, b_meas_uT, temp_c=None, currents_A: Mapping[str, np.ndarray] | None = None):
    """Calibrate (N,3) uT readings. Returns ``(b_uT (N,3), flags (N,) int)``; rows with a
    missing needed input give NaN and ``MISSING_INPUT``; rows outside the validity range
    are calibrated and flagged ``OUT_OF_VALIDITY``."""
    b = np.asarray(b_meas_uT, dtype=float).reshape(-1, 3)
    n = b.shape[0]
    flags = np.zeros(n, dtype=np.int64)
    need_t = _needs_temp(table)
    if need_t:
        if temp_c is None:
            raise ValueError("table has temperature terms: temp_c is required")
        t = np.asarray(temp_c, dtype=float).reshape(n)
    else:
        t = np.full(n, table.t0_c) if temp_c is None else np.asarray(temp_c, dtype=float).reshape(n)
    dT = (t - table.t0_c) if need_t else np.zeros(n)
    missing = ~np.all(np.isfinite(b), axis=1)
    if need_t:
        missing |= ~np.isfinite(t)
    cur = {}
    for name in table.currents:
        if currents_A is None or name not in currents_A:
            raise ValueError(f"table needs current {name!r}")
        cur[name] = np.asarray(currents_A[name], dtype=float).reshape(n)
        missing |= ~np.isfinite(cur[name])
    S, K = np.asarray(table.S), np.asarray(table.K_S)
    out = b @ S.T + dT[:, None] * (b @ K.T) + np.asarray(table.O)[None, :] + dT[:, None] * np.asarray(table.K_O)
    if "temperature_gain2" in table.terms:
        out = out + (dT * dT)[:, None] * np.asarray(table.K_S2)[None, :] * b
    for name, d in table.D:
        out = out + cur[name][:, None] * np.asarray(d)[None, :]
    if "cubic" in table.terms:
        out = out + np.asarray(table.c3)[None, :] * b ** 3
    if "cross_products" in table.terms:
        prods = np.column_stack([b[:, 0] * b[:, 1], b[:, 0] * b[:, 2], b[:, 1] * b[:, 2]])
        out = out + prods @ np.asarray(table.P).T
    out[missing] = np.nan
    flags[missing] |= ApplyFlag.MISSING_INPUT
    flags[~missing & outside_validity(table, out, t if need_t else None, cur)] |= ApplyFlag.OUT_OF_VALIDITY
    return out, flags


def outside_validity(table, b_uT: np.ndarray, temp_c, currents_A: Mapping[str, np.ndarray]) -> np.ndarray:
    """(N,) bool: row outside the table's validity region (NaN compares as outside); ``b_uT`` the calibrated
    field (the region's field limits are on the calibrated field, whatever the part's offsets)."""
    with np.errstate(invalid="ignore"):
        bad = ~np.all(np.abs(b_uT) <= np.asarray(table.field_limits_uT)[None, :], axis=1)
        if table.validity_field_norm_uT is not None:
            bad |= ~(np.einsum("ij,ij->i", b_uT, b_uT) <= table.validity_field_norm_uT ** 2)
        if temp_c is not None and table.validity_temp_c is not None:
            lo, hi = table.validity_temp_c
            bad |= ~((temp_c >= lo) & (temp_c <= hi))
        for name, (lo, hi) in table.validity_currents_A:
            v = currents_A[name]
            bad |= ~((v >= lo) & (v <= hi))
    return bad
