"""``magstack simulate``: write a v1 session file from a coil program and a chip's error-model preset."""
from __future__ import annotations

import argparse
import json
import math

import numpy as np

import magstack.sim.orbit_truth  # noqa: F401  (registers the orbit_* programs)
from magstack.data.session import Session, write_session
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.effects import EFFECT_NAMES, effect
from magstack.sim.coil_programs import PROGRAMS, program
from magstack.sim.error_model import ErrorParams
from magstack.sim.measurement_sim import FVM400_LSB_uT, FVM400_NOISE_uT, simulate_measurement
from magstack.sim.presets import PRESET_NAMES, preset, preset_info

#: Default start of the simulated run (Unix epoch s): 2020-08-25 12:00:00 UTC, the real bench's day.
DEFAULT_T0_EPOCH_S = 1598356800.0


def register(subparsers) -> None:
    progs = "\n".join(f"  {name:<13} {spec.help} [default {spec.default_duration_s:g} s]"
                      for name, spec in PROGRAMS.items())
    p = subparsers.add_parser(
        "simulate", help="simulate a bench run (reference + DUT) into a session file",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Simulate a bench run: truth from a coil program, DUT = the chip's error-model preset, "
                    "reference = truth + FVM400-like noise at 1 nT resolution. Deterministic for a seed.",
        epilog=f"programs:\n{progs}\n\neffects (pipeline order): {', '.join(EFFECT_NAMES)}")
    p.add_argument("--chip", choices=PRESET_NAMES, default="hmc1053", help="error-model preset (default hmc1053)")
    p.add_argument("--program", default="steps_xyz", metavar="NAME",
                   help="coil program (see list below; default steps_xyz)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--effects", metavar="A,B", help="only these effects on (comma separated)")
    g.add_argument("--without", metavar="A,B", help="every effect on except these")
    p.add_argument("--seed", type=int, default=0, help="random seed (int >= 0, default 0)")
    p.add_argument("--seconds", type=float, default=None, help="run length in s (default: the program's)")
    p.add_argument("--rate-hz", type=float, default=None, help="DUT sample rate (default: the preset's)")
    p.add_argument("--sessions", type=int, default=3, help="power cycles in the run (default 3)")
    p.add_argument("--interference", action="append", default=[], metavar="NAME=X,Y,Z",
                   help="add an interference coefficient (uT/A) for current NAME (repeatable)")
    p.add_argument("--t0", type=float, default=DEFAULT_T0_EPOCH_S,
                   help=f"epoch time (s) of the first row (default {DEFAULT_T0_EPOCH_S:.0f})")
    p.add_argument("--out", required=True, help="output session file (.csv)")
    p.set_defaults(func=run)


def _names(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    for n in names:
        try:
            effect(n)
        except ValueError as exc:
            raise ConfigurationError(str(exc)) from None
    return names


def _interference(items: list[str]) -> dict[str, tuple[float, float, float]]:
    out = {}
    for item in items:
        name, sep, vec = item.partition("=")
        try:
            vals = tuple(float(v) for v in vec.split(","))
        except ValueError:
            vals = ()
        if not sep or len(vals) != 3 or not all(math.isfinite(v) for v in vals):
            raise ConfigurationError(f"--interference expects NAME=X,Y,Z (uT/A), got {item!r}")
        out[name.strip()] = vals
    return out


#: Largest simulated session (rows) one command writes (about 1 GB of CSV).
MAX_ROWS = 10_000_000


def run(args) -> int:
    if args.program not in PROGRAMS:
        raise ConfigurationError(f"unknown program {args.program!r}; valid: {', '.join(PROGRAMS)}")
    if args.seed < 0:
        raise ConfigurationError(f"--seed must be >= 0, got {args.seed}")
    if args.sessions < 1:
        raise ConfigurationError(f"--sessions must be >= 1, got {args.sessions}")
    if args.effects is not None:
        effects = _names(args.effects)
    elif args.without is not None:
        drop = set(_names(args.without))
        effects = [e for e in EFFECT_NAMES if e not in drop]
    else:
        effects = list(EFFECT_NAMES)
    params = preset(args.chip)
    truth = program(args.program, args.seconds, sessions=args.sessions)
    orbit = hasattr(truth, "q_body_eci_series")
    if orbit:   # an orbit programme: its own epoch, currents and their field at the sensor
        truth = truth.at_epoch(args.t0)
    extra = {**(truth.default_interference_uT_per_A if orbit else {}), **_interference(args.interference)}
    if extra:
        d = params.to_dict()
        d["interference_uT_per_A"] = {**d["interference_uT_per_A"], **extra}
        params = ErrorParams.from_dict(d)
    info = preset_info(args.chip)
    rate = info.rate_hz if args.rate_hz is None else args.rate_hz
    if not (rate > 0 and math.isfinite(rate)):
        raise ConfigurationError(f"--rate-hz must be > 0, got {rate}")
    n_rows = truth.duration_s * rate
    if n_rows > MAX_ROWS:
        raise ConfigurationError(f"{truth.duration_s:g} s at {rate:g} Hz is {n_rows:.3g} rows, more than "
                                 f"{MAX_ROWS:.0e}: shorten --seconds or lower --rate-hz")
    run_ = simulate_measurement(params, truth, duration_s=truth.duration_s, rate_hz=rate, seed=args.seed,
                                effects=effects)
    from magstack import __version__ as version_str

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
        "effects": ",".join(run_.effects) if run_.effects else "none",
        "seed": str(args.seed),
        "ref_instrument": "FVM400-like simulation",
        "ref_noise_uT": ",".join(f"{v:g}" for v in FVM400_NOISE_uT),
        "ref_lsb_uT": f"{FVM400_LSB_uT:g}",
        "error_params": json.dumps(params.to_dict(), separators=(",", ":"), sort_keys=True),
    }
    currents = {k: v for k, v in run_.currents_A.items()}
    ref, extra_cols = run_.ref_uT, {}
    if orbit:
        ref, extra_cols = _orbit_columns(truth, run_, currents, metadata)
    session = Session(t_s=args.t0 + run_.t_s, ref_uT=ref, dut_uT=run_.dut_uT, temp_c=run_.temp_c,
                      session=run_.session.astype(np.int64), currents_A=currents, metadata=metadata,
                      extra=extra_cols)
    path = write_session(args.out, session)
    print(f"wrote {path}: {len(session)} rows, chip {args.chip}, program {args.program}, "
          f"{len(run_.effects)} effects, seed {args.seed}")
    return 0


def _orbit_columns(truth, run_, currents: dict, metadata: dict):
    """Telemetry columns of an orbit programme (data/telemetry.py): true field as ``ref``, position,
    attitude; housekeeping currents kept only at their own sampling instants (others empty)."""
    from magstack.data.telemetry import POS_COLUMNS, QUAT_COLUMNS

    t = run_.t_s
    pos = truth.pos_ecef_series_km(t)
    q = truth.q_body_eci_series(t)
    for name, period in truth.housekeeping_period_s.items():
        if name in currents and period > 0:
            k = np.floor(t / period)
            keep = np.concatenate([[True], k[1:] != k[:-1]])
            currents[name] = np.where(keep, currents[name], np.nan)
    metadata.update({"ref_instrument": "none: ref columns hold the true field (for scoring)",
                     "orbit_attitude": truth.attitude, "orbit_altitude_km": f"{truth.altitude_km:g}",
                     "housekeeping_period_s": json.dumps(truth.housekeeping_period_s, sort_keys=True)})
    metadata.pop("ref_noise_uT", None)
    metadata.pop("ref_lsb_uT", None)
    cols = {c: pos[:, k] for k, c in enumerate(POS_COLUMNS)}
    cols.update({c: q[:, k] for k, c in enumerate(QUAT_COLUMNS)})
    return run_.truth_uT, cols
