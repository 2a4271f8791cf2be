"""``magstack read --chip CHIP --bus sim [-n N] [--range UT] [--rate HZ]``: print N readings.

One line per new sample: time (s, the driver clock), field X/Y/Z in uT (``nan`` on an
overflowed axis, flagged ``OVF``), on-chip temperature in degC. Chips come from
:mod:`magstack.drivers.registry`.
"""
from __future__ import annotations

import math

from magstack.cli.options import finite_float, int_range
from magstack.cli.output import CommandResult, say
from magstack.drivers.errors import ConfigurationError
from magstack.drivers.registry import chip_names, clock_for, open_chip

#: Most readings one ``read`` prints.
MAX_READINGS = 1_000_000


def register(subparsers) -> None:
    p = subparsers.add_parser("read", help="print readings from one magnetometer",
                              description=__doc__.split("\n\n")[0].replace("``", ""))
    p.add_argument("--chip", required=True, choices=chip_names(), help="chip driver to read")
    p.add_argument("--bus", default="sim", help="'sim' (simulated bench) or an I2C bus: 1 or /dev/i2c-1")
    p.add_argument("-n", type=int_range(1, MAX_READINGS), default=10,
                   help=f"number of readings, 1..{MAX_READINGS} (default 10)")
    p.add_argument("--range", dest="range_uT", type=finite_float(0, 1e5, lo_open=True, unit="uT"), default=None,
                   help="full-scale range in uT (chip table values, e.g. 400 for the LIS3MDL's +-4 G)")
    p.add_argument("--rate", dest="odr_hz", type=finite_float(0, 1e5, lo_open=True, unit="Hz"), default=None,
                   help="output data rate in Hz (chip table values)")
    p.set_defaults(func=run)


def _fmt(v: float | None, width: int = 10, prec: int = 3) -> str:
    if v is None:
        return f"{'-':>{width}}"
    return f"{'nan':>{width}}" if math.isnan(v) else f"{v:{width}.{prec}f}"


def run(args) -> CommandResult:
    config = {}
    if args.range_uT is not None:
        config["range_uT"] = args.range_uT
    if args.odr_hz is not None:
        config["odr_hz"] = args.odr_hz
    if config and args.chip == "hmc1053":
        raise ConfigurationError("--range/--rate do not apply to hmc1053 (fixed analog front end)")
    clock = clock_for(args.bus)
    mag = open_chip(args.chip, args.bus, clock, **config)
    # readings are printed as they arrive (a real bus can be slow); --json collects them
    say(f"# {args.chip} on {args.bus}" + "".join(f" {k}={v:g}" for k, v in config.items()))
    say(f"{'t_s':>12} {'x_uT':>10} {'y_uT':>10} {'z_uT':>10} {'temp_c':>8}")
    samples = []
    for _ in range(args.n):
        s = mag.read()
        samples.append({"t_s": s.t_s, "b_uT": list(s.b_uT), "temp_c": s.temp_c, "overflow": list(s.overflow or ())})
        line = (f"{s.t_s:12.6f} {_fmt(s.b_uT[0])} {_fmt(s.b_uT[1])} {_fmt(s.b_uT[2])} "
                f"{_fmt(s.temp_c, 8, 2)}")
        if s.overflow:
            line += "  OVF " + ",".join("xyz"[i] for i in s.overflow)
        say(line)
    return CommandResult("read", {"chip": args.chip, "bus": args.bus, "config": config, "samples": samples})
