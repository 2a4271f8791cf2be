"""``magstack diagnose``: where the sim-to-real gap lies, which unmodelled effect causes it, how far it
shrinks (ground/diagnose, docs/diagnosis.md)."""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from magstack.cli.inputs import check_params_file, check_table_file
from magstack.cli.options import finite_float, int_range, nonempty_dir
from magstack.cli.output import CommandResult
from magstack.cli.progress import stages
from magstack.data.session import load_sessions
from magstack.data.windows import add_window_options, describe, select_rows
from magstack.ground.diagnose import Options, attach_rows, check_rows, diagnose, kept_rows, model_gap, parse_model
from magstack.ground.diagnose.spec import hysteresis_base, table_gap

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "diagnose", help="diagnose the gap between a simulator and a session",
        description="Where the gap between 'the simulator' and a session lies, which catalogue effect the "
                    "simulator leaves out (ranked on held-out time blocks, with a significance test) and how far "
                    "the gap shrinks once it is added. The simulator is either --model (parameters fitted to the "
                    "session) or fixed: --sim PARAMS.json (magstack simulate --save-params) or --table cal.json.")
    p.add_argument("sessions", nargs="+", metavar="SESSION.csv", help="session files (several = one series)")
    p.add_argument("--model", default="gain_offset", type=model_text,
                   help="effects the simulator models, parameters fitted: eq3, gain_offset or effects joined by "
                        "'+' (e.g. gain+offset+time_skew); default gain_offset")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--sim", metavar="PARAMS.json", help="error-model parameters held fixed (simulate --save-params)")
    g.add_argument("--table", metavar="cal.json", help="calibration table held fixed (fitted on earlier sessions)")
    p.add_argument("--report", metavar="DIR", type=nonempty_dir, help="write DIR/diagnosis.html (a page with the "
                                                                        "figures; written whole or not at all)")
    p.add_argument("--block-s", type=_block_s, default=None, metavar="S|auto",
                   help="held-out time-block length, (0, 86400] s, or 'auto' (default: chosen from the residual's "
                        "autocorrelation time, the session lengths and their number; stated in the output)")
    p.add_argument("--folds", type=int_range(2, 50), default=5, help="number of folds, [2, 50] (default 5)")
    p.add_argument("--alpha", type=finite_float(0, 1, lo_open=True, hi_open=True), default=0.05,
                   help="family-wise false-alarm level, (0, 1) (default 0.05)")
    p.add_argument("--null", choices=("surrogate", "blocks"), default="surrogate",
                   help="null model of the significance test: 'surrogate' (default: the block test with one-block "
                        "units and a surrogate test against noise with the residual's spectrum must both reject) "
                        "or 'blocks' (the block test alone, units grouped by the residual's block correlation)")
    p.add_argument("--keep-bends", action="store_true",
                   help="keep the rows at sharp bends of the reference field (default: left out)")
    p.add_argument("--include-saturated", action="store_true",
                   help="keep rows with the reference at or beyond its range (default: left out and counted, "
                        "the same guard as fit; the range comes from the session metadata 'reference')")
    p.add_argument("--reference", choices=("auto", "session", "igrf"), default="auto",
                   help="the reference field: 'session' = the files' ref_* columns; 'igrf' = orbit telemetry "
                        "(position and attitude columns, docs/refit.md): IGRF at the GPS position rotated by the "
                        "attitude, as refit computes it, with its error budget (crustal, external, attitude) in "
                        "the noise floor; 'auto' (default): igrf for telemetry without ref_* values (no columns, or "
                        "every cell empty as in flight telemetry), else session")
    p.add_argument("--attitude-sd-deg", type=finite_float(0, 30, unit="deg"), default=0.1,
                   help="attitude knowledge (1 sd per axis, deg) in the orbit reference's error budget (default 0.1)")
    p.add_argument("--chip", default=None, metavar="CHIP",
                   help="part whose datasheet priors decide what the session cannot (the base model's parameters "
                        "a session does not determine, and between explanations it cannot tell apart); default: "
                        "the session's dut_chip; an unknown part gets wide generic priors (said in the output)")
    p.add_argument("--t0", type=finite_float(-60, 150, unit="degC"), default=25.0,
                   help="temperature reference for --model, degC (default 25)")
    add_window_options(p)
    p.set_defaults(func=run)


def _read(args):
    """(session, notes): bench session files, or orbit telemetry through the refit's reference (--reference)."""
    from magstack.ground.diagnose.orbit import is_orbit_telemetry, orbit_session, without_missing_currents

    telemetry = [is_orbit_telemetry(p) for p in args.sessions]
    if args.reference == "igrf" or (args.reference == "auto" and all(telemetry)):
        from magstack.data.telemetry import read_header

        if not all(telemetry):
            bad = next(p for p, t in zip(args.sessions, telemetry, strict=True) if not t)
            read_header(bad)     # names the missing position/attitude columns (exit 3)
        # auto: the files' ref_* values when there are any (merged flight telemetry: columns, every cell empty)
        s, notes = without_missing_currents(orbit_session(args.sessions, reference=args.reference))
        own_ref = s.metadata.get("reference") != "igrf"
        what = "its ref_* columns (use --reference igrf for the refit's reference)" if own_ref else \
            "IGRF at the GPS position rotated by the attitude (the refit's reference)"
        log.info("diagnose: orbit telemetry, %d rows; reference %s", len(s), what)
        return s, [f"orbit telemetry: reference = {what}; housekeeping currents interpolated as refit does"] + notes
    return load_sessions(args.sessions)


def model_text(text: str) -> str:
    """argparse type of --model: names joined by single '+' (no empty name: ``gain++offset``); the
    names themselves are checked by ``parse_model``."""
    if not text or any(not part.strip() for part in text.split("+")):
        raise argparse.ArgumentTypeError(f"expected effect names joined by '+', got {text!r}")
    return text


def _check_blocks(s, block_s: float, folds: int) -> None:
    """ConfigurationError (exit 2) when the kept rows span fewer --block-s blocks than --folds: each
    fold must hold out at least one block (``--block-s 86400`` on a 20-minute session)."""
    from magstack.drivers.errors import ConfigurationError
    from magstack.ground.diagnose.gap import time_blocks

    n = int(np.unique(time_blocks(s.t_s, s.session, block_s)).size) if len(s) else 0
    if n < folds:
        raise ConfigurationError(f"--block-s {block_s:g} s cuts the {len(s)} usable rows into {n} time block(s), "
                                 f"fewer than --folds {folds}: lower --block-s (the session spans "
                                 f"{np.ptp(s.t_s) if len(s) else 0:.0f} s) or --folds")


def _block_s(text: str):
    return None if str(text).strip().lower() == "auto" else finite_float(0, 86400, lo_open=True, unit="s")(text)


def run(args: argparse.Namespace) -> CommandResult:
    opts = Options(block_s=args.block_s, n_folds=args.folds, alpha=args.alpha,
                   exclude_bends=None if args.keep_bends else 10.0, null=args.null,
                   include_saturated=args.include_saturated, chip=args.chip,
                   attitude_sd_deg=args.attitude_sd_deg)
    if args.sim is None and args.table is None:
        terms, modelled, hyst = parse_model(args.model)
    with stages("diagnose", ["read", "predict", "rank effects", "write"]) as st:
        st.next()
        session, notes = _read(args)
        if args.window or args.drop_window:
            sel = select_rows(session.t_s, session.session, args.window, args.drop_window)
            notes.append("time windows: " + describe(args.window, args.drop_window, int(sel.sum()), len(session)))
            session = session.select(sel)
        full, keep, more = check_rows(session, exclude_bends=opts.exclude_bends,
                                      include_saturated=opts.include_saturated)
        s = kept_rows(full, keep)
        if args.block_s is not None:       # 'auto' chooses a length the session can hold
            _check_blocks(s, args.block_s, args.folds)
        log.info("diagnose: %d rows read, %d kept (%s)", len(session), int(keep.sum()),
                 "; ".join(more) if more else "no row left out")
        log.info("diagnose: simulator %s; held-out blocks of %g s in %d folds, alpha %g, null model %s",
                 f"--table {args.table}" if args.table else f"--sim {args.sim}" if args.sim else
                 f"--model {args.model}", args.block_s, args.folds, args.alpha, args.null)
        st.next()
        if args.table:
            from magstack.firmware.cal_table import load_table, validate
            check_table_file(args.table)
            table = load_table(args.table)
            validate(table).raise_if_bad(str(args.table))
            gap = table_gap(s, table, f"--table {args.table}")
        elif args.sim:
            from magstack.ground.diagnose.sim_adapter import sim_gap
            check_params_file(args.sim)
            gap = sim_gap(full, keep, args.sim)
        else:
            gap = model_gap(s, terms, modelled, f"--model {args.model}", args.t0,
                            hysteresis_base(s.dut_uT) if hyst else None)
        attach_rows(gap, full, keep, notes + more)
        st.next()
        d = diagnose(gap, opts)
        st.next()
        log.info("diagnose: verdict %s", d.verdict if hasattr(d, "verdict") else d.to_dict().get("verdict"))
        doc = d.to_dict()
        doc["windows"] = describe(args.window, args.drop_window, len(session), len(session) if not (
            args.window or args.drop_window) else int(sel.size))
        lines = d.text().splitlines()
        if args.report:   # the folder appears with its page or not at all (Ctrl-C, SIGTERM)
            from magstack.data.io import staged_directory
            from magstack.ground.diagnose.figures import write_report
            with staged_directory(args.report) as stage:
                name = write_report(d, stage, inputs=args.sessions).name
            lines.append(f"wrote {Path(args.report) / name}")
    return CommandResult("diagnose", doc, lines)

