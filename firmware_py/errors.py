"""On-board branch of the exception tree: calibration fits and calibration tables."""
from __future__ import annotations

from magstack.errors import InputDataError


class CalTableInvalid(InputDataError):
    """A calibration table failed loading or validation; the active table stays in force."""


class FitError(InputDataError):
    """A calibration fit cannot be done with the given data / model."""


class NoValidityRegion(FitError):
    """The fit ran, but its predictive sd exceeds the validity bound even at the data's centre: no table region
    can be defended (the command's answer is negative: exit 1, nothing written)."""

    exit_code = 1


class FlightConfigError(InputDataError):
    """The flight configuration file is invalid (names the file and the key)."""
