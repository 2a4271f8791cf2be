"""Calibration priors of each part, as data: what the datasheets and the lab study say before any fit.

The calibration estimator (:mod:`magstack.firmware.calibration.estimator`) is maximum a posteriori with
Gaussian priors: the data decide every direction they can determine, the prior decides the rest. These
tables are the prior, one frozen :class:`CalPriors` per chip, every value with its source and confidence.

Sign conventions are those of the calibration model (belsten Eq. 3, *calibration* direction)::

    B_act = (S + K_S dT + diag(K_S2) dT^2) B_meas + O + K_O dT + sum_k D_k I_k

so a sensitivity that *falls* with temperature (datasheet tempco ``alpha`` < 0) gives ``K_S = -alpha S``
(``k_s_rel_per_c`` = -alpha, applied to the fitted S). A sensitivity ``s0 (1 + alpha dT)`` is calibrated by
``1 / (1 + alpha dT) = 1 - alpha dT + alpha^2 dT^2 - ...``: the second order ``K_S2 = alpha^2 S`` (positive
whatever alpha's sign); a sensitivity of the form ``s0 / (1 + alpha dT)`` is calibrated exactly by the linear
term (``K_S2 = 0``). The K_S2 prior is centred on ``alpha^2`` with an sd that reaches 0. An offset that
drifts by ``+o`` per degC in the reading gives ``K_O = -o``. A value the sources leave unverified (``[U]``)
or that is inferred (``[I]``) gets a wider sd than the source's own spread.

Source keys: [F:...] fact from a source, [F2:...] secondary, [I] inference, [U] unverified
(the datasheet behind each section of the hardware notes, docs/reference/sources.md); [LAB T1] = Table 1 of the
three-chip lab study (Sensors 2019, 19(8), 1850, doi:10.3390/s19081850); [B ...] = Belsten et al., Geosci.
Instrum. Method. Data Syst. 12, 2023, doi:10.5194/gi-12-201-2023.
"""
from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType


@dataclass(frozen=True)
class PriorValue:
    """A Gaussian prior: ``mean`` and ``sd`` in the parameter's unit, ``source`` with its confidence tag."""

    mean: float
    sd: float
    source: str

    def __post_init__(self) -> None:
        if not (self.sd >= 0.0) or self.mean != self.mean:
            raise ValueError(f"prior needs sd >= 0 and a finite mean, got {self.mean!r} +- {self.sd!r}")


@dataclass(frozen=True)
class CalPriors:
    """Prior of every calibration-model parameter group for one part.

    ``gain_diag`` S[i,i] (1), ``gain_offdiag`` S[i,j] (1), ``offset_uT`` O (uT), ``k_s_rel_per_c``
    the diagonal of K_S relative to the fitted S (1/degC: K_S[i,i] ~ k_s_rel S[i,i]), ``k_s_offdiag_per_c``
    K_S[i,j] (1/degC), ``k_o_uT_per_c`` K_O (uT/degC), ``current_uT_per_A`` D (uT/A), ``cubic_per_uT2`` c3,
    ``cross_products_per_uT`` P, ``k_s2_rel_per_c2`` the on-axis second-order sensitivity tempco relative to
    the fitted S (1/degC^2: K_S2[i] ~ k_s2_rel S[i,i]), ``k_s3_rel_per_c3`` its third order (1/degC^3; no table
    term: it bounds, with ``k_o2_uT_per_c2`` (the offset's second order, derived from the two tempcos) and the
    priors of the other terms a model leaves out, how far a table may extrapolate in temperature), and the
    nuisance terms (``time_skew_s``, ``session_offset_uT``,
    ``drift_uT_per_s``). ``operating_temp_c`` and ``field_range_uT`` bound a table's validity box.
    """

    chip: str
    gain_diag: PriorValue
    gain_offdiag: PriorValue
    offset_uT: PriorValue
    k_s_rel_per_c: PriorValue
    k_s_offdiag_per_c: PriorValue
    k_o_uT_per_c: PriorValue
    current_uT_per_A: PriorValue
    cubic_per_uT2: PriorValue
    cross_products_per_uT: PriorValue
    time_skew_s: PriorValue
    session_offset_uT: PriorValue
    drift_uT_per_s: PriorValue
    operating_temp_c: tuple[float, float]
    field_range_uT: float
    source: str
    k_s2_rel_per_c2: PriorValue = PriorValue(0.0, 1e-6, "[I] temperature-compensated part: the linear tempco is "
                                                        "small, its square smaller (1e-6 /degC^2 = 100 ppm at 10 degC)")
    k_s3_rel_per_c3: PriorValue = PriorValue(0.0, 1e-8, "[I] temperature-compensated part: third order of the "
                                                        "sensitivity tempco (1e-8 /degC^3 = 10 ppm at 10 degC)")

    @property
    def k_o2_uT_per_c2(self) -> PriorValue:
        """The offset's second order in temperature (uT/degC^2; no table term: like ``k_s3_rel_per_c3`` it bounds
        how far a table may extrapolate in temperature). An offset tempco ``k_o`` read through the sensitivity's
        ``1/(1 + alpha dT)`` curves by ``alpha k_o dT^2``: sd = (|alpha| + its sd) x the K_O prior's sd."""
        ks, ko = self.k_s_rel_per_c, self.k_o_uT_per_c
        return PriorValue(0.0, (abs(ks.mean) + ks.sd) * ko.sd,
                          "[I] second order of the offset: an offset tempco through the sensitivity tempco's "
                          f"1/(1 + alpha dT) curves by alpha k_o dT^2; sd ({abs(ks.mean):.3g} + {ks.sd:.3g}) /degC "
                          f"x {ko.sd:.3g} uT/degC")


# Nuisance terms of bench sessions: loose on every part (the data decide them whenever they can).
_SKEW = PriorValue(0.0, 1.0, "[I] loose: sequential sampling skews are tens of ms")
_SESSION = PriorValue(0.0, 10.0, "[I] loose: offset change between power cycles")
_DRIFT = PriorValue(0.0, 1e-3, "[I] loose: 3.6 uT per hour")
_CURRENT = PriorValue(0.0, 100.0, "[I] loose: harness/torquer coupling is the spacecraft's, not the part's")

_HMC1053 = CalPriors(
    chip="hmc1053",
    gain_diag=PriorValue(1.0, 0.1, "[F:HMC1055] sensitivity 0.8/1.0/1.2 mV/V/G (hardware-facts 5.1): +-20 % = 2 sd"),
    gain_offdiag=PriorValue(0.0, 0.05, "[F2:SEC-1053] cross-axis +-3 %FS (hardware-facts 5.1) plus package and "
                                      "mount misalignment [I]"),
    offset_uT=PriorValue(0.0, 10.0, "[F:HMC10 p.11] set/reset removes the bridge offset; residual electronics "
                                    "and board offset [I] (belsten Table 1: 0.03-0.47 uT)"),
    k_s_rel_per_c=PriorValue(2.7e-3, 0.6e-3, "[F2:SEC-1053] sensitivity tempco -2700 ppm/degC typ, range "
                                             "-3000..-2400 [U] (hardware-facts 5.1): sd widened for [U]"),
    k_s_offdiag_per_c=PriorValue(0.0, 0.3e-3, "[I] tempco x cross-axis coupling (0.1 x 2.7e-3)"),
    k_o_uT_per_c=PriorValue(0.0, 0.02, "[I] the bridge's own offset tempco is +-10 ppm/degC with set/reset "
                                       "[F2:SEC-1053] (6 nT/degC read as ppm of the 600 uT full scale); the board's "
                                       "set/reset asymmetry and electronics add to it: the AERO-VISTA board's fitted "
                                       "K_O was +36 nT/degC on x [B Table 7] (from a one-field thermal run, where K_O "
                                       "and K_S are one column [B sec. 3.3]). sd 20 nT/degC"),
    current_uT_per_A=_CURRENT,
    cubic_per_uT2=PriorValue(0.0, 1e-7, "[F2:SEC-1053] linearity 0.1 %FS over +-1 G: 0.1 uT at 100 uT"),
    cross_products_per_uT=PriorValue(0.0, 1e-5, "[I] the first-order cross-axis term (+-3 %FS for a 1 G cross "
                                                "field [F2:SEC-1053]: 3e-4 /uT) cancels in the set/reset "
                                                "difference (hardware-facts 5.4); a 3 % pulse asymmetry leaves 1e-5"),
    time_skew_s=_SKEW, session_offset_uT=_SESSION, drift_uT_per_s=_DRIFT,
    operating_temp_c=(-40.0, 125.0),       # [F:HMC1055]
    field_range_uT=600.0,                  # [F:HMC1055] +-6 G
    source="HMC1053 datasheet figures (hardware notes section 5, docs/reference/sources.md)",
    k_s2_rel_per_c2=PriorValue(7.3e-6, 7.3e-6, "[I] second order of the -2700 ppm/degC sensitivity tempco "
                                               "[F2:SEC-1053]: alpha^2 = 7.3e-6 for s0 (1 + alpha dT); sd reaches the "
                                               "s0 / (1 + alpha dT) form (0) at 1 sd and 2 alpha^2 (3000 ppm) at 1 sd"),
    k_s3_rel_per_c3=PriorValue(0.0, 2.7e-8, "[I] third order of the sensitivity tempco: |alpha|^3 with alpha up to "
                                            "-3000 ppm/degC [F2:SEC-1053] (1/(1 + alpha dT) = ... - alpha^3 dT^3)"),
)


def _digital(chip: str, k_s_rel: PriorValue, k_o: PriorValue, offset_sd_uT: float, misalign_sd: float,
             temp_c: tuple[float, float], range_uT: float, source: str) -> CalPriors:
    return CalPriors(
        chip=chip,
        gain_diag=PriorValue(1.0, 0.1, "[LAB T1] measured sensitivities scatter up to ~20 % from the datasheet "
                                       "LSB (z axis of HMC5983/LSM303DLHC): sd 0.1"),
        gain_offdiag=PriorValue(0.0, misalign_sd, "[LAB T1] misalignment median 0.7-1.2 deg, max 7.6 deg"),
        offset_uT=PriorValue(0.0, offset_sd_uT, "[LAB T1] offset range over the units measured"),
        k_s_rel_per_c=k_s_rel,
        k_s_offdiag_per_c=PriorValue(0.0, 1e-4, "[I] temperature-compensated part: small cross terms"),
        k_o_uT_per_c=k_o,
        current_uT_per_A=_CURRENT,
        cubic_per_uT2=PriorValue(0.0, 1e-6, "[I] loose"),
        cross_products_per_uT=PriorValue(0.0, 1e-3, "[I] loose"),
        time_skew_s=_SKEW, session_offset_uT=_SESSION, drift_uT_per_s=_DRIFT,
        operating_temp_c=temp_c, field_range_uT=range_uT, source=source)


# K_S (calibration direction) = a1 / S0 for a sensitivity S(T) = S0 + a1 dT in nT/LSB [LAB T1];
# K_O = -(offset drift); the lab study's +- is the spread over units, the sign of K_O varies per unit.
_LSM303DLHC = _digital(
    "lsm303dlhc",
    PriorValue(-15.3e-3 / 78.6, 25.0e-3 / 78.6, "[LAB T1] sensitivity drift -15.3 +- 25.0 pT/LSB/K at 25 degC "
                                                "over 78.6 nT/LSB"),
    PriorValue(0.0, 0.021, "[LAB T1] offset drift 15.2 +- 14.3 nT/K, max |.| 29.5: sd = rms of mean and spread"),
    25.0, 0.05, (-40.0, 85.0), 810.0, "lab study Table 1; hardware-facts section 2")
_HMC5983 = _digital(
    "hmc5983",
    PriorValue(-5.6e-3 / 65.7, 2.0e-3 / 65.7, "[LAB T1] sensitivity drift -5.6 +- 1.0 pT/LSB/K over 65.7 nT/LSB "
                                              "(sd doubled: three units)"),
    PriorValue(0.0, 0.046, "[LAB T1] offset drift 12.5 +- 44.4 nT/K, max |.| 56.8"),
    25.0, 0.05, (-30.0, 85.0), 810.0, "lab study Table 1; hardware-facts section 3")
_LIS3MDL = _digital(
    "lis3mdl",
    PriorValue(2.6e-3 / 14.7, 2.4e-3 / 14.7, "[LAB T1] sensitivity drift 2.6 +- 2.4 pT/LSB/K over 14.7 nT/LSB"),
    PriorValue(0.0, 0.45, "[LAB T1] offset drift -188.2 +- 410.4 nT/K, max |.| 598.6"),
    55.0, 0.05, (-40.0, 85.0), 1600.0, "lab study Table 1; hardware-facts section 1")

#: Wide priors for a part without a table (the report says so).
GENERIC = CalPriors(
    chip="generic",
    gain_diag=PriorValue(1.0, 0.3, "[I] generic: no chip table"),
    gain_offdiag=PriorValue(0.0, 0.1, "[I] generic: no chip table"),
    offset_uT=PriorValue(0.0, 100.0, "[I] generic: no chip table"),
    k_s_rel_per_c=PriorValue(0.0, 3e-3, "[I] generic: AMR bridges reach -3000 ppm/degC"),
    k_s_offdiag_per_c=PriorValue(0.0, 1e-3, "[I] generic: no chip table"),
    k_o_uT_per_c=PriorValue(0.0, 0.5, "[I] generic: no chip table"),
    current_uT_per_A=_CURRENT,
    cubic_per_uT2=PriorValue(0.0, 1e-6, "[I] generic"),
    cross_products_per_uT=PriorValue(0.0, 1e-3, "[I] generic"),
    time_skew_s=_SKEW, session_offset_uT=_SESSION, drift_uT_per_s=_DRIFT,
    operating_temp_c=(-40.0, 85.0), field_range_uT=1000.0,
    source="generic wide priors (no chip table)",
    k_s2_rel_per_c2=PriorValue(0.0, 1e-5, "[I] generic: the square of a 3000 ppm/degC tempco is 9e-6 /degC^2"),
    k_s3_rel_per_c3=PriorValue(0.0, 3e-8, "[I] generic: the cube of a 3000 ppm/degC tempco is 2.7e-8 /degC^3"))

#: Chip name -> priors.
PRIORS = MappingProxyType({p.chip: p for p in (_HMC1053, _LSM303DLHC, _HMC5983, _LIS3MDL)})


def priors_for(chip: str | None) -> CalPriors:
    """The chip's priors; :data:`GENERIC` for an unknown or missing name (e.g. ``hmc1053:sn1`` -> hmc1053)."""
    if not chip:
        return GENERIC
    name = str(chip).lower().split(":")[0].strip()
    if name.startswith("hmc5883l_or_"):
        name = name[len("hmc5883l_or_"):]
    return PRIORS.get(name, GENERIC)
