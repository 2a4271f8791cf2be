"""Simulated I2C bus implementing the same ``transfer`` protocol as the smbus2 adapter.

Devices attach at an address; an absent address NACKs with :class:`BusError`. The bus
can inject a NACK on the next N transfers to a given address.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from magstack.drivers.bus.i2c import I2CMessage, I2CRead, I2CWrite, _check_address
from magstack.drivers.errors import BusError


class I2CTarget(Protocol):
    """A simulated device on the bus. Raise BusError to NACK."""

    def i2c_start(self) -> None:
        """A (repeated-)start addressed to this device begins a transaction."""

    def i2c_write(self, data: bytes) -> None:
        """Bytes written by the controller in one write message."""

    def i2c_read(self, length: int) -> bytes:
        """Bytes returned for one read message."""


class SimI2CBus:
    """An address map of simulated devices; duplicate addresses are refused."""

    def __init__(self, name: str = "sim-i2c") -> None:
        self.name = name
        self._devices: dict[int, I2CTarget] = {}
        self._nack_next: dict[int, int] = {}
        self.transfer_count = 0

    def close(self) -> None:
        """Nothing to release (same interface as the real adapter)."""

    def attach(self, address: int, device: I2CTarget) -> None:
        _check_address(address)
        if address in self._devices:
            raise ValueError(f"address {address:#04x} already taken on {self.name}")
        self._devices[address] = device

    def detach(self, address: int) -> None:
        self._devices.pop(address)

    def addresses(self) -> list[int]:
        return sorted(self._devices)

    def device(self, address: int) -> I2CTarget:
        return self._devices[address]

    def inject_nack(self, address: int, count: int = 1) -> None:
        """Make the next ``count`` transfers to ``address`` fail with a NACK."""
        self._nack_next[address] = self._nack_next.get(address, 0) + count

    def transfer(self, address: int, messages: Sequence[I2CMessage]) -> list[bytes]:
        _check_address(address)
        self.transfer_count += 1
        dev = self._devices.get(address)
        if dev is None:
            raise BusError(f"no ACK on {self.name}", address=address, operation="address")
        if self._nack_next.get(address, 0) > 0:
            self._nack_next[address] -= 1
            raise BusError(f"injected NACK on {self.name}", address=address, operation="address")
        out: list[bytes] = []
        for msg in messages:
            dev.i2c_start()
            if isinstance(msg, I2CWrite):
                dev.i2c_write(msg.data)
            elif isinstance(msg, I2CRead):
                data = dev.i2c_read(msg.length)
                if len(data) != msg.length:
                    raise AssertionError("simulated device returned a wrong read length")
                out.append(bytes(data))
            else:
                raise TypeError(f"not an I2C message: {msg!r}")
        return out
