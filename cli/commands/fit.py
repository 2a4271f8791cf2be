"""``magstack fit``: fit the calibration model to session files and write a table."""
from __future__ import annotations

import argparse
import json
import logging

from magstack.cli.options import finite_float, float_list, nonempty_path, nonempty_text
from magstack.cli.output import CommandResult, say
from magstack.cli.progress import stages
from magstack.data.session import load_sessions, refuse_overwriting_inputs
from magstack.data.windows import add_window_options, describe, select_rows
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.cal_table import BOUNDS as TABLE_BOUNDS
from magstack.firmware.cal_table import save_table, table_from_fit, validate
from magstack.firmware.calibration import FitData, FitOptions, fit
from magstack.firmware.calibration.model import CAL_TERMS, MODELS
from magstack.firmware.calibration.reference import reference_range
from magstack.firmware.errors import CalTableInvalid, FitError, NoValidityRegion

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"

log = logging.getLogger(__name__)


def field_coverage_notes(ref_uT, field_present_uT: float) -> list[str]:
    """Warnings when the reference field cannot determine a calibration: an axis whose |B| never
    reaches ``field_present_uT`` leaves its gain column undetermined (a zero-field session fits
    offsets only, yet the table looks valid)."""
    import numpy as np

    peak = np.nanmax(np.abs(ref_uT), axis=0) if len(ref_uT) else np.zeros(3)
    weak = [ax for ax, p in zip("xyz", peak, strict=True) if not p >= field_present_uT]
    if not weak:
        return []
    return [f"the reference field never reaches {field_present_uT:g} uT on axis {', '.join(weak)} (peak "
            + ", ".join(f"{ax} {p:.3g}" for ax, p in zip("xyz", peak, strict=True))
            + " uT): the gains on that axis come from the prior or the other axes, not from this data; "
              "the table's output is not supported there"]


def _split(values) -> list[str]:
    out: list[str] = []
    for v in values or ():
        out += [x for x in v.split(",") if x]
    return out


def register(subparsers) -> None:
    p = subparsers.add_parser("fit", help="fit the calibration model to session files",
                              description="Fit the calibration model (several files = separate sessions), "
                                          "print the report and write a calibration table.")
    p.add_argument("sessions", nargs="+", metavar="SESSION.csv", help="session files (several = separate sessions)")
    p.add_argument("--model", default="eq3", choices=sorted(MODELS),
                   help="eq3: gain matrix, offset and their temperature terms (default); gain_offset: no "
                        "temperature terms")
    p.add_argument("--terms", nargs="*", default=[], metavar="TERM",
                   help=f"extra terms (comma or space separated): {', '.join(CAL_TERMS)}")
    p.add_argument("--tempco2", choices=("auto", "off"), default="auto",
                   help="auto (default): on a temperature span of 10 degC or more with field present, also fit the "
                        "second-order sensitivity tempco (temperature_gain2) and keep it when its held-out improvement "
                        "is significant; off: never add it (--terms temperature_gain2 forces it)")
    p.add_argument("--currents", default="", metavar="NAME,...", help="current columns to fit (D_k terms)")
    p.add_argument("--robust", action="store_true", help="Huber IRLS instead of plain least squares")
    t_lo, t_hi = TABLE_BOUNDS["temp_c"]
    p.add_argument("--t0", type=finite_float(t_lo, t_hi, unit="degC"), default=25.0,
                   help=f"reference temperature t0_c, {t_lo:g}..{t_hi:g} degC (default 25)")
    p.add_argument("--exclude-steps", type=finite_float(0, 1e4, lo_open=True, unit="uT"), default=None, metavar="UT",
                   help="exclude rows next to a reference change above UT between rows (field transitions)")
    p.add_argument("--min-temp-span", type=finite_float(0, 500, unit="degC"), default=5.0, metavar="DEGC",
                   help="temperature span below which the report names temperature terms as prior-determined "
                        "(default 5; the estimator itself needs no threshold)")
    p.add_argument("--field-present", type=finite_float(0, 1e4, unit="uT"), default=5.0, metavar="UT",
                   help="|B| counted as field on an axis for coverage rules (default 5)")
    p.add_argument("--include-saturated", action="store_true",
                   help="keep rows where the reference is at/beyond its range (default: excluded, counted)")
    p.add_argument("--max-vif", type=finite_float(1, None, lo_open=True), default=FitOptions.max_vif, metavar="VIF",
                   help=f"variance inflation at or above which a parameter group is degenerate: the data fix only "
                        f"its combination, the prior the rest (default {FitOptions.max_vif:g})")
    p.add_argument("--mount-frame", type=int, default=None, metavar="SESSION",
                   help="with --terms mount_rotation: the session whose mount defines the sensor frame "
                        "(default: the first session in which rotations about every axis are observable)")
    add_window_options(p)
    p.add_argument("--refuse-unidentifiable", action="store_true",
                   help="fail (exit 3) instead of letting the prior decide what the data cannot determine")
    p.add_argument("--no-holdout", action="store_true", help="skip held-out evaluation")
    p.add_argument("--block-s", type=finite_float(0, 1e7, lo_open=True, unit="s"), default=60.0,
                   help="time-block length for held-out folds (s, default 60)")
    p.add_argument("--device-id", default=None, type=nonempty_text,
                   help="device id for the table (default: session metadata)")
    p.add_argument("--description", default="", help="free text stored in the table (default: the files fitted)")
    p.add_argument("--validity-temp", default=None, metavar="LO,HI",
                   type=float_list(2, t_lo, t_hi, unit="degC", ordered=True),
                   help="table validity temperature range, degC (default: the data's range; write a negative LO as "
                        "--validity-temp=-20,60)")
    p.add_argument("--validity-field", type=finite_float(0, 1e4, lo_open=True, unit="uT"), default=None,
                   metavar="UT",
                   help="table validity |B| per axis, uT (default: the data's maximum)")
    p.add_argument("--prior", action="append", default=[], metavar="NAME=MEAN+-SD|FILE.json",
                   help="override a parameter's prior: 'K_S[x,x]=2.7e-3+-0.5e-3', 'O[z]=0.3' (fixed), 'O[z]=flat' "
                        "(no prior), or a JSON file {name: [mean, sd]}; repeatable")
    p.add_argument("--no-priors", action="store_true",
                   help="no priors at all: the unregularised least squares (for comparison)")
    p.add_argument("--chip", default=None, metavar="CHIP",
                   help="part whose datasheet priors apply (default: the session's dut_chip; unknown = wide "
                        "generic priors, named in the report)")
    p.add_argument("--validity-sd", type=finite_float(0, 1e6, lo_open=True, unit="nT"), default=None, metavar="NT",
                   help="largest predictive sd of the calibrated field vector inside the table's validity region, nT; "
                        "the table promises errors below twice it there (default: 1.5x its RMS over the data, up to "
                        "its largest value over the data's own region, at most 5x the RMS)")
    p.add_argument("--out", required=True, metavar="cal.json", type=nonempty_path, help="calibration table to write")
    p.set_defaults(func=run)


def prior_overrides(items) -> dict[str, tuple[float, float]]:
    """``--prior`` values -> {name: (mean, sd)}; a FILE.json holds {name: [mean, sd] or value}."""
    from pathlib import Path

    from magstack.data.errors import SessionFileError
    from magstack.firmware.calibration.estimator import parse_override

    out: dict[str, tuple[float, float]] = {}
    for item in items or ():
        if "=" not in item and item.endswith(".json"):
            path = Path(item)
            try:
                if path.stat().st_size > 1 << 20:
                    raise SessionFileError(f"{path}: prior file larger than 1 MiB")
                doc = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise SessionFileError(f"{path}: cannot read the prior file ({exc})") from None
            if not isinstance(doc, dict):
                raise SessionFileError(f"{path}: expected a JSON object {{name: [mean, sd]}}")
            for k, v in doc.items():
                vals = v if isinstance(v, list) else [v]
                if not (1 <= len(vals) <= 2) or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                       for x in vals):
                    raise SessionFileError(f"{path}: {k}: expected [mean, sd] or a number")
                text = f"{k}={vals[0]!r}" + (f"+-{vals[1]!r}" if len(vals) == 2 else "")
                name, mean, sd = parse_override(text)
                out[name] = (mean, sd)
        else:
            name, mean, sd = parse_override(item)
            out[name] = (mean, sd)
    return out


def run(args: argparse.Namespace) -> CommandResult:
    unknown = [t for t in _split(args.terms) if t not in CAL_TERMS]
    if unknown:
        raise ConfigurationError(f"--terms: unknown term(s) {unknown}; valid: {', '.join(CAL_TERMS)}")
    refuse_overwriting_inputs(args.out, args.sessions)
    fit_stage = "fit" if args.no_holdout else "fit + held-out folds"
    with stages("fit", ["read sessions", fit_stage, "validate + write table"]) as st:
        st.next()
        session, notes = load_sessions(args.sessions)
        keep = select_rows(session.t_s, session.session, args.window, args.drop_window)
        selection = {"windows": describe(args.window, args.drop_window, int(keep.sum()), len(session))}
        if args.window or args.drop_window:
            if not keep.any():
                raise ConfigurationError(f"the time windows select no rows ({selection['windows']})")
            session = session.select(keep)
            notes.append(f"time windows: {selection['windows']}")
        ids = sorted(set(session.session.tolist()))
        log.info("fit: %d rows from %d file(s), sessions %s; rows selected: %s", len(session), len(args.sessions),
                 ids, selection["windows"])
        if args.mount_frame is not None and args.mount_frame not in ids:
            raise ConfigurationError(f"--mount-frame {args.mount_frame}: no such session (have {ids})")
        ref_name, ref_range, ref_note = reference_range(session.metadata)
        if ref_note:
            notes.append(ref_note)
        selection["reference"] = f"{ref_name} +-{ref_range:g} uT" + (" (assumed)" if ref_note else "")
        device_id = args.device_id or session.metadata.get("device_id") or session.metadata.get("dut_chip")
        if not device_id:
            raise FitError("no device id in the session metadata: pass --device-id")
        opts = FitOptions(robust=args.robust, on_unidentifiable="refuse" if args.refuse_unidentifiable else "hold",
                          min_temp_span_c=args.min_temp_span, field_present_uT=args.field_present,
                          holdout=not args.no_holdout, block_s=args.block_s, exclude_ref_steps_uT=args.exclude_steps,
                          max_vif=args.max_vif, ref_range_uT=ref_range, include_saturated=args.include_saturated,
                          mount_frame=args.mount_frame, use_priors=not args.no_priors,
                          chip=args.chip or session.metadata.get("dut_chip"), priors=prior_overrides(args.prior),
                          second_order_tempco=args.tempco2)
        weak = field_coverage_notes(session.ref_uT, args.field_present)
        for w in weak:
            log.warning("fit: %s", w)
        notes += weak
        log.info("fit: model %s, extra terms %s, currents %s, t0 %g degC, %s; reference %s", args.model,
                 _split(args.terms) or "none", _split([args.currents]) or "none", args.t0,
                 "Huber IRLS" if args.robust else "least squares", selection["reference"])
        log.info("fit: held-out folds %s", "off" if args.no_holdout else f"time blocks of {args.block_s:g} s")
        log.debug("fit: options %s", opts)
        log.info("fit: priors %s%s", "none (--no-priors)" if args.no_priors else (opts.chip or "generic"),
                 f", overrides {sorted(opts.priors)}" if opts.priors else "")
        st.next()
        result = fit(FitData.from_session(session), args.model, _split(args.terms), _split([args.currents]),
                     args.t0, opts)
        result.selection.update(selection)
        stats = result.stats()
        log.info("fit: rows used %s, excluded %s (saturated reference %s, step rows %s)", stats.get("n_used"),
                 stats.get("n_excluded"), stats.get("saturated_rows"), stats.get("n_excluded_steps"))
        for h in stats.get("held", []):
            log.info("fit: held %s = %s: %s", h["param"], h["value"], h["reason"])
        st.next()
        report = result.report()
        try:
            table = table_from_fit(result, device_id, description=args.description or
                                   f"fit of {', '.join(str(p) for p in args.sessions)}",
                                   validity_temp_c=args.validity_temp, validity_field_uT=args.validity_field,
                                   validity_sd_uT=None if args.validity_sd is None else args.validity_sd / 1e3)
        except NoValidityRegion:
            say(report)   # the parameters and what the prior decided say why; the error itself stays one line
            raise
        v = validate(table)
        if not v.ok:   # never replace a file (perhaps a good table) with one the board would refuse
            say(report)   # the report explains why; the error itself stays one line
            raise CalTableInvalid(f"fitted table fails validation, {args.out} not written: " + "; ".join(v.problems))
        save_table(table, args.out)
    crc = table.to_document()["crc32"]
    vinfo = table.fit_stats.get("validity", {})
    box = (f"validity: {table.validity_temp_c[0]:g}..{table.validity_temp_c[1]:g} degC"
           if table.validity_temp_c is not None else "validity: any temperature") + \
        f", |B_i| <= {table.validity_field_uT:g} uT ({vinfo.get('rule', 'data range')}" + \
        (f", bound {vinfo['bound_uT'] * 1e3:.0f} nT)" if "bound_uT" in vinfo else ")")
    lines = [f"note: {n}" for n in notes if n not in weak] + [report,   # weak: said as warnings on stderr
             f"\nwrote {args.out} (device {device_id}, crc32 {crc})", box] + \
        [f"  {x}" for x in vinfo.get("notes", [])] + [f"WARNING: {w}" for w in vinfo.get("warnings", [])] + \
        [f"table validates: worst-case output {v.worst_output_uT:.1f} uT, max cond {v.max_cond:.3g}"]
    data = {"out": str(args.out), "device_id": device_id, "crc32": crc, "model": result.model.name,
            "terms": _split(args.terms), "currents": _split([args.currents]), "stats": stats,
            "validation": {"ok": v.ok, "worst_output_uT": v.worst_output_uT, "max_cond": v.max_cond},
            "notes": notes}
    return CommandResult("fit", data, lines)
