"""``magstack diagnose``: where the sim-to-real gap lies, which unmodelled effect causes it, how far it
shrinks (ground/diagnose, docs/diagnosis.md)."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from magstack.cli.options import finite_float, int_range, nonempty_dir, nonempty_path
from magstack.cli.output import CommandResult, dumps
from magstack.cli.progress import stages
from magstack.data.session import load_sessions, refuse_overwriting_inputs
from magstack.data.windows import add_window_options, describe, select_rows
from magstack.ground.diagnose import Options, attach_rows, check_rows, diagnose, model_gap, parse_model
from magstack.ground.diagnose.spec import hysteresis_base, table_gap


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "diagnose", help="diagnose the gap between a simulator and a session",
        description="Where the gap between 'the simulator' and a session lies, which catalogue effect the "
                    "simulator leaves out (ranked on held-out time blocks, with a significance test) and how far "
                    "the gap shrinks once it is added. The simulator is either --model (parameters fitted to the "
                    "session) or fixed: --sim PARAMS.json (magstack simulate --save-params) or --table cal.json.")
    p.add_argument("sessions", nargs="+", metavar="SESSION.csv")
    p.add_argument("--model", default="gain_offset",
                   help="effects the simulator models, parameters fitted: eq3, gain_offset or effects joined by "
                        "'+' (e.g. gain+offset+time_skew); default gain_offset")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--sim", metavar="PARAMS.json", help="error-model parameters held fixed (simulate --save-params)")
    g.add_argument("--table", metavar="cal.json", help="calibration table held fixed (fitted on earlier sessions)")
    # the issue's --json OUT.json (a file) replaces the common --json flag for this command
    p.add_argument("--json", dest="json_out", metavar="OUT.json", type=nonempty_path, default=None,
                   help="write the diagnosis as strict JSON (stable keys) to OUT.json")
    p.add_argument("--report", metavar="DIR", type=nonempty_dir, help="write DIR/diagnosis.html (needs matplotlib)")
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
    p.add_argument("--t0", type=finite_float(-60, 150, unit="degC"), default=25.0,
                   help="temperature reference for --model, degC (default 25)")
    add_window_options(p)
    p.set_defaults(func=run)


def _block_s(text: str):
    return None if str(text).strip().lower() == "auto" else finite_float(0, 86400, lo_open=True, unit="s")(text)


def run(args: argparse.Namespace) -> CommandResult:
    opts = Options(block_s=args.block_s, n_folds=args.folds, alpha=args.alpha,
                   exclude_bends=None if args.keep_bends else 10.0, null=args.null,
                   include_saturated=args.include_saturated)
    if args.sim is None and args.table is None:
        terms, modelled, hyst = parse_model(args.model)
    if args.json_out:
        refuse_overwriting_inputs(args.json_out, list(args.sessions) + [x for x in (args.sim, args.table) if x])
    with stages("diagnose", ["read", "predict", "rank effects", "write"]) as st:
        st.next()
        session, notes = load_sessions(args.sessions)
        if args.window or args.drop_window:
            sel = select_rows(session.t_s, session.session, args.window, args.drop_window)
            notes.append("time windows: " + describe(args.window, args.drop_window, int(sel.sum()), len(session)))
            session = session.select(sel)
        full, keep, more = check_rows(session, exclude_bends=opts.exclude_bends,
                                      include_saturated=opts.include_saturated)
        s = full.select(keep)
        st.next()
        if args.table:
            from magstack.firmware.cal_table import load_table, validate
            table = load_table(args.table)
            validate(table).raise_if_bad(str(args.table))
            gap = table_gap(s, table, f"--table {args.table}")
        elif args.sim:
            from magstack.ground.diagnose.sim_adapter import sim_gap
            gap = sim_gap(full, keep, args.sim)
        else:
            gap = model_gap(s, terms, modelled, f"--model {args.model}", args.t0,
                            hysteresis_base(s.dut_uT) if hyst else None)
        attach_rows(gap, full, keep, notes + more)
        st.next()
        d = diagnose(gap, opts)
        st.next()
        doc = d.to_dict()
        doc["windows"] = describe(args.window, args.drop_window, len(session), len(session) if not (
            args.window or args.drop_window) else int(sel.size))
        lines = d.text().splitlines()
        if args.json_out:
            _write_json(args.json_out, doc)
            lines.append(f"wrote {args.json_out}")
        if args.report:
            from magstack.ground.diagnose.figures import write_report
            lines.append(f"wrote {write_report(d, args.report)}")
    return CommandResult("diagnose", doc, lines)


def _write_json(path, doc) -> None:
    p = Path(path)
    part = p.with_name(p.name + ".part")
    with open(part, "w", encoding="utf-8") as fh:
        fh.write(dumps(doc) + "\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(part, p)
