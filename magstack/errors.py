"""Root of the one typed exception tree.

Every error magstack raises on purpose derives from :class:`MagError`, so a flight loop can
catch ``MagError``, count it and keep running, while programming errors (``TypeError``,
``AssertionError``) still propagate. Each layer adds its own branch beside the code that
raises it:

* ``magstack.drivers.errors``  - bus, device, configuration, protocol errors
* ``magstack.data.errors``     - session / telemetry files
* ``magstack.firmware.errors`` - calibration fit and calibration tables
* ``magstack.ground.errors``   - ground analysis (alignment, diagnosis, refit studies)

``exit_code`` is the ``magstack`` command's exit status for an error of that class
(the table is in docs/architecture.md): 1 ran but the answer is negative, 2 usage,
3 bad input data, 4 device or system error.
"""
from __future__ import annotations

#: Documented exit codes of the ``magstack`` command.
EXIT_OK = 0
EXIT_NEGATIVE = 1
EXIT_USAGE = 2
EXIT_BAD_DATA = 3
EXIT_DEVICE = 4


class MagError(Exception):
    """Root of all magstack errors."""

    exit_code: int = EXIT_BAD_DATA


class InputDataError(MagError, ValueError):
    """Input data (a file, a record, a value) is malformed or physically impossible.

    ``where`` is a short location such as ``"session.csv:12:4"`` (file, line, column) when known.
    """

    exit_code = EXIT_BAD_DATA
