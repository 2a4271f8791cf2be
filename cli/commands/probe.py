"""``magstack probe [--bus sim | --bus /dev/i2c-1]``: scan and identify the magnetometers.

Prints one line per device: bus, address, type, identity bytes (hex and ASCII), how it was
identified. ``--bus sim`` probes the default simulated bench (:mod:`magstack.sim.i2c_bench`).
Exit status 0 when at least one known magnetometer was found, 1 otherwise.
"""
from __future__ import annotations

from magstack.cli.output import CommandResult
from magstack.drivers.i2c_probe import PROBE_TABLE_HEADER, ProbeResult, driver_for, format_probe_result, probe


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


def run(args) -> CommandResult:
    found = probe_buses(args.bus)
    lines = [PROBE_TABLE_HEADER] + [format_probe_result(name, r) for name, r in found]
    known = [r for _, r in found if driver_for(r.chip) is not None]   # 'hmc5883l_or_hmc5983' counts
    if not known:
        lines.append(f"no supported magnetometer found on {args.bus}")
    devices = [{"bus": name, "address": r.address, "chip": r.chip, "identity_hex": r.identity.hex(),
                "notes": r.notes} for name, r in found]
    return CommandResult("probe", {"bus": args.bus, "devices": devices, "supported_found": len(known)}, lines,
                         0 if known else 1)
