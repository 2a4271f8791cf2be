"""``magstack bench --dut CHIP --ref fvm400 [--bus sim] --seconds N --out session.csv``: a bench session.

SIGTERM or Ctrl-C end the recording at the next sample: the rows so far are written, the file is
closed and renamed (a complete, shorter session), a message says so, and the exit status is
143 / 130. A second Ctrl-C interrupts at once (the ``.part`` file keeps every flushed row).
"""
from __future__ import annotations

import argparse
import time
from dataclasses import fields

from magstack.cli.interrupt import EXIT_FOR_SIGNAL, graceful_stop
from magstack.cli.options import finite_float, int_range, nonempty_path
from magstack.cli.output import CommandResult
from magstack.cli.progress import bar
from magstack.drivers.errors import ConfigurationError
from magstack.drivers.registry import chip_names, is_simulated, open_chip
from magstack.hil.bench import record_sim_session, run_bench

#: Reference query rate range (Hz): the FVM400 answers at 9600 baud, ~30 bytes a reply.
REF_RATE_RANGE_HZ = (0.01, 20.0)
#: DUT read rate range (Hz): the fastest chip table rate is 1000 Hz (LIS3MDL).
DUT_RATE_RANGE_HZ = (0.01, 1000.0)
#: Longest session one command records (s): 30 days.
MAX_SECONDS = 30 * 86400.0


def _faults(text: str) -> dict[str, float]:
    from magstack.sim.fvm400_model import FVM400Faults

    valid = [f.name for f in fields(FVM400Faults)]
    prob = finite_float(0.0, 1.0)
    out = {}
    for item in filter(None, text.split(",")):
        k, sep, v = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"expected name=probability, got {item!r}")
        if k.strip() not in valid:
            raise argparse.ArgumentTypeError(f"unknown fault {k.strip()!r}; valid: {', '.join(valid)}")
        out[k.strip()] = prob(v)
    return out


def _program(text: str) -> str:
    from magstack.sim.coil_programs import PROGRAMS

    if text not in PROGRAMS:
        raise argparse.ArgumentTypeError(f"unknown program {text!r}; valid: {', '.join(PROGRAMS)}")
    return text


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="record a DUT + FVM400 reference bench session",
                              description="Record DUT and reference side by side (each at its own rate) into a "
                                          "crash-safe session file. --bus sim drives both with a simulated coil "
                                          "program in virtual time. SIGTERM/Ctrl-C stop early with a complete "
                                          "file (exit 143/130).")
    p.add_argument("--dut", required=True, choices=chip_names(), help="device under test")
    p.add_argument("--ref", default="fvm400", choices=("fvm400",), help="reference instrument")
    p.add_argument("--bus", default="sim", help="'sim', or the DUT bus spec (I2C: 1 or /dev/i2c-1; "
                                                 "hmc1053: spi0.0[,pins...])")
    p.add_argument("--ref-port", default="/dev/ttyUSB0", help="FVM400 serial port or URL (real bench)")
    p.add_argument("--seconds", type=finite_float(0, MAX_SECONDS, lo_open=True, unit="s"), required=True,
                   help="session length (s, up to 30 days)")
    p.add_argument("--out", required=True, type=nonempty_path,
                   help="session file to write (crash-safe .part until done)")
    p.add_argument("--ref-rate-hz", type=finite_float(*REF_RATE_RANGE_HZ, unit="Hz"), default=4.0,
                   help=f"reference query rate, {REF_RATE_RANGE_HZ[0]:g}..{REF_RATE_RANGE_HZ[1]:g} Hz (default 4)")
    p.add_argument("--dut-rate-hz", type=finite_float(*DUT_RATE_RANGE_HZ, unit="Hz"), default=None,
                   help=f"DUT read rate, {DUT_RATE_RANGE_HZ[0]:g}..{DUT_RATE_RANGE_HZ[1]:g} Hz "
                        "(default: every new sample)")
    p.add_argument("--session-id", type=int_range(0, 2 ** 31 - 1), default=0,
                   help="integer run id written in every row")
    p.add_argument("--program", default="steps_x", type=_program,
                   help="simulated coil program (--bus sim), e.g. steps_x, sweeps")
    p.add_argument("--seed", type=int_range(0, 2 ** 63 - 1), default=0, help="simulation seed (int >= 0)")
    p.add_argument("--sim-ref-faults", type=_faults, default={},
                   help="simulated FVM400 fault probabilities (0..1), e.g. garble=0.02,dropout=0.01,partial=0.01")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (as --quiet does)")
    p.set_defaults(func=run)


def _progress_callback(pbar, min_interval_s: float = 0.1):
    """run_bench's progress callback drawing ``pbar`` (throttled: the event loop calls it per sample)."""
    last = [-1.0]

    def progress(elapsed_s: float, res, final: bool = False) -> None:
        now = time.monotonic()
        if not final and now - last[0] < min_interval_s:
            return
        last[0] = now
        pbar.n = min(float(pbar.total), round(elapsed_s, 1))
        errs = sum(res.dut_errors.values()) + sum(res.ref_errors.values())
        pbar.set_postfix(dut=res.dut_samples, ref=res.ref_samples, skipped=sum(res.ref_skipped.values()),
                         errors=errs, refresh=False)
        pbar.refresh() if final else pbar.update(0)
    return progress


def run(args: argparse.Namespace) -> CommandResult:
    with graceful_stop() as stop, bar(args.seconds, "bench", unit="s", enabled=not args.no_progress) as pbar:
        progress = None if pbar.disable else _progress_callback(pbar)
        if is_simulated(args.bus):
            res, _ = record_sim_session(args.dut, args.out, program=args.program, seconds=args.seconds,
                                        seed=args.seed, session_id=args.session_id, ref_rate_hz=args.ref_rate_hz,
                                        dut_rate_hz=args.dut_rate_hz, ref_faults=args.sim_ref_faults,
                                        progress=progress, stop=stop)
        else:
            if args.sim_ref_faults:
                raise ConfigurationError("--sim-ref-faults only applies with --bus sim")
            from magstack.drivers.clock import SystemClock
            from magstack.drivers.fvm400 import FVM400

            clock = SystemClock()
            ref = FVM400.open(args.ref_port, clock)
            try:
                dut = open_chip(args.dut, args.bus, clock)
                meta = {"bus": args.bus, "ref_port": args.ref_port, "clock": "system"}
                res = run_bench(dut, ref, clock, args.out, seconds=args.seconds, ref_rate_hz=args.ref_rate_hz,
                                dut_rate_hz=args.dut_rate_hz, session_id=args.session_id, metadata=meta,
                                progress=progress, stop=stop)
            finally:
                ref.close()
    lines = [res.summary()]
    code = 0
    if res.stopped_early:
        lines.append(f"stopped by {stop.signal_name} after {res.duration_s:.1f} of {args.seconds:g} s: {res.path} is "
                     f"complete with the {res.rows} rows recorded so far")
        code = EXIT_FOR_SIGNAL.get(stop.signal_name or "", 130)
    return CommandResult("bench", {**res.to_dict(), "stopped_by": stop.signal_name if res.stopped_early else None},
                         lines, code)
