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
from magstack.data.dictionary import FLAG
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


#: Largest telemetry file streamed (read in blocks: memory does not grow with it).
MAX_TELEMETRY_BYTES = 64 << 30
#: Metadata lines and the header row must end within this many bytes.
MAX_HEADER_BYTES = 1 << 20


def _open(path: str | os.PathLike):
    """The telemetry file, opened under the bounds (:func:`magstack.data.session.open_regular`)."""
    return _session.open_regular(path, "telemetry file", MAX_TELEMETRY_BYTES)


def read_header(path: str | os.PathLike) -> TelemetryHeader:
    """Metadata and column names; SessionFileError if a required column is missing, or the file is not a
    regular file (a FIFO or /dev/zero never blocks nor fills memory: at most ``MAX_HEADER_BYTES`` are read)."""
    name = str(path)
    meta: dict[str, str] = {}
    with _open(path) as fh:
        try:
            head = fh.read(MAX_HEADER_BYTES)
        except OSError as exc:
            raise SessionFileError(f"{name}: cannot read ({exc.strerror or exc})") from None
    if head.startswith(b"\xef\xbb\xbf"):                 # a byte-order mark is accepted, as by read_session
        head = head[3:]
    lines = head.split(b"\n")
    complete = lines if len(head) < MAX_HEADER_BYTES else lines[:-1]     # the last piece may be cut by the limit
    cols = None
    lineno = 0
    try:
        for raw in complete:
            lineno += 1
            line = raw.decode("utf-8")
            if line.startswith("#"):
                body = line[1:].strip()
                if ":" in body:
                    k, v = body.split(":", 1)
                    meta[k.strip()] = v.strip()
                continue
            cols = tuple(c.strip() for c in line.rstrip("\r").split(","))
            break
    except UnicodeDecodeError as exc:
        raise SessionFileError(f"{name}: not a text telemetry file ({exc})") from None
    if cols is None or (cols == ("",) and lineno == len(complete)):
        where = f"within the first {MAX_HEADER_BYTES} bytes " if len(head) >= MAX_HEADER_BYTES else ""
        raise SessionFileError(f"{name}: no header row {where}(file empty or truncated)")
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
    import io

    with io.TextIOWrapper(_open(path), encoding="utf-8-sig", errors="replace") as fh:
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
    with _open(path) as fh:               # a FIFO swapped in after read_header is refused, never read
        try:
            reader = pd.read_csv(fh, skiprows=hdr.header_line, header=None, names=list(cols), comment="#",
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
        odd = np.isfinite(fl) & ((fl != np.round(fl)) | (fl < 0) | (fl >= 2.0 ** 62))
        if odd.any():
            k = int(np.flatnonzero(odd)[0])
            raise SessionFileError(f"{hdr.path}: data row {first + k + 1} after the header (line "
                                   f"{hdr.header_line}): 'flag' must be a non-negative integer (bit set), "
                                   f"got {fl[k]!r}")
        flag = np.where(np.isfinite(fl), fl, 0).astype(np.int64)
    return TelemetryBlock(
        hdr.path, first, col("t_s").copy(), np.column_stack([col(c) for c in DUT_COLUMNS]), col("temp_c").copy(),
        sess.astype(np.int64), np.column_stack([col(c) for c in POS_COLUMNS]),
        np.column_stack([col(c) for c in QUAT_COLUMNS]),
        {m.group(1): col(c).copy() for c in hdr.columns if (m := _CURRENT_RE.match(c))},
        np.column_stack([col(c) for c in REF_COLUMNS]) if hdr.has_ref else None, flag)


# ------------------------------------------------------------------------ ADCS files (magstack merge)
#: Columns of an ADCS file (``magstack merge``): time, position and attitude, as in telemetry.
ADCS_REQUIRED = ("t_s", *POS_COLUMNS, *QUAT_COLUMNS)
#: ``flag`` bit of a merged telemetry row that got no ADCS position/attitude within the tolerance
#: (the flight dictionary's ``NO_ADCS``: one owner per bit).
NO_ADCS_FLAG = FLAG["NO_ADCS"].value


#: ADCS positions must lie between these distances from the Earth's centre (km): not inside the Earth (the
#: WGS84 polar radius, 6356.752 km, less 10 km for the deepest ocean floor) and not beyond the Earth's Hill
#: sphere (about 1.5 million km: nothing farther orbits the Earth).
ADCS_MIN_RADIUS_KM = 6346.0
ADCS_MAX_RADIUS_KM = 1.5e6
#: A quaternion whose norm is off 1 by more than this is refused (scalar last? not a rotation); within it,
#: it is normalised (a logged 1.0009 is rounding, and is written as a unit quaternion).
QUAT_NORM_TOL = 1e-3


@dataclass
class AdcsTrack:
    """Time-ordered ADCS samples of one file: ``t_s`` (N,), ``pos_ecef_km`` (N, 3), ``q_body_eci`` (N, 4)
    scalar first, unit norm; ``dropped`` rows had an empty or non-finite cell (no fix) and are not in the
    arrays (``dropped_lines``: the file lines of the first few)."""

    path: str
    t_s: np.ndarray
    pos_ecef_km: np.ndarray
    q_body_eci: np.ndarray
    dropped: int = 0
    dropped_lines: tuple[int, ...] = ()


def read_adcs(path: str | os.PathLike) -> AdcsTrack:
    """An ADCS file: ``#`` metadata lines, a header with :data:`ADCS_REQUIRED` (other columns ignored),
    rows in time order. Bad cells, a missing column, time going backwards or repeating, a position inside
    the Earth or beyond any Earth orbit (:data:`ADCS_MIN_RADIUS_KM`, :data:`ADCS_MAX_RADIUS_KM`), or a
    quaternion that is not unit (norm off by more than :data:`QUAT_NORM_TOL`: scalar last?) raise
    SessionFileError naming file and line. Quaternions within the tolerance are normalised. Rows with an
    empty or non-finite cell are skipped and counted (``dropped``, ``dropped_lines``)."""
    name = str(path)
    raw = _session.read_file_bytes(path, "ADCS file")
    pos, lineno = 0, 1
    while pos < len(raw):
        end = raw.find(b"\n", pos)
        end = len(raw) if end < 0 else end
        line = raw[pos:end].strip()
        if line and not line.startswith(b"#"):
            break
        pos, lineno = end + 1, lineno + 1
    else:
        raise SessionFileError(f"{name}: no header row (file empty or only comments)")
    try:
        header = [c.strip() for c in line.decode("utf-8").split(",")]
    except UnicodeDecodeError:
        raise SessionFileError(f"{name}: not a text ADCS file") from None
    missing = [c for c in ADCS_REQUIRED if c not in header]
    if missing:
        raise SessionFileError(f"{name}: header (line {lineno}) lacks ADCS columns {missing}")
    body_start = end + 1
    table = _session.parse_table(raw, lineno + 1, header, name, start=body_start)
    cols = [header.index(c) for c in ADCS_REQUIRED]
    a = table[:, cols]
    t = a[:, 0]

    def line_of(k: int) -> int:
        return _session.data_row_line(raw[body_start:], lineno + 1, k)

    if not np.all(np.isfinite(t)):
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise SessionFileError(f"{name}: line {line_of(k)}: column 't_s' is empty or not finite")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        k = int(back[0]) + 1
        raise SessionFileError(f"{name}: line {line_of(k)}: t_s {t[k]!r} does not increase "
                               f"(previous row {t[k - 1]!r}); ADCS rows must be in time order without repeats")
    ok = np.all(np.isfinite(a), axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        r_km = np.linalg.norm(a[:, 1:4], axis=1)
        q = a[:, 4:8]
        qn = np.linalg.norm(q, axis=1)
    far = ok & ~((r_km >= ADCS_MIN_RADIUS_KM) & (r_km <= ADCS_MAX_RADIUS_KM))
    if far.any():
        k = int(np.flatnonzero(far)[0])
        where = "inside the Earth" if r_km[k] < ADCS_MIN_RADIUS_KM else "beyond any Earth orbit"
        raise SessionFileError(f"{name}: line {line_of(k)}: position {r_km[k]:.6g} km from the Earth's centre is "
                               f"{where} (allowed {ADCS_MIN_RADIUS_KM:g}..{ADCS_MAX_RADIUS_KM:g} km; columns "
                               f"pos_ecef_x/y/z_km, Earth-fixed, km); {int(far.sum())} such rows")
    bad_q = ok & (np.abs(qn - 1.0) > QUAT_NORM_TOL)
    if bad_q.any():
        k = int(np.flatnonzero(bad_q)[0])
        raise SessionFileError(f"{name}: line {line_of(k)}: quaternion norm {qn[k]:.6f} is not 1 within "
                               f"{QUAT_NORM_TOL:g} (columns q_body_eci_w,x,y,z, scalar first)")
    skipped = np.flatnonzero(~ok)
    return AdcsTrack(name, t[ok].copy(), a[ok, 1:4].copy(), q[ok] / qn[ok, None], int(skipped.size),
                     tuple(line_of(int(k)) for k in skipped[:5]))
