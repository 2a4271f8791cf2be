"""File helpers shared by every layer that writes results: atomic writes and NumPy-safe JSON.

* :func:`atomic_write_text` - write a whole file so that it appears whole or not at all:
  a temporary file in the same directory, ``fsync``, ``os.replace`` onto the target, ``fsync``
  of the directory (so the rename itself survives a power cut).
* :func:`fsync_dir` - the directory half of that, for writers that stream into their own
  ``.part`` file (``magstack.data.session.SessionWriter``).
* :func:`json_safe` / :func:`to_json` - strict JSON (RFC 8259) from results that hold NumPy
  scalars and arrays, tuples, paths and non-finite floats: NumPy types become Python numbers and
  lists, paths strings, and ``nan``/``inf``/``-inf`` become ``null`` (JSON has no such numbers;
  Python's default ``NaN``/``Infinity`` tokens are rejected by strict parsers).
* :func:`write_error` - an ``OSError`` from writing (``File too large``, ``No space left on
  device``) re-raised as :class:`~magstack.data.errors.FileWriteError` naming the file.
"""
from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from magstack.data.errors import FileWriteError


def write_error(path: str | os.PathLike, exc: OSError) -> FileWriteError:
    """A :class:`FileWriteError` for ``exc`` raised while writing ``path`` (the caller raises it)."""
    err = FileWriteError(f"{path}: cannot write ({exc.strerror or exc})")
    err.errno, err.strerror, err.filename = exc.errno, exc.strerror, str(path)
    return err


def fsync_dir(directory: str | os.PathLike) -> None:
    """``fsync`` a directory so that a rename or a new file in it is durable."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_text(path: str | os.PathLike, text: str, *, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically and durably; returns ``Path(path)``.

    The text goes to ``.<name>.tmp-<pid>`` beside ``path``, is flushed and fsynced, renamed onto
    ``path`` (``os.replace``) and the directory is fsynced. On any failure the temporary file is
    removed and ``path`` is untouched; write errors name the file (:class:`FileWriteError`).
    """
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "w", encoding=encoding, newline="") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
        fsync_dir(p.parent)
    except FileWriteError:
        raise
    except OSError as exc:
        raise write_error(p, exc) from exc
    finally:
        if tmp.exists():
            tmp.unlink()
    return p


def json_safe(x: Any) -> Any:
    """``x`` with NumPy scalars/arrays, tuples and paths made JSON-native and non-finite floats ``None``.

    Mapping keys become strings. Anything else that ``json`` cannot encode is returned as is (and
    ``json.dumps`` then raises ``TypeError`` naming it).
    """
    if isinstance(x, Mapping):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, PurePath):
        return str(x)
    return x


def to_json(obj: Any, **kwargs: Any) -> str:
    """Strict JSON text of ``obj`` after :func:`json_safe` (``allow_nan=False``; kwargs go to ``json.dumps``)."""
    return json.dumps(json_safe(obj), allow_nan=False, **kwargs)
