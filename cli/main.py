"""``magstack`` command line.

Each sub-command lives in its own module under :mod:`magstack.cli.commands` and exposes
``register(subparsers)``, which adds its parser and sets ``func(args) -> int``.
Modules are discovered, so adding a command never edits this file.
"""
from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from magstack.errors import EXIT_DEVICE, MagError


def build_parser() -> argparse.ArgumentParser:
    import magstack.cli.commands as commands

    parser = argparse.ArgumentParser(prog="magstack", description="magstack: AMR magnetometer sensor stack")
    parser.add_argument("--version", action="version", version=f"magstack {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"magstack.cli.commands.{info.name}")
        module.register(sub)
    return parser


def version() -> str:
    from magstack import __version__

    return __version__


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except MagError as exc:
        print(f"magstack {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except BrokenPipeError:
        # output piped into a reader that stopped (``| head``): files are already written
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except OSError as exc:
        # a file-system problem outside the typed tree (missing output directory, permissions)
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"magstack {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return EXIT_DEVICE
    except KeyboardInterrupt:
        print(f"magstack {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
