"""The one intake rule: every file the flight application reads goes through here.

Commands, telecommand packet files, calibration tables (every format), refit inputs, the receiver's saved
state and the configuration are all read with the same checks, and no check may block a rate group:

* :func:`inside_roots` - a path a command names is accepted only inside one of the configured directories
  (lexically and after resolving links: a symbolic link anywhere below the root is refused);
* :func:`read_bounded` - opens with ``O_NOFOLLOW | O_NONBLOCK`` (a symlink is refused, a FIFO never
  blocks), checks on the open descriptor (so nothing can be swapped in between the check and the read)
  that it is a regular file no larger than ``max_bytes`` before reading a byte (a 6 GiB sparse file costs
  one ``fstat``), that it belongs to a trusted owner (this process's effective user, or root) and that
  nobody else may write it, then reads at most ``max_bytes`` (a file growing meanwhile is refused);
* :func:`check_file` - the same checks without reading (inputs a worker reads later in blocks: refit);
* :func:`check_private_dir` - a directory the application takes orders from (command directory,
  telecommand directory) is created 0700 whatever the umask, and refused when another user owns it or
  group or others may write it.

Failures raise :class:`UnsafeInput` (a ``ValueError``) with a one-line reason naming the path; callers
count and report them (a rejected command, a refused telecommand, a rejected table), never crash.
"""
from __future__ import annotations

import errno
import os
import stat
from collections.abc import Sequence
from pathlib import Path

#: Owners whose files are trusted besides the application's own user (root can write anything anyway).
TRUSTED_UIDS = (0,)
#: Largest refit input (telemetry read in blocks by the refit worker).
MAX_REFIT_INPUT_BYTES = 64 << 30


class UnsafeInput(ValueError):
    """A file the application was asked to read is not acceptable; ``kind`` says which check refused it:
    "location" (outside the roots, a link below a root), "type" (symlink, FIFO, device, directory, cannot
    open), "size", "owner" (another user, or writable by group or others)."""

    def __init__(self, message: str, kind: str = "type") -> None:
        super().__init__(message)
        self.kind = kind


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
                raise UnsafeInput(f"{path}: refused: the path goes through a symbolic link", "location")
            return real
    raise UnsafeInput(f"{path}: refused: outside the allowed directories ({', '.join(str(r) for r in roots)})",
                      "location")


def _open_checked(path: str | os.PathLike, max_bytes: int, own_only: bool) -> tuple[int, os.stat_result]:
    """An open descriptor of ``path`` that passed the rule (the caller closes it), with its ``fstat``."""
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
            raise UnsafeInput(f"{path}: refused: {st.st_size} bytes, more than the limit of {max_bytes}", "size")
        if own_only:
            if st.st_uid != os.geteuid() and st.st_uid not in TRUSTED_UIDS:
                raise UnsafeInput(f"{path}: refused: owned by uid {st.st_uid}, the application runs as uid "
                                  f"{os.geteuid()}", "owner")
            if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
                raise UnsafeInput(f"{path}: refused: writable by group or others (mode {st.st_mode & 0o777:04o}; "
                                  f"chmod go-w)", "owner")
    except BaseException:
        os.close(fd)
        raise
    return fd, st


def read_bounded(path: str | os.PathLike, max_bytes: int, *, own_only: bool = True) -> bytes:
    """The bytes of the regular file ``path`` (at most ``max_bytes``) under the intake rule (module doc).

    ``own_only`` (the rule; only tests turn it off): the file must belong to this process's effective user
    (or root) and be writable by nobody else. Raises :class:`UnsafeInput`.
    """
    fd, _ = _open_checked(path, max_bytes, own_only)
    try:
        chunks, n = [], 0
        while n <= max_bytes:
            b = os.read(fd, min(1 << 16, max_bytes + 1 - n))
            if not b:
                break
            chunks.append(b)
            n += len(b)
        if n > max_bytes:
            raise UnsafeInput(f"{path}: refused: grew beyond the limit of {max_bytes} bytes while read", "size")
        return b"".join(chunks)
    except OSError as exc:
        raise UnsafeInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def check_file(path: str | os.PathLike, max_bytes: int) -> int:
    """Apply the intake rule to ``path`` without reading it (a worker reads it later); its size in bytes."""
    fd, st = _open_checked(path, max_bytes, True)
    os.close(fd)
    return st.st_size


def check_private_dir(path: Path) -> str:
    """Create ``path`` (mode 0700, whatever the umask) if missing; a reason if it is not private to this user,
    else ""."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.mkdir(path, 0o700)
    except FileExistsError:
        pass
    else:
        os.chmod(path, 0o700)              # explicit: the mode must not depend on the umask
    st = os.lstat(path)
    if not stat.S_ISDIR(st.st_mode):
        return f"{path} is not a directory"
    if st.st_uid != os.geteuid():
        return f"{path} is owned by uid {st.st_uid}, the application runs as uid {os.geteuid()}"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"{path} is writable by group or others (mode {st.st_mode & 0o777:04o}): chmod go-w {path}"
    return ""
