"""``magstack simulate``: write a v1 session file from a coil program and a chip's error-model preset.

Rows are generated in blocks and streamed to ``OUT.part`` (fsynced per block) as they are
produced, then renamed to ``OUT``: a killed run keeps every block already written; SIGTERM or
Ctrl-C stop it at a block boundary, keep the ``.part`` and exit 143 / 130.
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

import magstack.sim.hand_rotation  # noqa: F401  (registers the hand_* programs)
from magstack.cli.interrupt import EXIT_FOR_SIGNAL, graceful_stop
from magstack.cli.options import finite_float, int_range, name_list, named_vector, nonempty_path
from magstack.cli.output import CommandResult
from magstack.cli.progress import bar
from magstack.data.session import SessionWriter
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.effects import EFFECT_NAMES
from magstack.sim.coil_programs import PROGRAMS, program
from magstack.sim.error_model import ErrorParams
from magstack.sim.measurement_sim import FVM400_LSB_uT, FVM400_NOISE_uT, measurement_rows, simulate_measurement_blocks
from magstack.sim.presets import PRESET_NAMES, preset, preset_info

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"

#: Default start of the simulated run (Unix epoch s): 2020-08-25 12:00:00 UTC, the real bench's day.
DEFAULT_T0_EPOCH_S = 1598356800.0
#: Accepted --t0 (Unix epoch s): 1970-01-01 .. 2100-01-01.
T0_RANGE_S = (0.0, 4102444800.0)
#: Largest simulated session (rows) one command writes (about 1 GB of CSV).
MAX_ROWS = 10_000_000
#: Fewest rows per power cycle (--sessions): fewer would not let a fit see a session's offset.
MIN_ROWS_PER_SESSION = 5
#: Rows generated and written per block (fixed: the output depends on it only by rounding).
BLOCK_ROWS = 20_000
#: The progress bar advances every this many rows written.
PROGRESS_ROWS = 1000


log = logging.getLogger(__name__)


def register(subparsers) -> None:
    progs = "\n".join(f"  {name:<13} {spec.help} [default {spec.default_duration_s:g} s]"
                      for name, spec in PROGRAMS.items())
    p = subparsers.add_parser(
        "simulate", help="simulate a bench run (reference + DUT) into a session file",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Simulate a bench run: truth from a coil program, DUT = the chip's error-model preset, "
                    "reference = truth + FVM400-like noise at 1 nT resolution. Deterministic for a seed. "
                    "Rows stream to OUT.part while generated.",
        epilog=f"programs:\n{progs}\n\neffects (pipeline order): {', '.join(EFFECT_NAMES)}")
    p.add_argument("--chip", choices=PRESET_NAMES, default="hmc1053", help="error-model preset (default hmc1053)")
    p.add_argument("--program", default="steps_xyz", choices=list(PROGRAMS), metavar="NAME",
                   help="coil program (see list below; default steps_xyz)")
    g = p.add_mutually_exclusive_group()
    effects = name_list(EFFECT_NAMES, "effect")
    g.add_argument("--effects", metavar="A,B", type=effects, help="only these effects on (comma separated)")
    g.add_argument("--without", metavar="A,B", type=effects, help="every effect on except these")
    p.add_argument("--seed", type=int_range(0, 2 ** 63 - 1), default=0, help="random seed (int >= 0, default 0)")
    p.add_argument("--seconds", type=finite_float(0, 90 * 86400.0, lo_open=True, unit="s"), default=None,
                   help="run length in s, (0, 90 days] (default: the program's)")
    p.add_argument("--rate-hz", type=finite_float(1e-3, 1e4, unit="Hz"), default=None,
                   help="DUT sample rate, 0.001..10000 Hz (default: the preset's)")
    p.add_argument("--sessions", type=int_range(1, 1000), default=3,
                   help=f"power cycles in the run, 1..1000 (default 3; each needs >= {MIN_ROWS_PER_SESSION} rows)")
    p.add_argument("--interference", action="append", default=[], metavar="NAME=X,Y,Z",
                   type=named_vector(3, -1e4, 1e4, unit="uT/A"),
                   help="add an interference coefficient (uT/A) for the program's current NAME (repeatable)")
    p.add_argument("--t0", type=finite_float(*T0_RANGE_S, unit="s"), default=DEFAULT_T0_EPOCH_S,
                   help=f"Unix epoch time (s) of the first row, years 1970..2100 (default {DEFAULT_T0_EPOCH_S:.0f})")
    p.add_argument("--out", required=True, type=nonempty_path, help="output session file (.csv)")
    p.add_argument("--save-params", metavar="PARAMS.json", type=nonempty_path, default=None,
                   help="also write the error-model parameters and effects used (for diagnose --sim)")
    p.set_defaults(func=run)


def _params(chip: str, interference: list[tuple[str, tuple[float, ...]]], currents: list[str],
            prog: str) -> ErrorParams:
    params = preset(chip)
    if not interference:
        return params
    unknown = [name for name, _ in interference if name not in currents]
    if unknown:
        have = ", ".join(currents) or "none"
        raise ConfigurationError(f"--interference: program {prog!r} has no current {', '.join(unknown)} "
                                 f"(its currents: {have})")
    d = params.to_dict()
    d["interference_uT_per_A"] = {**d["interference_uT_per_A"], **dict(interference)}
    return ErrorParams.from_dict(d)


def _save_params(path, params: ErrorParams, effects, chip: str) -> None:
    """PARAMS.json for ``diagnose --sim`` (format in ground/diagnose/sim_adapter.py), written atomically."""
    import os
    from pathlib import Path

    from magstack.ground.diagnose.sim_adapter import params_document
    p = Path(path)
    part = p.with_name(p.name + ".part")
    with open(part, "w", encoding="utf-8") as fh:
        json.dump(params_document(params, effects, chip), fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(part, p)


def run(args) -> CommandResult:
    if args.save_params is not None and Path(args.save_params).resolve() == Path(args.out).resolve():
        raise ConfigurationError(f"--save-params {args.save_params} is the --out file: write it elsewhere")
    if args.effects is not None:
        effects = args.effects
    elif args.without is not None:
        effects = [e for e in EFFECT_NAMES if e not in set(args.without)]
    else:
        effects = list(EFFECT_NAMES)
    truth = program(args.program, args.seconds, sessions=args.sessions)
    orbit = hasattr(truth, "q_body_eci_series")
    interference = list(args.interference)
    if orbit:   # an orbit programme: its own epoch, and its currents' field at the sensor unless overridden
        truth = truth.at_epoch(args.t0)
        interference = list(truth.default_interference_uT_per_A.items()) + interference
    params = _params(args.chip, interference, sorted(truth.currents_A(0.0)), args.program)
    info = preset_info(args.chip)
    rate = info.rate_hz if args.rate_hz is None else args.rate_hz
    n_rows = measurement_rows(truth.duration_s, rate)
    if n_rows > MAX_ROWS:
        raise ConfigurationError(f"{truth.duration_s:g} s at {rate:g} Hz is {n_rows:.3g} rows, more than "
                                 f"{MAX_ROWS:.0e}: shorten --seconds or lower --rate-hz")
    if n_rows < MIN_ROWS_PER_SESSION * args.sessions:
        raise ConfigurationError(f"{truth.duration_s:g} s at {rate:g} Hz is {n_rows} rows, fewer than "
                                 f"{MIN_ROWS_PER_SESSION} per session for --sessions {args.sessions}: raise "
                                 "--seconds or --rate-hz, or lower --sessions")
    from magstack import __version__ as version_str

    effects_on = [e for e in EFFECT_NAMES if e in set(effects)]  # pipeline order, as the model applies them
    metadata = {
        "source": "magstack simulate",
        "software_version": version_str,
        "dut_chip": args.chip,
        "preset": args.chip,
        "preset_source": info.source,
        "program": args.program,
        "program_seconds": f"{truth.duration_s:g}",
        "sessions": str(truth.sessions),
        "rate_hz": f"{rate:g}",
        "effects": ",".join(effects_on) if effects_on else "none",
        "seed": str(args.seed),
        "ref_instrument": "FVM400-like simulation",
        "ref_noise_uT": ",".join(f"{v:g}" for v in FVM400_NOISE_uT),
        "ref_lsb_uT": f"{FVM400_LSB_uT:g}",
        "error_params": json.dumps(params.to_dict(), separators=(",", ":"), sort_keys=True),
    }
    names = sorted(truth.currents_A(0.0))
    log.info("simulate: %s, program %s, %g s at %g Hz = %d rows in %d session(s), seed %d", args.chip, args.program,
             truth.duration_s, rate, n_rows, truth.sessions, args.seed)
    log.info("simulate: effects on: %s", ", ".join(effects_on) or "none")
    log.debug("simulate: error-model parameters %s", metadata["error_params"])
    extra_columns = _orbit_metadata(truth, metadata) if orbit else []
    blocks = simulate_measurement_blocks(params, truth, duration_s=truth.duration_s, rate_hz=rate, seed=args.seed,
                                         effects=effects, block_rows=BLOCK_ROWS)
    writer = SessionWriter(args.out, metadata, current_names=names, block_rows=BLOCK_ROWS,
                           extra_names=extra_columns)
    stopped = None
    with graceful_stop() as stop, bar(n_rows, "simulate", unit="row") as pbar:
        try:
            for blk in blocks:
                t = args.t0 + blk.t_s
                session = blk.session.astype(np.int64)
                cur = {k: blk.currents_A[k] for k in names}
                ref, extra = blk.ref_uT, {}
                if orbit:
                    ref, extra = _orbit_columns(truth, blk, cur, rate)
                for i in range(t.size):
                    writer.write_row(t[i], ref[i], blk.dut_uT[i], blk.temp_c[i], session[i],
                                     {k: v[i] for k, v in cur.items()}, extra={k: v[i] for k, v in extra.items()})
                    if i % PROGRESS_ROWS == PROGRESS_ROWS - 1:
                        pbar.update(PROGRESS_ROWS)   # by work done: rows written, not blocks finished
                writer.flush()
                pbar.update(t.size % PROGRESS_ROWS)
                if stop.is_set():
                    stopped = stop.signal_name
                    break
        except BaseException:
            writer.abort()
            raise
    data = {"out": str(args.out), "rows": writer.rows_written, "rows_requested": n_rows, "chip": args.chip,
            "program": args.program, "seconds": truth.duration_s, "rate_hz": rate, "sessions": truth.sessions,
            "effects": effects_on, "seed": args.seed, "complete": stopped is None, "stopped_by": stopped}
    if stopped is not None:
        writer.abort()
        return CommandResult("simulate", {**data, "out": str(writer.part_path)},
                             [f"stopped by {stopped}: {writer.part_path} kept with {writer.rows_written} of "
                              f"{n_rows} rows (not renamed: the run is incomplete)"], EXIT_FOR_SIGNAL[stopped])
    path = writer.close()
    lines = [f"wrote {path}: {writer.rows_written} rows, chip {args.chip}, program {args.program}, "
             f"{len(effects_on)} effects, seed {args.seed}"]
    if args.save_params is not None:
        _save_params(args.save_params, params, effects_on, args.chip)
        data["params"] = str(args.save_params)
        lines.append(f"wrote {args.save_params}: error-model parameters ({len(effects_on)} effects on)")
    return CommandResult("simulate", data, lines)


def _orbit_metadata(truth, metadata: dict) -> list[str]:
    """Metadata of an orbit programme's telemetry; returns its extra columns (data/telemetry.py)."""
    from magstack.data.telemetry import POS_COLUMNS, QUAT_COLUMNS

    metadata.update({"ref_instrument": "none: ref columns hold the true field (for scoring)",
                     "orbit_attitude": truth.attitude, "orbit_altitude_km": f"{truth.altitude_km:g}",
                     "housekeeping_period_s": json.dumps(truth.housekeeping_period_s, sort_keys=True)})
    metadata.pop("ref_noise_uT", None)
    metadata.pop("ref_lsb_uT", None)
    return list(POS_COLUMNS + QUAT_COLUMNS)


def _orbit_columns(truth, blk, currents: dict, rate_hz: float):
    """Telemetry of one block of an orbit programme: the true field as ``ref``, position and attitude
    columns; housekeeping currents kept only at their own sampling instants (other cells empty)."""
    from magstack.data.telemetry import POS_COLUMNS, QUAT_COLUMNS

    t = blk.t_s
    pos = truth.pos_ecef_series_km(t)
    q = truth.q_body_eci_series(t)
    for name, period in truth.housekeeping_period_s.items():
        if name in currents and period > 0:   # a sample at the first row of every period (sim time)
            keep = np.floor(t / period) != np.floor((t - 1.0 / rate_hz) / period)
            currents[name] = np.where(keep, currents[name], np.nan)
    cols = {c: pos[:, j] for j, c in enumerate(POS_COLUMNS)}
    cols.update({c: q[:, j] for j, c in enumerate(QUAT_COLUMNS)})
    return blk.truth_uT, cols
