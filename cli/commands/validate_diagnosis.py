"""``magstack validate-diagnosis``: withheld-effect validation of the diagnosis (ground/diagnose/validate.py)."""
from __future__ import annotations

import argparse
from pathlib import Path

from magstack.cli.interrupt import EXIT_FOR_SIGNAL
from magstack.cli.options import finite_float, int_range, nonempty_dir
from magstack.cli.output import CommandResult
from magstack.cli.progress import bar
from magstack.errors import EXIT_NEGATIVE

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "validate-diagnosis", help="prove the diagnosis on simulated sessions with one effect withheld",
        description="For each catalogue effect the diagnosis can name: simulate sessions (coil program 'full') with "
                    "the effect at a realistic strength and at half, diagnose with it withheld; plus sessions with "
                    "nothing withheld (false alarms; with the base noise and with LIS3MDL-level 1/f noise) and the "
                    "fixed-table / fixed-parameter path. Writes "
                    "results.json, confusion.csv and summary.md into --out; exit 1 when a target is missed. "
                    "Ctrl-C (or SIGTERM / SIGHUP) stops at once and writes the sessions completed so far "
                    "(\"interrupted\": true, targets not decided), exit 130 (143 / 129). To try it: --quick (the same "
                    "targets on a subset; exit 0 on a healthy build). --seconds below 3600 makes sessions too short "
                    "for drift and cross-axis: targets are missed (exit 1).")
    p.add_argument("--seeds", type=int_range(1, 100), default=1, help="sessions per effect and strength (default 1)")
    p.add_argument("--nulls", type=int_range(1, 10000), default=None,
                   help="sessions with nothing withheld, run with the base noise and again with slow (1/f) noise "
                        "(default max(20, 10*seeds) each)")
    p.add_argument("--seconds", type=finite_float(600, 86400, unit="s"), default=3600.0,
                   help="length of each simulated session, [600, 86400] s (default 3600)")
    p.add_argument("--quick", action="store_true",
                   help="a quick check with the same targets (about 30 sessions: every effect at realistic strength, "
                        "three scenarios, one orbit case and null, the stale-offset (b) path, 5 null sessions with "
                        "each noise; docs/diagnosis.md gives its run time); exit 0 on a healthy build")
    p.add_argument("--out", required=True, metavar="DIR", type=nonempty_dir,
                   help="directory for results.json, confusion.csv and summary.md (created)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> CommandResult:
    from magstack.ground.diagnose.validate import jobs_count, run_validation
    with bar(jobs_count(args.seeds, args.nulls, args.quick), "validate-diagnosis", unit="session") as pb:
        s = run_validation(args.out, seeds=args.seeds, n_null=args.nulls, duration_s=args.seconds,
                           on_session=lambda: pb.update(1), quick=args.quick)
    summary = Path(args.out) / "summary.md"
    if s.get("interrupted"):   # Ctrl-C / SIGTERM / SIGHUP: what was done is written
        done = s["sessions_completed"]
        lines = summary.read_text(encoding="utf-8").splitlines() if done else []
        lines.append(f"interrupted by {s['stopped_by']} after {done} of {s['sessions_planned']} sessions: " + (
            f"wrote the partial results.json, confusion.csv and summary.md to {args.out}" if done else
            "nothing written"))
        return CommandResult("validate-diagnosis", {"out": str(args.out), **s}, lines,
                             EXIT_FOR_SIGNAL.get(s["stopped_by"], 130))
    lines = summary.read_text(encoding="utf-8").splitlines()
    ok = all(v is not False for v in s["targets"].values())
    return CommandResult("validate-diagnosis", {"out": str(args.out), **s}, lines, 0 if ok else EXIT_NEGATIVE)
