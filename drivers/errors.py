"""One typed exception tree for the whole stack.

Every error raised on purpose by magstack derives from :class:`MagError`, so a flight
loop can catch ``MagError``, count it and keep running, while programming errors
(``TypeError``, ``AssertionError``) still propagate.
"""
from __future__ import annotations


class MagError(Exception):
    """Root of all magstack errors."""


class BusError(MagError, OSError):
    """A bus transaction failed (NACK, I/O error, SPI fault, closed port).

    ``address`` is the 7-bit I2C address, SPI chip-select or port name;
    ``operation`` says what was attempted.
    """

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


class DeviceNotFound(MagError):
    """No known chip answered at the probed location."""


class ConfigurationError(MagError, ValueError):
    """An invalid configuration value (range, rate, mode) was requested."""


class ReadbackMismatch(MagError):
    """A configuration register read back a value other than the one written."""


class DataOverflow(MagError):
    """A sensor reported saturation / overflow for a sample."""


class StaleData(MagError):
    """No new sample is available yet (data-ready not set)."""


class SelfTestFailed(MagError):
    """Self-test response outside its acceptance window."""


class ProtocolError(MagError, ValueError):
    """A garbled or unexpected reply on a serial / command protocol."""


class SessionFileError(MagError, ValueError):
    """A session file is corrupt, truncated or not in a supported format."""


class CalTableInvalid(MagError, ValueError):
    """A calibration table failed loading or validation; the active table stays in force."""


class FitError(MagError, ValueError):
    """A calibration fit cannot be done with the given data / model."""


class AlignmentError(MagError, ValueError):
    """Two streams cannot be aligned (no overlap, data does not determine the parameter)."""
