"""On-orbit telemetry columns (session file v1 plus position and attitude) and a chunked reader.

A telemetry file is a v1 session file (docs/session-file.md) whose rows also carry

* ``pos_ecef_x_km, pos_ecef_y_km, pos_ecef_z_km``: position, Earth-fixed frame (ITRS/WGS84), km;
* ``q_body_eci_w, q_body_eci_x, q_body_eci_y, q_body_eci_z``: unit quaternion, scalar first, of the
  rotation taking GCRS components to body components
  (``b_body = Rotation.from_quat([x, y, z, w]).apply(b_eci)``).

and in which the ``ref_*_uT`` columns are optional (a simulator writes the true field there for
scoring; flight telemetry has none). Required: ``t_s`` (Unix s, UTC), ``dut_x/y/z_uT``, ``temp_c``,
``session``, the position and attitude columns; any ``current_<name>_A`` (empty cells where the
housekeeping channel was not sampled at that row's instant); optional ``flag``.

:func:`iter_telemetry` reads a file block by block (memory independent of its length). Parsing
uses pandas' C reader; a cell that is not a number, an infinity or a bad row length raises
:class:`SessionFileError` naming file, line and column.
"""
from __future__ import annotations

import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from magstack.data import session as _session
from magstack.data.errors import SessionFileError

POS_COLUMNS = ("pos_ecef_x_km", "pos_ecef_y_km", "pos_ecef_z_km")
QUAT_COLUMNS = ("q_body_eci_w", "q_body_eci_x", "q_body_eci_y", "q_body_eci_z")
DUT_COLUMNS = ("dut_x_uT", "dut_y_uT", "dut_z_uT")
REF_COLUMNS = ("ref_x_uT", "ref_y_uT", "ref_z_uT")
#: Columns every telemetry file has.
TELEMETRY_REQUIRED = ("t_s", *DUT_COLUMNS, "temp_c", "session", *POS_COLUMNS, *QUAT_COLUMNS)
#: Column meanings (session file v1 carries them as extra numeric columns, ``Session.extra``).
TELEMETRY_COLUMNS = {
    **{c: f"position {c[9]}, Earth-fixed frame (ITRS/WGS84), km" for c in POS_COLUMNS},
    **{c: f"attitude quaternion {c[-1]} (scalar first), GCRS -> body" for c in QUAT_COLUMNS},
}
_CURRENT_RE = re.compile(r"^current_([A-Za-z0-9_]+)_A$")
#: Rows per block read by default.
BLOCK_ROWS = 16384


@dataclass
class TelemetryBlock:
    """Rows ``first_row .. first_row + N`` (0-based data rows) of one file; arrays of length N."""

    path: str
    first_row: int
    t_s: np.ndarray
    dut_uT: np.ndarray
    temp_c: np.ndarray
    session: np.ndarray
    pos_ecef_km: np.ndarray
    q_body_eci: np.ndarray             # (N, 4) scalar first
    currents_A: dict[str, np.ndarray] = field(default_factory=dict)
    ref_uT: np.ndarray | None = None
    flag: np.ndarray | None = None

    def __len__(self) -> int:
        return self.t_s.size

    def select(self, mask: np.ndarray) -> TelemetryBlock:
        return TelemetryBlock(self.path, self.first_row, self.t_s[mask], self.dut_uT[mask], self.temp_c[mask],
                              self.session[mask], self.pos_ecef_km[mask], self.q_body_eci[mask],
                              {k: v[mask] for k, v in self.currents_A.items()},
                              None if self.ref_uT is None else self.ref_uT[mask],
                              None if self.flag is None else self.flag[mask])

    @staticmethod
    def concatenate(parts: list[TelemetryBlock]) -> TelemetryBlock:
        p0 = parts[0]
        cat = np.concatenate
        return TelemetryBlock(p0.path, p0.first_row, cat([p.t_s for p in parts]), cat([p.dut_uT for p in parts]),
                              cat([p.temp_c for p in parts]), cat([p.session for p in parts]),
                              cat([p.pos_ecef_km for p in parts]), cat([p.q_body_eci for p in parts]),
                              {k: cat([p.currents_A[k] for p in parts]) for k in p0.currents_A},
                              None if p0.ref_uT is None else cat([p.ref_uT for p in parts]),
                              None if p0.flag is None else cat([p.flag for p in parts]))


@dataclass(frozen=True)
class TelemetryHeader:
    path: str
    metadata: dict
    columns: tuple[str, ...]
    header_line: int                   # 1-based line number of the column header

    @property
    def currents(self) -> tuple[str, ...]:
        return tuple(m.group(1) for c in self.columns if (m := _CURRENT_RE.match(c)))

    @property
    def has_ref(self) -> bool:
        return all(c in self.columns for c in REF_COLUMNS)


def read_header(path: str | os.PathLike) -> TelemetryHeader:
    """Metadata and column names; SessionFileError if a required column is missing."""
    name = str(path)
    meta: dict[str, str] = {}
    try:
        with open(path, encoding="utf-8-sig") as fh:   # a byte-order mark is accepted, as by read_session
            lineno = 0
            for line in fh:
                lineno += 1
                if line.startswith("#"):
                    body = line[1:].strip()
                    if ":" in body:
                        k, v = body.split(":", 1)
                        meta[k.strip()] = v.strip()
                    continue
                cols = tuple(c.strip() for c in line.rstrip("\n").split(","))
                break
            else:
                raise SessionFileError(f"{name}: no header row (file empty or truncated)")
    except FileNotFoundError:
        raise SessionFileError(f"{name}: no such telemetry file") from None
    except UnicodeDecodeError as exc:
        raise SessionFileError(f"{name}: not a text telemetry file ({exc})") from None
    except OSError as exc:
        raise SessionFileError(f"{name}: cannot read ({exc.strerror or exc})") from None
    if meta.get(_session.FORMAT_KEY) not in (None, _session.FORMAT_VERSION):
        raise SessionFileError(f"{name}: unsupported session format version {meta[_session.FORMAT_KEY]!r}")
    missing = [c for c in TELEMETRY_REQUIRED if c not in cols]
    if missing:
        raise SessionFileError(f"{name}: header (line {lineno}) lacks telemetry columns {missing}")
    if len(set(cols)) != len(cols):
        raise SessionFileError(f"{name}: duplicate column names in header")
    return TelemetryHeader(name, meta, cols, lineno)


def _locate_bad_cell(path: str, header: TelemetryHeader, first_row: int, n_rows: int) -> SessionFileError:
    """Slow scan of rows first_row .. first_row + n_rows for the first bad cell (exact line and column)."""
    with open(path, encoding="utf-8-sig") as fh:
        lineno, row = 0, -1
        for line in fh:
            lineno += 1
            if lineno <= header.header_line or line.startswith("#") or not line.strip():
                continue
            row += 1
            if row < first_row:
                continue
            if row >= first_row + n_rows:
                break
            cells = line.rstrip("\n").split(",")
            if len(cells) != len(header.columns):
                return SessionFileError(f"{path}: line {lineno}: {len(cells)} cells, header has "
                                        f"{len(header.columns)}")
            for c, cell in zip(header.columns, cells, strict=True):
                _session._parse_float(cell, lineno, c, path)   # raises on a bad cell
    return SessionFileError(f"{path}: rows {first_row + 1}..{first_row + n_rows} after the header: unreadable")


def iter_telemetry(path: str | os.PathLike, block_rows: int = BLOCK_ROWS) -> Iterator[TelemetryBlock]:
    """Blocks of at most ``block_rows`` rows, in file order (memory independent of the file length)."""
    import pandas as pd

    hdr = read_header(path)
    name = str(path)
    cols = hdr.columns
    try:
        reader = pd.read_csv(name, skiprows=hdr.header_line, header=None, names=list(cols), comment="#",
                             chunksize=int(block_rows), dtype=np.float64, na_values=["", "nan", "NaN"],
                             keep_default_na=False, skip_blank_lines=True, engine="c")
        first = 0
        for chunk in reader:
            a = chunk.to_numpy(dtype=np.float64, copy=False)
            if a.shape[1] != len(cols):
                raise _locate_bad_cell(name, hdr, first, a.shape[0])
            if np.isinf(a).any():
                r, c = np.argwhere(np.isinf(a))[0]
                raise _locate_bad_cell(name, hdr, first + int(r), 1)
            yield _block(hdr, first, a)
            first += a.shape[0]
    except (ValueError, pd.errors.ParserError) as exc:
        if isinstance(exc, SessionFileError):
            raise
        raise _locate_bad_cell(name, hdr, 0, 2 ** 62) from None


def _block(hdr: TelemetryHeader, first: int, a: np.ndarray) -> TelemetryBlock:
    idx = {c: k for k, c in enumerate(hdr.columns)}

    def col(c):
        return a[:, idx[c]]

    sess = col("session")
    bad = ~np.isfinite(sess) | (sess != np.round(sess))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise SessionFileError(f"{hdr.path}: data row {first + k + 1} after the header (line "
                               f"{hdr.header_line}): 'session' must be an integer, got {sess[k]!r}")
    flag = None
    if "flag" in idx:
        fl = col("flag")
        flag = np.where(np.isfinite(fl), fl, 0).astype(np.int64)
    return TelemetryBlock(
        hdr.path, first, col("t_s").copy(), np.column_stack([col(c) for c in DUT_COLUMNS]), col("temp_c").copy(),
        sess.astype(np.int64), np.column_stack([col(c) for c in POS_COLUMNS]),
        np.column_stack([col(c) for c in QUAT_COLUMNS]),
        {m.group(1): col(c).copy() for c in hdr.columns if (m := _CURRENT_RE.match(c))},
        np.column_stack([col(c) for c in REF_COLUMNS]) if hdr.has_ref else None, flag)
