"""``magstack`` command line.

Each sub-command lives in its own module under :mod:`magstack.cli.commands` and exposes
``register(subparsers)``, which adds its parser and sets ``func(args)``. Modules are discovered,
so adding a command never edits this file. Conventions every command follows (docs/cli.md):

* ``func(args)`` returns a :class:`magstack.cli.output.CommandResult` (text lines, ``to_dict()``
  for ``--json``, exit code); an int is still accepted as a bare exit code;
* the common flags ``--json``, ``-v/--verbose``, ``-q/--quiet`` come from one parent parser
  (:class:`magstack.cli.options.CommandParser`); option values are validated at parse time by
  the types in :mod:`magstack.cli.options` (usage error, exit 2, option named);
* errors: a :class:`~magstack.errors.MagError` becomes one line ``magstack <command>: error: ...``
  on stderr and its ``exit_code`` (table in docs/architecture.md), never a traceback; under
  ``--json`` stdout also gets ``{"command", "exit_code", "error"}``.
"""
from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from magstack.cli.options import CommandParser, common_flags
from magstack.cli.output import CommandResult, configure_logging, dumps, set_json_mode
from magstack.cli.progress import set_progress_policy
from magstack.errors import EXIT_DEVICE, EXIT_USAGE, MagError


def build_parser() -> argparse.ArgumentParser:
    import magstack.cli.commands as commands

    parser = argparse.ArgumentParser(prog="magstack", description="magstack: AMR magnetometer sensor stack",
                                     epilog="exit status: 0 ok, 1 ran but the answer is negative, 2 usage error, "
                                            "3 bad input data, 4 device or system error, 130/143 interrupted "
                                            "(SIGINT/SIGTERM). Every command takes --json, -v/--verbose, -q/--quiet.")
    parser.add_argument("--version", action="version", version=f"magstack {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=CommandParser)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"magstack.cli.commands.{info.name}")
        module.register(sub)
    return parser


def version() -> str:
    from magstack import __version__

    return __version__


def _emit(result, args: argparse.Namespace, json_mode: bool) -> int:
    if isinstance(result, CommandResult) or hasattr(result, "to_dict"):
        if json_mode:
            print(dumps(result.to_dict()))
        else:
            text = result.text() if hasattr(result, "text") else ""
            if text:
                print(text)
        return int(getattr(result, "exit_code", 0))
    return int(result or 0)


def _error(args: argparse.Namespace, json_mode: bool, message: str, code: int, kind: str = "error") -> int:
    print(f"magstack {args.command}: {kind}: {message}" if kind else f"magstack {args.command}: {message}",
          file=sys.stderr)
    if json_mode:
        print(dumps({"command": args.command, "exit_code": code, "error": message}))
    return code


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    CommandParser.last_error = None
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage error (2) or --help / --version (0)
        if exc.code in (0, None):
            return 0
        if "--json" in argv and CommandParser.last_error is not None:
            command = next((a for a in argv if not a.startswith("-")), None)
            print(dumps({"command": command, "exit_code": EXIT_USAGE, "error": CommandParser.last_error}))
        return EXIT_USAGE
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    json_mode, verbose, quiet = common_flags(args)
    set_json_mode(json_mode, quiet)
    set_progress_policy(json_mode, quiet)
    configure_logging(verbose, quiet)
    try:
        return _emit(args.func(args), args, json_mode)
    except MagError as exc:
        return _error(args, json_mode, str(exc), exc.exit_code)
    except BrokenPipeError:
        # output piped into a reader that stopped (``| head``): files are already written
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except OSError as exc:
        # a file-system problem outside the typed tree (missing output directory, permissions)
        where = f" ({exc.filename})" if exc.filename else ""
        return _error(args, json_mode, f"{exc.strerror or exc}{where}", EXIT_DEVICE)
    except KeyboardInterrupt:
        return _error(args, json_mode, "interrupted", 130, kind="")


class _PipeSafe:
    """stdout for the command line: once the reader has gone (``magstack demo | head``), further output is
    dropped quietly (fd 1 goes to /dev/null) and the command finishes its work and exits with its own status,
    instead of dying in BrokenPipeError half-way."""

    def __init__(self, stream) -> None:
        self._stream = stream

    def _closed(self) -> None:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.__stdout__.fileno() if sys.__stdout__ is not None else 1)
        os.close(devnull)

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._closed()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._closed()

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    """The ``magstack`` entry point: :func:`_main` under the Unix conventions every command shares (issue 24
    item 10): a reader closing stdout ends output quietly (:class:`_PipeSafe`); Ctrl-C before a command has
    installed its own handler (while the command modules load) is one line and exit 130, never a traceback."""
    saved = sys.stdout
    sys.stdout = _PipeSafe(saved) if saved is not None and not isinstance(saved, _PipeSafe) else saved
    try:
        return _main(argv)
    except KeyboardInterrupt:
        print("magstack: interrupted", file=sys.stderr)
        return 130
    finally:
        sys.stdout = saved


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
