"""``magstack apply cal.json SESSION.csv --out calibrated.csv``."""
from __future__ import annotations

import argparse

import numpy as np

from drivers.errors import CalTableInvalid, SessionFileError
from firmware_py.cal_table import load_table, validate
from firmware_py.fixed_point import FixedPointTable, output_to_uT, to_fixed_inputs
from firmware_py.float_applier import ApplyFlag, apply_float
from hil.session_file import Session, read_session, refuse_overwriting_inputs, write_session

#: apply's status bits sit above the first 8 bits so flags already in the file are kept.
FLAG_SHIFT = 8


def register(subparsers) -> None:
    p = subparsers.add_parser("apply", help="apply a calibration table to a session file",
                              description="Write a session whose dut_*_uT columns hold the calibrated field. "
                                          "Rows that cannot be calibrated are kept (NaN) and flagged.")
    p.add_argument("table", metavar="cal.json")
    p.add_argument("session", metavar="SESSION.csv")
    p.add_argument("--out", required=True, metavar="calibrated.csv")
    p.add_argument("--applier", choices=("float", "fixed"), default="float",
                   help="float64 reference (default) or the on-board integer applier")
    p.set_defaults(func=run)


def calibrate_session(table, s: Session, applier: str = "float") -> Session:
    """Calibrated copy of ``s`` (all rows kept) with flags and metadata."""
    missing = [k for k in table.currents if k not in s.currents_A]
    if missing:
        raise SessionFileError(f"table needs current column(s) {missing}; session has {list(s.currents_A)}")
    cur = {k: s.currents_A[k] for k in table.currents}
    if applier == "fixed":
        fx = FixedPointTable.from_table(table)
        need_t = bool({"temperature_gain", "temperature_offset"} & set(table.terms))
        c = np.column_stack([cur[k] for k in table.currents]) if table.currents else None
        bi, ti, ci, bad = to_fixed_inputs(s.dut_uT, s.temp_c if need_t else None, c)
        q, flags = fx.apply_block(bi, ti, ci)
        out = output_to_uT(q)
        out[bad] = np.nan
        flags[bad] = int(ApplyFlag.MISSING_INPUT)
    else:
        out, flags = apply_float(table, s.dut_uT, s.temp_c, cur)
    old = s.flag if s.flag is not None else np.zeros(len(s), np.int64)
    meta = dict(s.metadata)
    meta.update({"calibrated": "true", "dut_field": "calibrated", "cal_device_id": table.device_id,
                 "cal_model": table.model_name, "cal_table_crc32": (f"0x{table.crc32:08x}" if table.crc32 is not None
                                     else table.to_document()["crc32"]),
                 "cal_applier": applier,
                 "cal_flag_bits": f"{int(ApplyFlag.MISSING_INPUT) << FLAG_SHIFT}=missing_input "
                                  f"{int(ApplyFlag.OUT_OF_VALIDITY) << FLAG_SHIFT}=out_of_validity "
                                  f"{int(ApplyFlag.SATURATED) << FLAG_SHIFT}=saturated"})
    return Session(s.t_s, s.ref_uT, out, s.temp_c, s.session, dict(s.currents_A), meta,
                   old | (flags.astype(np.int64) << FLAG_SHIFT))


def run(args: argparse.Namespace) -> int:
    table = load_table(args.table)
    validate(table).raise_if_bad(str(args.table))
    refuse_overwriting_inputs(args.out, [args.session, args.table])
    s = read_session(args.session)
    if s.metadata.get("calibrated") == "true":
        raise SessionFileError(f"{args.session} is already calibrated (table {s.metadata.get('cal_table_crc32')}); "
                               "apply the table to the raw session")
    for w in s.warnings:
        print(f"note: {args.session}: {w}")
    dev = s.metadata.get("device_id")
    if dev is not None and dev != table.device_id:
        raise CalTableInvalid(f"table is for device {table.device_id!r}, session is from {dev!r}")
    out = calibrate_session(table, s, args.applier)
    write_session(args.out, out)
    f = out.flag >> FLAG_SHIFT
    n_missing = int(np.count_nonzero(f & ApplyFlag.MISSING_INPUT))
    n_oov = int(np.count_nonzero(f & ApplyFlag.OUT_OF_VALIDITY))
    n_sat = int(np.count_nonzero(f & ApplyFlag.SATURATED))
    print(f"wrote {args.out}: {len(out)} rows ({args.applier} applier); not calibrated (missing input) "
          f"{n_missing}, outside validity {n_oov}, saturated {n_sat}")
    ok = np.all(np.isfinite(out.ref_uT), axis=1) & np.all(np.isfinite(out.dut_uT), axis=1)
    if ok.any():
        rms = np.sqrt(np.mean((out.ref_uT[ok] - out.dut_uT[ok]) ** 2, axis=0)) * 1e3
        print(f"calibrated vs ref RMS (nT): x {rms[0]:.1f} y {rms[1]:.1f} z {rms[2]:.1f} "
              f"norm {np.linalg.norm(rms):.1f}")
    return 0
