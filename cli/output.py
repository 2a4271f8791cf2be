"""What a ``magstack`` command hands back, and how it reaches the user.

A command's ``func(args)`` returns a :class:`CommandResult` (or, for older commands, an int
exit code). :func:`magstack.cli.main.main` then prints either the result's text lines (the
human view) or, with ``--json``, ``to_dict()`` as one strict JSON object (RFC 8259: NaN and
infinities become ``null``; numpy scalars and arrays, paths, tuples and dataclasses are
converted by :func:`json_safe`). Keys of ``to_dict()`` are stable per command; the key set is
pinned in tests/test_cli_conventions.py.

Text meant for a person while a command runs goes through :func:`say` (stdout, silent under
``--json``, printed above an active progress bar); diagnostics go through ``logging`` on stderr
(:func:`configure_logging`, set by ``--verbose/--quiet``). Library modules log; only ``cli/`` prints.
"""
from __future__ import annotations

import dataclasses
import enum
import json
import logging
import math
import sys
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["CommandResult", "json_safe", "dumps", "say", "configure_logging", "set_json_mode"]

_state = {"json": False, "quiet": False}


@dataclass
class CommandResult:
    """A command's answer: ``data`` (stable keys, JSON-safe after :func:`json_safe`), the text a
    person reads (``lines``, printed in order) and the exit code (0 ok, 1 ran but negative)."""

    command: str
    data: dict[str, Any]
    lines: list[str] = field(default_factory=list)
    exit_code: int = 0

    def to_dict(self) -> dict[str, Any]:
        """``{"command", "exit_code", **data}`` with every value JSON-safe."""
        return json_safe({"command": self.command, "exit_code": self.exit_code, **self.data})

    def text(self) -> str:
        return "\n".join(self.lines)


def json_safe(x: Any) -> Any:
    """``x`` as plain JSON types: non-finite floats -> None, numpy -> Python, Path -> str,
    tuples/sets -> lists, dataclasses -> dicts, enums -> their value, bytes -> hex."""
    if x is None or isinstance(x, (bool, str)):
        return x
    np = sys.modules.get("numpy")   # numpy values exist only once numpy is imported: never import it here
    if np is not None:
        if isinstance(x, np.bool_):
            return bool(x)
        if isinstance(x, np.integer):
            return int(x)
        if isinstance(x, np.floating):
            x = float(x)
        elif isinstance(x, np.ndarray):
            return json_safe(x.tolist())
    if isinstance(x, enum.Enum):
        return json_safe(x.value)
    if isinstance(x, int):
        return int(x)
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, (bytes, bytearray)):
        return bytes(x).hex()
    if isinstance(x, Mapping):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, set, frozenset)):
        return [json_safe(v) for v in (sorted(x) if isinstance(x, (set, frozenset)) else x)]
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: json_safe(getattr(x, f.name)) for f in dataclasses.fields(x) if f.repr}
    if hasattr(x, "to_dict"):
        return json_safe(x.to_dict())
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def dumps(x: Any, indent: int | None = 2) -> str:
    """Strict JSON text of ``json_safe(x)`` (never ``NaN``/``Infinity``)."""
    return json.dumps(json_safe(x), indent=indent, allow_nan=False)


def set_json_mode(json_mode: bool, quiet: bool = False) -> None:
    """Called by main: under ``--json`` :func:`say` prints nothing (stdout holds only the JSON)."""
    _state["json"] = bool(json_mode)
    _state["quiet"] = bool(quiet)


def say(text: str = "") -> None:
    """Print a line for a person (stdout). Silent under ``--json``; keeps an active tqdm bar intact."""
    if _state["json"]:
        return
    from tqdm import tqdm

    tqdm.write(text, file=sys.stdout)


def configure_logging(verbose: int = 0, quiet: bool = False) -> None:
    """Log records of ``magstack.*`` to stderr: WARNING by default, INFO with -v, DEBUG with -vv,
    ERROR only with -q. Format: ``magstack: <level>: <message>``."""
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    logger = logging.getLogger("magstack")
    for h in list(logger.handlers):
        if getattr(h, "_magstack_cli", False):
            logger.removeHandler(h)
    handler = _TqdmAwareHandler()
    handler._magstack_cli = True  # type: ignore[attr-defined]
    handler.setFormatter(logging.Formatter("magstack: %(levelname)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False
    warnings.showwarning = _log_warning


def _log_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Python warnings (numpy's ``RuntimeWarning: invalid value encountered``) are details of a
    computation, not messages for the user: logged at DEBUG (``-vv``) instead of written to stderr."""
    logging.getLogger("magstack.warnings").debug("%s:%s: %s: %s", filename, lineno, category.__name__, message)


class _TqdmAwareHandler(logging.Handler):
    """Writes records to the *current* sys.stderr through tqdm.write, so that an active progress
    bar is redrawn below the message instead of being torn."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:  # noqa: BLE001 - logging must never raise
            self.handleError(record)
