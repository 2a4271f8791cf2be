"""``magstack diagnose``: where the sim-to-real gap lies, which unmodelled effect causes it, how far it
shrinks (ground/diagnose, docs/diagnosis.md)."""
from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

from magstack.data.session import load_sessions, refuse_overwriting_inputs
from magstack.drivers.errors import ConfigurationError
from magstack.ground.diagnose import Options, check_rows, diagnose, model_gap, parse_model, shift_source
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
    p.add_argument("--json", metavar="OUT.json", help="write the diagnosis as JSON (stable keys)")
    p.add_argument("--report", metavar="DIR", help="write DIR/diagnosis.html (plots embedded; needs matplotlib)")
    p.add_argument("--block-s", type=float, default=60.0, help="held-out time-block length in s (default 60)")
    p.add_argument("--folds", type=int, default=5, help="number of folds (default 5)")
    p.add_argument("--alpha", type=float, default=0.05, help="family-wise false-alarm level (default 0.05)")
    p.add_argument("--keep-bends", action="store_true",
                   help="keep the rows at sharp bends of the reference field (default: left out)")
    p.add_argument("--t0", type=float, default=25.0, help="temperature reference for --model, degC (default 25)")
    p.set_defaults(func=run)


def _options(args) -> Options:
    if not (math.isfinite(args.block_s) and args.block_s > 0):
        raise ConfigurationError(f"--block-s must be > 0 s, got {args.block_s}")
    if args.folds < 2:
        raise ConfigurationError(f"--folds must be >= 2, got {args.folds}")
    if not 0 < args.alpha < 1:
        raise ConfigurationError(f"--alpha must be in (0, 1), got {args.alpha}")
    return Options(block_s=args.block_s, n_folds=args.folds, alpha=args.alpha,
                   exclude_bends=None if args.keep_bends else 10.0)


def run(args: argparse.Namespace) -> int:
    opts = _options(args)
    if args.sim is None and args.table is None:
        terms, modelled, hyst = parse_model(args.model)
    inputs = list(args.sessions) + [x for x in (args.sim, args.table) if x]
    if args.json:
        refuse_overwriting_inputs(args.json, inputs)
    session, notes = load_sessions(args.sessions)
    full, keep, more = check_rows(session, exclude_bends=opts.exclude_bends)
    s = full.select(keep)
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
    gap.shift_source = shift_source(full, keep)
    gap.notes += notes + more
    d = diagnose(gap, opts)
    print(d.text())
    if args.json:
        _write_json(args.json, d.to_dict())
        print(f"wrote {args.json}")
    if args.report:
        from magstack.ground.diagnose.figures import write_report
        print(f"wrote {write_report(d, args.report)}")
    return 0


def _write_json(path, doc) -> None:
    p = Path(path)
    part = p.with_name(p.name + ".part")
    with open(part, "w", encoding="utf-8") as fh:
        json.dump(doc, fh, indent=1, allow_nan=True, default=float)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(part, p)
