"""Shared option handling of the ``magstack`` command: common flags and validated option types.

Every sub-command parser gets the common flags automatically (:class:`CommandParser` is the
``parser_class`` of the sub-command registry, so a command module that calls
``subparsers.add_parser(...)`` needs nothing extra):

``--json [FILE]``     the command's result object (``to_dict()``) as strict JSON: on stdout without
                      FILE or with ``-``, else written atomically to FILE (which must end in ``.json``)
``-v/--verbose``      more log output on stderr (repeat for debug)
``-q/--quiet``        only errors on stderr, no progress bar

Option values are checked at parse time by the type factories below: a bad value is a usage
error (exit 2) whose message names the option (argparse prefixes ``argument --NAME:``), e.g.
``p.add_argument("--rate-hz", type=finite_float(0, 1e6, lo_open=True, unit="Hz"))``.

* :func:`finite_float` - a finite float within [lo, hi] (either end open or absent);
* :func:`int_range` - an integer within [lo, hi];
* :func:`nonempty_path` - a path that is not empty and not a directory (output files);
* :func:`nonempty_dir` - a path that is not empty and not an existing file (output directories);
* :func:`float_list` - ``A,B[,C]``: a fixed number of finite floats, each within a range;
* :func:`name_list` - ``A,B``: names, each from a given set;
* :func:`named_vector` - ``NAME=X,Y,Z``: a name and a fixed number of finite floats.

Each factory returns a callable with a ``help_range`` string, to quote the range in help text.
"""
from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

__all__ = ["CommandParser", "common_parser", "common_flags", "json_target", "split_json_flag", "declared_paths",
           "nonempty_text",
           "finite_float", "int_range", "nonempty_path",
           "nonempty_dir", "float_list", "name_list", "named_vector"]


def common_parser() -> argparse.ArgumentParser:
    """The parent parser holding the flags every sub-command has (defaults suppressed, so that a
    nested sub-command does not reset a flag given to its parent; read them with :func:`common_flags`)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--json", nargs="?", const="-", metavar="FILE.json", type=json_target, default=argparse.SUPPRESS,
                   help="the result as one strict JSON object (numbers as numbers, missing values null): on "
                        "stdout without FILE or with '-', else written atomically to FILE.json")
    v = p.add_mutually_exclusive_group()
    v.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                   help="more log messages on stderr (-vv: debug)")
    v.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                   help="only errors on stderr; no progress bar")
    return p


def common_flags(args: argparse.Namespace) -> tuple[str | None, int, bool]:
    """(json target, verbose count, quiet) of parsed arguments, with their defaults filled in; the
    json target is None (no --json), ``"-"`` (stdout) or a file path."""
    target = getattr(args, "json", None)
    return (None if target is None else str(target), int(getattr(args, "verbose", 0) or 0),
            bool(getattr(args, "quiet", False)))


def json_target(text: str) -> str:
    """argparse type of ``--json [FILE]``: ``-`` (stdout) or a file name ending in ``.json``."""
    if text == "-":
        return text
    if not text.strip() or not text.endswith(".json") or text.endswith(("/", os.sep)) or Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"expected '-' or a file name ending in .json, got {text!r}")
    return text


json_target.is_output = True  # type: ignore[attr-defined]


def split_json_flag(argv: list[str]) -> list[str]:
    """``--json X`` takes X as its FILE only when X is ``-`` or ends in ``.json``; otherwise X is the
    command's own argument (``align --json session.csv``) and ``--json`` means stdout."""
    out: list[str] = []
    for i, a in enumerate(argv):
        if a == "--":
            return out + argv[i:]
        if a == "--json":
            nxt = argv[i + 1] if i + 1 < len(argv) else None
            if nxt is None or not (nxt == "-" or (nxt.endswith(".json") and not nxt.startswith("-"))):
                a = "--json=-"
        out.append(a)
    return out


#: An argument starting with '-' that is a value: a negative number or a comma list starting with one.
_NEGATIVE_VALUE = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?(,[-+]?[\d.eE+-]*)*$")


class CommandParser(argparse.ArgumentParser):
    """ArgumentParser of a sub-command: adds the common flags as a parent parser.

    A command that defines one of these flags itself (e.g. its own ``--json``) overrides the
    common one (``conflict_handler="resolve"``) instead of failing at start-up.
    """

    #: The last usage-error message (main() repeats it as JSON when --json was asked for).
    last_error: str | None = None

    def __init__(self, *a: Any, **kw: Any) -> None:
        kw["parents"] = [*kw.get("parents", ()), common_parser()]
        kw.setdefault("conflict_handler", "resolve")
        super().__init__(*a, **kw)
        # negative numbers and lists of them are values, not options: --validity-temp -20,60
        self._negative_number_matcher = _NEGATIVE_VALUE

    def error(self, message: str):
        CommandParser.last_error = message
        super().error(message)


# ------------------------------------------------------------------------------ option types
def _num_text(v: float) -> str:
    return str(v) if isinstance(v, int) else f"{v:.15g}"


def _range_text(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool, unit: str) -> str:
    u = f" {unit}" if unit else ""
    if lo is not None and hi is not None:
        return f"{'(' if lo_open else '['}{_num_text(lo)}, {_num_text(hi)}{')' if hi_open else ']'}{u}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {_num_text(lo)}{u}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {_num_text(hi)}{u}"
    return f"finite{u}"


def _parse_finite(text: str, what: str) -> float:
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r} (not finite)")
    return v


def _check_range(v: float, text: str, lo, hi, lo_open: bool, hi_open: bool, rng: str) -> None:
    bad = ((lo is not None and (v <= lo if lo_open else v < lo))
           or (hi is not None and (v >= hi if hi_open else v > hi)))
    if bad:
        raise argparse.ArgumentTypeError(f"must be within {rng}, got {text!r}")


def finite_float(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                 hi_open: bool = False, unit: str = "") -> Callable[[str], float]:
    """argparse type: a finite float within the range (None = unbounded on that side)."""
    rng = _range_text(lo, hi, lo_open, hi_open, unit)

    def parse(text: str) -> float:
        v = _parse_finite(text, f"a finite number {rng}")
        _check_range(v, text, lo, hi, lo_open, hi_open, rng)
        return v

    parse.help_range = rng  # type: ignore[attr-defined]
    parse.__name__ = "finite_float"  # argparse names the type in some messages
    return parse


def int_range(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """argparse type: an integer (decimal digits, optional sign) within [lo, hi]."""
    rng = _range_text(lo, hi, False, False, "")

    def parse(text: str) -> int:
        t = text.strip()
        if not t.lstrip("+-").isdigit() or len(t) > 19:
            raise argparse.ArgumentTypeError(f"expected an integer {rng}, got {text!r}")
        v = int(t)
        _check_range(v, text, lo, hi, False, False, rng)
        return v

    parse.help_range = rng  # type: ignore[attr-defined]
    parse.__name__ = "int_range"
    return parse


def nonempty_path(text: str) -> Path:
    """argparse type: an output path; not empty, not a directory."""
    if not text or not text.strip():
        raise argparse.ArgumentTypeError("expected a file name, got an empty string")
    p = Path(text)
    if p.is_dir() or text.endswith(("/", os.sep)):
        raise argparse.ArgumentTypeError(f"{text!r} is a directory, expected a file name")
    return p


nonempty_path.is_output = True  # type: ignore[attr-defined]


def nonempty_text(text: str) -> str:
    """argparse type: a name that is not empty or blank (a device id)."""
    if not text or not text.strip():
        raise argparse.ArgumentTypeError("expected a non-empty name, got an empty string")
    return text


def nonempty_dir(text: str) -> Path:
    """argparse type: an output directory (may not exist yet); not empty, not an existing file."""
    if not text or not text.strip():
        raise argparse.ArgumentTypeError("expected a directory name, got an empty string")
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} exists and is not a directory")
    return p


nonempty_dir.is_output = True  # type: ignore[attr-defined]
nonempty_dir.is_directory = True  # type: ignore[attr-defined]


def float_list(n: int | Iterable[int], lo: float | None = None, hi: float | None = None, *,
               unit: str = "", ordered: bool = False) -> Callable[[str], tuple[float, ...]]:
    """argparse type: comma-separated finite floats, ``n`` of them (an int or a set of allowed counts),
    each within [lo, hi]; ``ordered``: strictly increasing."""
    counts = {n} if isinstance(n, int) else set(n)
    rng = _range_text(lo, hi, False, False, unit)
    shape = " or ".join(str(c) for c in sorted(counts))

    def parse(text: str) -> tuple[float, ...]:
        parts = [x.strip() for x in text.split(",")]
        if len(parts) not in counts:
            raise argparse.ArgumentTypeError(f"expected {shape} comma-separated numbers, got {text!r}")
        vals = tuple(_parse_finite(x, f"finite numbers {rng}") for x in parts)
        for v, x in zip(vals, parts, strict=True):
            _check_range(v, x, lo, hi, False, False, rng)
        if ordered and any(b <= a for a, b in zip(vals, vals[1:], strict=False)):
            raise argparse.ArgumentTypeError(f"expected increasing values, got {text!r}")
        return vals

    parse.help_range = rng  # type: ignore[attr-defined]
    parse.__name__ = "float_list"
    return parse


def name_list(valid: Iterable[str], what: str = "name") -> Callable[[str], list[str]]:
    """argparse type: comma-separated names, each one of ``valid`` (empty items ignored); the
    message calls them ``what`` ("unknown effect 'x'; valid: ...")."""
    names = list(valid)

    def parse(text: str) -> list[str]:
        out = [x.strip() for x in text.split(",") if x.strip()]
        bad = [x for x in out if x not in names]
        if bad:
            raise argparse.ArgumentTypeError(f"unknown {what} {', '.join(repr(b) for b in bad)}; "
                                             f"valid: {', '.join(names)}")
        return out

    parse.__name__ = "name_list"
    return parse


def named_vector(n: int = 3, lo: float | None = None, hi: float | None = None, *,
                 unit: str = "") -> Callable[[str], tuple[str, tuple[float, ...]]]:
    """argparse type: ``NAME=X,Y,Z`` (``n`` finite floats within [lo, hi]) -> (name, values)."""
    values = float_list(n, lo, hi, unit=unit)

    def parse(text: str) -> tuple[str, tuple[float, ...]]:
        name, sep, rest = text.partition("=")
        if not sep or not name.strip() or not name.strip().replace("_", "").isalnum():
            raise argparse.ArgumentTypeError(f"expected NAME={','.join(['X', 'Y', 'Z'][:n] if n <= 3 else ['V'] * n)}"
                                             f" with NAME of letters, digits and _, got {text!r}")
        return name.strip(), values(rest)

    parse.__name__ = "named_vector"
    return parse


def declared_paths(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[dict, dict, dict]:
    """(output files, output directories, inputs) named on a parsed command line, each ``{label: path}``.

    Outputs are the values of options whose type is marked ``is_output`` (:func:`nonempty_path`,
    :func:`nonempty_dir`, ``--json FILE``); every other string or path value that names an existing
    file or directory counts as an input. ``main`` hands them to
    :func:`magstack.data.io.check_output_paths`: one rule for every command.
    """
    files: dict = {}
    dirs: dict = {}
    inputs: dict = {}
    for action in _all_actions(parser, args):
        value = getattr(args, action.dest, None)
        label = action.option_strings[-1] if action.option_strings else action.metavar or action.dest
        label = label if isinstance(label, str) else action.dest
        if getattr(action.type, "is_output", False):
            if value is not None and str(value) != "-":
                (dirs if getattr(action.type, "is_directory", False) else files)[label] = value
            continue
        values = value if isinstance(value, (list, tuple)) else [value]
        for i, v in enumerate(values):
            if isinstance(v, (str, os.PathLike)) and str(v) and os.path.exists(v):
                inputs[f"{label}[{i}]" if len(values) > 1 else label] = v
    return files, dirs, inputs


def _all_actions(parser: argparse.ArgumentParser, args: argparse.Namespace):
    """The actions of ``parser`` and of the sub-command parsers ``args`` selected."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = getattr(args, action.dest, None) if action.dest != argparse.SUPPRESS else None
            if chosen in action.choices:
                yield from _all_actions(action.choices[chosen], args)
        elif action.dest not in (argparse.SUPPRESS, "help", "version"):
            yield action
