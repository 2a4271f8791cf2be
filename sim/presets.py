"""Error-model presets from the seed papers: one :class:`~magstack.sim.error_model.ErrorParams` per chip.

Sources (every value below cites its table):

* ``[LAB T1]`` = Table 1 of the three-chip lab study
  ("Calibration of Off-the-Shelf Anisotropic Magnetoresistance Magnetometers", Sensors 2019, 19(8), 1850,
  doi:10.3390/s19081850): sensitivity (nT/LSB), misalignment,
  noise sigma and density, offsets, sensitivity and offset temperature drift.
* ``[B Tn]`` / ``[B s.x]`` = Belsten et al. (HMC1053; Geosci. Instrum. Method. Data Syst. 12, 2023,
  doi:10.5194/gi-12-201-2023).
* ``[HF n]`` = hardware notes section n: the datasheet it cites (LSB, range, timing); docs/reference/sources.md.

Conventions. Presets describe the sensor's reported value in uT *as the driver converts it with the
datasheet LSB*. The lab study's "sensitivity" is the true field per count, so the gain in reported
units is ``datasheet_LSB / measured_sensitivity``. Noise is added after gain, so noise sigmas are
stated in reported units: ``sigma_true * gain``. The paper's noise sigma includes quantisation (it
was measured on integer counts); the Gaussian part is recovered with Sheppard's correction
``sigma_g^2 = sigma^2 - q^2/12`` (q = measured nT/LSB) so that noise + quantization reproduces the
paper's sigma. Values the papers do not give are left neutral (listed in docs/error-model.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from magstack.sim.error_params import ErrorParams

__all__ = ["PRESET_NAMES", "preset", "preset_info", "PresetInfo", "LAB_STUDY_TABLE1"]


@dataclass(frozen=True)
class PresetInfo:
    """What a preset represents: the chip, its output rate used in the source, the source."""

    chip: str
    rate_hz: float
    source: str


# ---------------------------------------------------------------- lab study Table 1, as printed
#: Lab-study Table 1 numbers used by the digital presets (paper units), per chip.
LAB_STUDY_TABLE1 = MappingProxyType({
    "lsm303dlhc": MappingProxyType({
        "sensitivity_nT_per_lsb": (78.6, 78.6, 93.9),      # [LAB T1] linear sensitivity x/y, z
        "misalignment_median_deg": 0.68,                   # [LAB T1] 0 deg 41'
        "noise_sigma_nT": (133.7, 133.7, 147.1),           # [LAB T1] mean noise std x/y, z
        "noise_density_1hz_nT": (21.2, 21.2, 23.4),        # [LAB T1] at 1 Hz, white
        "offset_min_nT": -2.50e4, "offset_max_nT": 2.09e4,  # [LAB T1] offset range over units
        "sens_drift_25c_pT_per_lsb_K": -15.3,              # [LAB T1] at 25 degC
        "sens_drift_formula_slope": 1.4,                   # [LAB T1] mean formula 1.4*T - 53 (pT/LSB/K)
        "offset_drift_nT_per_K": 15.2,                     # [LAB T1] mean
        "rate_hz": 75.0,                                   # lab study sec. 2 (data rate used)
    }),
    "hmc5983": MappingProxyType({
        "sensitivity_nT_per_lsb": (65.7, 65.7, 73.0),
        "misalignment_median_deg": 1.18,                   # 1 deg 11'
        "noise_sigma_nT": (54.3, 54.3, 59.5),
        "noise_density_1hz_nT": (11.5, 11.5, 11.9),
        "offset_min_nT": -2.55e4, "offset_max_nT": 9.9e3,
        "sens_drift_25c_pT_per_lsb_K": -5.6,
        "sens_drift_formula_slope": 1.0,                   # 1.0*T - 30
        "offset_drift_nT_per_K": 12.5,
        "rate_hz": 75.0,
    }),
    "lis3mdl": MappingProxyType({
        "sensitivity_nT_per_lsb": (14.7, 14.7, 14.9),
        "misalignment_median_deg": 1.00,                   # 1 deg 00'
        "noise_sigma_nT": (331.3, 331.3, 706.3),
        "noise_density_1hz_nT": (86.6, 86.6, 124.2),       # 1/f (sec. 3.3)
        "offset_min_nT": -5.05e4, "offset_max_nT": 5.37e4,
        "sens_drift_25c_pT_per_lsb_K": 2.6,
        "sens_drift_formula_slope": 0.01,                  # 0.01*T + 3
        "offset_drift_nT_per_K": -188.2,
        "rate_hz": 80.0,
    }),
})

#: Datasheet LSB (uT per count) of each axis at the lowest range and that range (uT), [HF 1-3].
_DATASHEET = {
    "lsm303dlhc": ((100.0 / 1100, 100.0 / 1100, 100.0 / 980), 130.0),  # [HF 2.2] GN=001 +-1.3 G, 1100/980 LSB/G
    "hmc5983": ((100.0 / 1370,) * 3, 88.0),                           # [HF 3.2] GN=0 +-0.88 G, 1370 LSB/G
    "lis3mdl": ((100.0 / 6842,) * 3, 400.0),                          # [HF 1.2] FS=00 +-4 G, 6842 LSB/G
}

#: Noise record of the lab study: 5 min in the shield [LAB sec. 2.5] sampled at the chip's rate.
_LAB_NOISE_RECORD_S = 300.0


def _lis3mdl_pink_split(sigma_nT: float, density_1hz_nT: float, rate_hz: float) -> tuple[float, float]:
    """Split a 1/f + white noise record into (white sigma, pink sigma) in nT.

    PSD(f) = w + p/f (one-sided, nT^2/Hz). The 1 Hz density gives w + p = d^2; the record's
    variance over [1/T_record, f_nyquist] gives w*f_ny + p*ln(f_ny*T_record) = sigma^2.
    """
    f_ny = rate_hz / 2.0
    ln_band = math.log(f_ny * _LAB_NOISE_RECORD_S)
    d2, s2 = density_1hz_nT ** 2, sigma_nT ** 2
    p = (f_ny * d2 - s2) / (f_ny - ln_band)
    w = d2 - p
    if p < 0 or w < 0:
        raise ValueError("noise numbers inconsistent with a white + 1/f spectrum")
    return math.sqrt(w * f_ny), math.sqrt(p * ln_band)


def _digital(chip: str) -> ErrorParams:
    t = LAB_STUDY_TABLE1[chip]
    lsb_uT, range_uT = _DATASHEET[chip]
    sens_nT = np.array(t["sensitivity_nT_per_lsb"])
    gain = np.array(lsb_uT) * 1000.0 / sens_nT                  # reported uT per true uT
    q_true_nT = sens_nT                                         # one count in true nT
    sigma_nT = np.array(t["noise_sigma_nT"])
    sigma_g_nT = np.sqrt(sigma_nT ** 2 - q_true_nT ** 2 / 12.0)  # Sheppard's correction
    if chip == "lis3mdl":
        split = [_lis3mdl_pink_split(s, d, t["rate_hz"])
                 for s, d in zip(sigma_g_nT, t["noise_density_1hz_nT"], strict=True)]
        white_nT = np.array([w for w, _ in split])
        pink_nT = np.array([p for _, p in split])
    else:
        white_nT, pink_nT = sigma_g_nT, np.zeros(3)
    # sensitivity S(T) = S0 + a1*dT + a2*dT^2 (nT/LSB) -> reported gain factor S0/S(T)
    a1 = t["sens_drift_25c_pT_per_lsb_K"] / 1000.0              # nT/LSB/K
    a2 = t["sens_drift_formula_slope"] / 2.0 / 1000.0           # nT/LSB/K^2 (derivative of the mean formula)
    k1 = -a1 / sens_nT
    k2 = -a2 / sens_nT + (a1 / sens_nT) ** 2
    mis = math.radians(t["misalignment_median_deg"])
    return ErrorParams(
        # [LAB T1] median misalignment angle on each of the three angles; signs alternate (not given)
        misalignment_rad=(mis, -mis, mis),
        gain_matrix=np.diag(gain),                               # [LAB T1] sensitivity vs [HF] datasheet LSB
        k_s_per_c=np.diag(k1), k_s2_per_c2=k2, temp_ref_c=25.0,  # [LAB T1] sensitivity temperature drift
        # [LAB T1] offsets vary per unit: x at the reported minimum, y at the maximum, z at the midpoint
        offset_uT=np.array([t["offset_min_nT"], t["offset_max_nT"],
                            0.5 * (t["offset_min_nT"] + t["offset_max_nT"])]) / 1000.0,
        k_o_uT_per_c=(t["offset_drift_nT_per_K"] / 1000.0,) * 3,  # [LAB T1] mean offset drift
        noise_white_uT=white_nT * gain / 1000.0,                 # [LAB T1] noise sigma (reported units)
        noise_pink_uT=pink_nT * gain / 1000.0,                   # [LAB T1] LIS3MDL 1/f part
        noise_pink_band_hz=(1.0 / _LAB_NOISE_RECORD_S, t["rate_hz"] / 2.0),
        range_uT=range_uT,                                       # [HF] lowest range
        lsb_uT=lsb_uT,                                           # [HF] datasheet LSB
    )


# HMC1053 on the AERO-VISTA board, Belsten et al.
_B_TABLE3 = np.array([[1.0949, 0.0939, -0.0342],    # [B T3] rows: incident X, Y, Z; columns: affected X, Y, Z
                      [0.0477, 1.1200, -0.0703],
                      [0.0165, 0.0317, 1.1150]])
_B_TABLE1_OFFSET_uT = (0.328, 0.034, -0.467)         # [B T1] average delta, near-zero field
_B_TABLE1_RMS_uT = (0.013, 0.024, 0.018)             # [B T1] RMS delta - offset
_HMC1053_TEMPCO_PER_C = -2700e-6                     # [HF 5.1] sensitivity tempco (datasheet, Vbridge drive)
_HMC1053_H0_uT = 100.0 / 0.03                        # [HF 5.4] +-3 %FS for 1 G cross field at 1 G applied
_HMC1053_HYST_DIFF_uT = 0.050                        # [B s.2.3.4] DUT-only difference after +-150 uT
_HMC1053_HYST_FIELD_uT = 150.0                       # [B s.2.3.4] excursion amplitude


def _hmc1053() -> ErrorParams:
    return ErrorParams(
        # [B s.2.1] one 20 SPS ADC converts X, Y, Z, T sequentially; [HF 4.2/8.3] 50.822 ms per channel
        # after each MUX0 write at DR=0010 (the register-level front end measures the same spacing)
        axis_delay_s=(0.0, 0.050822, 0.101644),
        gain_matrix=_B_TABLE3.T,                     # [B T3] (coil-common misalignment is inside it)
        # [HF 5.4] AMR model H0 from the datasheet cross-axis figure; set/reset used [B s.2.1];
        # easy axes: X bridge <- Y, Y bridge <- X (2-axis die), Z bridge <- X (assumed, 1-axis die)
        cross_axis_h0_uT=_HMC1053_H0_uT, cross_axis_easy_axis=(1, 0, 0), cross_axis_mode="set_reset",
        k_s_per_c=np.eye(3) * _HMC1053_TEMPCO_PER_C, temp_ref_c=25.0,
        # [B s.2.3.4] +-excursions differ by 50 nT: remanence +-25 nT signed by the excursion
        hysteresis_uT=(_HMC1053_HYST_DIFF_uT / 2.0,) * 3, hysteresis_threshold_uT=_HMC1053_HYST_FIELD_uT,
        offset_uT=_B_TABLE1_OFFSET_uT,               # [B T1]
        noise_white_uT=_B_TABLE1_RMS_uT,             # [B T1]
        range_uT=600.0,                              # [HF 5.1] field range +-6 G
        lsb_uT=0.001,                                # [HF 7.3] logged to 1 nT (bench data files)
    )


_BUILDERS = {
    "hmc1053": _hmc1053,
    "lis3mdl": lambda: _digital("lis3mdl"),
    "hmc5983": lambda: _digital("hmc5983"),
    "lsm303dlhc": lambda: _digital("lsm303dlhc"),
}

_INFO = {
    "hmc1053": PresetInfo("hmc1053", 2.5, "Belsten et al. Tables 1, 3; sec. 2.1, 2.3.4; hardware-facts 5"),
    "lis3mdl": PresetInfo("lis3mdl", 80.0, "lab study Table 1; hardware-facts 1"),
    "hmc5983": PresetInfo("hmc5983", 75.0, "lab study Table 1; hardware-facts 3"),
    "lsm303dlhc": PresetInfo("lsm303dlhc", 75.0, "lab study Table 1; hardware-facts 2"),
}

#: Valid preset names.
PRESET_NAMES: tuple[str, ...] = ("hmc1053", "lis3mdl", "hmc5983", "lsm303dlhc")


def preset(name: str) -> ErrorParams:
    """The ErrorParams of chip ``name``; unknown names raise ValueError naming the valid ones."""
    try:
        build = _BUILDERS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown preset {name!r}; valid: {', '.join(PRESET_NAMES)}") from None
    return build()


def preset_info(name: str) -> PresetInfo:
    """Chip, sample rate (Hz) the preset's noise refers to, and its sources."""
    preset(name)  # validates the name
    return _INFO[name]
