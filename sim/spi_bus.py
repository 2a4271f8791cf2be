"""Simulated SPI device implementing ``transfer(tx) -> rx``.

The bus checks that the driver configured the SPI mode the chip requires and that
the clock is within the chip's limit: a wrong mode is a driver bug and fails loudly.
"""
from __future__ import annotations

from typing import Protocol

from magstack.drivers.errors import BusError


class SpiTarget(Protocol):
    required_mode: int
    max_clock_hz: int

    def spi_transfer(self, tx: bytes) -> bytes:
        """One CS-low window: return as many bytes as clocked out."""


class SimSpiBus:
    def __init__(self, target: SpiTarget, *, mode: int, max_speed_hz: int, name: str = "sim-spi0.0") -> None:
        self.target = target
        self.mode = mode
        self.max_speed_hz = max_speed_hz
        self.name = name
        self._fail_next = 0
        self.transfer_count = 0

    def inject_fault(self, count: int = 1) -> None:
        """Make the next ``count`` transfers raise BusError (e.g. a cable fault)."""
        self._fail_next += count

    def transfer(self, tx: bytes) -> bytes:
        self.transfer_count += 1
        if self._fail_next > 0:
            self._fail_next -= 1
            raise BusError("injected SPI fault", address=self.name, operation="transfer")
        if self.mode != self.target.required_mode:
            raise BusError(f"SPI mode {self.mode} but chip needs mode {self.target.required_mode}",
                           address=self.name, operation="transfer")
        if self.max_speed_hz > self.target.max_clock_hz:
            raise BusError(f"SPI clock {self.max_speed_hz} Hz above chip limit {self.target.max_clock_hz} Hz",
                           address=self.name, operation="transfer")
        rx = self.target.spi_transfer(bytes(tx))
        if len(rx) != len(tx):
            raise AssertionError("simulated SPI target returned a wrong length")
        return bytes(rx)
