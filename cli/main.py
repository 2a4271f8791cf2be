"""``magstack`` command line.

Each sub-command lives in its own module under :mod:`magstack.cli.commands` and exposes
``register(subparsers)``, which adds its parser and sets ``func(args)``. Modules are discovered,
so adding a command never edits this file; only the module of the command being run is imported
(``magstack --help`` reads the command names and help lines from the modules' source).
Conventions every command follows (docs/cli.md):

* ``func(args)`` returns a :class:`magstack.cli.output.CommandResult` (text lines, ``to_dict()``
  for ``--json``, exit code); an int is still accepted as a bare exit code;
* the common flags ``--json [FILE]``, ``-v/--verbose``, ``-q/--quiet`` come from one parent parser
  (:class:`magstack.cli.options.CommandParser`); option values are validated at parse time by
  the types in :mod:`magstack.cli.options` (usage error, exit 2, option named);
* one output-path rule for every command (:func:`magstack.data.io.check_output_paths`), applied
  here before the command runs: no output may be an input or another output;
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
from pathlib import Path

from magstack.cli.extras import MissingExtra, as_missing_extra, require
from magstack.cli.interrupt import exit_for, signals_raise
from magstack.cli.options import CommandParser, common_flags, declared_paths, split_json_flag
from magstack.cli.output import CommandResult, configure_logging, dumps, set_json_mode
from magstack.cli.progress import set_progress_policy
from magstack.errors import EXIT_DEVICE, EXIT_USAGE, MagError

#: ``build_parser(load=ALL)``: register every command module (tests, docs); the default of ``main``
#: loads only the command named on the command line (start-up time).
ALL = "*"


def command_index() -> dict[str, tuple[str, str, str | None]]:
    """``{command: (module, one-line help, extra)}`` for every module in :mod:`magstack.cli.commands`, read
    from the source of its ``subparsers.add_parser("name", help="...")`` call and its module-level
    ``EXTRA = "..."`` (the optional extra it needs, cli/extras.py), without importing it: ``magstack --help``
    lists the commands without importing what they use."""
    import magstack.cli.commands as commands

    index: dict[str, tuple[str, str, str | None]] = {}
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        name, helptext, extra = _declared_command(Path(info.module_finder.path) / f"{info.name}.py")
        index[name or info.name.replace("_", "-")] = (info.name, helptext, extra)
    return index


def _declared_command(source: Path) -> tuple[str | None, str, str | None]:
    """(name, help, extra) of ``source``: the first ``add_parser("name", help="...")`` call (name None if not
    literal) and the module-level ``EXTRA = "..."`` (None without one)."""
    import ast

    try:
        tree = ast.parse(source.read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError):
        return None, "", None
    extra = next((node.value.value for node in tree.body if isinstance(node, ast.Assign)
                  and any(isinstance(t, ast.Name) and t.id == "EXTRA" for t in node.targets)
                  and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str)), None)
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_parser"
                and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            helptext = next((k.value.value for k in node.keywords if k.arg == "help"
                             and isinstance(k.value, ast.Constant) and isinstance(k.value.value, str)), "")
            return node.args[0].value, helptext, extra
    return None, "", extra


def build_parser(load: str | None = ALL) -> argparse.ArgumentParser:
    """The ``magstack`` parser. ``load``: :data:`ALL` registers every command module; a command name
    registers that command's module and lists the others by name and help only; None lists them all."""
    parser = argparse.ArgumentParser(prog="magstack", description="magstack: AMR magnetometer sensor stack",
                                     epilog="exit status: 0 ok, 1 ran but the answer is negative, 2 usage error, "
                                            "3 bad input data, 4 device or system error, 130/143 interrupted "
                                            "(SIGINT/SIGTERM). Every command takes --json [FILE.json], -v/--verbose, "
                                            "-q/--quiet.")
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=CommandParser)
    for name, (module_name, helptext, extra) in command_index().items():
        if load == ALL or load == name:
            require(extra)   # MissingExtra (one line, exit 4) before importing what the extra brings
            importlib.import_module(f"magstack.cli.commands.{module_name}").register(sub)
        else:
            sub.add_parser(name, help=helptext)
    return parser


def _command_named(argv: list[str]) -> str | None:
    """The command word of ``argv`` (the first argument that is not an option), if any."""
    return next((a for a in argv if not a.startswith("-")), None)


class _VersionAction(argparse.Action):
    """``--version``: the version is looked up only when asked for (importlib.metadata is slow to import)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest, nargs=0, default=default,
                         help=help or "show program's version number and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"magstack {version()}")
        parser.exit()


def version() -> str:
    from magstack import __version__

    return __version__


def _emit(result, json_target: str | None) -> int:
    """Print the result (text, or JSON on stdout) and write ``--json FILE``; returns the exit code."""
    if not (isinstance(result, CommandResult) or hasattr(result, "to_dict")):
        return int(result or 0)
    if json_target == "-":
        print(dumps(result.to_dict()))
    else:
        text = result.text() if hasattr(result, "text") else ""
        if text:
            print(text)
        if json_target:
            from magstack.data.io import atomic_write_text

            atomic_write_text(json_target, dumps(result.to_dict()) + "\n")
    return int(getattr(result, "exit_code", 0))


def _error(args: argparse.Namespace, json_target: str | None, message: str, code: int, kind: str = "error") -> int:
    print(f"magstack {args.command}: {kind}: {message}" if kind else f"magstack {args.command}: {message}",
          file=sys.stderr)
    if json_target == "-":   # a failed command writes no --json FILE (outputs appear whole or not at all)
        print(dumps({"command": args.command, "exit_code": code, "error": message}))
    return code


def check_outputs(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """The shared output-path rule (data/io.py) on every path the command line names."""
    from magstack.data.io import check_output_paths

    files, dirs, inputs = declared_paths(parser, args)
    check_output_paths({**files, **dirs}, inputs, directories=set(dirs))


def _main(argv: list[str] | None) -> int:
    argv = split_json_flag(sys.argv[1:] if argv is None else list(argv))
    try:
        parser = build_parser(load=_command_named(argv))
    except (MissingExtra, ModuleNotFoundError) as exc:   # the command's module needs an extra not installed
        missing = exc if isinstance(exc, MissingExtra) else as_missing_extra(exc)
        if missing is None:
            raise
        args = argparse.Namespace(command=_command_named(argv))
        return _error(args, "-" if "--json=-" in argv else None, str(missing), missing.exit_code)
    CommandParser.last_error = None
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage error (2) or --help / --version (0)
        if exc.code in (0, None):
            return 0
        if "--json=-" in argv and CommandParser.last_error is not None:
            command = next((a for a in argv if not a.startswith("-")), None)
            print(dumps({"command": command, "exit_code": EXIT_USAGE, "error": CommandParser.last_error}))
        return EXIT_USAGE
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    json_target, verbose, quiet = common_flags(args)
    json_mode = json_target == "-"   # stdout holds only the JSON object
    set_json_mode(json_mode, quiet)
    set_progress_policy(json_mode, quiet)
    configure_logging(verbose, quiet)
    try:
        check_outputs(parser, args)
        return _emit(args.func(args), json_target)
    except MagError as exc:
        return _error(args, json_target, str(exc), exc.exit_code)
    except ModuleNotFoundError as exc:   # a library of an optional extra, imported where it is used
        missing = as_missing_extra(exc)
        if missing is None:
            raise
        return _error(args, json_target, str(missing), missing.exit_code)
    except BrokenPipeError:
        # output piped into a reader that stopped (``| head``): files are already written
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except MemoryError:
        # an input larger than this machine can hold (the readers' size limits keep /dev/zero and the like out)
        return _error(args, json_target, "out of memory: the input is too large for this machine", EXIT_DEVICE)
    except OSError as exc:
        # a file-system problem outside the typed tree (missing output directory, permissions)
        where = f" ({exc.filename})" if exc.filename else ""
        return _error(args, json_target, f"{exc.strerror or exc}{where}", EXIT_DEVICE)
    except KeyboardInterrupt as exc:   # Ctrl-C, or SIGTERM / SIGHUP raised as Stopped (cli/interrupt.py)
        name, code = exit_for(exc)
        return _error(args, json_target, "interrupted" if name == "SIGINT" else f"stopped by {name}", code,
                      kind="")


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
    """The ``magstack`` entry point: :func:`_main` under the Unix conventions every command shares: a
    reader closing stdout ends output quietly (:class:`_PipeSafe`); Ctrl-C before a command has
    installed its own handler (while the command modules load) is one line and exit 130, never a traceback;
    SIGTERM / SIGHUP outside a command's own handler raise :class:`~magstack.cli.interrupt.Stopped` (clean-up
    runs: no temporary file or half-made folder is left), one line, exit 143 / 129."""
    saved = sys.stdout
    sys.stdout = _PipeSafe(saved) if saved is not None and not isinstance(saved, _PipeSafe) else saved
    try:
        with signals_raise():
            return _main(argv)
    except KeyboardInterrupt as exc:
        name, code = exit_for(exc)
        print("magstack: interrupted" if name == "SIGINT" else f"magstack: stopped by {name}", file=sys.stderr)
        return code
    finally:
        sys.stdout = saved


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
