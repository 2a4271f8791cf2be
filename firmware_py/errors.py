"""On-board branch of the exception tree: calibration fits and calibration tables."""
from __future__ import annotations

from magstack.errors import InputDataError


class CalTableInvalid(InputDataError):
    """A calibration table failed loading or validation; the active table stays in force."""


class FitError(InputDataError):
    """A calibration fit cannot be done with the given data / model."""


class FlightConfigError(InputDataError):
    """The flight configuration file is invalid (names the file and the key)."""
