"""The manual builds: ``mkdocs build --strict`` (mkdocs.yml: MkDocs Material, mkdocstrings, the hooks of
tools/mkdocs_hooks.py) exits 0 with no warning, so every internal link and anchor resolves, every page is in the
nav, and every ``:::`` API block finds its module. The generated pages come from the code: the command-line
reference from the argparse parser, the flight dictionary from ``magstack.data.dictionary``."""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytest.importorskip("mkdocs", reason="the docs extra (pip install -e '.[docs]') builds the manual")


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)], cwd=ROOT,
                       capture_output=True, text=True, timeout=300, env=env)
    log = r.stdout + r.stderr
    problems = [line for line in log.splitlines() if re.match(r"\s*(WARNING|ERROR)\b", line)]
    assert r.returncode == 0 and not problems, f"mkdocs build --strict failed ({r.returncode}):\n{log[-4000:]}"
    return out


def _text(html_file: Path) -> str:
    return html_file.read_text(encoding="utf-8")


def test_the_manual_builds_strict_with_every_part(site):
    for page in ("index.html", "tutorial/index.html", "how-to/calibrate-with-a-coil/index.html",
                 "how-to/raspberry-pi/index.html", "reference/cli/index.html",
                 "reference/flight-dictionary/index.html", "reference/api/index.html", "explanation/index.html"):
        assert (site / page).is_file(), page


def test_the_cli_reference_is_the_parser(site):
    """Every command and sub-command of the parser has its section, with its options."""
    from magstack.cli.main import ALL, build_parser, command_index

    def subs(p):
        return next((dict(a.choices) for a in p._actions if isinstance(a, argparse._SubParsersAction)), {})
    html = _text(site / "reference" / "cli" / "index.html")
    commands = subs(build_parser(ALL))
    assert sorted(commands) == sorted(command_index()) and len(commands) > 12
    for name, parser in commands.items():
        for title, p in [(name, parser), *((f"{name} {s}", sp) for s, sp in subs(parser).items())]:
            assert f"magstack {title}</code>" in html, title
            for option in (o for a in p._actions for o in a.option_strings if o.startswith("--")):
                assert option in html, (title, option)


def test_the_flight_dictionary_page_is_the_dictionary(site):
    from magstack.data.dictionary import COMMANDS, EVENTS, TM_PACKETS

    html = _text(site / "reference" / "flight-dictionary" / "index.html")
    names = [p.name for p in TM_PACKETS] + [e.name for e in EVENTS] + [c.name for c in COMMANDS]
    assert len(names) > 20 and [n for n in names if n not in html] == []


def test_the_api_reference_renders_docstrings(site):
    """mkdocstrings found the modules (a missing one fails the strict build) and rendered their docstrings."""
    html = _text(site / "reference" / "api" / "index.html")
    from magstack.firmware.cal_uncertainty import Predictive

    first = Predictive.__doc__.split(":")[0].split("``")[0].strip()[:40]
    assert first and first in html and "magstack.drivers.registry" in html
