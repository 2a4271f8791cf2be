"""ArduPilot compass calibration parameters (``COMPASS_OFS_*``, ``COMPASS_DIA_*``, ``COMPASS_ODI_*``).

Convention, from ArduPilot ``libraries/AP_Compass/AP_Compass_Backend.cpp`` (``correct_field``) and the
parameter descriptions in ``AP_Compass.cpp`` (OFS in milligauss, "added to the compass values"; DIA/ODI
placed in the matrix ``[[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]``)::

    B_cal = M (SCALE (b + OFS)),   b, OFS in milligauss (1 mG = 0.1 uT)

applied after the board orientation (``rotate_field``); motor compensation (``COMPASS_MOT_*``) is added
after and written as nothing here. A table ``B = S b + O`` (uT) maps to ``M = S`` (symmetric),
``SCALE = 1`` and ``OFS = S^-1 O * 10``. Temperature terms have no ArduPilot compass parameter: dropped,
their cost reported. For the second and third compass the names are ``COMPASS_OFS2_X``, ``COMPASS_DIA2_X``...
"""
from __future__ import annotations

import numpy as np

from magstack.ground.export import Export, Exporter, held_linear, register_exporter

MGAUSS_PER_UT = 10.0
FORMULA = ("B_cal[mG] = M (SCALE (b[mG] + OFS)), M symmetric [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], "
           "[ODI_Y, ODI_Z, DIA_Z]] (AP_Compass_Backend::correct_field; orientation and motor terms not written)")


def _names(instance: int) -> tuple[str, str, str]:
    n = "" if int(instance) == 0 else str(int(instance) + 1)
    return f"COMPASS_OFS{n}_", f"COMPASS_DIA{n}_", f"COMPASS_ODI{n}_"


def params_from_table(table, b_uT=None, temp_c=None, instance: int = 0):
    """(ArduPilot parameters, dropped terms, table output on the session)."""
    M, c, _, dropped, ref = held_linear(table, b_uT, temp_c, symmetric=True, sensor_bounds="ArduPilot's COMPASS")
    ofs_uT = np.linalg.solve(M, c)
    o, d, od = _names(instance)
    params = {}
    for k, a in enumerate("XYZ"):
        params[f"{o}{a}"] = float(ofs_uT[k] * MGAUSS_PER_UT)
    for k, a in enumerate("XYZ"):
        params[f"{d}{a}"] = float(M[k, k])
    params[f"{od}X"], params[f"{od}Y"], params[f"{od}Z"] = float(M[0, 1]), float(M[0, 2]), float(M[1, 2])
    params["COMPASS_SCALE" + ("" if int(instance) == 0 else str(int(instance) + 1))] = 1.0
    return params, dropped, ref


def apply_params(params: dict, b_uT: np.ndarray, instance: int = 0) -> np.ndarray:
    """(N, 3) uT: ArduPilot's ``correct_field`` (no orientation, no motor compensation) on readings in uT."""
    o, d, od = _names(instance)
    ofs = np.array([params[f"{o}{a}"] for a in "XYZ"])
    dx, dy, dz = (params[f"{d}{a}"] for a in "XYZ")
    ox, oy, oz = (params[f"{od}{a}"] for a in "XYZ")
    scale = params.get("COMPASS_SCALE" + ("" if int(instance) == 0 else str(int(instance) + 1)), 0.0)
    M = np.array([[dx, ox, oy], [ox, dy, oz], [oy, oz, dz]])
    mag = np.asarray(b_uT, dtype=float) * MGAUSS_PER_UT + ofs
    if scale != 0.0:
        mag = mag * scale
    return (mag @ M.T) / MGAUSS_PER_UT


def export(table, b_uT=None, temp_c=None, *, instance: int = 0) -> Export:
    """A parameter file (``NAME,VALUE`` per line, as Mission Planner and MAVProxy load)."""
    params, dropped, ref = params_from_table(table, b_uT, temp_c, instance)
    rows = [f"# ArduPilot compass calibration from magstack table {table.device_id} (crc32 "
            f"{table.to_document()['crc32']}); {FORMULA}"]
    rows += [f"{k},{v:.9g}" for k, v in params.items()]
    notes = ["the table's frame is the sensor's: COMPASS_ORIENT / AHRS_ORIENTATION stay for the mounting",
             "set COMPASS_DEV_ID to this compass before loading (the values belong to one device)"]
    return Export("ardupilot", "\n".join(rows) + "\n", params, FORMULA, dropped, notes,
                  None if ref is None else (ref, apply_params(params, b_uT, instance)))


register_exporter(Exporter("ardupilot",
                           lambda table, b_uT=None, temp_c=None, **kw: export(table, b_uT, temp_c, **kw),
                           ".parm", "ArduPilot parameters COMPASS_OFS_*, COMPASS_DIA_*, COMPASS_ODI_*"))
