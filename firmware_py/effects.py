"""The one catalogue of magnetometer error effects.

Each effect has a stable name used everywhere: the simulator's error model
(``magstack.sim.error_model``) implements its forward physics, the calibration model
(``magstack.firmware.calibration``) offers the matching correction term where one exists, and
the sim-to-real gap diagnosis attributes residuals to it. Define an effect here once;
other modules look it up by name and must not keep their own lists.

``order`` is the effect's position in the forward pipeline truth -> sensed value.
``cal_term`` names the calibration-model term that can absorb it (None: cannot be
calibrated, e.g. noise); ``cal_terms_extra`` names terms for its higher orders (the
sensitivity tempco's second order, ``temperature_gain2``).
"""
from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType


@dataclass(frozen=True)
class Effect:
    name: str
    order: int
    summary: str
    physics: str
    units: str
    source: str
    cal_term: str | None
    #: Further calibration terms for the same effect's higher orders (after ``cal_term`` in the term order).
    cal_terms_extra: tuple[str, ...] = ()


_EFFECTS = (
    Effect("thermal_lag", 5, "the die temperature lags the measured (board) temperature",
           "The sensing element follows the board thermistor through a thermal resistance: T_die obeys "
           "dT_die/dt = (T_board - T_die)/tau. Every temperature effect (temperature_gain, "
           "temperature_offset) acts on T_die; with T_board in the data the residual is those effects "
           "evaluated on T_board - T_die, largest while the temperature changes fast.",
           "tau in s", "real thermal runs (AV-MagEval-Data): the residual trails the thermistor by minutes", None),
    Effect("time_skew", 10, "each axis sampled at its own instant",
           "Sequential conversion (one multiplexed ADC) samples X, Y, Z at different times; "
           "for a changing field the axis reading is B_i(t + dt_i). Residual ~ dB/dt * dt_i.",
           "dt_i in s", "belsten 2.1 (sequential axes, 0.4 s vector period); hardware-facts 8.3", "time_skew"),
    Effect("interference", 20, "field proportional to named currents",
           "A current loop of fixed geometry adds D_i * I_i at the sensor (Eq. 4 of belsten, sec. 3.4.2).",
           "D_i in uT/A", "belsten sec. 3.4.2", "currents"),
    Effect("mount_rotation", 25, "the sensor is mounted slightly rotated, differently each session",
           "A bench remount turns the sensor by a small rotation R_s per session s: it senses R_s^T B_true "
           "(R_s = I for the frame session). Acts on the body-frame field (after interference, whose "
           "coefficients are body frame) before the sensor's own misalignment. "
           "A property of the bench, not of the sensor: calibration fits the angles as per-session "
           "nuisance parameters and never writes them into the table.",
           "rad (rotation vector per session)", "real bench (AV-MagEval-Data): X->Z slope changes sign between "
           "sessions; belsten sec. 3.2 (power cycles, remounts)", "mount_rotation"),
    Effect("misalignment", 30, "sensor axes rotated / non-orthogonal w.r.t. the body frame",
           "Small rotation and non-orthogonality angles mixing the true field into each axis.",
           "rad", "lab study (misalignment); belsten Eq. 1 matrix C", "gain_matrix"),
    Effect("gain", 40, "per-axis scale and soft-iron coupling",
           "B <- G B with G = diag(scale) + soft-iron off-diagonals.",
           "unitless", "belsten Tables 2-3; lab study scale factors", "gain_matrix"),
    Effect("cross_axis", 50, "AMR cross-axis effect",
           "Field along the easy (magnetisation) axis changes a bridge's sensitivity: "
           "B_i <- B_i * H0/(H0 + s*B_c) (sign s by set/reset state); set/reset averaging leaves "
           "a second-order (B_c/H0)^2 term.", "H0 in uT", "hardware-facts 5.4; HMC105x cross-axis +-3 %FS",
           "cross_products"),
    Effect("nonlinearity", 60, "on-axis odd-order nonlinearity",
           "B_i <- B_i + c3_i * B_i^3.", "c3 in 1/uT^2", "HMC105x linearity 0.1 %FS; belsten Fig. 3", "cubic"),
    Effect("temperature_gain", 70, "sensitivity changes with temperature",
           "B <- (I + K_S dT + diag(k_s2) dT^2) B, dT = T - T0: a bridge's sensitivity s0/(1 + a dT) is "
           "linear in dT only to first order; its second order a^2 dT^2 is the on-axis k_s2.",
           "1/degC, 1/degC^2", "belsten Eq. 3 (K_S), Table 7; HMC1053 datasheet -2700 ppm/degC",
           "temperature_gain", ("temperature_gain2",)),
    Effect("hysteresis", 80, "remanent offset after a large field",
           "After the sensed field on an axis reaches a threshold the offset shifts by a remanent amount "
           "signed by the excursion's sign, until an opposite excursion (power cycles do not clear it: "
           "belsten attributes it to magnetised material near the sensor).",
           "uT", "belsten sec. 2.3.4 (+50 nT after +-150 uT)", "session_offset"),
    Effect("offset", 90, "constant bias (hard iron, bridge offset after set/reset)",
           "B <- B + O.", "uT", "belsten Table 1; lab study offsets", "offset"),
    Effect("temperature_offset", 100, "offset linear in temperature",
           "B <- B + K_O (T - T0).", "uT/degC", "belsten Eq. 3 (K_O); sec. 2.3.3 -140 nT/degC on X",
           "temperature_offset"),
    Effect("drift", 110, "slow offset change in time",
           "B <- B + r * (t - t0) (random walk optional).", "uT/s", "lab study stability", "drift"),
    Effect("session_offset", 120, "offset jump per power cycle",
           "Each power cycle / session draws a new offset step.", "uT", "belsten sec. 3.2 (several power cycles)",
           "session_offset"),
    Effect("noise", 130, "white and 1/f noise",
           "Additive Gaussian white noise plus a 1/f (pink) component (sum of first-order processes "
           "with log-spaced corners across a band).", "uT rms",
           "belsten Table 1 (13-24 nT rms); lab study noise per chip", None),
    Effect("saturation", 140, "output clipped at the range",
           "Readings beyond the full-scale range clip (or give the overflow code on digital chips).",
           "uT", "datasheets (hardware-facts 1-4)", None),
    Effect("quantization", 150, "finite resolution",
           "Output rounded to the LSB.", "uT per LSB", "datasheets (hardware-facts 1-4)", None),
)

#: name -> Effect, in pipeline order. Read-only.
EFFECTS = MappingProxyType({e.name: e for e in sorted(_EFFECTS, key=lambda e: e.order)})

#: Effect names in forward-pipeline order.
EFFECT_NAMES: tuple[str, ...] = tuple(EFFECTS)


def effect(name: str) -> Effect:
    """Look an effect up by name; unknown names raise ValueError listing the valid ones."""
    try:
        return EFFECTS[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; valid: {', '.join(EFFECT_NAMES)}") from None
