"""Scan an I2C bus and identify the magnetometers on it (hardware-facts section 9).

Address 0x1E is shared by the LIS3MDL (SA1 high), HMC5983 (and HMC5883L) and the LSM303DLHC
magnetometer. Identification, in this order:

1. register 0x0F = 0x3D -> LIS3MDL (WHO_AM_I);
2. registers 0x0A..0x0C = 'H','4','3' and 0x0F = 0x3C -> LSM303DLHC (undocumented WHO_AM_I;
   the accelerometer at 0x19 is reported as supporting evidence);
3. 'H','4','3' without 0x3C at 0x0F -> HMC5983 when the temperature register 0x31 answers,
   else HMC5883L (not supported by a driver here).

A register that a part does not implement may NACK; that counts as "no match", never as a
crash. Only bus-level failures of the scan itself propagate.
"""
from __future__ import annotations

from dataclasses import dataclass

from magstack.drivers.bus.i2c import I2CBus, I2CDevice, I2CWrite
from magstack.drivers.errors import BusError, DeviceNotFound

MAGNETOMETER_ADDRESSES = (0x1C, 0x1E)
LSM303DLHC_ACCEL_ADDRESS = 0x19


@dataclass(frozen=True)
class ProbeResult:
    """One device found: ``chip`` is a driver name, "hmc5883l", or None (unknown device)."""

    address: int
    chip: str | None
    identity: bytes
    notes: str = ""


#: Column header matching :func:`format_probe_result` lines.
PROBE_TABLE_HEADER = f"{'bus':<12} {'addr':<5} {'type':<11} {'identity':<22} notes"


def identity_text(r: ProbeResult) -> str:
    """Identity bytes as hex and printable ASCII, e.g. ``48 34 33 'H43'``."""
    text = "".join(chr(b) if 0x20 <= b < 0x7F else "." for b in r.identity)
    return f"{r.identity.hex(' ')} '{text}'"


def format_probe_result(bus_name: str, r: ProbeResult) -> str:
    """One fixed-width line: bus, address, chip, identity, notes (columns of PROBE_TABLE_HEADER)."""
    return f"{bus_name:<12} {r.address:#04x}  {(r.chip or 'unknown'):<11} {identity_text(r):<22} {r.notes}"


def scan(bus: I2CBus, addresses=range(0x08, 0x78)) -> list[int]:
    """Addresses that acknowledge an address-only write (like ``i2cdetect -q``)."""
    found = []
    for a in addresses:
        try:
            bus.transfer(a, [I2CWrite(b"")])
        except BusError:
            continue
        found.append(a)
    return found


def _read(dev: I2CDevice, reg: int, n: int = 1) -> bytes | None:
    try:
        return dev.read_registers(reg, n)
    except BusError:
        return None


def identify(bus: I2CBus, address: int, *, present: set[int] | None = None) -> ProbeResult:
    """Identify the device at ``address``; DeviceNotFound if nothing acknowledges there."""
    dev = I2CDevice(bus, address)
    try:
        bus.transfer(address, [I2CWrite(b"")])
        who = _read(dev, 0x0F)
    except BusError as exc:
        # some adapters refuse zero-length messages: a register read also proves presence
        who = _read(dev, 0x0F)
        if who is None:
            raise DeviceNotFound(f"no device acknowledges at {address:#04x}: {exc}") from exc
    if who == b"\x3d" and address in MAGNETOMETER_ADDRESSES:
        return ProbeResult(address, "lis3mdl", who, "WHO_AM_I 0x0F = 0x3D")
    ids = _read(dev, 0x0A, 3)
    if ids == b"H43":
        if who == b"\x3c":
            notes = "IRA..IRC = 'H43', WHO_AM_I 0x0F = 0x3C"
            if present is not None:
                notes += "; accelerometer at 0x19 " + ("present" if LSM303DLHC_ACCEL_ADDRESS in present else "absent")
            return ProbeResult(address, "lsm303dlhc", ids + who, notes)
        temp = _read(dev, 0x31)
        if temp is not None:
            return ProbeResult(address, "hmc5983", ids, "ID A..C = 'H43', temperature register 0x31 answers")
        return ProbeResult(address, "hmc5883l", ids, "ID A..C = 'H43', no temperature register: HMC5883L "
                                                     "(no driver)")
    ident = (who or b"") + (ids or b"")
    return ProbeResult(address, None, ident, "unknown device")


def probe(bus: I2CBus, addresses=range(0x08, 0x78)) -> list[ProbeResult]:
    """Scan ``addresses`` and identify every device that acknowledges.

    The magnetometer addresses (0x1C, 0x1E) are also tried by a register read when the
    address-only scan missed them (adapters without zero-length message support).
    """
    present = scan(bus, addresses)
    pset = set(present)
    results = [identify(bus, a, present=pset) for a in present]
    for a in MAGNETOMETER_ADDRESSES:
        if a in addresses and a not in pset:
            try:
                results.append(identify(bus, a, present=pset))
            except DeviceNotFound:
                continue
    return sorted(results, key=lambda r: r.address)
