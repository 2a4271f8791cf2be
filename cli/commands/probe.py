"""``magstack probe [--bus sim | --bus /dev/i2c-1]``: scan and identify the magnetometers.

Prints one line per device: bus, address, type, identity bytes (hex and ASCII), how it was
identified. ``--bus sim`` probes the default simulated bench (:mod:`magstack.sim.i2c_bench`).
Exit status 0 when at least one known magnetometer was found, 1 otherwise.
"""
from __future__ import annotations

from magstack.drivers.i2c_probe import ProbeResult, driver_for, probe


def register(subparsers) -> None:
    p = subparsers.add_parser("probe", help="scan I2C bus(es) and identify magnetometers",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--bus", default="sim", help="'sim' (default simulated bench) or an I2C bus: 1 or /dev/i2c-1")
    p.set_defaults(func=run)


def _ident(r: ProbeResult) -> str:
    text = "".join(chr(b) if 0x20 <= b < 0x7F else "." for b in r.identity)
    return f"{r.identity.hex(' ')} '{text}'"


def format_result(bus_name: str, r: ProbeResult) -> str:
    return f"{bus_name:<12} {r.address:#04x}  {(r.chip or 'unknown'):<11} {_ident(r):<22} {r.notes}"


def probe_buses(bus_spec: str) -> list[tuple[str, ProbeResult]]:
    """(bus name, result) for every device on ``bus_spec``'s bus(es)."""
    from magstack.drivers.registry import i2c_buses

    buses = i2c_buses(bus_spec)
    try:
        return [(name, r) for name, bus in buses for r in probe(bus)]
    finally:
        for _, bus in buses:
            bus.close()


def run(args) -> int:
    found = probe_buses(args.bus)
    print(f"{'bus':<12} {'addr':<5} {'type':<11} {'identity':<22} notes")
    for name, r in found:
        print(format_result(name, r))
    known = [r for _, r in found if driver_for(r.chip) is not None]
    if not known:
        print(f"no supported magnetometer found on {args.bus}")
        return 1
    return 0
