"""Bounded, checked reads of files the flight application is told to read (commands, tables, refit inputs).

Everything a command names is hostile until checked, and no check may block a rate group:

* :func:`inside_roots` - a path is accepted only inside one of the configured directories (lexically
  and after resolving links: a symbolic link anywhere below the root is refused);
* :func:`read_bounded` - opens with ``O_NOFOLLOW | O_NONBLOCK`` (a symlink is refused, a FIFO never
  blocks), checks on the open descriptor that it is a regular file no larger than ``max_bytes`` before
  reading a byte, optionally that it belongs to this process's user and is writable by nobody else,
  and reads at most ``max_bytes`` (a file growing meanwhile is refused, not read further).

Failures raise :class:`UnsafeInput` (a ``ValueError``) with a one-line reason naming the path.
"""
from __future__ import annotations

import errno
import os
import stat
from collections.abc import Sequence
from pathlib import Path


class UnsafeInput(ValueError):
    """A file the application was asked to read is not acceptable (location, type, size, owner, mode)."""


def inside_roots(path: str | os.PathLike, roots: Sequence[Path], base: Path) -> Path:
    """``path`` (relative to ``base``) as an absolute path inside one of ``roots``, with no link below the root.

    Returns the resolved path; :class:`UnsafeInput` when it lies outside every root or a component below
    the root is a symbolic link.
    """
    p = Path(path)
    lexical = Path(os.path.abspath(p if p.is_absolute() else base / p))     # normalised, absolute
    real = Path(os.path.realpath(lexical))
    for root in roots:
        root_lex = Path(os.path.normpath(os.path.abspath(root)))
        root_real = Path(os.path.realpath(root))
        for top in dict.fromkeys((root_lex, root_real)):
            try:
                rel = lexical.relative_to(top)
            except ValueError:
                continue
            if real != root_real / rel:
                raise UnsafeInput(f"{path}: refused: the path goes through a symbolic link")
            return real
    raise UnsafeInput(f"{path}: refused: outside the allowed directories ({', '.join(str(r) for r in roots)})")


def read_bounded(path: str | os.PathLike, max_bytes: int, *, own_only: bool = False) -> bytes:
    """The bytes of the regular file ``path`` (at most ``max_bytes``), never following a final symlink.

    ``own_only``: the file must belong to this process's effective user and be writable by nobody else
    (the command spool's rule). Raises :class:`UnsafeInput`.
    """
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        why = "is a symbolic link" if exc.errno == errno.ELOOP else (exc.strerror or str(exc))
        raise UnsafeInput(f"{path}: cannot read: {why}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise UnsafeInput(f"{path}: refused: not a regular file")
        if st.st_size > max_bytes:
            raise UnsafeInput(f"{path}: refused: {st.st_size} bytes, more than the limit of {max_bytes}")
        if own_only:
            if st.st_uid != os.geteuid():
                raise UnsafeInput(f"{path}: refused: owned by uid {st.st_uid}, the application runs as uid "
                                  f"{os.geteuid()}")
            if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
                raise UnsafeInput(f"{path}: refused: writable by group or others (mode {st.st_mode & 0o777:04o})")
        chunks, n = [], 0
        while n <= max_bytes:
            b = os.read(fd, min(1 << 16, max_bytes + 1 - n))
            if not b:
                break
            chunks.append(b)
            n += len(b)
        if n > max_bytes:
            raise UnsafeInput(f"{path}: refused: grew beyond the limit of {max_bytes} bytes while read")
        return b"".join(chunks)
    except OSError as exc:
        raise UnsafeInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def check_private_dir(path: Path) -> str:
    """Create ``path`` (mode 0700) if missing; return a reason if it is not private to this user, else ""."""
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = os.lstat(path)
    if not stat.S_ISDIR(st.st_mode):
        return f"{path} is not a directory"
    if st.st_uid != os.geteuid():
        return f"{path} is owned by uid {st.st_uid}, the application runs as uid {os.geteuid()}"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"{path} is writable by group or others (mode {st.st_mode & 0o777:04o}): chmod go-w {path}"
    return ""
