"""PX4 magnetometer calibration parameters (``CAL_MAGn_*``).

Convention, from PX4-Autopilot ``src/lib/sensor_calibration/Magnetometer.hpp`` (``Correct``) and
``Magnetometer.cpp`` (``ParametersUpdate``, ``set_offdiagonal``), names from ``Utilities.cpp``
(``CAL_%s%u_%c%s``: ``CAL_MAG0_XOFF`` ...), units from ``msg/SensorMag.msg`` (gauss)::

    B_cal = R (M ((b + power * COMP) - OFF)),   b, OFF in gauss (1 G = 100 uT)

    M = [[XSCALE, XODIAG, YODIAG],
         [XODIAG, YSCALE, ZODIAG],
         [YODIAG, ZODIAG, ZSCALE]]

``R`` is the board/sensor rotation (``CAL_MAGn_ROT``, ``SENS_BOARD_ROT``): left as it is (the table's frame is
the sensor's). The power compensation ``COMP`` is written as 0. A table ``B = S b + O`` (uT) maps to
``M = S`` (symmetric) and ``OFF = -S^-1 O / 100``. PX4's thermal compensation (``TC_M*``) is not written:
it holds an offset polynomial only (no scale tempco), so the temperature terms are dropped and their cost
reported.
"""
from __future__ import annotations

import numpy as np

from magstack.ground.export import Export, Exporter, held_linear, register_exporter

UT_PER_GAUSS = 100.0
FORMULA = ("B_cal[G] = M (b[G] - OFF), M symmetric [[XSCALE, XODIAG, YODIAG], [XODIAG, YSCALE, ZODIAG], "
           "[YODIAG, ZODIAG, ZSCALE]] (PX4 Magnetometer::Correct, CAL_MAGn_ROT and COMP not written)")


def params_from_table(table, b_uT=None, temp_c=None, instance: int = 0):
    """(PX4 parameters, dropped terms, table output on the session)."""
    M, c, _, dropped, ref = held_linear(table, b_uT, temp_c, symmetric=True, sensor_bounds="PX4's CAL_MAG")
    off_uT = -np.linalg.solve(M, c)
    p = f"CAL_MAG{int(instance)}_"
    params = {}
    for k, a in enumerate("XYZ"):
        params[f"{p}{a}OFF"] = float(off_uT[k] / UT_PER_GAUSS)
        params[f"{p}{a}SCALE"] = float(M[k, k])
    params[f"{p}XODIAG"] = float(M[0, 1])
    params[f"{p}YODIAG"] = float(M[0, 2])
    params[f"{p}ZODIAG"] = float(M[1, 2])
    return params, dropped, ref


def apply_params(params: dict, b_uT: np.ndarray, instance: int = 0) -> np.ndarray:
    """(N, 3) uT: PX4's ``Correct`` (rotation identity, no power compensation) on readings in uT."""
    p = f"CAL_MAG{int(instance)}_"
    off = np.array([params[f"{p}{a}OFF"] for a in "XYZ"])
    dx, dy, dz = (params[f"{p}{a}SCALE"] for a in "XYZ")
    ox, oy, oz = (params[f"{p}{a}ODIAG"] for a in "XYZ")
    M = np.array([[dx, ox, oy], [ox, dy, oz], [oy, oz, dz]])
    b_G = np.asarray(b_uT, dtype=float) / UT_PER_GAUSS
    return ((b_G - off) @ M.T) * UT_PER_GAUSS


def export(table, b_uT=None, temp_c=None, *, instance: int = 0, device_id: int = 0) -> Export:
    """A QGroundControl parameter file (tab-separated: vehicle, component, name, value, type; 9 = float)."""
    params, dropped, ref = params_from_table(table, b_uT, temp_c, instance)
    p = f"CAL_MAG{int(instance)}_"
    rows = [f"# PX4 magnetometer calibration from magstack table {table.device_id} (crc32 "
            f"{table.to_document()['crc32']}); {FORMULA}",
            "# Vehicle-Id\tComponent-Id\tName\tValue\tType"]
    if device_id:
        rows.append(f"1\t1\t{p}ID\t{int(device_id)}\t6")
    rows += [f"1\t1\t{k}\t{v:.9g}\t9" for k, v in params.items()]
    notes = ["the table's frame is the sensor's: leave CAL_MAGn_ROT / SENS_BOARD_ROT for the mounting"]
    if not device_id:
        notes.append(f"{p}ID not written: it must equal the device id PX4 reports for this magnetometer")
    return Export("px4", "\n".join(rows) + "\n", params, FORMULA, dropped, notes,
                  None if ref is None else (ref, apply_params(params, b_uT, instance)))


register_exporter(Exporter("px4", lambda table, b_uT=None, temp_c=None, **kw: export(table, b_uT, temp_c, **kw),
                           ".params", "PX4 parameters CAL_MAGn_{X,Y,Z}{OFF,SCALE,ODIAG}"))
