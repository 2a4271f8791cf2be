"""Data-layer branch of the exception tree: session and telemetry files."""
from __future__ import annotations

from magstack.errors import InputDataError


class SessionFileError(InputDataError):
    """A session file is corrupt, truncated or not in a supported format."""
