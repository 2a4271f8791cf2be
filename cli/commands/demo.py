"""``magstack demo [--out DIR] [--seed S] [--seconds N]``: the whole stack on the simulated bench.

Probe and read every chip, record a bench session (HMC1053 DUT + FVM400 reference), align,
fit the calibration, save/validate/activate the table (corrupted copies refused), apply it
with the fixed-point applier to an independent session, and run the flight sampling loop
with injected faults. No hardware needed; deterministic for a seed. The orchestrator is
cli/demo/; docs/demo.md explains each step.
"""
from __future__ import annotations

import argparse

from magstack.cli.demo import MAX_SECONDS, MIN_SECONDS, STEPS, DemoConfig, run_demo
from magstack.cli.options import finite_float, int_range, nonempty_dir
from magstack.cli.output import CommandResult, say
from magstack.cli.progress import stages

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the whole stack end to end on the simulated bench (no hardware)",
                              description=__doc__.split("\n\n")[1].replace("\n", " "))
    p.add_argument("--out", "--out-dir", dest="out", default="magstack-demo", type=nonempty_dir, metavar="DIR",
                   help="directory for the artefacts (default ./magstack-demo; --out-dir is an alias)")
    p.add_argument("--seed", type=int_range(0, 2 ** 32 - 1), default=0, help="simulation seed (int >= 0, default 0)")
    p.add_argument("--seconds", type=finite_float(MIN_SECONDS, MAX_SECONDS, unit="s"), default=DemoConfig.seconds,
                   help=f"length of the calibration bench session in simulated seconds "
                        f"({MIN_SECONDS:g}..{MAX_SECONDS:g}, default {DemoConfig.seconds:g}); the held-out "
                        f"session lasts half of it (at least {MIN_SECONDS:g} s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> CommandResult:
    with stages("demo", [key for key, _ in STEPS]) as st:
        res = run_demo(DemoConfig(out_dir=args.out, seed=args.seed, seconds=args.seconds), say=say,
                       on_step=st.next)
    return CommandResult("demo", {"out_dir": str(res.config.out_dir), **res.figures()})
