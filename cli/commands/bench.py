"""``magstack bench --dut CHIP --ref fvm400 [--bus sim] --seconds N --out session.csv``: a bench session."""
from __future__ import annotations

import argparse

from magstack.drivers.errors import ConfigurationError
from magstack.drivers.registry import chip_names, is_simulated, open_chip
from magstack.hil.bench import ProgressLine, build_sim_bench, run_bench, truth_currents


def _faults(text: str) -> dict[str, float]:
    from dataclasses import fields

    from magstack.sim.fvm400_model import FVM400Faults

    valid = [f.name for f in fields(FVM400Faults)]
    out = {}
    for item in filter(None, text.split(",")):
        k, sep, v = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"expected name=probability, got {item!r}")
        if k.strip() not in valid:
            raise argparse.ArgumentTypeError(f"unknown fault {k.strip()!r}; valid: {', '.join(valid)}")
        out[k.strip()] = float(v)
    return out


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="record a DUT + FVM400 reference bench session",
                              description="Record DUT and reference side by side (each at its own rate) into a "
                                          "crash-safe session file. --bus sim drives both with a simulated coil "
                                          "program in virtual time.")
    p.add_argument("--dut", required=True, choices=chip_names(), help="device under test")
    p.add_argument("--ref", default="fvm400", choices=("fvm400",), help="reference instrument")
    p.add_argument("--bus", default="sim", help="'sim', or the DUT bus spec (I2C: 1 or /dev/i2c-1; "
                                                 "hmc1053: spi0.0[,pins...])")
    p.add_argument("--ref-port", default="/dev/ttyUSB0", help="FVM400 serial port or URL (real bench)")
    p.add_argument("--seconds", type=float, required=True, help="session length (s)")
    p.add_argument("--out", required=True, help="session file to write (crash-safe .part until done)")
    p.add_argument("--ref-rate-hz", type=float, default=4.0, help="reference query rate (default 4 Hz)")
    p.add_argument("--dut-rate-hz", type=float, default=None, help="DUT read rate (default: every new sample)")
    p.add_argument("--session-id", type=int, default=0, help="integer run id written in every row")
    p.add_argument("--program", default="steps_x", help="simulated coil program (--bus sim), e.g. steps_x, sweeps")
    p.add_argument("--seed", type=int, default=0, help="simulation seed")
    p.add_argument("--sim-ref-faults", type=_faults, default={},
                   help="simulated FVM400 faults, e.g. garble=0.02,dropout=0.01,partial=0.01")
    p.add_argument("--no-progress", action="store_true", help="no progress line")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    progress = None if args.no_progress else ProgressLine(args.seconds)
    if is_simulated(args.bus):
        sb = build_sim_bench(args.dut, program=args.program, seconds=args.seconds, seed=args.seed,
                             ref_faults=args.sim_ref_faults)
        names, cur = truth_currents(sb.truth)
        meta = {"bus": "sim", "program": args.program, "seed": str(args.seed), "ref_port": sb.ref_url,
                "clock": "virtual"}
        res = run_bench(sb.dut, sb.ref, sb.clock, args.out, seconds=args.seconds, ref_rate_hz=args.ref_rate_hz,
                        ref_clock=sb.ref_clock,
                        dut_rate_hz=args.dut_rate_hz, session_id=args.session_id, metadata=meta,
                        currents=cur, current_names=names, progress=progress)
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
                            progress=progress)
        finally:
            ref.close()
    print(res.summary())
    return 0
