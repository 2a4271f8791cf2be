"""``magstack demo [--out-dir DIR] [--seed S] [--seconds N]``: the whole stack on the simulated bench.

Probe and read every chip, record a bench session (HMC1053 DUT + FVM400 reference), align,
fit the calibration, save/validate/activate the table (corrupted copies refused), apply it
with the fixed-point applier to an independent session, and run the flight sampling loop
with injected faults. No hardware needed; deterministic for a seed. The logic lives in
cli/demo.py; docs/demo.md explains each step.
"""
from __future__ import annotations

import argparse

from magstack.cli.demo import MAX_SECONDS, MIN_SECONDS, DemoConfig, run_demo


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the whole stack end to end on the simulated bench (no hardware)",
                              description=__doc__.split("\n\n")[1].replace("\n", " "))
    p.add_argument("--out-dir", default="magstack-demo", help="directory for the artefacts (default ./magstack-demo)")
    p.add_argument("--seed", type=int, default=0, help="simulation seed (int >= 0, default 0)")
    p.add_argument("--seconds", type=float, default=DemoConfig.seconds,
                   help=f"length of the calibration bench session in simulated seconds "
                        f"({MIN_SECONDS:g}..{MAX_SECONDS:g}, default {DemoConfig.seconds:g}); the held-out "
                        f"session lasts half of it (at least {MIN_SECONDS:g} s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    run_demo(DemoConfig(out_dir=args.out_dir, seed=args.seed, seconds=args.seconds))
    return 0
