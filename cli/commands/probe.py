"""``magstack probe [--bus sim | --bus /dev/i2c-1]``: scan and identify the magnetometers.

Prints one line per device: bus, address, type, identity bytes (hex and ASCII), how it was
identified; in JSON the 7-bit address is a hex string ("0x1e"), as i2cdetect prints it.
``--bus sim`` probes the default simulated bench (:mod:`magstack.sim.i2c_bench`).
Exit status 0 when at least one known magnetometer was found, 1 otherwise.
"""
from __future__ import annotations

from magstack.cli.output import CommandResult
from magstack.drivers.i2c_probe import ProbeResult, driver_for, identity_text, probe


def register(subparsers) -> None:
    p = subparsers.add_parser("probe", help="scan I2C bus(es) and identify magnetometers",
                              description=__doc__.split("\n\n")[0].replace("``", ""))
    p.add_argument("--bus", default="sim", help="'sim' (default simulated bench) or an I2C bus: 1 or /dev/i2c-1")
    p.set_defaults(func=run)


def probe_buses(bus_spec: str) -> list[tuple[str, ProbeResult]]:
    """(bus name, result) for every device on ``bus_spec``'s bus(es)."""
    from magstack.drivers.registry import i2c_buses

    buses = i2c_buses(bus_spec)
    try:
        return [(name, r) for name, bus in buses for r in probe(bus)]
    finally:
        for _, bus in buses:
            bus.close()


def table_lines(header: list[str], rows: list[list[str]]) -> list[str]:
    """Left-aligned columns as wide as their widest cell (the last column is not padded)."""
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows, strict=False)]
    return ["  ".join(f"{str(c):<{w}}" for c, w in zip(r[:-1], widths, strict=False)) + "  " + str(r[-1])
            for r in [header, *rows]]


def run(args) -> CommandResult:
    found = probe_buses(args.bus)
    lines = table_lines(["bus", "addr", "type", "identity", "notes"],
                        [[name, f"{r.address:#04x}", r.chip or "unknown", identity_text(r), r.notes]
                         for name, r in found])
    known = [r for _, r in found if driver_for(r.chip) is not None]   # 'hmc5883l_or_hmc5983' counts
    if not known:
        lines.append(f"no supported magnetometer found on {args.bus}")
    devices = [{"bus": name, "address": f"0x{r.address:02x}", "chip": r.chip, "identity_hex": r.identity.hex(),
                "notes": r.notes} for name, r in found]
    return CommandResult("probe", {"bus": args.bus, "devices": devices, "supported_found": len(known)}, lines,
                         0 if known else 1)
