"""``magstack refit TELEMETRY.csv [...] [--active cal.json] --out candidate.json [--method ...]``.

``attitude`` (default) refits against IGRF-14 rotated into the body frame by the telemetry attitude;
``scalar`` fits against the IGRF-14 magnitude only (attitude not trusted;
:func:`magstack.firmware.calibration.refit.refit_scalar_telemetry` around
``magstack.firmware.calibration.scalar.refit_scalar``); ``pso --paper-model N`` reruns the riwanto
study (:mod:`magstack.cli.refit_pso`). Exit 0 when a candidate is proposed and written, 1 when the run
worked but nothing is proposed (the candidate is not written).
"""
from __future__ import annotations

import argparse
import logging

from magstack.cli.inputs import check_table_file
from magstack.cli.options import finite_float, int_range, nonempty_path, nonempty_text
from magstack.cli.output import CommandResult
from magstack.cli.progress import bar
from magstack.drivers.errors import ConfigurationError

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"

METHODS = ("attitude", "scalar", "pso")


log = logging.getLogger(__name__)


def sel_text(band: str | None) -> str:
    return "any" if band is None else band


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "refit", help="refit the calibration from on-orbit telemetry (IGRF reference)",
        description="Refit the calibration table from telemetry files (position, attitude, sensor, temperature, "
                    "currents; docs/refit.md). Prints coverage, held and fitted parameters and the candidate "
                    "against the active table on held-out rows; writes the candidate only if it validates and "
                    "is better.")
    p.add_argument("telemetry", nargs="*", metavar="TELEMETRY.csv", help="telemetry files (flight `run` output)")
    p.add_argument("--active", metavar="cal.json", help="table in force (default: identity, raw output)")
    p.add_argument("--out", metavar="candidate.json", type=nonempty_path, help="where to write a proposed candidate")
    p.add_argument("--method", choices=METHODS, default="attitude",
                   help="attitude: against IGRF-14 rotated into the body frame by the telemetry attitude "
                        "(default); scalar: against the IGRF-14 magnitude only (attitude not trusted); "
                        "pso: scalar fit by particle swarm (riwanto study)")
    p.add_argument("--engine", choices=("local", "dask"), default="local",
                   help="local (in process) or dask (optional extra: map files to statistics, reduce)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="dask.distributed scheduler (default: local threads)")
    p.add_argument("--model", default="eq3", choices=("eq3", "gain_offset"),
                   help="calibration model: eq3 (gain, offset and their temperature terms; default) or "
                        "gain_offset (no temperature terms)")
    p.add_argument("--currents", metavar="A,B", help="currents to fit (default: every current column)")
    p.add_argument("--no-currents", action="store_true", help="fit no current terms")
    p.add_argument("--lat-band", metavar="LO,HI", help="geodetic latitude band to use, deg (e.g. --lat-band=-40,40)")
    p.add_argument("--temp-band", metavar="LO,HI", help="temperature band to use, degC")
    p.add_argument("--eclipse", choices=("any", "sunlit", "eclipse"), default="any",
                   help="use rows in sunlight, in eclipse or any (default)")
    p.add_argument("--no-robust", action="store_true", help="plain least squares (no Huber passes)")
    p.add_argument("--robust-passes", type=int_range(0, 50), default=4,
                   help="Huber passes after the OLS pass (default 4)")
    p.add_argument("--holdout-block-s", type=finite_float(0, None, lo_open=True, unit="s"), default=600.0,
                   help="held-out time block length (s, default 600)")
    p.add_argument("--holdout-every", type=int_range(2, 1000), default=5,
                   help="every N-th time block is held out (default 5)")
    p.add_argument("--max-current-gap-s", type=finite_float(0, None, lo_open=True, unit="s"), default=60.0,
                   help="largest gap between housekeeping samples to interpolate across (s, default 60)")
    p.add_argument("--dut1", type=finite_float(-1.0, 1.0, unit="s"), default=0.0, metavar="S",
                   help="UT1 - UTC (s, IERS Bulletin A; default 0)")
    p.add_argument("--min-improvement", type=finite_float(0.0, 1.0, hi_open=True), default=0.0, metavar="FRAC",
                   help="propose only if the held-out RMS improves by this fraction (default 0), in addition to "
                        "the paired test over held-out blocks (one-sided p <= 0.01, >= 1 %% of the sum of squares)")
    p.add_argument("--device-id", type=nonempty_text, help="device id (default: active table, then telemetry metadata)")
    p.add_argument("--paper-model", type=int_range(1, 5), metavar="N", help="(pso) rerun the riwanto paper's model N")
    p.add_argument("--seed", type=int_range(0, None), default=0, help="(pso) random seed")
    p.add_argument("--iterations", type=int_range(1, None), default=None, metavar="K",
                   help="(pso) PSO iterations k_max (default: the paper's 500)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=run)


def _band(text: str | None, name: str):
    if text is None:
        return None
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise ConfigurationError(f"{name} wants LO,HI, got {text!r}") from None
    if not lo < hi:
        raise ConfigurationError(f"{name} wants LO < HI, got {text!r}")
    return lo, hi


def _progress(enabled: bool):
    """``progress(rows, label)`` callback: one tqdm bar per pass on stderr (cli.progress policy)."""
    bars: dict = {}

    def cb(n: int, label: str) -> None:
        if label not in bars:
            for b in bars.values():
                b.close()
            bars[label] = bar(None, f"refit {label}", unit="row", enabled=enabled)
        bars[label].update(n)

    def close() -> None:
        for b in bars.values():
            b.close()

    return cb, close


def run(args: argparse.Namespace) -> CommandResult:
    from magstack.data.session import refuse_overwriting_inputs
    from magstack.firmware.cal_table import load_table, save_table, validate

    paths = list(args.telemetry)
    if args.paper_model is not None:
        if args.method != "pso" or paths:
            raise ConfigurationError("--paper-model N reruns the riwanto PSO study: use --method pso and no "
                                     "telemetry files")
        from magstack.cli.refit_pso import paper_model_result

        return paper_model_result(args)
    if not paths:
        raise ConfigurationError("give at least one TELEMETRY.csv")
    if not args.out:
        raise ConfigurationError("--out candidate.json is required with telemetry files")
    if args.engine == "local" and args.scheduler:
        raise ConfigurationError("--scheduler needs --engine dask")
    if args.method in ("scalar", "pso") and args.engine != "local":
        raise ConfigurationError("--engine dask runs the attitude method only (scalar and PSO fits are batch fits)")
    refuse_overwriting_inputs(args.out, paths + ([args.active] if args.active else []))
    active = None
    if args.active:
        check_table_file(args.active)
        active = load_table(args.active)
        validate(active).raise_if_bad(str(args.active))
    log.info("refit: %d telemetry file(s), method %s, model %s, engine %s; active table %s", len(paths), args.method,
             args.model, args.engine, args.active or "none (identity)")
    currents = () if args.no_currents else (None if args.currents is None else
                                            tuple(c for c in args.currents.split(",") if c))
    progress, close = _progress(not args.no_progress)
    try:
        if args.method == "attitude":
            result = _attitude(args, paths, active, currents, progress)
        else:
            from magstack.firmware.calibration.refit import refit_scalar_telemetry

            result = refit_scalar_telemetry(paths, active, _options(args, currents), progress=progress,
                                            method=args.method, seed=args.seed)
    finally:
        close()
    lines = [result.report()]
    doc = result.to_dict()
    log.info("refit: rows %s, fitted %s, held out %s; %s", doc.get("rows"), doc.get("rows_fitted"),
             doc.get("rows_holdout"), "; ".join(doc.get("reasons") or []) or "no reason given")
    log.debug("refit: excluded rows %s", doc.get("excluded"))
    written = None
    if result.proposed and result.candidate is not None and args.out:
        v = validate(result.candidate)   # whatever the method: an invalid table is never written
        if v.ok:
            save_table(result.candidate, args.out)
            written = str(args.out)
            lines.append(f"wrote {args.out} (device {result.candidate.device_id}, "
                         f"crc32 {result.candidate.to_document()['crc32']})")
        else:
            lines.append(f"{args.out} not written: candidate fails validation: " + "; ".join(v.problems))
    elif args.out:
        lines.append(f"{args.out} not written: no candidate proposed")
    data = {**doc, "out": written, "method": args.method}
    return CommandResult("refit", data, lines, 0 if written is not None else 1)


def _options(args, currents):
    from magstack.firmware.calibration.refit import RefitOptions, Selection

    sel = Selection(_band(args.lat_band, "--lat-band"), _band(args.temp_band, "--temp-band"), args.eclipse)
    log.info("refit: rows selected: latitude %s deg, temperature %s degC, %s; currents %s; held-out block %g s "
             "(every %d-th)", sel_text(args.lat_band), sel_text(args.temp_band), args.eclipse,
             "none" if currents == () else "all columns" if currents is None else ",".join(currents),
             args.holdout_block_s, args.holdout_every)
    return RefitOptions(model=args.model, currents=currents, selection=sel, robust=not args.no_robust,
                        robust_passes=args.robust_passes, holdout_block_s=args.holdout_block_s,
                        holdout_every=args.holdout_every, max_current_gap_s=args.max_current_gap_s,
                        dut1_s=args.dut1, min_improvement=args.min_improvement, device_id=args.device_id)


def _attitude(args, paths, active, currents, progress):
    from magstack.firmware.calibration.refit import refit

    mapper = None
    if args.engine == "dask":
        from magstack.ground.refit_dask import dask_mapper

        mapper = dask_mapper(args.scheduler)
        progress = None
    return refit(paths, active, _options(args, currents), progress=progress, mapper=mapper)
