"""File helpers shared by every layer that writes results: atomic writes and NumPy-safe JSON.

* :func:`atomic_write_text` - write a whole file so that it appears whole or not at all:
  a temporary file in the same directory, ``fsync``, ``os.replace`` onto the target, ``fsync``
  of the directory (so the rename itself survives a power cut).
* :func:`staged_directory` - fill a directory that appears whole or not at all (a hidden sibling,
  moved into place on success, removed on any exception, Ctrl-C and SIGTERM under ``magstack`` included).
* :func:`fsync_dir` - the directory half of that, for writers that stream into their own
  ``.part`` file (``magstack.data.session.SessionWriter``).
* :func:`json_safe` / :func:`to_json` - strict JSON (RFC 8259) from results that hold NumPy
  scalars and arrays, tuples, paths and non-finite floats: NumPy types become Python numbers and
  lists, paths strings, and ``nan``/``inf``/``-inf`` become ``null`` (JSON has no such numbers;
  Python's default ``NaN``/``Infinity`` tokens are rejected by strict parsers).
* :func:`write_error` - an ``OSError`` from writing (``File too large``, ``No space left on
  device``) re-raised as :class:`~magstack.data.errors.FileWriteError` naming the file.
* :func:`check_output_paths` - the one output-path rule of every command: an output is never an
  input nor another output of the same command, and its directory exists.
* :func:`open_exclusive` - create a temporary output exclusively (``O_EXCL``, a symlink in its
  place is refused, never followed).
* :func:`open_bounded` / :func:`read_bytes_bounded` - open (to stream) or read a regular file of bounded
  size: a FIFO, device or directory, or a file beyond the limit, is one :class:`~magstack.errors.InputDataError`
  before a byte is read.
* :func:`read_json_bounded` - read a small JSON document from a regular file with bounds checked
  before and while reading (size, nesting depth, integer digits): hostile input is one
  :class:`~magstack.errors.InputDataError`, never a hang, a MemoryError or a RecursionError.
"""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import stat as stat_mod
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from magstack.data.errors import FileWriteError
from magstack.drivers.errors import ConfigurationError
from magstack.errors import InputDataError


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


def atomic_write_text(path: str | os.PathLike, text: str, *, encoding: str = "utf-8",
                      perm: int | None = None) -> Path:
    """Write ``text`` to ``path`` atomically and durably (:func:`atomic_write_bytes`); returns ``Path(path)``."""
    return atomic_write_bytes(path, text.encode(encoding), perm=perm)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, perm: int | None = None) -> Path:
    """Write ``data`` to ``path`` atomically and durably; returns ``Path(path)``.

    The bytes go to ``.<name>.tmp-<pid>`` beside ``path``, are flushed and fsynced, renamed onto
    ``path`` (``os.replace``) and the directory is fsynced. On any failure the temporary file is
    removed and ``path`` is untouched; write errors name the file (:class:`FileWriteError`).
    ``perm``: the file's mode whatever the umask (e.g. ``0o600``); default: 0666 less the umask.
    """
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp-{os.getpid()}")
    created = False
    try:
        with open_exclusive(tmp, "wb", perm=perm) as fh:
            created = True
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
        created = False
        fsync_dir(p.parent)
    except FileWriteError:
        raise
    except OSError as exc:
        raise write_error(p, exc) from exc
    finally:
        if created:
            tmp.unlink(missing_ok=True)
    return p


@contextmanager
def staged_directory(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a new empty directory to fill in place of ``path``; on a normal exit its files appear at
    ``path`` whole or not at all, on any exception it is removed and ``path`` is untouched.

    The stage is a hidden sibling (``.<name>.tmp-XXXX``, same file system, the umask's mode). When
    ``path`` does not exist the stage is renamed onto it (the folder appears with its files); when it
    does, each file is moved over with ``os.replace`` (each file whole; other files in ``path`` are
    kept). Only files at the top level of the stage are published.
    """
    p = Path(path)
    stage = Path(tempfile.mkdtemp(prefix=f".{p.name}.tmp-", dir=p.parent))
    try:
        umask = os.umask(0)
        os.umask(umask)
        stage.chmod(0o777 & ~umask)   # mkdtemp's 0700 would become the published folder's mode
        yield stage
        if not p.exists():
            os.rename(stage, p)
        else:
            for f in sorted(stage.iterdir()):
                os.replace(f, p / f.name)
        fsync_dir(p)
        fsync_dir(p.parent)
    except OSError as exc:
        raise write_error(p, exc) from exc
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def open_exclusive(path: str | os.PathLike, mode: str = "w", *, perm: int | None = None, **kwargs: Any):
    """Open a new file for writing, created exclusively (``O_CREAT | O_EXCL | O_NOFOLLOW``).

    A file or a symlink already at ``path`` is never truncated nor followed: ``FileExistsError``.
    ``mode`` is ``"w"`` (text, kwargs go to :func:`open`) or ``"wb"``; ``perm`` the file's mode whatever
    the umask (default: 0666 less the umask).
    """
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    fd = os.open(path, flags, 0o666 if perm is None else perm)
    try:
        if perm is not None:
            os.fchmod(fd, perm)
        return open(fd, mode, **kwargs)
    except BaseException:
        os.close(fd)
        raise


def _same_file(a: Path, b: Path) -> bool:
    if a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)   # hard links, bind mounts
    except OSError:
        return False


def check_output_paths(outputs: Mapping[str, str | os.PathLike | None],
                       inputs: Mapping[str, str | os.PathLike | None] | None = None, *,
                       directories: Iterable[str] = ()) -> None:
    """The output-path rule of every command, checked before anything is read or written.

    ``outputs`` and ``inputs`` map a label (the option, e.g. ``"--json"``, or ``"input"``) to a path
    (None = not given). :class:`ConfigurationError` (exit 2) when an output names an input or another
    output (also through symlinks or hard links); :class:`FileWriteError` (exit 4) when an output
    file's directory does not exist. Labels in ``directories`` are output directories (created by
    the command, so their parent need not exist yet).
    """
    directories = set(directories)
    outs = [(k, Path(v)) for k, v in outputs.items() if v is not None and str(v) != "-"]
    ins = [(k, Path(v)) for k, v in (inputs or {}).items() if v is not None and str(v) != "-"]
    for i, (name, out) in enumerate(outs):
        for in_name, p in ins:
            if _same_file(out, p):
                raise ConfigurationError(f"{name} {out} is the {in_name} {p}: write the result elsewhere")
        for other, q in outs[i + 1:]:
            if _same_file(out, q):
                raise ConfigurationError(f"{name} {out} and {other} {q} name the same file: give two paths")
    for name, out in outs:
        if name in directories:
            continue
        parent = out.parent
        if not parent.is_dir():
            raise FileWriteError(f"{name} {out}: directory {parent} does not exist")


#: Default bounds of :func:`read_json_bounded`.
JSON_MAX_BYTES = 1 << 20
JSON_MAX_DEPTH = 32
JSON_MAX_INT_DIGITS = 30


def open_bounded(path: str | os.PathLike, max_bytes: int, what: str = "file"):
    """A binary file object of the regular file ``path`` to read in blocks, every bound checked before a byte
    is read: ``stat`` first (a FIFO, device or directory is refused without opening it), opened with
    ``O_NONBLOCK`` (a FIFO swapped in after the check cannot block) and checked again on the descriptor,
    at most ``max_bytes`` long (a 6 GiB sparse file costs one ``stat``). :class:`InputDataError` naming the
    file otherwise ("cannot read: no such <what>", "cannot read: not a regular file ..."). The caller reads
    at most ``max_bytes`` (a file that grows meanwhile is its to refuse)."""
    p = Path(path)

    def check(st: os.stat_result) -> None:
        if not stat_mod.S_ISREG(st.st_mode):
            raise InputDataError(f"{p}: cannot read: not a regular file (a {what} must be one; a directory, FIFO "
                                 "or device is refused)")
        if st.st_size > max_bytes:
            raise InputDataError(f"{p}: cannot read: {st.st_size} bytes, more than the {max_bytes} a {what} may "
                                 "have")
    try:
        check(os.stat(p))
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise InputDataError(f"{p}: cannot read: no such {what}") from None
    except OSError as exc:
        raise InputDataError(f"{p}: cannot read {what} ({exc.strerror or exc})") from None
    try:
        check(os.fstat(fd))
        return open(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes_bounded(path: str | os.PathLike, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (:func:`open_bounded`; read in one bounded read,
    never beyond the limit: ``/dev/zero`` never fills memory). :class:`InputDataError` naming the file
    otherwise."""
    p = Path(path)
    fh = open_bounded(p, max_bytes, what)
    try:
        with fh:
            raw = fh.read(max_bytes + 1)
    except OSError as exc:
        raise InputDataError(f"{p}: cannot read {what} ({exc.strerror or exc})") from None
    if len(raw) > max_bytes:
        raise InputDataError(f"{p}: cannot read: grew beyond the {max_bytes} bytes a {what} may have")
    return raw


def read_json_bounded(path: str | os.PathLike, *, max_bytes: int = JSON_MAX_BYTES, max_depth: int = JSON_MAX_DEPTH,
                      max_int_digits: int = JSON_MAX_INT_DIGITS, what: str = "JSON file") -> Any:
    """Parse a small JSON document from ``path`` with every bound checked before it can hurt.

    * only a regular file (``stat`` before opening; a FIFO, device or directory is refused, opened
      with ``O_NONBLOCK`` so that a FIFO swapped in after the check cannot block);
    * at most ``max_bytes`` (checked on the size and again while reading: ``/dev/zero`` never fills memory);
    * integers of at most ``max_int_digits`` digits (a 400-digit integer would overflow a float later);
    * nesting at most ``max_depth`` deep; no ``NaN``/``Infinity`` tokens (RFC 8259).

    Any violation, an unreadable file or bad JSON raises :class:`InputDataError` naming the file
    (and line/column for syntax errors).
    """
    p = Path(path)
    raw = read_bytes_bounded(p, max_bytes, what)
    return parse_json_bounded(raw, str(p), max_depth=max_depth, max_int_digits=max_int_digits, what=what)


def parse_json_bounded(raw: bytes | str, source: str, *, max_depth: int = JSON_MAX_DEPTH,
                       max_int_digits: int = JSON_MAX_INT_DIGITS, what: str = "JSON file") -> Any:
    """The parsing half of :func:`read_json_bounded` (bytes or text already in memory)."""
    if isinstance(raw, bytes):
        try:
            raw = raw.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise InputDataError(f"{source}: byte {exc.start}: not UTF-8 text") from None
    depth = _max_nesting(raw)
    if depth > max_depth:
        raise InputDataError(f"{source}: nested {depth} levels deep, more than the {max_depth} a {what} may have")

    def parse_int(text: str) -> int:
        if len(text.lstrip("-")) > max_int_digits:
            raise InputDataError(f"{source}: an integer of {len(text.lstrip('-'))} digits "
                                 f"(at most {max_int_digits} allowed)")
        return int(text)

    def refuse_constant(name: str):
        raise InputDataError(f"{source}: {name} is not JSON (RFC 8259)")

    try:
        return json.loads(raw, parse_int=parse_int, parse_constant=refuse_constant)
    except json.JSONDecodeError as exc:
        raise InputDataError(f"{source}: line {exc.lineno}: column {exc.colno}: not valid JSON (corrupt or "
                             f"truncated: {exc.msg})") from None
    except (RecursionError, ValueError, OverflowError) as exc:   # belt and braces: nothing escapes as a traceback
        if isinstance(exc, InputDataError):
            raise
        raise InputDataError(f"{source}: unreadable {what} ({type(exc).__name__})") from None


#: A JSON string literal (skipped when counting nesting).
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")


def _max_nesting(text: str) -> int:
    """Deepest ``[``/``{`` nesting of JSON text, strings skipped (linear, no recursion)."""
    depth = best = 0
    for ch in _NOT_BRACKET.sub("", _JSON_STRING.sub("", text)):
        if ch in "[{":
            depth += 1
            best = max(best, depth)
        else:
            depth -= 1
    return best


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
