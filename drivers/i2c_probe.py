"""Scan an I2C bus and identify the magnetometers on it (hardware-facts section 9).

Address 0x1E is shared by the LIS3MDL (SA1 high), HMC5983 (and HMC5883L) and the LSM303DLHC
magnetometer. Identification, in this order:

1. register 0x0F = 0x3D -> LIS3MDL (WHO_AM_I);
2. registers 0x0A..0x0C = 'H','4','3' and 0x0F = 0x3C -> LSM303DLHC (undocumented WHO_AM_I;
   the accelerometer at 0x19 is reported as supporting evidence);
3. 'H','4','3' without 0x3C at 0x0F: an HMC5983 or an HMC5883L. The HMC5883L datasheet (p.11)
   says an invalid address reads as 0 (the part acknowledges), so the temperature registers
   0x31/0x32 tell them apart only one way: a **nonzero** temperature word can only come from an
   HMC5983 -> ``"hmc5983"``. A zero word is what an HMC5883L returns, and also what an HMC5983
   may hold before its temperature sensor (CRA bit 7, off at power-on) has converted, or at
   exactly 25.00 degC -> ``"hmc5883l_or_hmc5983"`` (reported honestly, never guessed). A NACK at
   0x31 (not datasheet behaviour for either part) -> ``"hmc5883l"``. The probe only reads: it
   never sets CRA bit 7, which the HMC5883L requires to stay 0.

A register that a part does not implement may NACK; that counts as "no match", never as a
crash. Only bus-level failures of the scan itself propagate.
"""
from __future__ import annotations

from dataclasses import dataclass

from magstack.drivers.bus.i2c import I2CBus, I2CDevice, I2CWrite
from magstack.drivers.errors import BusError, DeviceNotFound

MAGNETOMETER_ADDRESSES = (0x1C, 0x1E)
LSM303DLHC_ACCEL_ADDRESS = 0x19
#: Probe answer for an 'H43' part that is an HMC5883L or an HMC5983 (cannot tell by reading).
HMC5883L_OR_HMC5983 = "hmc5883l_or_hmc5983"
#: Probe answer -> the driver that can open it (an HMC5883L: the hmc5983 driver, temperature=False).
DRIVER_FOR = {"lis3mdl": "lis3mdl", "lsm303dlhc": "lsm303dlhc", "hmc5983": "hmc5983",
              HMC5883L_OR_HMC5983: "hmc5983"}


def driver_for(chip: str | None) -> str | None:
    """Driver name for a probe answer (None: no driver here, e.g. a known HMC5883L or unknown device)."""
    return DRIVER_FOR.get(chip) if chip is not None else None


@dataclass(frozen=True)
class ProbeResult:
    """One device found: ``chip`` is a driver name, "hmc5883l", "hmc5883l_or_hmc5983" (see module
    docstring), or None (unknown device)."""

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
        # two single-byte reads: at or above 0x0C the pointer returns to 0x00 on this family
        msb, lsb = _read(dev, 0x31), _read(dev, 0x32)
        if msb is None or lsb is None:
            return ProbeResult(address, "hmc5883l", ids, "ID A..C = 'H43', temperature register 0x31/0x32 "
                                                         "NACKed: not an HMC5983")
        if msb + lsb != b"\x00\x00":
            return ProbeResult(address, "hmc5983", ids + msb + lsb, "ID A..C = 'H43', temperature word "
                               f"{(msb + lsb).hex()} nonzero (an HMC5883L reads 0 there)")
        return ProbeResult(address, HMC5883L_OR_HMC5983, ids + msb + lsb,
                           "ID A..C = 'H43', temperature word 0: an HMC5883L, or an HMC5983 whose temperature "
                           "sensor has not converted; use the hmc5983 driver with temperature=False unless "
                           "the part is known")
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
