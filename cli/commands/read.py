"""``magstack read --chip CHIP --bus sim [-n N] [--range UT] [--rate HZ]``: print N readings.

One line per new sample: time (s, the driver clock), field X/Y/Z in uT (``nan`` on an
overflowed axis, flagged ``OVF``), on-chip temperature in degC. Chips come from
:mod:`magstack.drivers.registry`.
"""
from __future__ import annotations

import math

from magstack.drivers.errors import ConfigurationError
from magstack.drivers.registry import chip_names, clock_for, open_chip


def register(subparsers) -> None:
    p = subparsers.add_parser("read", help="print readings from one magnetometer",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--chip", required=True, choices=chip_names())
    p.add_argument("--bus", default="sim", help="'sim' (simulated bench) or an I2C bus: 1 or /dev/i2c-1")
    p.add_argument("-n", type=int, default=10, help="number of readings (default 10)")
    p.add_argument("--range", dest="range_uT", type=float, default=None,
                   help="full-scale range in uT (chip table values, e.g. 400 for the LIS3MDL's +-4 G)")
    p.add_argument("--rate", dest="odr_hz", type=float, default=None, help="output data rate in Hz")
    p.set_defaults(func=run)


def _fmt(v: float | None, width: int = 10, prec: int = 3) -> str:
    if v is None:
        return f"{'-':>{width}}"
    return f"{'nan':>{width}}" if math.isnan(v) else f"{v:{width}.{prec}f}"


def run(args) -> int:
    if args.n < 1:
        raise ConfigurationError(f"-n must be >= 1, got {args.n}")
    config = {}
    if args.range_uT is not None:
        config["range_uT"] = args.range_uT
    if args.odr_hz is not None:
        config["odr_hz"] = args.odr_hz
    if config and args.chip == "hmc1053":
        raise ConfigurationError("--range/--rate do not apply to hmc1053 (fixed analog front end)")
    clock = clock_for(args.bus)
    mag = open_chip(args.chip, args.bus, clock, **config)
    print(f"# {args.chip} on {args.bus}" + "".join(f" {k}={v:g}" for k, v in config.items()))
    print(f"{'t_s':>12} {'x_uT':>10} {'y_uT':>10} {'z_uT':>10} {'temp_c':>8}")
    for _ in range(args.n):
        s = mag.read()
        line = (f"{s.t_s:12.6f} {_fmt(s.b_uT[0])} {_fmt(s.b_uT[1])} {_fmt(s.b_uT[2])} "
                f"{_fmt(s.temp_c, 8, 2)}")
        if s.overflow:
            line += "  OVF " + ",".join("xyz"[i] for i in s.overflow)
        print(line, flush=True)
    return 0
