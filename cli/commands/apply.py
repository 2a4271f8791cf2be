"""``magstack apply cal.json SESSION.csv --out calibrated.csv``."""
from __future__ import annotations

import argparse

import numpy as np

from magstack.data.errors import SessionFileError
from magstack.data.session import read_session, refuse_overwriting_inputs, write_session
from magstack.data.windows import add_window_options, describe, select_rows
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.cal_table import load_table, validate
from magstack.firmware.calibration.fit import reference_steps, step_threshold_uT
from magstack.firmware.calibration.reference import reference_range, saturated_rows
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.float_applier import ApplyFlag
from magstack.ground.apply_session import FLAG_SHIFT, calibrate_session


def register(subparsers) -> None:
    p = subparsers.add_parser("apply", help="apply a calibration table to a session file",
                              description="Write a session whose dut_*_uT columns hold the calibrated field. "
                                          "Rows that cannot be calibrated are kept (NaN) and flagged.")
    p.add_argument("table", metavar="cal.json")
    p.add_argument("session", metavar="SESSION.csv")
    p.add_argument("--out", required=True, metavar="calibrated.csv")
    p.add_argument("--applier", choices=("float", "fixed"), default="float",
                   help="float64 reference (default) or the on-board integer applier")
    p.add_argument("--exclude-steps", type=float, default=None, metavar="UT",
                   help="score 'away from steps' without rows next to a reference change above UT (as fit); "
                        "default: the automatic threshold of fit's step diagnosis")
    add_window_options(p)
    p.set_defaults(func=run)


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
    if args.exclude_steps is not None and not args.exclude_steps > 0:
        raise ConfigurationError(f"--exclude-steps must be > 0 uT, got {args.exclude_steps}")
    if args.window or args.drop_window:
        keep = select_rows(s.t_s, s.session, args.window, args.drop_window)
        if not keep.any():
            raise ConfigurationError("the time windows select no rows")
        how = describe(args.window, args.drop_window, int(keep.sum()), len(s))
        s = s.select(keep)
        s.metadata["rows_selected"] = how
        print(f"note: time windows: {how}")
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
    for line in score_lines(out, args.exclude_steps):
        print(line)
    return 0


def score_lines(out, exclude_steps_uT: float | None) -> list[str]:
    """Calibrated-vs-reference RMS over all rows and away from reference steps (as ``fit`` scores)."""
    ok = np.all(np.isfinite(out.ref_uT), axis=1) & np.all(np.isfinite(out.dut_uT), axis=1)
    if not ok.any():
        return ["calibrated vs ref: no row has both values"]
    name, rng, note = reference_range(out.metadata)
    sat = ok & saturated_rows(out.ref_uT, rng)
    thr = step_threshold_uT(out.ref_uT[ok], out.session[ok]) if exclude_steps_uT is None else exclude_steps_uT
    at = np.zeros(len(out), dtype=bool)
    if np.isfinite(thr) and thr > 0:
        at[ok] = reference_steps(out.ref_uT[ok], out.session[ok], thr)

    def fmt(label, m):
        if not m.any():
            return f"{label}: no rows"
        rms = np.sqrt(np.mean((out.ref_uT[m] - out.dut_uT[m]) ** 2, axis=0)) * 1e3
        return (f"{label} ({int(m.sum())} rows): x {rms[0]:.1f} y {rms[1]:.1f} z {rms[2]:.1f} "
                f"norm {np.linalg.norm(rms):.1f}")
    how = ("--exclude-steps" if exclude_steps_uT is not None else "automatic threshold")
    lines = ["calibrated vs ref RMS (nT):", fmt("  all rows", ok),
             fmt(f"  away from steps (reference change > {thr:.2g} uT, {how})", ok & ~at)]
    if sat.any():
        lines.append(f"note: {int(sat.sum())} rows have the reference at/beyond its range ({name} +-{rng:g} uT)"
                     + (f"; {note}" if note else "") + "; they are in both figures")
    return lines
