"""How far a calibration fit is from the exact inverse of a simulator preset (a fit-vs-simulator check).

The error model (:mod:`magstack.sim.error_model`) applies ``b = (I + dT K) G b_true + o`` (gain
matrix G, temperature gain K, offset o; ``dT = T - temp_ref_c``), so to first order in dT the
calibration that undoes it is ``S = G^-1``, ``K_S = -G^-1 K``, ``O = -G^-1 o`` at
``t0_c = temp_ref_c``. Used by the demo's fit step and by any validation that fits simulated data.
"""
from __future__ import annotations

import numpy as np

from magstack.firmware.errors import FitError
from magstack.sim.presets import preset

__all__ = ["preset_inverse", "recovery_vs_preset"]


def preset_inverse(preset_name: str) -> dict[str, np.ndarray | float]:
    """The first-order inverse calibration of a preset: S (3,3), K_S (3,3) 1/degC, O (3,) uT, t0_c."""
    p = preset(preset_name)
    g_inv = np.linalg.inv(np.asarray(p.gain_matrix, float))
    return {"S": g_inv, "K_S": -g_inv @ np.asarray(p.k_s_per_c, float), "O": -g_inv @ np.asarray(p.offset_uT, float),
            "t0_c": float(p.temp_ref_c)}


def recovery_vs_preset(result, preset_name: str = "hmc1053") -> dict[str, float]:
    """Max absolute differences of a fit's S, K_S (1/degC) and O (uT) from :func:`preset_inverse`.

    ``result`` is a :class:`magstack.firmware.calibration.FitResult` (``params``, ``model.t0_c``);
    FitError when its reference temperature is not the preset's (the comparison would be meaningless).
    """
    inv = preset_inverse(preset_name)
    if abs(result.model.t0_c - inv["t0_c"]) > 1e-9:
        raise FitError(f"fit t0 {result.model.t0_c} degC differs from the preset's {inv['t0_c']} degC")
    fitted = result.params
    return {"S_max_abs": float(np.max(np.abs(fitted["S"] - inv["S"]))),
            "K_S_max_abs_per_c": float(np.max(np.abs(fitted["K_S"] - inv["K_S"]))),
            "O_max_abs_uT": float(np.max(np.abs(fitted["O"] - inv["O"])))}
