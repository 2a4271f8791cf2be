"""SPI transport: full-duplex ``transfer(tx) -> rx`` with mode and speed per device.

Chip select is asserted for exactly one ``transfer`` call, so a command and its
read-back that must share one CS-low window go in one call.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

from magstack.drivers.errors import BusError


@runtime_checkable
class SpiBus(Protocol):
    """One SPI device (bus + chip select) as seen by a driver."""

    mode: int
    max_speed_hz: int

    def transfer(self, tx: bytes) -> bytes:
        """Clock ``tx`` out while CS is low; return the same number of bytes clocked in."""


class SpidevSpiBus:
    """Real adapter over ``spidev`` (Linux ``/dev/spidevB.C``)."""

    def __init__(self, bus: int, device: int, *, mode: int, max_speed_hz: int) -> None:
        try:
            import spidev  # only present on Linux hosts with the [pi] extra
        except ImportError as exc:  # pragma: no cover - depends on host
            raise BusError("spidev is not installed: on the Raspberry Pi install the pi extra (pip install "
                           "-e '.[pi]') or Debian's python3-spidev (README, 'On a Raspberry Pi')",
                           address=f"spi{bus}.{device}", operation="open") from exc
        self._dev = spidev.SpiDev()
        try:
            self._dev.open(bus, device)
        except OSError as exc:
            raise BusError(f"cannot open /dev/spidev{bus}.{device}: {exc.strerror or exc} (SPI enabled with "
                           "dtparam=spi=on? user in group spi?)", address=f"spi{bus}.{device}",
                           operation="open") from exc
        self._dev.mode = mode
        self._dev.max_speed_hz = max_speed_hz
        self.mode = mode
        self.max_speed_hz = max_speed_hz
        self.name = f"spi{bus}.{device}"

    def transfer(self, tx: bytes) -> bytes:
        try:
            return bytes(self._dev.xfer2(list(tx)))
        except OSError as exc:  # pragma: no cover - depends on host
            raise BusError(f"SPI transfer failed: {exc}", address=self.name, operation="transfer") from exc

    def close(self) -> None:  # pragma: no cover - depends on host
        self._dev.close()
