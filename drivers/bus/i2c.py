"""I2C transport: one message-list transfer shaped like Linux ``I2C_RDWR``.

``transfer(addr, [I2CWrite(b"\\x28"), I2CRead(6)])`` performs the messages as one
combined transaction (repeated start between them) and returns one ``bytes`` per read
message. Any failure raises :class:`magstack.drivers.errors.BusError` naming address and operation.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from magstack.drivers.errors import BusError


@dataclass(frozen=True)
class I2CWrite:
    """A write message: bytes sent to the device."""

    data: bytes

    def __post_init__(self) -> None:
        object.__setattr__(self, "data", bytes(self.data))


@dataclass(frozen=True)
class I2CRead:
    """A read message: ``length`` bytes clocked from the device."""

    length: int

    def __post_init__(self) -> None:
        if self.length < 1:
            raise ValueError(f"I2C read length must be >= 1, got {self.length}")


I2CMessage = I2CWrite | I2CRead


@runtime_checkable
class I2CBus(Protocol):
    """The one I2C protocol every adapter (real or simulated) implements."""

    def transfer(self, address: int, messages: Sequence[I2CMessage]) -> list[bytes]:
        """Run ``messages`` as one combined transaction; return the data of each read."""


def _check_address(address: int) -> None:
    if not 0x03 <= address <= 0x77:
        raise ValueError(f"7-bit I2C address out of range 0x03..0x77: {address:#x}")


class SMBus2I2CBus:
    """Real adapter: smbus2 ``i2c_msg`` + ``i2c_rdwr`` on ``/dev/i2c-N``.

    The caller creates it (``SMBus2I2CBus(1)``); drivers only receive it.
    """

    def __init__(self, bus: int | str) -> None:
        from smbus2 import SMBus  # imported here: a host without I2C can still use the simulator

        try:
            self._smbus = SMBus(bus)
        except OSError as exc:
            raise BusError(f"cannot open I2C bus {bus!r}: {exc}", address=None, operation="open") from exc
        self.name = f"/dev/i2c-{bus}" if isinstance(bus, int) else str(bus)

    def transfer(self, address: int, messages: Sequence[I2CMessage]) -> list[bytes]:
        from smbus2 import i2c_msg

        _check_address(address)
        msgs = []
        for m in messages:
            msgs.append(i2c_msg.write(address, m.data) if isinstance(m, I2CWrite) else i2c_msg.read(address, m.length))
        try:
            self._smbus.i2c_rdwr(*msgs)
        except OSError as exc:
            raise BusError(f"I2C transfer failed on {self.name}: {exc}", address=address, operation="i2c_rdwr") from exc
        return [bytes(list(raw)) for raw, m in zip(msgs, messages, strict=True) if isinstance(m, I2CRead)]

    def close(self) -> None:
        self._smbus.close()


class I2CDevice:
    """Register access helpers for one device address on an :class:`I2CBus`.

    ``auto_increment_flag`` is ORed into the register address of multi-byte reads
    (0x80 for ST's LIS3MDL); chips that auto-increment on their own use 0.
    """

    def __init__(self, bus: I2CBus, address: int, *, auto_increment_flag: int = 0) -> None:
        _check_address(address)
        self.bus = bus
        self.address = address
        self.auto_increment_flag = auto_increment_flag

    def read_registers(self, register: int, count: int) -> bytes:
        """Read ``count`` consecutive registers starting at ``register``."""
        sub = register | (self.auto_increment_flag if count > 1 else 0)
        (data,) = self.bus.transfer(self.address, [I2CWrite(bytes([sub])), I2CRead(count)])
        if len(data) != count:
            raise BusError(f"short read: {len(data)} of {count} bytes", address=self.address,
                           operation=f"read {register:#04x}")
        return data

    def read_register(self, register: int) -> int:
        return self.read_registers(register, 1)[0]

    def write_register(self, register: int, value: int) -> None:
        if not 0 <= value <= 0xFF:
            raise ValueError(f"register value out of byte range: {value}")
        self.bus.transfer(self.address, [I2CWrite(bytes([register, value]))])

    def update_bits(self, register: int, mask: int, value: int) -> int:
        """Masked read-modify-write; ``value`` is masked too. Returns the new register value."""
        old = self.read_register(register)
        new = (old & ~mask & 0xFF) | (value & mask)
        if new != old:
            self.write_register(register, new)
        return new
