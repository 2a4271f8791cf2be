"""Session file v1: the CSV every bench, simulation, fit and apply step reads and writes.

Layout (documented in docs/session-file.md)::

    # magstack-session: 1
    # dut_chip: hmc1053
    # ... more "# key: value" metadata lines ...
    t_s,ref_x_uT,ref_y_uT,ref_z_uT,dut_x_uT,dut_y_uT,dut_z_uT,temp_c,session[,current_<name>_A ...][,flag]
    1598371866.645000,0.575000,...

``t_s`` is Unix epoch seconds (UTC); fields in uT; ``temp_c`` in degC; ``session`` an integer
run id. Empty cells and ``nan`` mean "no value" (gaps). Writing is crash-safe: rows go to
``<out>.part``, flushed and fsynced per block, and the file is renamed to ``<out>`` on
close; a killed session leaves a ``.part`` file whose every complete row is readable.
"""
from __future__ import annotations

import io
import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magstack.data.errors import SessionFileError
from magstack.drivers.errors import ConfigurationError

FORMAT_KEY = "magstack-session"
FORMAT_VERSION = "1"
REQUIRED_COLUMNS = ("t_s", "ref_x_uT", "ref_y_uT", "ref_z_uT", "dut_x_uT", "dut_y_uT", "dut_z_uT",
                    "temp_c", "session")
_CURRENT_RE = re.compile(r"^current_([A-Za-z0-9_]+)_A$")
#: Optional non-current columns that v1 readers understand.
OPTIONAL_COLUMNS = ("flag",)
#: Extra numeric columns (name -> meaning) registered by other data modules (e.g. data/telemetry.py):
#: read into ``Session.extra`` (other unknown columns are ignored with a warning); ``write_session``
#: writes ``Session.extra`` as the writer's ``extra_columns`` (after the flag column).
EXTRA_COLUMNS: dict[str, str] = {}


def register_extra_columns(columns: Mapping[str, str]) -> None:
    """Make v1 readers and writers carry these numeric columns (name -> one-line meaning)."""
    EXTRA_COLUMNS.update(columns)


@dataclass
class Session:
    """A session in memory. Arrays share one length N.

    ``ref_uT``/``dut_uT`` are (N, 3); ``currents_A`` maps a current's name to an (N,) array;
    ``flag`` is an (N,) int array (0 = ok) or None; ``metadata`` preserves order.
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
        if self.flag is not None:
            self.flag = np.asarray(self.flag).astype(np.int64).reshape(n)
        self.metadata = {str(k): str(v) for k, v in self.metadata.items()}
        self.extra = {k: np.asarray(v, dtype=float).reshape(n) for k, v in self.extra.items()}
        unknown = [k for k in self.extra if k not in EXTRA_COLUMNS]
        if unknown:
            raise ValueError(f"extra columns {unknown} not registered (register_extra_columns)")

    def __len__(self) -> int:
        return self.t_s.size

    @property
    def columns(self) -> list[str]:
        cols = list(REQUIRED_COLUMNS) + [f"current_{k}_A" for k in self.currents_A]
        if self.flag is not None:
            cols.append("flag")
        return cols + list(self.extra)

    def select(self, mask: np.ndarray) -> Session:
        """A new Session with the rows where ``mask`` is true."""
        return Session(self.t_s[mask], self.ref_uT[mask], self.dut_uT[mask], self.temp_c[mask],
                       self.session[mask], {k: v[mask] for k, v in self.currents_A.items()},
                       dict(self.metadata), None if self.flag is None else self.flag[mask], list(self.warnings),
                       {k: v[mask] for k, v in self.extra.items()})

    @staticmethod
    def concatenate(parts: Sequence[Session]) -> Session:
        """Join sessions row-wise; current columns must match; metadata of the first is kept."""
        if not parts:
            raise ValueError("nothing to concatenate")
        names = list(parts[0].currents_A)
        for p in parts[1:]:
            if list(p.currents_A) != names:
                raise SessionFileError(f"current columns differ: {names} vs {list(p.currents_A)}")
        flags = None
        if any(p.flag is not None for p in parts):
            flags = np.concatenate([p.flag if p.flag is not None else np.zeros(len(p), np.int64) for p in parts])
        return Session(np.concatenate([p.t_s for p in parts]), np.vstack([p.ref_uT for p in parts]),
                       np.vstack([p.dut_uT for p in parts]), np.concatenate([p.temp_c for p in parts]),
                       np.concatenate([p.session for p in parts]),
                       {k: np.concatenate([p.currents_A[k] for p in parts]) for k in names},
                       dict(parts[0].metadata), flags,
                       extra={k: np.concatenate([p.extra[k] for p in parts]) for k in parts[0].extra
                              if all(k in p.extra for p in parts)})


def _fmt(x: float, decimals: int) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return ""
    if isinstance(x, float) and math.isinf(x):
        # the reader rejects infinities: refuse here instead of writing an unreadable file
        raise ValueError(f"cannot write an infinite value ({x}) to a session file")
    return f"{x:.{decimals}f}"


def _row_text(t_s, ref, dut, temp_c, session, currents: Iterable[float], flag, extra: Iterable[float] = ()) -> str:
    cells = [_fmt(float(t_s), 6), *(_fmt(float(v), 6) for v in ref), *(_fmt(float(v), 6) for v in dut),
             _fmt(float(temp_c), 4), str(int(session)), *(_fmt(float(c), 6) for c in currents)]
    if flag is not None:
        cells.append(str(int(flag)))
    cells += [_fmt(float(v), 6) for v in extra]
    return ",".join(cells) + "\n"


def _check_metadata(metadata: Mapping[str, str]) -> None:
    for k, v in metadata.items():
        if not re.fullmatch(r"[A-Za-z0-9_.\-]+", str(k)):
            raise ValueError(f"metadata key must be [A-Za-z0-9_.-]+: {k!r}")
        if "\n" in str(v) or "\r" in str(v):
            raise ValueError(f"metadata value for {k!r} must be one line")


class SessionWriter:
    """Streaming, crash-safe writer. Use as a context manager.

    Rows are buffered and written, flushed and fsynced every ``block_rows`` rows (and
    on :meth:`flush`/:meth:`close`). On clean close ``<path>.part`` is renamed to ``path``.
    """

    def __init__(self, path: str | os.PathLike, metadata: Mapping[str, str] | None = None, *,
                 current_names: Sequence[str] = (), with_flag: bool = False, block_rows: int = 50,
                 extra_columns: Sequence[str] = ()) -> None:
        self.path = Path(path)
        if not self.path.name or self.path.is_dir():
            raise SessionFileError(f"{path}: is a directory, not a session file name")
        if not self.path.parent.is_dir():
            raise SessionFileError(f"{path}: directory {self.path.parent} does not exist")
        self.part_path = self.path.with_name(self.path.name + ".part")
        self.current_names = list(current_names)
        self.with_flag = with_flag
        self.extra_columns = list(extra_columns)
        clash = set(self.extra_columns) & (set(REQUIRED_COLUMNS) | set(OPTIONAL_COLUMNS))
        if clash or not all(re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", c) for c in self.extra_columns) \
                or any(_CURRENT_RE.match(c) for c in self.extra_columns):
            raise ValueError(f"extra columns must be new [A-Za-z][A-Za-z0-9_]* names: {self.extra_columns}")
        self.block_rows = max(1, int(block_rows))
        meta = {FORMAT_KEY: FORMAT_VERSION, **{k: v for k, v in (metadata or {}).items() if k != FORMAT_KEY}}
        _check_metadata(meta)
        self._buf: list[str] = []
        self.rows_written = 0
        try:
            # exclusive: never truncate the .part left by an earlier, killed session
            self._fh = open(self.part_path, "x", encoding="utf-8", newline="")
        except FileExistsError:
            raise SessionFileError(f"{self.part_path} exists (left by an interrupted session?): "
                                   "read, rename or remove it first") from None
        header = "".join(f"# {k}: {v}\n" for k, v in meta.items())
        cols = list(REQUIRED_COLUMNS) + [f"current_{n}_A" for n in self.current_names]
        if with_flag:
            cols.append("flag")
        cols += self.extra_columns
        self._fh.write(header + ",".join(cols) + "\n")
        self._sync()

    def _sync(self) -> None:
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def write_row(self, t_s: float, ref_uT, dut_uT, temp_c: float, session: int,
                  currents_A: Mapping[str, float] | None = None, flag: int | None = None,
                  extra: Mapping[str, float] | None = None) -> None:
        """One row; ``extra`` gives the values of ``extra_columns`` (missing ones are written empty)."""
        cur = currents_A or {}
        missing = [n for n in self.current_names if n not in cur]
        if missing:
            raise ValueError(f"row lacks currents {missing}")
        ex = extra or {}
        self._buf.append(_row_text(t_s, ref_uT, dut_uT, temp_c, session,
                                   (cur[n] for n in self.current_names), flag if self.with_flag else None,
                                   (ex.get(c, math.nan) for c in self.extra_columns)))
        if len(self._buf) >= self.block_rows:
            self.flush()

    def flush(self) -> None:
        if self._buf:
            self._fh.write("".join(self._buf))
            self.rows_written += len(self._buf)
            self._buf.clear()
        self._sync()

    def close(self) -> Path:
        """Flush, fsync, and atomically rename ``.part`` to the final path."""
        if self._fh.closed:
            return self.path
        self.flush()
        self._fh.close()
        os.replace(self.part_path, self.path)
        dir_fd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
        return self.path

    def abort(self) -> None:
        """Flush what was written and leave the ``.part`` file in place (no rename)."""
        if not self._fh.closed:
            self.flush()
            self._fh.close()

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def refuse_overwriting_inputs(out: str | os.PathLike, inputs: Iterable[str | os.PathLike]) -> None:
    """ConfigurationError (a usage error) when the output path names one of the input files."""
    o = Path(out).resolve()
    for p in inputs:
        if Path(p).resolve() == o:
            raise ConfigurationError(f"--out {out} is the input file {p}: write the result elsewhere")


def write_session(path: str | os.PathLike, s: Session, *, block_rows: int = 5000) -> Path:
    """Write a whole :class:`Session` crash-safely."""
    names = list(s.currents_A)
    with SessionWriter(path, s.metadata, current_names=names, with_flag=s.flag is not None,
                       block_rows=block_rows, extra_columns=list(s.extra)) as w:
        for i in range(len(s)):
            w.write_row(s.t_s[i], s.ref_uT[i], s.dut_uT[i], s.temp_c[i], s.session[i],
                        {n: s.currents_A[n][i] for n in names}, None if s.flag is None else s.flag[i],
                        {k: v[i] for k, v in s.extra.items()})
    return Path(path)


def _parse_float(cell: str, lineno: int, col: str, path: object) -> float:
    cell = cell.strip()
    if cell == "" or cell.lower() == "nan":
        return math.nan
    try:
        v = float(cell)
    except ValueError:
        raise SessionFileError(f"{path}: line {lineno}: column {col!r}: not a number: {cell!r}") from None
    if math.isinf(v):
        raise SessionFileError(f"{path}: line {lineno}: column {col!r}: infinite value")
    return v


def _check_integer_column(v: np.ndarray, col: str, name: object, *, header_line: int, allow_empty: bool) -> None:
    """SessionFileError naming the first row whose cell is not an integer within +-2**53."""
    with np.errstate(invalid="ignore"):
        bad = ~((v == np.round(v)) & (np.abs(v) <= 2.0 ** 53))
    if allow_empty:
        bad &= np.isfinite(v)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise SessionFileError(f"{name}: {col!r} column must hold integers on every row "
                               f"(data row {k + 1} after the header on line {header_line} has {float(v[k])!r})")


def read_text_file(path: str | os.PathLike, kind: str) -> str:
    """UTF-8 text of ``path``; a missing, unreadable or binary file raises SessionFileError naming it."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SessionFileError(f"{path}: no such {kind}") from None
    except UnicodeDecodeError as exc:
        raise SessionFileError(f"{path}: not a text {kind} ({exc})") from None
    except OSError as exc:
        raise SessionFileError(f"{path}: cannot read ({exc.strerror or exc})") from None


def read_session(source: str | os.PathLike | io.TextIOBase) -> Session:
    """Read a v1 session file (or a ``.part`` file left by a killed session).

    A final line without newline that does not parse (a write cut short) is dropped
    with a warning in ``Session.warnings``; any other bad line raises
    :class:`SessionFileError` naming file, line and column.
    """
    if isinstance(source, io.TextIOBase):
        text, name = source.read(), getattr(source, "name", "<stream>")
    else:
        name = str(source)
        text = read_text_file(source, "session file")
    lines = text.split("\n")
    cut_tail = not text.endswith("\n")
    if not cut_tail:
        lines = lines[:-1]
    metadata: dict[str, str] = {}
    i = 0
    while i < len(lines) and lines[i].startswith("#"):
        body = lines[i][1:].strip()
        if ":" in body:
            k, v = body.split(":", 1)
            metadata[k.strip()] = v.strip()
        i += 1
    if metadata.get(FORMAT_KEY) not in (None, FORMAT_VERSION):
        raise SessionFileError(f"{name}: unsupported session format version {metadata[FORMAT_KEY]!r}")
    if i >= len(lines) or (cut_tail and i == len(lines) - 1):
        raise SessionFileError(f"{name}: no header row (file empty or truncated)")
    header = [c.strip() for c in lines[i].split(",")]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise SessionFileError(f"{name}: header lacks required columns {missing}")
    if len(set(header)) != len(header):
        raise SessionFileError(f"{name}: duplicate column names in header")
    current_cols = [c for c in header if _CURRENT_RE.match(c)]
    unknown = [c for c in header if c not in REQUIRED_COLUMNS and c not in current_cols and c not in OPTIONAL_COLUMNS
               and c not in EXTRA_COLUMNS]
    warnings: list[str] = []
    if unknown:
        warnings.append(f"ignored unknown columns {unknown}")
    idx = {c: k for k, c in enumerate(header)}
    rows: list[list[float]] = []
    data_lines = lines[i + 1:]
    for j, line in enumerate(data_lines):
        lineno = i + 2 + j
        if not line.strip() or line.startswith("#"):
            continue
        cells = line.split(",")
        is_last = j == len(data_lines) - 1
        if is_last and cut_tail and name.endswith(".part"):
            # in a killed writer's .part file an unterminated line was cut short even if it
            # parses ("12" cut to "1"): never trust it
            warnings.append(f"dropped incomplete last line {lineno} (write cut short)")
            break
        try:
            if len(cells) != len(header):
                raise SessionFileError(f"{name}: line {lineno}: {len(cells)} cells, header has {len(header)}")
            rows.append([_parse_float(cells[idx[c]], lineno, c, name) for c in header])
        except SessionFileError:
            if is_last and cut_tail:
                warnings.append(f"dropped incomplete last line {lineno} (write cut short)")
                break
            raise
    arr = np.array(rows, dtype=float).reshape(len(rows), len(header))

    def col(c: str) -> np.ndarray:
        return arr[:, idx[c]]

    sess = col("session")
    _check_integer_column(sess, "session", name, header_line=i + 1, allow_empty=False)
    flag = None
    if "flag" in idx:
        fl = col("flag")
        _check_integer_column(fl, "flag", name, header_line=i + 1, allow_empty=True)
        flag = np.where(np.isfinite(fl), fl, 0).astype(np.int64)   # an empty flag cell means 0 (ok)
    s = Session(col("t_s"), np.column_stack([col(f"ref_{a}_uT") for a in "xyz"]),
                np.column_stack([col(f"dut_{a}_uT") for a in "xyz"]), col("temp_c"), sess.astype(np.int64),
                {_CURRENT_RE.match(c).group(1): col(c) for c in current_cols}, metadata, flag,
                extra={c: col(c) for c in header if c in EXTRA_COLUMNS})
    s.warnings.extend(warnings)
    return s


def load_sessions(paths) -> tuple[Session, list[str]]:
    """Read files; each keeps its session ids unless ids collide across files, in which case
    every (file, session) pair gets a new id 1..M (the mapping is returned as text lines)."""
    parts = [read_session(p) for p in paths]
    notes = []
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
            s.session = np.array([remap[int(x)] for x in s.session], dtype=np.int64)
    names = [list(s.currents_A) for s in parts]
    if any(n != names[0] for n in names):
        common = [c for c in names[0] if all(c in n for n in names)]
        for s in parts:
            s.currents_A = {k: s.currents_A[k] for k in common}
        notes.append(f"current columns differ between files; kept the common ones {common}")
    return Session.concatenate(parts), notes
