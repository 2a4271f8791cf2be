"""Ground-analysis branch of the exception tree."""
from __future__ import annotations

from magstack.errors import InputDataError


class GroundError(InputDataError):
    """Ground analysis cannot answer with the given data."""


class AlignmentError(GroundError):
    """Two streams cannot be aligned (no overlap, data does not determine the parameter)."""


class DiagnosisError(GroundError):
    """The gap diagnosis cannot run on the given data (too few usable rows, no prediction)."""
