"""Bounded pre-checks of the small JSON inputs commands read (tables, PARAMS.json).

Each check reads the file once through :func:`magstack.data.io.read_json_bounded` before the
layer's own reader parses it: a path that is not a regular file (a directory, ``/dev/zero``, a
FIFO), a file larger than any such document, nesting deeper than the format has, or an integer
with more digits than any field holds is bad input (exit 3, one line naming the file), never a
hang, a MemoryError, an OverflowError or a RecursionError.
"""
from __future__ import annotations

import os

from magstack.data.io import read_json_bounded
from magstack.errors import InputDataError

__all__ = ["check_table_file", "check_params_file"]

#: Bounds of a calibration table file (firmware_py/table_schema.py: MAX_BYTES, MAX_DEPTH).
TABLE_MAX_BYTES = 1 << 20
TABLE_MAX_DEPTH = 8
#: Bounds of an error-model PARAMS.json (simulate --save-params writes depth 4, a few kB).
PARAMS_MAX_BYTES = 1 << 20
PARAMS_MAX_DEPTH = 8
#: Format name and versions of PARAMS.json (ground/diagnose/sim_adapter.py writes version 1).
PARAMS_FORMAT = "magstack-error-params"
PARAMS_VERSIONS = (1,)
#: Largest magnitude of any number in PARAMS.json (the presets' largest is a ~3.3e3 uT cross-axis field).
PARAMS_MAX_ABS = 1e6
#: Longest integer any of these documents holds (a CRC-32 has 10 digits, a seed 20).
MAX_INT_DIGITS = 20


def check_table_file(path: str | os.PathLike) -> None:
    """InputDataError unless ``path`` is a regular file within a calibration table's bounds."""
    read_json_bounded(path, max_bytes=TABLE_MAX_BYTES, max_depth=TABLE_MAX_DEPTH, max_int_digits=MAX_INT_DIGITS,
                      what="calibration table")


def check_params_file(path: str | os.PathLike) -> None:
    """InputDataError unless ``path`` is a regular file within an error-model PARAMS.json's bounds:
    a format version this reader knows, and no number beyond :data:`PARAMS_MAX_ABS` (an axis delay of
    1e300 s is a corrupt file, not a sensor)."""
    doc = read_json_bounded(path, max_bytes=PARAMS_MAX_BYTES, max_depth=PARAMS_MAX_DEPTH,
                            max_int_digits=MAX_INT_DIGITS, what="parameter file")
    if isinstance(doc, dict) and doc.get("format") == PARAMS_FORMAT and doc.get("version") not in PARAMS_VERSIONS:
        raise InputDataError(f"{path}: parameter file version {doc.get('version')!r} is not one this reader knows "
                             f"({', '.join(map(str, PARAMS_VERSIONS))})")
    for where, v in _numbers(doc):
        if abs(v) > PARAMS_MAX_ABS:
            raise InputDataError(f"{path}: {where} = {v:g} is beyond any physical sensor parameter "
                                 f"(|value| <= {PARAMS_MAX_ABS:g})")


def _numbers(x, where: str = ""):
    """(path, value) of every number in a JSON document."""
    if isinstance(x, dict):
        for k, v in x.items():
            yield from _numbers(v, f"{where}.{k}" if where else str(k))
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from _numbers(v, f"{where}[{i}]")
    elif isinstance(x, (int, float)) and not isinstance(x, bool):
        yield where, x
