"""MkDocs hooks of the manual (mkdocs.yml ``hooks:``): the pages generated from the code, and the API sources.

* ``reference/cli.md``: every command's usage, options and help, written from the argparse parser
  (``magstack.cli.main.build_parser``), so the reference is the parser.
* ``reference/flight-dictionary.md``: the flight dictionary's tables, as ``magstack tm dictionary`` prints them.
* ``how-to/raspberry-pi.md``: hil/README.md (the Pi set-up lives beside the code it describes).
* ``build/docs-api/magstack``: a tree of symbolic links that lays the repository's layer folders (``drivers/``,
  ``firmware_py/``, ...) out as the ``magstack`` package they install as, for mkdocstrings' static analysis.
* RST roles left in docstrings (``:func:`x```) are shown as the code they name.

Build: ``python -m mkdocs build --strict`` (the ``docs`` extra); tests/test_docs_build.py runs it."""
from __future__ import annotations

import argparse
import os
import re
import shutil
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
API_TREE = ROOT / "build" / "docs-api"
#: package -> repository folder (pyproject's [tool.setuptools.package-dir], without the C applier's data folder)
#: the width the help texts are wrapped to on the CLI reference page
HELP_COLUMNS = 100
PACKAGE_DIRS = {"drivers": "drivers", "data": "data", "firmware": "firmware_py", "sim": "sim", "ground": "ground",
                "hil": "hil", "cli": "cli"}


@event_priority(100)     # before mkdocstrings reads its handler paths
def on_config(config, **kwargs):
    _api_tree()
    return config


def _api_tree() -> None:
    """build/docs-api/magstack/...: links to magstack/'s files and to each layer's folder. Idempotent (a link
    already in place is kept), so two builds at once do not pull the tree from under each other."""
    pkg = API_TREE / "magstack"
    pkg.mkdir(parents=True, exist_ok=True)
    links = {pkg / f.name: f for f in (ROOT / "magstack").iterdir() if f.suffix == ".py"}
    links.update({pkg / name: ROOT / folder for name, folder in PACKAGE_DIRS.items()})
    for link, target in links.items():
        if link.is_symlink() and Path(os.readlink(link)) == target:
            continue
        if link.is_symlink() or link.is_file():
            link.unlink()
        elif link.is_dir():
            shutil.rmtree(link)
        try:
            os.symlink(target, link, target_is_directory=target.is_dir())
        except FileExistsError:     # made by a build running at the same time
            pass


def on_files(files, config, **kwargs):
    for uri, text in (("reference/cli.md", cli_reference()),
                      ("reference/flight-dictionary.md", dictionary_page()),
                      ("how-to/raspberry-pi.md", pi_page())):
        files.append(File.generated(config, uri, content=text))
    return files


def cli_reference() -> str:
    """The CLI reference page: the top-level usage, then each command (and sub-command) with its options."""
    from magstack.cli.main import ALL, build_parser

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(HELP_COLUMNS)     # argparse wraps to the terminal: the page must not depend on it
    try:
        return _cli_reference(build_parser(ALL))
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old


def _cli_reference(parser: argparse.ArgumentParser) -> str:
    out = ["# Command-line reference", "",
           "Generated from the argparse parser of `magstack` (`magstack.cli.main.build_parser`) when the manual is "
           "built, so it is what `magstack COMMAND --help` prints. Conventions shared by every command (`--json`, "
           "`-v`, `-q`, exit status, output paths): [CLI conventions](../cli.md).", "",
           "```text", parser.format_help().rstrip(), "```", ""]
    for name, sub in _subcommands(parser):
        out += _command_section(f"magstack {name}", sub, level=2)
    return "\n".join(out) + "\n"


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.ArgumentParser]]:
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return sorted(a.choices.items())
    return []


def _command_section(title: str, parser: argparse.ArgumentParser, level: int) -> list[str]:
    lines = [f"{'#' * level} `{title}`", "", "```text", parser.format_help().rstrip(), "```", ""]
    for name, sub in _subcommands(parser):
        lines += _command_section(f"{title} {name}", sub, level + 1)
    return lines


def dictionary_page() -> str:
    from magstack.data.dictionary_doc import dictionary_markdown

    return ("# Flight dictionary\n\nThe packets, events, commands and counters of the flight application, as "
            "`magstack tm dictionary` prints them (generated from `magstack.data.dictionary` when the manual is "
            "built). How they travel: [CCSDS packets and telecommands](../ccsds.md). For a ground system, the "
            "packets a flight configuration produces as an XTCE 1.2 document: "
            "`magstack tm xtce --config flight.toml`.\n\n"
            + _demote_headings(dictionary_markdown()))


def _demote_headings(md: str) -> str:
    """Headings one level down, so the page keeps one title."""
    return re.sub(r"^(#{1,5}) ", lambda m: "#" + m.group(1) + " ", md, flags=re.M)


def pi_page() -> str:
    """hil/README.md as a page, its links to the repository's files made plain text (they are not in the site)."""
    text = (ROOT / "hil" / "README.md").read_text(encoding="utf-8")
    text = re.sub(r"\A# [^\n]*\n", "# Run on a Raspberry Pi\n\nThis page is the repository's `hil/README.md`: the "
                  "set-up, wiring and service recipe live beside the code they describe.\n", text)
    return re.sub(r"\[([^\]]+)\]\((?!https?:)([^)]+)\)", r"\1 (`\2`)", text)


ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|data|attr|exc|obj|const):(<code>)~?")


def on_page_content(html, page, config, files, **kwargs):
    """``:func:`x``` left by an RST docstring: show the code alone."""
    return ROLE.sub(r"\1", html)
