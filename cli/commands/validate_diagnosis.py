"""``magstack validate-diagnosis``: withheld-effect validation of the diagnosis (ground/diagnose/validate.py)."""
from __future__ import annotations

import argparse
import json

from magstack.drivers.errors import ConfigurationError
from magstack.errors import EXIT_NEGATIVE


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "validate-diagnosis", help="prove the diagnosis on simulated sessions with one effect withheld",
        description="For each catalogue effect the diagnosis can name: simulate sessions (coil program 'full') with "
                    "the effect at a realistic strength and at half, diagnose with it withheld; plus sessions with "
                    "nothing withheld (false alarms) and the fixed-table / fixed-parameter path. Writes "
                    "results.json, confusion.csv and summary.md into --out; exit 1 when a target is missed.")
    p.add_argument("--seeds", type=int, default=1, help="sessions per effect and strength (default 1)")
    p.add_argument("--nulls", type=int, default=None, help="sessions with nothing withheld (default max(20, 10*seeds))")
    p.add_argument("--seconds", type=float, default=3600.0, help="length of each simulated session in s (default 3600)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.seeds < 1:
        raise ConfigurationError(f"--seeds must be >= 1, got {args.seeds}")
    if args.nulls is not None and args.nulls < 1:
        raise ConfigurationError(f"--nulls must be >= 1, got {args.nulls}")
    if not args.seconds >= 600:
        raise ConfigurationError(f"--seconds must be >= 600 (the program needs its four parts), got {args.seconds}")
    from magstack.ground.diagnose.validate import run_validation
    s = run_validation(args.out, seeds=args.seeds, n_null=args.nulls, duration_s=args.seconds,
                       progress=not args.no_progress)
    print(open(f"{args.out}/summary.md", encoding="utf-8").read())
    print(json.dumps(s["targets"]))
    return 0 if all(v is not False for v in s["targets"].values()) else EXIT_NEGATIVE
