"""Driver-layer branch of the exception tree (root: :class:`magstack.errors.MagError`).

Bus, device, configuration and protocol errors. Errors of the layers above live beside their
code (``magstack.data.errors``, ``magstack.firmware.errors``, ``magstack.ground.errors``).
"""
from __future__ import annotations

from magstack.errors import EXIT_DEVICE, EXIT_NEGATIVE, EXIT_USAGE, InputDataError, MagError

__all__ = ["MagError", "InputDataError", "BusError", "BusTimeout", "DeviceIdMismatch", "DeviceNotFound",
           "ConfigurationError", "ReadbackMismatch", "DataOverflow", "StaleData", "SelfTestFailed", "ProtocolError"]


class BusError(MagError, OSError):
    """A bus transaction failed (NACK, I/O error, SPI fault, closed port).

    ``address`` is the 7-bit I2C address, SPI chip-select or port name;
    ``operation`` says what was attempted.
    """

    exit_code = EXIT_DEVICE

    def __init__(self, message: str, *, address: object = None, operation: str = "") -> None:
        self.address = address
        self.operation = operation
        where = []
        if address is not None:
            where.append(f"address={address:#04x}" if isinstance(address, int) else f"address={address}")
        if operation:
            where.append(f"op={operation}")
        super().__init__(f"{message} ({', '.join(where)})" if where else message)


class BusTimeout(BusError, TimeoutError):
    """A device did not answer in time (DRDY never asserted, serial read timed out)."""


class DeviceIdMismatch(MagError):
    """The identity registers do not match the expected chip."""

    exit_code = EXIT_DEVICE


class DeviceNotFound(MagError):
    """No known chip answered at the probed location."""

    exit_code = EXIT_NEGATIVE


class ConfigurationError(MagError, ValueError):
    """An invalid configuration value (range, rate, mode) was requested."""

    exit_code = EXIT_USAGE


class ReadbackMismatch(MagError):
    """A configuration register read back a value other than the one written."""

    exit_code = EXIT_DEVICE


class DataOverflow(MagError):
    """A sensor reported saturation / overflow for a sample."""

    exit_code = EXIT_DEVICE


class StaleData(MagError):
    """No new sample is available yet (data-ready not set)."""

    exit_code = EXIT_DEVICE


class SelfTestFailed(MagError):
    """Self-test response outside its acceptance window."""

    exit_code = EXIT_DEVICE


class ProtocolError(MagError, ValueError):
    """A garbled or unexpected reply on a serial / command protocol."""

    exit_code = EXIT_DEVICE
