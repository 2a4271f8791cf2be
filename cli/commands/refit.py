"""``magstack refit TELEMETRY.csv [...] [--active cal.json] --out candidate.json [--method ...]``.

``attitude`` (this module's default) refits against IGRF-14 rotated into the body frame by the
telemetry attitude (:mod:`magstack.firmware.calibration.refit`). ``scalar`` and ``pso`` dispatch
to ``magstack.firmware.calibration.scalar.refit_scalar`` / ``...pso.refit_pso`` when installed,
with the hook signature documented in docs/refit.md. Exit 0 when a candidate is proposed and
written, 1 when the run worked but nothing is proposed (the candidate is not written).
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
from pathlib import Path

from magstack.drivers.errors import ConfigurationError

METHODS = ("attitude", "scalar", "pso")
HOOKS = {"scalar": ("magstack.firmware.calibration.scalar", "refit_scalar"),
         "pso": ("magstack.firmware.calibration.pso", "refit_pso")}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "refit", help="refit the calibration from on-orbit telemetry (IGRF reference)",
        description="Refit the calibration table from telemetry files (position, attitude, sensor, temperature, "
                    "currents; docs/refit.md). Prints coverage, held and fitted parameters and the candidate "
                    "against the active table on held-out rows; writes the candidate only if it validates and "
                    "is better.")
    p.add_argument("telemetry", nargs="*", metavar="TELEMETRY.csv")
    p.add_argument("--active", metavar="cal.json", help="table in force (default: identity, raw output)")
    p.add_argument("--out", metavar="candidate.json", help="where to write a proposed candidate")
    p.add_argument("--json", metavar="OUT.json", help="also write the report as JSON")
    p.add_argument("--method", choices=METHODS, default="attitude")
    p.add_argument("--engine", choices=("local", "dask"), default="local",
                   help="local (in process) or dask (optional extra: map files to statistics, reduce)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="dask.distributed scheduler (default: local threads)")
    p.add_argument("--model", default="eq3", choices=("eq3", "gain_offset"))
    p.add_argument("--currents", metavar="A,B", help="currents to fit (default: every current column)")
    p.add_argument("--no-currents", action="store_true", help="fit no current terms")
    p.add_argument("--lat-band", metavar="LO,HI", help="geodetic latitude band to use, deg (e.g. --lat-band=-40,40)")
    p.add_argument("--temp-band", metavar="LO,HI", help="temperature band to use, degC")
    p.add_argument("--eclipse", choices=("any", "sunlit", "eclipse"), default="any")
    p.add_argument("--no-robust", action="store_true", help="plain least squares (no Huber passes)")
    p.add_argument("--robust-passes", type=int, default=4, help="Huber passes after the OLS pass (default 4)")
    p.add_argument("--holdout-block-s", type=float, default=600.0, help="held-out time block length (s)")
    p.add_argument("--holdout-every", type=int, default=5, help="every N-th time block is held out (default 5)")
    p.add_argument("--max-current-gap-s", type=float, default=60.0,
                   help="largest gap between housekeeping samples to interpolate across (s)")
    p.add_argument("--dut1", type=float, default=0.0, metavar="S", help="UT1 - UTC (s, IERS Bulletin A)")
    p.add_argument("--min-improvement", type=float, default=0.0, metavar="FRAC",
                   help="propose only if the held-out RMS improves by this fraction (default 0)")
    p.add_argument("--device-id", help="device id (default: active table, then telemetry metadata)")
    p.add_argument("--paper-model", type=int, metavar="N", help="(pso) rerun the riwanto paper's model N")
    p.add_argument("--seed", type=int, default=0, help="(pso) random seed")
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


def _write_json_atomic(path: str, doc: dict) -> None:
    p = Path(path)
    tmp = p.with_name(p.name + ".part")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(doc, fh, indent=1, sort_keys=True, allow_nan=False, default=float)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, p)


def _jsonable(x):
    import math
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _progress(disabled: bool):
    from tqdm import tqdm

    bars: dict[str, tqdm] = {}

    def cb(n: int, label: str) -> None:
        if label not in bars:
            for b in bars.values():
                b.close()
            bars[label] = tqdm(desc=f"refit {label}", unit=" rows", file=sys.stderr, disable=disabled or None,
                               leave=False, mininterval=0.5)
        bars[label].update(n)

    def close() -> None:
        for b in bars.values():
            b.close()

    return cb, close


def run(args: argparse.Namespace) -> int:
    from magstack.data.session import refuse_overwriting_inputs
    from magstack.firmware.cal_table import load_table, save_table, validate

    paths = list(args.telemetry)
    if args.method == "attitude" and not paths:
        raise ConfigurationError("give at least one TELEMETRY.csv")
    if paths and not args.out:
        raise ConfigurationError("--out candidate.json is required with telemetry files")
    if args.engine == "local" and args.scheduler:
        raise ConfigurationError("--scheduler needs --engine dask")
    if args.out:
        refuse_overwriting_inputs(args.out, paths + ([args.active] if args.active else []))
    active = None
    if args.active:
        active = load_table(args.active)
        validate(active).raise_if_bad(str(args.active))
    currents = () if args.no_currents else (None if args.currents is None else
                                            tuple(c for c in args.currents.split(",") if c))
    progress, close = _progress(args.no_progress)
    try:
        if args.method == "attitude":
            result = _attitude(args, paths, active, currents, progress)
        else:
            module, name = HOOKS[args.method]
            try:
                hook = getattr(importlib.import_module(module), name)
            except (ImportError, AttributeError):
                raise ConfigurationError(f"--method {args.method} is not available in this build "
                                         f"({module}.{name} not found)") from None
            opts = {k: v for k, v in vars(args).items() if k not in ("func", "telemetry", "active")}
            opts["currents"] = currents
            result = hook(paths, active=active, options=opts, progress=progress)
    finally:
        close()
    print(result.report())
    if args.json:
        _write_json_atomic(args.json, _jsonable(result.to_dict()))
        print(f"wrote {args.json}")
    if result.proposed and result.candidate is not None and args.out:
        v = validate(result.candidate)   # whatever the method: an invalid table is never written
        if not v.ok:
            print(f"{args.out} not written: candidate fails validation: " + "; ".join(v.problems))
            return 1
        save_table(result.candidate, args.out)
        print(f"wrote {args.out} (device {result.candidate.device_id}, "
              f"crc32 {result.candidate.to_document()['crc32']})")
        return 0
    if args.out:
        print(f"{args.out} not written: no candidate proposed")
    return 0 if (result.proposed or not paths) else 1


def _attitude(args, paths, active, currents, progress):
    from magstack.firmware.calibration.refit import RefitOptions, Selection, refit

    sel = Selection(_band(args.lat_band, "--lat-band"), _band(args.temp_band, "--temp-band"), args.eclipse)
    opts = RefitOptions(model=args.model, currents=currents, selection=sel, robust=not args.no_robust,
                        robust_passes=args.robust_passes, holdout_block_s=args.holdout_block_s,
                        holdout_every=args.holdout_every, max_current_gap_s=args.max_current_gap_s,
                        dut1_s=args.dut1, min_improvement=args.min_improvement, device_id=args.device_id)
    mapper = None
    if args.engine == "dask":
        from magstack.ground.refit_dask import dask_mapper

        mapper = dask_mapper(args.scheduler)
        progress = None
    return refit(paths, active, opts, progress=progress, mapper=mapper)
