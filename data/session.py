"""Session file v1: the CSV every bench, simulation, fit and apply step reads and writes.

Layout (documented in docs/session-file.md)::

    # magstack-session: 1
    # dut_chip: hmc1053
    # ... more "# key: value" metadata lines ...
    t_s,ref_x_uT,ref_y_uT,ref_z_uT,dut_x_uT,dut_y_uT,dut_z_uT,temp_c,session[,current_<name>_A ...][,<extra> ...][,flag]
    1598371866.645000,0.575000,...
    # magstack-end: rows=N crc32=0x1234abcd

``t_s`` is Unix epoch seconds (UTC); fields in uT; ``temp_c`` in degC; ``session`` an integer
run id. Empty cells and ``nan`` mean "no value" (gaps); every other cell must be a plain decimal
number (``[+-]digits[.digits][e[+-]digits]``). Other numeric columns (``<extra>``, names
``[A-Za-z_][A-Za-z0-9_]*``) are kept in ``Session.extra`` and written back. Writing is
crash-safe: rows go to ``<out>.part``, flushed and fsynced per block; on close a closing line
with the row count and the CRC-32 of the row bytes is written and the file is renamed to
``<out>``; a killed session leaves a ``.part`` file whose every complete row is readable.

Reading is vectorised (``numpy.loadtxt`` on the rows after a byte-level check that every cell can
only be a plain decimal or a gap); any file the fast path does not take is read by the
line-by-line parser, which is the reference and names file, line and column of a bad cell.
"""
from __future__ import annotations

import io
import logging
import math
import os
import re
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magstack.data.errors import SessionFileError
from magstack.data.io import fsync_dir, open_bounded, read_bytes_bounded, write_error
from magstack.drivers.errors import ConfigurationError
from magstack.errors import InputDataError

_log = logging.getLogger(__name__)

FORMAT_KEY = "magstack-session"
FORMAT_VERSION = "1"
#: Key of the closing line ``# magstack-end: rows=N crc32=0x........`` written by ``SessionWriter.close``.
END_KEY = "magstack-end"
REQUIRED_COLUMNS = ("t_s", "ref_x_uT", "ref_y_uT", "ref_z_uT", "dut_x_uT", "dut_y_uT", "dut_z_uT",
                    "temp_c", "session")
_CURRENT_RE = re.compile(r"^current_([A-Za-z0-9_]+)_A$")
_EXTRA_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: A cell is empty / ``nan`` (a gap) or a plain decimal number matching this (after stripping blanks).
DECIMAL_RE = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
#: Optional non-current columns that v1 readers understand.
OPTIONAL_COLUMNS = ("flag",)
_BOM = b"\xef\xbb\xbf"
#: Physical range of the field columns (uT): 0.1 T, far beyond every sensor of the stack (LIS3MDL
#: +-1600 uT at its widest); a value outside is a corrupt cell, not a measurement.
FIELD_LIMIT_UT = 1e5
#: Physical range of ``temp_c`` (degC): absolute zero .. far beyond any electronics.
TEMP_RANGE_C = (-273.15, 500.0)
_END_PREFIX = f"# {END_KEY}:".encode()
_END_RE = re.compile(r"#\s*magstack-end:\s*rows=(\d+)\s+crc32=0x([0-9a-fA-F]{8})\s*")
#: Bytes a body of plain decimals and gaps consists of (fast path); ``nan`` letters checked apart.
_PLAIN_BYTES = b"0123456789.,+-eE \t\r\n"
_NAN_BYTES = b"naNA"
_SIGNED_NAN_RE = re.compile(rb"[+-][ \t]*[nN]")


@dataclass
class Session:
    """A session in memory. Arrays share one length N.

    ``ref_uT``/``dut_uT`` are (N, 3); ``currents_A`` maps a current's name to an (N,) array;
    ``flag`` is an (N,) int array (0 = ok) or None; ``metadata`` preserves order; ``extra`` maps
    the header name of any other numeric column (telemetry, ...) to an (N,) float array;
    ``source`` is the file the session was read from ("" when built in memory).
    """

    t_s: np.ndarray
    ref_uT: np.ndarray
    dut_uT: np.ndarray
    temp_c: np.ndarray
    session: np.ndarray
    currents_A: dict[str, np.ndarray] = field(default_factory=dict)
    metadata: dict[str, str] = field(default_factory=dict)
    flag: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = ""

    def __post_init__(self) -> None:
        self.t_s = np.asarray(self.t_s, dtype=float).reshape(-1)
        n = self.t_s.size
        self.ref_uT = np.asarray(self.ref_uT, dtype=float).reshape(n, 3)
        self.dut_uT = np.asarray(self.dut_uT, dtype=float).reshape(n, 3)
        self.temp_c = np.asarray(self.temp_c, dtype=float).reshape(n)
        self.session = np.asarray(self.session).astype(np.int64).reshape(n)
        self.currents_A = {k: np.asarray(v, dtype=float).reshape(n) for k, v in self.currents_A.items()}
        for name in self.currents_A:
            if not re.fullmatch(r"[A-Za-z0-9_]+", name):
                raise ValueError(f"current name must be [A-Za-z0-9_]+: {name!r}")
        self.extra = {k: np.asarray(v, dtype=float).reshape(n) for k, v in self.extra.items()}
        taken = set(REQUIRED_COLUMNS) | set(OPTIONAL_COLUMNS) | {f"current_{k}_A" for k in self.currents_A}
        for name in self.extra:
            if not _EXTRA_RE.fullmatch(name) or name in taken or _CURRENT_RE.match(name):
                raise ValueError(f"extra column name must be [A-Za-z_][A-Za-z0-9_]* and not a v1 column: {name!r}")
        if self.flag is not None:
            self.flag = np.asarray(self.flag).astype(np.int64).reshape(n)
        self.metadata = {str(k): str(v) for k, v in self.metadata.items()}

    def __len__(self) -> int:
        return self.t_s.size

    @property
    def columns(self) -> list[str]:
        cols = list(REQUIRED_COLUMNS) + [f"current_{k}_A" for k in self.currents_A] + list(self.extra)
        if self.flag is not None:
            cols.append("flag")
        return cols

    def select(self, mask: np.ndarray) -> Session:
        """A new Session with the rows where ``mask`` is true (or at the given row indices)."""
        return Session(self.t_s[mask], self.ref_uT[mask], self.dut_uT[mask], self.temp_c[mask],
                       self.session[mask], {k: v[mask] for k, v in self.currents_A.items()},
                       dict(self.metadata), None if self.flag is None else self.flag[mask], list(self.warnings),
                       {k: v[mask] for k, v in self.extra.items()}, self.source)

    @staticmethod
    def concatenate(parts: Sequence[Session]) -> Session:
        """Join sessions row-wise; current and extra columns must match; metadata of the first is kept."""
        if not parts:
            raise ValueError("nothing to concatenate")
        names = list(parts[0].currents_A)
        extras = list(parts[0].extra)
        for p in parts[1:]:
            if list(p.currents_A) != names:
                raise SessionFileError(f"current columns differ: {names} vs {list(p.currents_A)}")
            if list(p.extra) != extras:
                raise SessionFileError(f"extra columns differ: {extras} vs {list(p.extra)}")
        flags = None
        if any(p.flag is not None for p in parts):
            flags = np.concatenate([p.flag if p.flag is not None else np.zeros(len(p), np.int64) for p in parts])
        return Session(np.concatenate([p.t_s for p in parts]), np.vstack([p.ref_uT for p in parts]),
                       np.vstack([p.dut_uT for p in parts]), np.concatenate([p.temp_c for p in parts]),
                       np.concatenate([p.session for p in parts]),
                       {k: np.concatenate([p.currents_A[k] for p in parts]) for k in names},
                       dict(parts[0].metadata), flags,
                       extra={k: np.concatenate([p.extra[k] for p in parts]) for k in extras})


# ---------------------------------------------------------------------------------------- writing
def _check_metadata(metadata: Mapping[str, str]) -> None:
    for k, v in metadata.items():
        if not re.fullmatch(r"[A-Za-z0-9_.\-]+", str(k)):
            raise ValueError(f"metadata key must be [A-Za-z0-9_.-]+: {k!r}")
        if "\n" in str(v) or "\r" in str(v):
            raise ValueError(f"metadata value for {k!r} must be one line")


class SessionWriter:
    """Streaming, crash-safe writer. Use as a context manager.

    Rows are buffered and written, flushed and fsynced every ``block_rows`` rows (and on
    :meth:`flush`/:meth:`close`); each block is formatted in one vectorised step. On clean close
    the closing line (row count, CRC-32 of the row bytes) is written and ``<path>.part`` is renamed
    to ``path``. A write that fails (file too large, disk full) raises
    :class:`~magstack.data.errors.FileWriteError` naming the ``.part`` file. Extra columns named in
    ``integer_extras`` hold integers (a table CRC-32, a count) and are written without decimals.
    """

    def __init__(self, path: str | os.PathLike, metadata: Mapping[str, str] | None = None, *,
                 current_names: Sequence[str] = (), with_flag: bool = False, block_rows: int = 50,
                 extra_names: Sequence[str] = (), integer_extras: Sequence[str] = ()) -> None:
        self.path = Path(path)
        if not self.path.name or self.path.is_dir():
            raise SessionFileError(f"{path}: is a directory, not a session file name")
        if not self.path.parent.is_dir():
            raise SessionFileError(f"{path}: directory {self.path.parent} does not exist")
        self.part_path = self.path.with_name(self.path.name + ".part")
        self.current_names = list(current_names)
        self.extra_names = list(extra_names)
        _empty_session(self.current_names, self.extra_names)   # ValueError for a bad column name
        self.with_flag = with_flag
        self.block_rows = max(1, int(block_rows))
        meta = {FORMAT_KEY: FORMAT_VERSION, **{k: v for k, v in (metadata or {}).items() if k != FORMAT_KEY}}
        _check_metadata(meta)
        cols = (list(REQUIRED_COLUMNS) + [f"current_{n}_A" for n in self.current_names] + self.extra_names
                + (["flag"] if with_flag else []))
        # integer_extras (a CRC-32, a count) are written without decimals ("%.0f": an empty cell stays empty)
        extra_fmt = ["%.0f" if n in set(integer_extras) else "%.6f" for n in self.extra_names]
        self._row_fmt = ",".join(["%.6f"] * 7 + ["%.4f", "%d"] + ["%.6f"] * len(self.current_names) + extra_fmt
                                 + (["%d"] if with_flag else [])) + "\n"
        self._int_cols = [8] + ([len(cols) - 1] if with_flag else [])
        self._ncols = len(cols)
        self._buf: list[tuple[float, ...]] = []
        self._crc = 0
        self.rows_written = 0
        self._size = 0                      # bytes of whole writes in the file (a failed write is cut back to it)
        try:
            # exclusive: never truncate the .part left by an earlier, killed session; unbuffered: each block is
            # one write, so a failed one can be cut back off the file (no partial row stays in it)
            self._fh = open(self.part_path, "xb", buffering=0)
        except FileExistsError:
            raise SessionFileError(f"{self.part_path} exists (left by an interrupted session?): "
                                   "read, rename or remove it first") from None
        header = "".join(f"# {k}: {v}\n" for k, v in meta.items())
        self._write((header + ",".join(cols) + "\n").encode("utf-8"))
        self._sync()

    def _write(self, data: bytes) -> None:
        """Write ``data`` whole, or cut what was written of it back off the file and raise FileWriteError."""
        view, done = memoryview(data), 0
        try:
            while done < len(data):
                n = self._fh.write(view[done:])
                if not n:
                    raise OSError(28, "No space left on device (nothing written)")
                done += n
        except OSError as exc:
            if done:
                try:
                    os.ftruncate(self._fh.fileno(), self._size)
                except OSError:
                    pass
            raise write_error(self.part_path, exc) from exc
        self._size += len(data)

    def _sync(self) -> None:
        try:
            self._fh.flush()
            os.fsync(self._fh.fileno())
        except OSError as exc:
            raise write_error(self.part_path, exc) from exc

    def write_row(self, t_s: float, ref_uT, dut_uT, temp_c: float, session: int,
                  currents_A: Mapping[str, float] | None = None, flag: int | None = None,
                  extra: Mapping[str, float] | None = None) -> None:
        cur = currents_A or {}
        missing = [n for n in self.current_names if n not in cur]
        ext = extra or {}
        missing += [n for n in self.extra_names if n not in ext]
        if missing:
            raise ValueError(f"row lacks currents {missing}")
        row = (float(t_s), *(float(v) for v in ref_uT), *(float(v) for v in dut_uT), float(temp_c),
               float(int(session)), *(float(cur[n]) for n in self.current_names),
               *(float(ext[n]) for n in self.extra_names))
        if self.with_flag:
            row += (float(int(flag or 0)),)
        if len(row) != self._ncols:
            raise ValueError(f"row has {len(row)} values for {self._ncols} columns (ref_uT, dut_uT need 3 each)")
        _check_row(row, self._int_cols)
        self._buf.append(row)
        if len(self._buf) >= self.block_rows:
            self.flush()

    def write_block(self, table: np.ndarray) -> None:
        """Write rows given as an (n, columns) float array in header order; flushed and fsynced."""
        table = np.asarray(table, dtype=float)
        if table.ndim != 2 or table.shape[1] != self._ncols:
            raise ValueError(f"block must be (n, {self._ncols}), got {table.shape}")
        if self._buf:
            self.flush()
        _check_block(table, self._int_cols)
        self._write_table(table)
        self._sync()

    def _write_table(self, table: np.ndarray) -> None:
        if not table.shape[0]:
            return
        text = (self._row_fmt * table.shape[0]) % tuple(table.ravel().tolist())
        data = text.replace("nan", "").encode("ascii")
        self._write(data)
        self._crc = zlib.crc32(data, self._crc)
        self.rows_written += table.shape[0]

    def flush(self) -> None:
        if self._buf:
            table = np.asarray(self._buf, dtype=float).reshape(len(self._buf), self._ncols)
            self._buf.clear()
            self._write_table(table)
        self._sync()

    def close(self) -> Path:
        """Flush, write the closing line, fsync, and atomically rename ``.part`` to the final path."""
        if self._fh.closed:
            return self.path
        self.flush()
        self._write(f"# {END_KEY}: rows={self.rows_written} crc32=0x{self._crc:08x}\n".encode())
        self._sync()
        self._fh.close()
        try:
            os.replace(self.part_path, self.path)
            fsync_dir(self.path.parent)
        except OSError as exc:
            raise write_error(self.path, exc) from exc
        return self.path

    def abort(self) -> None:
        """Flush what was written and leave the ``.part`` file in place (no rename, no closing line)."""
        if self._fh.closed:
            return
        try:
            self.flush()
        finally:
            try:
                self._fh.close()
            except OSError:
                pass   # bytes still buffered could not be written: the flush has raised that already

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
            return
        try:
            self.abort()
        except OSError:
            pass   # keep the original exception; the .part holds every block written before it


def _empty_session(current_names: Sequence[str], extra_names: Sequence[str]) -> Session:
    z = np.zeros(0)
    return Session(z, np.zeros((0, 3)), np.zeros((0, 3)), z, z, {n: z for n in current_names},
                   extra={n: z for n in extra_names})


def _check_block(table: np.ndarray, int_cols: Sequence[int]) -> None:
    """ValueError for an infinite value or an integer column value that is not an integer within +-2**53."""
    if np.isinf(table).any():
        x = float(table[np.isinf(table)][0])
        # the reader rejects infinities: refuse here instead of writing an unreadable file
        raise ValueError(f"cannot write an infinite value ({x}) to a session file")
    for c in int_cols:
        v = table[:, c]
        if not np.all((np.abs(v) <= 2.0 ** 53) & (v == np.round(v))):
            raise ValueError("session and flag values must be integers within +-2**53")


def _check_row(row: tuple[float, ...], int_cols: Sequence[int]) -> None:
    """:func:`_check_block` of one row of floats, without building an array (the same checks and messages)."""
    isinf = math.isinf
    for x in row:
        if isinf(x):
            raise ValueError(f"cannot write an infinite value ({x}) to a session file")
    for c in int_cols:
        v = row[c]
        if not (abs(v) <= 2.0 ** 53 and v == round(v)):
            raise ValueError("session and flag values must be integers within +-2**53")


def refuse_overwriting_inputs(out: str | os.PathLike, inputs: Iterable[str | os.PathLike]) -> None:
    """ConfigurationError (a usage error) when the output path names one of the input files."""
    o = Path(out).resolve()
    for p in inputs:
        if Path(p).resolve() == o:
            raise ConfigurationError(f"--out {out} is the input file {p}: write the result elsewhere")


def session_table(s: Session, rows: slice | np.ndarray = slice(None)) -> np.ndarray:
    """The rows of ``s`` as an (n, columns) float array in the order of ``s.columns``."""
    cols = [s.t_s[rows, None], s.ref_uT[rows], s.dut_uT[rows], s.temp_c[rows, None],
            s.session[rows, None].astype(float)]
    cols += [s.currents_A[k][rows, None] for k in s.currents_A]
    cols += [s.extra[k][rows, None] for k in s.extra]
    if s.flag is not None:
        cols.append(s.flag[rows, None].astype(float))
    return np.concatenate(cols, axis=1)


def write_session(path: str | os.PathLike, s: Session, *, block_rows: int = 20000) -> Path:
    """Write a whole :class:`Session` crash-safely (blocks of ``block_rows`` rows, each fsynced)."""
    with SessionWriter(path, s.metadata, current_names=list(s.currents_A), with_flag=s.flag is not None,
                       block_rows=block_rows, extra_names=list(s.extra)) as w:
        for start in range(0, len(s), w.block_rows):
            w.write_block(session_table(s, slice(start, start + w.block_rows)))
    return Path(path)


# ---------------------------------------------------------------------------------------- reading
def _parse_float(cell: str, lineno: int, col: str, path: object) -> float:
    cell = cell.strip()
    if cell == "" or cell.lower() == "nan":
        return math.nan
    if not DECIMAL_RE.fullmatch(cell):
        if cell.lower().lstrip("+-") in ("inf", "infinity"):
            raise SessionFileError(f"{path}: line {lineno}: column {col!r}: infinite value {cell!r} "
                                   "(a cell must be a plain decimal number or empty)")
        raise SessionFileError(f"{path}: line {lineno}: column {col!r}: not a plain decimal number: {cell[:40]!r}")
    v = float(cell)
    if math.isinf(v):
        raise SessionFileError(f"{path}: line {lineno}: column {col!r}: infinite value (overflows a double)")
    return v


#: Largest session, ADCS or import file read whole (about 8 million rows of a bench session); readers that
#: stream in blocks (telemetry for refit and diagnose, packet streams) have their own, larger limits.
MAX_FILE_BYTES = 1 << 30


def open_regular(path: str | os.PathLike, kind: str, max_bytes: int = MAX_FILE_BYTES):
    """A binary file object of the regular file ``path`` of at most ``max_bytes``
    (:func:`magstack.data.io.open_bounded`: a FIFO, a device such as /dev/zero or a directory is refused
    without being read, a FIFO swapped in never blocks); SessionFileError naming the file otherwise."""
    try:
        return open_bounded(path, max_bytes, kind)
    except InputDataError as exc:
        raise SessionFileError(str(exc)) from None


def read_text_file(path: str | os.PathLike, kind: str) -> str:
    """UTF-8 text of ``path`` (a leading byte-order mark is dropped); a missing, unreadable, non-regular,
    oversized or binary file raises SessionFileError naming it."""
    raw = read_file_bytes(path, kind)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SessionFileError(f"{path}: not a text {kind} ({exc})") from None


def read_file_bytes(path: str | os.PathLike, kind: str, max_bytes: int = MAX_FILE_BYTES) -> bytes:
    """Bytes of ``path`` without a leading UTF-8 byte-order mark (:func:`magstack.data.io.read_bytes_bounded`:
    a regular file of at most ``max_bytes``, never read beyond the limit); SessionFileError naming it
    otherwise."""
    try:
        raw = read_bytes_bounded(path, max_bytes, kind)
    except InputDataError as exc:
        raise SessionFileError(str(exc)) from None
    return raw[len(_BOM):] if raw.startswith(_BOM) else raw


def _read_bytes(source: str | os.PathLike | io.IOBase) -> tuple[bytes, str]:
    if isinstance(source, io.TextIOBase):
        return source.read().encode("utf-8", "surrogateescape"), getattr(source, "name", "<stream>")
    return read_file_bytes(source, "session file"), str(source)


def _decode(b: bytes, name: str) -> str:
    try:
        return b.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SessionFileError(f"{name}: not a text session file ({exc})") from None


def _fill_gaps(body: bytes) -> bytes:
    """Empty cells written as ``nan`` so that ``numpy.loadtxt`` reads them as NaN."""
    body = body.replace(b",,", b",nan,").replace(b",,", b",nan,")
    if body.startswith(b","):
        body = b"nan" + body
    return body.replace(b"\n,", b"\nnan,").replace(b",\n", b",nan\n").replace(b",\r", b",nan\r")


def _fast_table(body: bytes, ncols: int) -> np.ndarray | None:
    """All rows of ``body`` (complete lines) as an (n, ncols) array, or None to use the line parser.

    Taken only when every byte can belong to a plain decimal, a gap or ``nan`` (no ``#``, no
    letters but ``e``/``nan``, no signed ``nan``), so a file the line parser would refuse never
    passes: ``loadtxt`` then parses exactly the cells ``float()`` would.
    """
    if not body or body.isspace():
        return np.empty((0, ncols))
    rest = body.translate(None, _PLAIN_BYTES)   # any non-ASCII byte stays in ``rest``
    if rest and (rest.translate(None, _NAN_BYTES) or _SIGNED_NAN_RE.search(body)):
        return None
    for attempt in (body, None):
        text = attempt if attempt is not None else _fill_gaps(body)
        try:
            arr = np.loadtxt(io.BytesIO(text), delimiter=",", dtype=float, ndmin=2, encoding="latin-1",
                             comments=None)
        except Exception:  # noqa: BLE001 - any refusal: retry with gaps filled, then the line parser
            continue
        if arr.shape[1] != ncols or np.isinf(arr).any():
            return None   # the line parser names the line (cell count, a number that overflows)
        return arr
    return None


#: Bytes per block of rows given to the fast path (a bad block alone goes through the line parser).
_CHUNK_BYTES = 8 << 20


def parse_table(body: bytes, first_lineno: int, header: Sequence[str], name: str, start: int = 0,
                end: int | None = None) -> np.ndarray:
    """All rows of ``body[start:end]`` (complete lines, the first being line ``first_lineno``) as an
    (n, columns) float array.

    Blocks of about :data:`_CHUNK_BYTES` go through :func:`_fast_table`; a block it refuses goes
    through :func:`_line_table`, which names the bad cell or, when the block is valid after all
    (blank or comment lines, blanks in cells), parses it. Cells: plain decimals; empty or ``nan`` = NaN.
    The result is filled in place (no concatenation copy); ``body`` itself is not copied.
    """
    end = len(body) if end is None else end
    out = np.empty((body.count(b"\n", start, end), len(header)))
    n, pos = 0, start
    while pos < end:
        stop = body.find(b"\n", min(pos + _CHUNK_BYTES, end - 1), end)
        stop = end if stop < 0 else stop + 1
        chunk = body[pos:stop]
        arr = _fast_table(chunk, len(header))
        if arr is None:
            arr = _line_table(_decode(chunk, name), first_lineno + body.count(b"\n", start, pos), header, name)
        out[n:n + arr.shape[0]] = arr
        n += arr.shape[0]
        pos = stop
    return out[:n]


def _line_table(body: str, first_lineno: int, header: Sequence[str], name: str) -> np.ndarray:
    """Line-by-line parser (the reference): rows of complete lines; SessionFileError names the cell."""
    rows: list[list[float]] = []
    for j, line in enumerate(body.split("\n")[:-1] if body else []):
        lineno = first_lineno + j
        if not line.strip() or line.startswith("#"):
            continue
        cells = line.split(",")
        if len(cells) != len(header):
            raise SessionFileError(f"{name}: line {lineno}: {len(cells)} cells, header has {len(header)}")
        rows.append([_parse_float(cells[k], lineno, c, name) for k, c in enumerate(header)])
    return np.array(rows, dtype=float).reshape(len(rows), len(header))


def data_row_line(body: bytes, first_lineno: int, k: int) -> int:
    """File line number of data row ``k`` (0-based) of ``body`` (blank and ``#`` lines skipped)."""
    n = -1
    for j, line in enumerate(body.split(b"\n")):
        if line.strip() and not line.startswith(b"#"):
            n += 1
            if n == k:
                return first_lineno + j
    return first_lineno + max(k, 0)


def _check_integer_column(v: np.ndarray, col: str, name: object, *, header_line: int, allow_empty: bool,
                          locate: Callable[[int], int]) -> None:
    """SessionFileError naming the line of the first row whose cell is not an integer within +-2**53."""
    with np.errstate(invalid="ignore"):
        bad = ~((v == np.round(v)) & (np.abs(v) <= 2.0 ** 53))
    if allow_empty:
        bad &= np.isfinite(v)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        line = locate(k)
        raise SessionFileError(f"{name}: line {line}: {col!r} column must hold integers on every row "
                               f"(data row {k + 1} after the header on line {header_line} has {float(v[k])!r})")


def read_session(source: str | os.PathLike | io.TextIOBase) -> Session:
    """Read a v1 session file (or a ``.part`` file left by a killed session).

    A final line without newline that does not parse (a write cut short) is dropped with a
    warning in ``Session.warnings`` (in a ``.part`` file always); any other bad line raises
    :class:`SessionFileError` naming file, line and column. A finished file (not ``.part``) whose
    closing line is missing or disagrees with the rows read gets a warning. Each warning is also
    logged (logger ``magstack.data.session``, level WARNING). A UTF-8 byte-order mark is accepted.
    """
    raw, name = _read_bytes(source)
    if raw.startswith(_BOM):
        raw = raw[len(_BOM):]
    if not raw.isascii():
        _decode(raw, name)   # SessionFileError for a binary / non-UTF-8 file
    is_part = name.endswith(".part")
    # metadata lines and the header row
    metadata: dict[str, str] = {}
    pos, lineno = 0, 0
    while raw.startswith(b"#", pos):
        end = raw.find(b"\n", pos)
        if end < 0:
            pos = len(raw)
            break
        body_line = _decode(raw[pos + 1:end], name).strip()
        if ":" in body_line:
            k, v = body_line.split(":", 1)
            metadata[k.strip()] = v.strip()
        pos, lineno = end + 1, lineno + 1
    if metadata.get(FORMAT_KEY) not in (None, FORMAT_VERSION):
        raise SessionFileError(f"{name}: unsupported session format version {metadata[FORMAT_KEY]!r}")
    end = raw.find(b"\n", pos)
    if pos >= len(raw) or end < 0:
        raise SessionFileError(f"{name}: no header row (file empty or truncated)")
    header = [c.strip() for c in _decode(raw[pos:end], name).split(",")]
    header_line = lineno + 1
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise SessionFileError(f"{name}: line {header_line}: header lacks required columns {missing}")
    if len(set(header)) != len(header):
        raise SessionFileError(f"{name}: line {header_line}: duplicate column names in header")
    current_cols = [c for c in header if _CURRENT_RE.match(c)]
    known = set(REQUIRED_COLUMNS) | set(current_cols) | set(OPTIONAL_COLUMNS)
    extra_cols = [c for c in header if c not in known and _EXTRA_RE.fullmatch(c)]
    unknown = [c for c in header if c not in known and c not in extra_cols]
    warnings: list[str] = []
    if unknown:
        warnings.append(f"ignored columns with names that are not [A-Za-z_][A-Za-z0-9_]*: {unknown}")

    first_lineno = header_line + 1
    b0 = b1 = end + 1
    if len(raw) > b0:
        # an unterminated last line is a write cut short (always dropped from a .part; kept if it parses otherwise)
        b1 = len(raw) if raw.endswith(b"\n") else raw.rfind(b"\n", b0 - 1) + 1
    tail = raw[b1:]
    closing, has_closing_line = None, False
    if b1 > b0:
        start = raw.rfind(b"\n", b0 - 1, b1 - 1) + 1
        if raw.startswith(_END_PREFIX, start):
            has_closing_line = True
            closing = _END_RE.fullmatch(_decode(raw[start:b1], name).strip())
            if closing is None:
                warnings.append("unreadable closing line (the row count cannot be checked)")
            b1 = start
    arr = parse_table(raw, first_lineno, header, name, b0, b1)
    if tail.strip() and not tail.startswith(b"#"):
        tail_lineno = first_lineno + raw.count(b"\n", b0, b1) + has_closing_line
        if is_part:
            # in a killed writer's .part file an unterminated line was cut short even if it
            # parses ("12" cut to "1"): never trust it
            warnings.append(f"dropped incomplete last line {tail_lineno} (write cut short)")
        else:
            try:
                last = _line_table(_decode(tail, name) + "\n", tail_lineno, header, name)
                arr = np.vstack([arr, last])
            except SessionFileError:
                warnings.append(f"dropped incomplete last line {tail_lineno} (write cut short)")
    if not is_part:
        if closing is None and metadata.get(FORMAT_KEY) == FORMAT_VERSION:
            warnings.append(f"no closing '# {END_KEY}' line: the file may have been cut short "
                            f"({arr.shape[0]} rows read)")
        elif closing is not None:
            n_said, crc_said = int(closing.group(1)), int(closing.group(2), 16)
            crc = zlib.crc32(memoryview(raw)[b0:b1])
            if crc != crc_said and raw.find(b"\r", b0, b1) >= 0:
                crc = zlib.crc32(raw[b0:b1].replace(b"\r\n", b"\n"))   # line endings converted (CRLF): same data
            if n_said != arr.shape[0] or crc_said != crc or tail.strip():
                warnings.append(f"closing line says {n_said} rows, crc32 0x{crc_said:08x}, but the file has "
                                f"{arr.shape[0]} rows, crc32 0x{crc:08x}: the file was cut or changed after it "
                                "was written")
    def locate(k: int) -> int:
        return data_row_line(raw[b0:b1], first_lineno, k)

    for w in warnings:
        _log.warning("%s: %s", name, w)

    return _session_from_table(arr, header, current_cols, extra_cols, metadata, warnings, name, header_line, locate)


def _session_from_table(arr: np.ndarray, header: list[str], current_cols: list[str], extra_cols: list[str],
                        metadata: dict[str, str], warnings: list[str], name: str, header_line: int,
                        locate: Callable[[int], int]) -> Session:
    idx = {c: k for k, c in enumerate(header)}

    def col(c: str) -> np.ndarray:
        return arr[:, idx[c]]

    _check_physical_range(arr, header, name, locate)
    sess = col("session")
    _check_integer_column(sess, "session", name, header_line=header_line, allow_empty=False, locate=locate)
    flag = None
    if "flag" in idx:
        fl = col("flag")
        _check_integer_column(fl, "flag", name, header_line=header_line, allow_empty=True, locate=locate)
        flag = np.where(np.isfinite(fl), fl, 0).astype(np.int64)   # an empty flag cell means 0 (ok)
    def vec(prefix: str) -> np.ndarray:
        k = [idx[f"{prefix}_{a}_uT"] for a in "xyz"]
        return arr[:, k[0]:k[0] + 3] if k == list(range(k[0], k[0] + 3)) else arr[:, k]

    currents = {_CURRENT_RE.match(c).group(1): col(c) for c in current_cols}
    s = Session(col("t_s"), vec("ref"), vec("dut"), col("temp_c"), sess.astype(np.int64), currents,
                metadata, flag, extra={c: col(c) for c in extra_cols}, source=name)
    s.warnings.extend(warnings)
    return s


def _check_physical_range(arr: np.ndarray, header: list[str], name: str, locate: Callable[[int], int]) -> None:
    """SessionFileError naming line and column of the first field cell beyond +-FIELD_LIMIT_UT or
    temperature outside TEMP_RANGE_C (empty cells are gaps, not errors)."""
    checks = [(k, -FIELD_LIMIT_UT, FIELD_LIMIT_UT, "uT") for k, c in enumerate(header)
              if c.startswith(("ref_", "dut_")) and c.endswith("_uT")]
    if "temp_c" in header:
        checks.append((header.index("temp_c"), *TEMP_RANGE_C, "degC"))
    for k, lo, hi, unit in checks:
        v = arr[:, k]
        with np.errstate(invalid="ignore"):
            bad = np.flatnonzero((v < lo) | (v > hi))
        if bad.size:
            raise SessionFileError(f"{name}: line {locate(int(bad[0]))}: column {header[k]!r}: {v[bad[0]]:g} {unit} "
                                   f"is outside the physical range [{lo:g}, {hi:g}] {unit} ({bad.size} such rows)")


def row_line(s: Session, k: int) -> int | None:
    """File line number of row ``k`` of a session read from ``s.source`` (None when unknown)."""
    if not s.source or not os.path.isfile(s.source):
        return None
    try:
        raw = read_file_bytes(s.source, "session file")
    except SessionFileError:
        return None
    lines = raw.split(b"\n")
    h = 0
    while h < len(lines) and lines[h].startswith(b"#"):
        h += 1
    return data_row_line(b"\n".join(lines[h + 1:]), h + 2, k)


def _file_identity(path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except (OSError, TypeError, ValueError):
        return None
    return st.st_dev, st.st_ino


def load_sessions(paths) -> tuple[Session, list[str]]:
    """Read files; each keeps its session ids unless ids collide across files, in which case
    every (file, session) pair gets a new id 1..M (the mapping is returned as text lines).

    A file given twice (the same file by device and inode: a repeated name, a symlink, a hard
    link) is read once and the fact is noted.
    """
    paths = list(paths)
    notes: list[str] = []
    unique: list = []
    seen: dict[tuple[int, int], object] = {}
    for p in paths:
        ident = _file_identity(p)
        if ident is not None and ident in seen:
            notes.append(f"{p}: the same file as {seen[ident]} (same device and inode): read once, not counted "
                         "as another session")
            continue
        if ident is not None:
            seen[ident] = p
        unique.append(p)
    paths = unique
    parts = [read_session(p) for p in paths]
    for path, s in zip(paths, parts, strict=True):
        notes += [f"{path}: {w}" for w in s.warnings]
    ids = [set(np.unique(s.session).tolist()) for s in parts]
    if sum(len(i) for i in ids) != len(set().union(*ids)):
        new = 0
        for path, s in zip(paths, parts, strict=True):
            remap = {}
            for old in sorted(set(np.unique(s.session).tolist())):
                new += 1
                remap[old] = new
                notes.append(f"{path}: session {old} -> {new}")
            uniq, inv = np.unique(s.session, return_inverse=True)
            s.session = np.array([remap[int(x)] for x in uniq], dtype=np.int64)[inv]
    for attr, what in (("currents_A", "current"), ("extra", "extra")):
        names = [list(getattr(s, attr)) for s in parts]
        if any(n != names[0] for n in names):
            common = [c for c in names[0] if all(c in n for n in names)]
            for s in parts:
                setattr(s, attr, {k: getattr(s, attr)[k] for k in common})
            notes.append(f"{what} columns differ between files; kept the common ones {common}")
    return Session.concatenate(parts), notes
