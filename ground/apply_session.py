"""Apply a calibration table to a whole session (``magstack apply``, the demo, ``diagnose --table``).

Every row is kept: rows that cannot be calibrated hold NaN and carry the applier's flag bits,
shifted to the dictionary's APPLY_* bits (``FLAG_SHIFT``) so flags already in the file survive. Rows
outside the table's validity box are flagged and, like the flight corrector, get no calibrated value
(NaN) unless ``extrapolate`` is asked for. A table with a posterior block adds per row the predictive sd of the
calibrated sample against the true field (:mod:`magstack.firmware.cal_uncertainty`): ``cal_sigma_x_nT``,
``cal_sigma_y_nT``, ``cal_sigma_z_nT`` per axis (parameters + discrepancy + noise), ``cal_sigma_nT`` their
root-sum-square (the sd of the vector error, the figure to read), and ``cal_param_sd_nT`` the parameter part alone
(what averaging many samples would leave; vector).
"""
from __future__ import annotations

import numpy as np

from magstack.data.dictionary import APPLY, APPLY_FLAG_SHIFT, flag_legend
from magstack.data.errors import SessionFileError
from magstack.data.session import Session
from magstack.firmware.cal_terms import TEMPERATURE_TERMS
from magstack.firmware.calibration.housekeeping import merge_currents
from magstack.firmware.fixed_point import FixedPointTable, output_to_uT, to_fixed_inputs
from magstack.firmware.float_applier import ApplyFlag, apply_float

#: apply's status bits (``ApplyFlag`` << this) are the dictionary's APPLY_* bits, clear of every other owner's.
FLAG_SHIFT = APPLY_FLAG_SHIFT


def calibrate_session(table, s: Session, applier: str = "float", extrapolate: bool = False) -> Session:
    """Calibrated copy of ``s`` (all rows kept) with flags, metadata and, when the table carries its
    posterior, ``cal_sigma_nT``. ``extrapolate``: keep the value of out-of-validity rows (still flagged)."""
    missing = [k for k in table.currents if k not in s.currents_A]
    if missing:
        raise SessionFileError(f"table needs current column(s) {missing}; session has {list(s.currents_A)}")
    cur = merge_currents(s.t_s, s.session, s.currents_A, table.currents)   # refit's rule
    if applier == "fixed":
        fx = FixedPointTable.from_table(table)
        need_t = bool(set(TEMPERATURE_TERMS) & set(table.terms))
        c = np.column_stack([cur[k] for k in table.currents]) if table.currents else None
        bi, ti, ci, bad = to_fixed_inputs(s.dut_uT, s.temp_c if need_t else None, c)
        q, flags = fx.apply_block(bi, ti, ci)
        out = output_to_uT(q)
        out[bad] = np.nan
        flags[bad] = int(ApplyFlag.MISSING_INPUT)
    else:
        out, flags = apply_float(table, s.dut_uT, s.temp_c, cur)
    if not extrapolate:
        out[(flags & int(ApplyFlag.OUT_OF_VALIDITY)) != 0] = np.nan
    extra = dict(s.extra)
    if table.posterior is not None:
        from magstack.firmware.cal_uncertainty import Predictive
        pred = Predictive(table.posterior, table.t0_c)
        par = pred.param_var_uT2(s.dut_uT, s.temp_c, cur)
        sd = np.sqrt(par + pred.disc_var_uT2(s.dut_uT, s.temp_c) + pred.noise_uT ** 2) * 1e3
        gone = ~np.all(np.isfinite(out), axis=1)
        for i, a in enumerate("xyz"):
            extra[f"cal_sigma_{a}_nT"] = np.where(gone, np.nan, sd[:, i])
        extra["cal_sigma_nT"] = np.where(gone, np.nan, np.sqrt(np.sum(sd ** 2, axis=1)))
        extra["cal_param_sd_nT"] = np.where(gone, np.nan, np.sqrt(np.sum(par, axis=1)) * 1e3)
    old = s.flag if s.flag is not None else np.zeros(len(s), np.int64)
    meta = dict(s.metadata)
    meta.update({"calibrated": "true", "dut_field": "calibrated", "cal_device_id": table.device_id,
                 "cal_model": table.model_name, "cal_table_crc32": (f"0x{table.crc32:08x}" if table.crc32 is not None
                                     else table.to_document()["crc32"]),
                 "cal_applier": applier, "cal_out_of_validity": "extrapolated" if extrapolate else "NaN",
                 "cal_flag_bits": flag_legend(APPLY)})
    return Session(s.t_s, s.ref_uT, out, s.temp_c, s.session, dict(s.currents_A), meta,
                   old | (flags.astype(np.int64) << FLAG_SHIFT), extra=extra)
