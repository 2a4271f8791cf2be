"""Demo step 6: an independent session (other seed, other length), aligned and calibrated with
the fixed-point applier exactly as ``magstack apply --applier fixed`` does
(:func:`magstack.ground.apply_session.calibrate_session`); residual before/after."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magstack.cli.demo.bench import AlignFigures, BenchFigures, align_session, record_session
from magstack.cli.demo.config import Say, norm_rms_uT
from magstack.data.session import read_session, write_session
from magstack.firmware.calibration.fit import reference_steps
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.fixed_point import to_fixed_inputs
from magstack.firmware.float_applier import ApplyFlag, apply_float
from magstack.ground.apply_session import FLAG_SHIFT, calibrate_session


@dataclass
class HoldoutFigures:
    bench: BenchFigures
    align: AlignFigures
    calibrated_path: Path
    n_rows: int
    n_steady: int
    raw_rmse_norm_uT: float          # rows outside coil transitions (the fit's rule)
    cal_rmse_norm_uT: float
    raw_rmse_uT: list[float]
    cal_rmse_uT: list[float]
    raw_rmse_all_norm_uT: float      # every paired row, transitions included
    cal_rmse_all_norm_uT: float
    out_of_validity_rows: int
    saturated_rows: int
    fixed_vs_float_max_nT: float     # same quantised inputs: the integer arithmetic alone
    fixed_vs_float_unquantised_max_nT: float  # float64 on the unrounded inputs (adds input rounding)


def holdout_check(table, out_dir: Path, *, program: str, seconds: float, seed: int, ref_garble: float,
                  exclude_steps_uT: float, say: Say = print) -> HoldoutFigures:
    """Record an independent session, pair it, calibrate it with the fixed-point applier."""
    bench = record_session(out_dir / "holdout-session.csv", program=program, seconds=seconds, seed=seed,
                           session_id=2, ref_garble=ref_garble, instrument_name="demo-holdout", say=say)
    al = align_session(bench.path, out_dir / "holdout-paired.csv", say=say, verbose=False)
    say(f"  aligned: offset {al.offset_s:+.4f} +- {al.offset_sigma_s:.4f} s, axis map "
        f"{'identity' if al.axis_map_identity else al.axis_map}; {al.paired_rows} paired rows")
    paired = read_session(al.paired_path)
    dev = paired.metadata.get("device_id")
    if dev is not None and dev != table.device_id:  # the check `magstack apply` makes
        raise CalTableInvalid(f"table is for device {table.device_id!r}, session is from {dev!r}")
    cal = calibrate_session(table, paired, "fixed")
    cal_path = write_session(out_dir / "holdout-calibrated.csv", cal)
    apply_flags = cal.flag >> FLAG_SHIFT
    ok = (paired.flag == 0) & ~(apply_flags & int(ApplyFlag.MISSING_INPUT)).astype(bool)
    ok &= np.all(np.isfinite(cal.dut_uT), axis=1) & np.all(np.isfinite(paired.ref_uT), axis=1)
    steady = ok & ~reference_steps(paired.ref_uT, paired.session, exclude_steps_uT)
    raw_e = paired.ref_uT - paired.dut_uT
    cal_e = paired.ref_uT - cal.dut_uT

    def per_axis(e, m) -> list[float]:
        return [float(x) for x in np.sqrt(np.mean(e[m] ** 2, axis=0))]

    def max_diff_nT(x) -> float:
        return float(np.max(np.abs(x[ok] - cal.dut_uT[ok]))) * 1e3 if ok.any() else math.nan

    bi, ti, _, _ = to_fixed_inputs(paired.dut_uT, paired.temp_c)
    flt_q, _ = apply_float(table, bi / 1e3, ti / 1e2)
    flt, _ = apply_float(table, paired.dut_uT, paired.temp_c)
    diff_nT, diff_unq_nT = max_diff_nT(flt_q), max_diff_nT(flt)
    fig = HoldoutFigures(bench, al, Path(cal_path), int(ok.sum()), int(steady.sum()),
                         norm_rms_uT(raw_e[steady]), norm_rms_uT(cal_e[steady]), per_axis(raw_e, steady),
                         per_axis(cal_e, steady), norm_rms_uT(raw_e[ok]), norm_rms_uT(cal_e[ok]),
                         int(np.count_nonzero(apply_flags & int(ApplyFlag.OUT_OF_VALIDITY))),
                         int(np.count_nonzero(apply_flags & int(ApplyFlag.SATURATED))), diff_nT, diff_unq_nT)
    say(f"  fixed-point applier (magstack apply --applier fixed) on {fig.n_rows} rows: outside validity "
        f"{fig.out_of_validity_rows}, saturated {fig.saturated_rows}; |fixed - float64| <= {diff_nT:.4f} nT on the "
        f"same 1 nT / 0.01 degC inputs ({diff_unq_nT:.2f} nT against float64 on unrounded inputs)")
    per = ", ".join(f"{v * 1e3:.1f}" for v in fig.cal_rmse_uT)
    say(f"  residual vs reference, {fig.n_steady} rows outside coil transitions: raw {fig.raw_rmse_norm_uT:.3f} uT"
        f" -> calibrated {fig.cal_rmse_norm_uT * 1e3:.1f} nT (x/y/z {per} nT)")
    say(f"  all {fig.n_rows} rows incl. transitions: raw {fig.raw_rmse_all_norm_uT:.3f} uT -> calibrated "
        f"{fig.cal_rmse_all_norm_uT * 1e3:.1f} nT (the excess sits next to coil steps and ramps, where a 0.36 s DUT "
        f"cycle and a 4 Hz reference cannot be paired sample-exactly)")
    return fig
