"""CLI glue for ``magstack refit --method pso --paper-model N [--seed S] --json OUT.json``.

Not a discovered command (cli/commands/ holds those): the ``refit`` command hands over to
:func:`paper_model_result` when ``--paper-model`` is set (its ``--json [FILE]`` is the common one);
:func:`add_paper_model_arguments` + :func:`run_paper_model_cli` serve a stand-alone parser.
The JSON holds at least ``fitness``, ``S_mc``,
``offset_nT`` and ``runtime_s`` (the full record is ``PaperModelResult.to_dict()``, see
docs/refit-pso.md); it is written whole or not at all (temp file, fsync, rename).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from magstack.drivers.errors import ConfigurationError
from magstack.ground.studies.riwanto import PAPER_MODELS, run_paper_model


def add_paper_model_arguments(parser: argparse.ArgumentParser) -> None:
    """``--paper-model N``, ``--seed S``, ``--json OUT.json``, ``--iterations K`` (PSO k_max)."""
    g = parser.add_argument_group("paper study (riwanto PSO, docs/refit-pso.md)")
    g.add_argument("--paper-model", type=int, choices=sorted(PAPER_MODELS), default=None, metavar="N",
                   help="rerun the paper's simulation model N (1-5) instead of refitting telemetry")
    g.add_argument("--seed", type=int, default=0, help="seed of the simulated data and the swarm (default 0)")
    g.add_argument("--json", default=None, metavar="OUT.json", help="write the result as JSON")
    g.add_argument("--iterations", type=int, default=None, metavar="K",
                   help="PSO iterations k_max (default: the paper's 500)")


def _write_json_atomic(path: Path, doc: dict) -> None:
    from magstack.data.io import atomic_write_text

    atomic_write_text(path, json.dumps(doc, indent=1, sort_keys=True, allow_nan=False) + "\n")


def paper_model_result(args: argparse.Namespace):
    """Run ``args.paper_model`` with ``args.seed`` (``args.iterations`` PSO iterations, None = the
    paper's); the result as a :class:`~magstack.cli.output.CommandResult` of ``refit``."""
    from magstack.cli.output import CommandResult
    from magstack.firmware.calibration.pso import PsoOptions

    if getattr(args, "method", "pso") != "pso":
        raise ConfigurationError("--paper-model reruns the PSO study: use it with --method pso")
    if args.paper_model is None:
        raise ConfigurationError("--paper-model N is required here")
    if args.seed < 0:
        raise ConfigurationError(f"--seed must be >= 0, got {args.seed}")
    if args.iterations is not None and args.iterations < 1:
        raise ConfigurationError(f"--iterations must be >= 1, got {args.iterations}")
    opts = PsoOptions() if args.iterations is None else PsoOptions(k_max=args.iterations)
    doc = run_paper_model(args.paper_model, args.seed, opts).to_dict()
    line = (f"paper model {doc['model']} seed {doc['seed']}: PSO fitness {doc['fitness']:.2f} nT "
            f"(paper {doc['paper']['fitness']} nT, at truth {doc['fitness_at_truth']:.2f} nT, noise floor "
            f"{doc['noise_floor_nT']:.0f} nT) in {doc['runtime_s']:.2f} s; |dS|_F {doc['dS_fro']:.3f}, "
            f"|d off| {doc['doff_nT']:.0f} nT; least squares: fitness {doc['least_squares']['fitness']:.2f} nT, "
            f"|dS|_F {doc['least_squares']['dS_fro']:.3f}, |d off| {doc['least_squares']['doff_nT']:.0f} nT "
            f"in {doc['least_squares']['runtime_s']:.4f} s")
    return CommandResult("refit", doc, [line])


def run_paper_model_cli(args: argparse.Namespace) -> int:
    """:func:`paper_model_result` for a stand-alone parser (:func:`add_paper_model_arguments`): prints the
    summary and writes ``args.json``."""
    out = Path(args.json) if args.json else None
    if out is not None and not out.parent.is_dir():
        raise ConfigurationError(f"--json: directory {out.parent} does not exist")
    res = paper_model_result(args)
    print(res.text())
    if out is not None:
        _write_json_atomic(out, res.data)
        print(f"wrote {out}", file=sys.stderr)
    return 0
