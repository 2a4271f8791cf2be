"""``magstack apply cal.json SESSION.csv --out calibrated.csv``."""
from __future__ import annotations

import argparse
import logging

import numpy as np

from magstack.cli.inputs import check_table_file
from magstack.cli.options import finite_float, nonempty_path
from magstack.cli.output import CommandResult
from magstack.cli.progress import stages
from magstack.data.errors import SessionFileError
from magstack.data.session import read_session, refuse_overwriting_inputs, write_session
from magstack.data.windows import add_window_options, describe, select_rows
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.cal_table import load_table, validate
from magstack.firmware.calibration.reference import reference_range, saturated_rows
from magstack.firmware.calibration.steps import reference_steps, step_threshold_uT
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.float_applier import ApplyFlag
from magstack.ground.apply_session import FLAG_SHIFT, calibrate_session

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    p = subparsers.add_parser("apply", help="apply a calibration table to a session file",
                              description="Write a session whose dut_*_uT columns hold the calibrated field. "
                                          "Rows that cannot be calibrated are kept (NaN) and flagged.")
    p.add_argument("table", metavar="cal.json", help="calibration table (magstack fit / refit)")
    p.add_argument("session", metavar="SESSION.csv", help="raw session file to calibrate")
    p.add_argument("--out", required=True, metavar="calibrated.csv", type=nonempty_path,
                   help="calibrated session file to write")
    p.add_argument("--extrapolate", action="store_true",
                   help="write values for rows outside the table's validity box (still flagged); default: no "
                        "value (NaN), as the flight corrector publishes none")
    p.add_argument("--applier", choices=("float", "fixed"), default="float",
                   help="float64 reference (default) or the on-board integer applier")
    p.add_argument("--exclude-steps", type=finite_float(0, 1e4, lo_open=True, unit="uT"), default=None, metavar="UT",
                   help="score 'away from steps' without rows next to a reference change above UT (as fit); "
                        "default: the automatic threshold of fit's step diagnosis")
    add_window_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> CommandResult:
    with stages("apply", ["read table", "read session", "apply", "write"]) as st:
        st.next()
        check_table_file(args.table)
        table = load_table(args.table)
        validate(table).raise_if_bad(str(args.table))
        log.info("apply: table %s for %s, terms %s, valid for temp_c %s and |B| <= %g uT; %s applier",
                 "none" if table.crc32 is None else f"0x{table.crc32:08x}", table.device_id, ", ".join(table.terms),
                 table.validity_temp_c,
                 table.validity_field_uT, args.applier)
        refuse_overwriting_inputs(args.out, [args.session, args.table])
        st.next()
        s = read_session(args.session)
        if s.metadata.get("calibrated") == "true":
            raise SessionFileError(f"{args.session} is already calibrated (table "
                                   f"{s.metadata.get('cal_table_crc32')}); apply the table to the raw session")
        notes = [f"{args.session}: {w}" for w in s.warnings]
        if args.window or args.drop_window:
            keep = select_rows(s.t_s, s.session, args.window, args.drop_window)
            if not keep.any():
                raise ConfigurationError("the time windows select no rows")
            how = describe(args.window, args.drop_window, int(keep.sum()), len(s))
            s = s.select(keep)
            s.metadata["rows_selected"] = how
            notes.append(f"time windows: {how}")
        log.info("apply: %d rows of %s (%s)", len(s), args.session, s.metadata.get("rows_selected", "all rows"))
        dev = s.metadata.get("device_id")
        if dev is not None and dev != table.device_id:
            raise CalTableInvalid(f"table is for device {table.device_id!r}, session is from {dev!r}")
        st.next()
        out = calibrate_session(table, s, args.applier, extrapolate=args.extrapolate)
        st.next()
        write_session(args.out, out)
    f = out.flag >> FLAG_SHIFT
    counts = {"missing_input": int(np.count_nonzero(f & ApplyFlag.MISSING_INPUT)),
              "out_of_validity": int(np.count_nonzero(f & ApplyFlag.OUT_OF_VALIDITY)),
              "saturated": int(np.count_nonzero(f & ApplyFlag.SATURATED))}
    log.info("apply: not calibrated: missing input %d, outside validity %d, saturated %d", counts["missing_input"],
             counts["out_of_validity"], counts["saturated"])
    lines = [f"note: {n}" for n in notes]
    lines.append(f"wrote {args.out}: {len(out)} rows ({args.applier} applier); not calibrated (missing input) "
                 f"{counts['missing_input']}, outside validity {counts['out_of_validity']}"
                 + (" (extrapolated, flagged)" if args.extrapolate else " (no value, as on board)")
                 + f", saturated {counts['saturated']}")
    sig = out.extra.get("cal_sigma_nT")
    sig_stats = None
    if sig is not None and np.isfinite(sig).any():
        q = np.nanpercentile(sig, [50, 95])
        sig_stats = {"median": float(q[0]), "p95": float(q[1]), "max": float(np.nanmax(sig))}
        lines.append(f"cal_sigma_nT (predictive sd of the calibrated vector: parameters + discrepancy + noise): "
                     f"median {q[0]:.1f}, 95 % {q[1]:.1f}, max {sig_stats['max']:.1f} nT")
    score = scores(out, args.exclude_steps)
    lines += score.pop("lines")
    data = {"out": str(args.out), "rows": len(out), "applier": args.applier,
            "table_crc32": table.to_document()["crc32"], "flag_counts": counts,
            "calibrated_vs_ref_rms_nT": score["all_rows"],
            "calibrated_vs_ref_rms_away_from_steps_nT": score["away_from_steps"],
            "rows_selected": out.metadata.get("rows_selected"), "cal_sigma_nT": sig_stats, "notes": notes}
    return CommandResult("apply", data, lines)


def scores(out, exclude_steps_uT: float | None) -> dict:
    """Calibrated-vs-reference RMS (nT) over all rows and away from reference steps, as ``fit`` scores:
    ``{"all_rows", "away_from_steps", "lines"}`` (the figures None when no row has both values)."""
    ok = np.all(np.isfinite(out.ref_uT), axis=1) & np.all(np.isfinite(out.dut_uT), axis=1)
    if not ok.any():
        return {"all_rows": None, "away_from_steps": None, "lines": ["calibrated vs ref: no row has both values"]}
    name, rng, note = reference_range(out.metadata)
    sat = ok & saturated_rows(out.ref_uT, rng)
    thr = step_threshold_uT(out.ref_uT[ok], out.session[ok]) if exclude_steps_uT is None else exclude_steps_uT
    at = np.zeros(len(out), dtype=bool)
    if np.isfinite(thr) and thr > 0:
        at[ok] = reference_steps(out.ref_uT[ok], out.session[ok], thr)

    def rms(m):
        if not m.any():
            return None
        r = np.sqrt(np.mean((out.ref_uT[m] - out.dut_uT[m]) ** 2, axis=0)) * 1e3
        return {"x": r[0], "y": r[1], "z": r[2], "norm": np.linalg.norm(r), "n": int(m.sum())}

    def fmt(label, r):
        if r is None:
            return f"{label}: no rows"
        return f"{label} ({r['n']} rows): x {r['x']:.1f} y {r['y']:.1f} z {r['z']:.1f} norm {r['norm']:.1f}"
    how = "--exclude-steps" if exclude_steps_uT is not None else "automatic threshold"
    log.info("apply: scoring away from reference steps above %.3g uT (%s): %d step rows", thr, how, int(at.sum()))
    all_rows, away = rms(ok), rms(ok & ~at)
    if away is not None:
        away.update({"threshold_uT": thr, "threshold_source": how})
    lines = ["calibrated vs ref RMS (nT):", fmt("  all rows", all_rows),
             fmt(f"  away from steps (reference change > {thr:.2g} uT, {how})", away)]
    if sat.any():
        lines.append(f"note: {int(sat.sum())} rows have the reference at/beyond its range ({name} +-{rng:g} uT)"
                     + (f"; {note}" if note else "") + "; they are in both figures")
    return {"all_rows": all_rows, "away_from_steps": away, "lines": lines}
