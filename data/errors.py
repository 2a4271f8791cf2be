"""Data-layer branch of the exception tree: session and telemetry files."""
from __future__ import annotations

from magstack.errors import EXIT_DEVICE, InputDataError, MagError


class SessionFileError(InputDataError):
    """A session file is corrupt, truncated or not in a supported format."""


class FileWriteError(MagError, OSError):
    """An output file could not be written (file too large, disk full, permissions); names the file."""

    exit_code = EXIT_DEVICE
