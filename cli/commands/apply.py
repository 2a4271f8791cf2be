"""``magstack apply cal.json SESSION.csv --out calibrated.csv``."""
from __future__ import annotations

import argparse

import numpy as np

from magstack.cli.options import nonempty_path
from magstack.cli.output import CommandResult
from magstack.cli.progress import stages
from magstack.data.errors import SessionFileError
from magstack.data.session import read_session, refuse_overwriting_inputs, write_session
from magstack.firmware.cal_table import load_table, validate
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.float_applier import ApplyFlag
from magstack.ground.apply_session import FLAG_SHIFT, calibrate_session


def register(subparsers) -> None:
    p = subparsers.add_parser("apply", help="apply a calibration table to a session file",
                              description="Write a session whose dut_*_uT columns hold the calibrated field. "
                                          "Rows that cannot be calibrated are kept (NaN) and flagged.")
    p.add_argument("table", metavar="cal.json")
    p.add_argument("session", metavar="SESSION.csv")
    p.add_argument("--out", required=True, metavar="calibrated.csv", type=nonempty_path)
    p.add_argument("--applier", choices=("float", "fixed"), default="float",
                   help="float64 reference (default) or the on-board integer applier")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> CommandResult:
    with stages("apply", ["read table", "read session", "apply", "write"]) as st:
        st.next()
        table = load_table(args.table)
        validate(table).raise_if_bad(str(args.table))
        refuse_overwriting_inputs(args.out, [args.session, args.table])
        st.next()
        s = read_session(args.session)
        if s.metadata.get("calibrated") == "true":
            raise SessionFileError(f"{args.session} is already calibrated (table "
                                   f"{s.metadata.get('cal_table_crc32')}); apply the table to the raw session")
        notes = [f"{args.session}: {w}" for w in s.warnings]
        dev = s.metadata.get("device_id")
        if dev is not None and dev != table.device_id:
            raise CalTableInvalid(f"table is for device {table.device_id!r}, session is from {dev!r}")
        st.next()
        out = calibrate_session(table, s, args.applier)
        st.next()
        write_session(args.out, out)
    f = out.flag >> FLAG_SHIFT
    counts = {"missing_input": int(np.count_nonzero(f & ApplyFlag.MISSING_INPUT)),
              "out_of_validity": int(np.count_nonzero(f & ApplyFlag.OUT_OF_VALIDITY)),
              "saturated": int(np.count_nonzero(f & ApplyFlag.SATURATED))}
    lines = [f"note: {n}" for n in notes]
    lines.append(f"wrote {args.out}: {len(out)} rows ({args.applier} applier); not calibrated (missing input) "
                 f"{counts['missing_input']}, outside validity {counts['out_of_validity']}, saturated "
                 f"{counts['saturated']}")
    ok = np.all(np.isfinite(out.ref_uT), axis=1) & np.all(np.isfinite(out.dut_uT), axis=1)
    rms_nT = None
    if ok.any():
        rms = np.sqrt(np.mean((out.ref_uT[ok] - out.dut_uT[ok]) ** 2, axis=0)) * 1e3
        rms_nT = {"x": rms[0], "y": rms[1], "z": rms[2], "norm": np.linalg.norm(rms), "n": int(ok.sum())}
        lines.append(f"calibrated vs ref RMS (nT): x {rms[0]:.1f} y {rms[1]:.1f} z {rms[2]:.1f} "
                     f"norm {np.linalg.norm(rms):.1f}")
    data = {"out": str(args.out), "rows": len(out), "applier": args.applier,
            "table_crc32": table.to_document()["crc32"], "flag_counts": counts, "calibrated_vs_ref_rms_nT": rms_nT,
            "notes": notes}
    return CommandResult("apply", data, lines)
