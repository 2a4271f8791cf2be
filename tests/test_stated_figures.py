"""Every speed or size the `--help` texts and the user pages state is measured: it is a row of the registry in
docs/benchmarks.md ("Stated figures": id, where it is stated, the figure as stated, the command that measured it,
the measured figure), and the statement is found where the registry says.

A statement is found by patterns for how long something takes (`takes 3 s`, `186 s CPU`, `12 s wall`, `takes
minutes`), how much faster than real time, and data rates and volumes (`659 B/s`, `3.76 MB per orbit`). Each one in
a `--help` text (every command and sub-command) or in the prose and tables of the pages in PAGES (code blocks are
transcripts of commands, not statements) must lie inside a registered statement for that place; each registered
statement must be there, name a benchmark script that exists (or a magstack command) and a measured figure."""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from magstack.cli.main import ALL, build_parser

ROOT = Path(__file__).resolve().parents[1]
REGISTRY = ROOT / "docs" / "benchmarks.md"
PAGES = ["README.md", "docs/flight.md", "docs/ccsds.md", "docs/demo.md", "docs/cli.md"]
NUM = r"\d[\d.,]*\s*(?:-\s*\d[\d.,]*\s*)?"
PATTERNS = [
    re.compile(r"\b(?:takes?|took|taking|finish(?:es|ed)? in|runs? in)\b[^.;]{0,40}?" + NUM
               + r"(?:s|ms|us|min|minutes?|hours?|h)\b", re.I),
    re.compile(NUM + r"(?:s|ms|us|min|minutes?|hours?)\s+(?:of\s+)?(?:CPU|wall)\b", re.I),
    re.compile(r"\b(?:takes?|took)\s+(?:seconds|minutes|hours)\b", re.I),
    re.compile(NUM + r"x\s+(?:faster|slower|real[ -]time)", re.I),
    re.compile(NUM + r"(?:B|kB|KiB|MB|MiB|GB|packets)/s\b"),
    re.compile(r"\bper\s+(?:\d+-minute\s+)?(?:day|orbit|hour)\b[^.;]{0,12}?" + NUM + r"(?:kB|KiB|MB|MiB|GB)\b", re.I),
    re.compile(NUM + r"(?:kB|KiB|MB|MiB|GB)\s+per\s+(?:day|orbit|hour)\b", re.I),
]


def _norm(text: str) -> str:
    return re.sub(r"\s+", " ", text.replace("`", "").replace("*", "")).strip()


def registry(text: str | None = None) -> list[dict]:
    """The rows of the "Stated figures" table of docs/benchmarks.md."""
    text = REGISTRY.read_text(encoding="utf-8") if text is None else text
    lines = text.split("## Stated figures", 1)[1].splitlines()
    start = next(i for i, r in enumerate(lines) if r.startswith("|"))
    rows = []
    for r in lines[start:]:
        if not r.startswith("|"):
            break
        rows.append(r)
    head = [c.strip() for c in rows[0].strip("|").split("|")]
    out = []
    for r in rows[2:]:
        cells = [c.strip() for c in r.strip().strip("|").split("|")]
        out.append(dict(zip(head, cells, strict=True)))
    return out


def _places(row: dict) -> list[str]:
    return [w.strip().strip("`") for w in row["where"].split(";")]


def help_texts() -> dict[str, str]:
    """`magstack X --help` -> that help text, for every command and sub-command."""
    out = {}

    def walk(parser: argparse.ArgumentParser, prefix: str) -> None:
        out[f"{prefix} --help"] = _norm(parser.format_help())
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sub in a.choices.items():
                    walk(sub, f"{prefix} {name}")
    walk(build_parser(ALL), "magstack")
    return out


def page_texts() -> dict[str, str]:
    """Each page's prose and table rows (code blocks left out), whitespace-normalised."""
    out = {}
    for page in PAGES:
        keep, block = [], False
        for line in (ROOT / page).read_text(encoding="utf-8").splitlines():
            if line.lstrip().startswith("```"):
                block = not block
                continue
            keep.append("" if block else line)
        out[page] = _norm("\n".join(keep))
    return out


def unregistered(texts: dict[str, str], rows: list[dict]) -> list[str]:
    """Statements in ``texts`` that no registry row for that place covers."""
    missing = []
    for place, text in texts.items():
        stated = [_norm(r["stated"]) for r in rows if place in _places(r)]
        spans = [(m.start(), m.start() + len(s)) for s in stated for m in re.finditer(re.escape(s), text)]
        for p in PATTERNS:
            for m in p.finditer(text):
                if not any(a <= m.start() and m.end() <= b for a, b in spans):
                    missing.append(f"{place}: '{m.group(0)}' in ...{text[max(0, m.start() - 80):m.end() + 40]}...")
    return missing


ROWS = registry()


def test_the_registry_has_the_flight_and_demo_figures():
    ids = {r["id"] for r in ROWS}
    assert {"run-sim-day", "run-sim-orbit-day", "demo-default"} <= ids and len(ids) == len(ROWS)


@pytest.mark.parametrize("row", ROWS, ids=[r["id"] for r in ROWS])
def test_each_registered_figure_is_stated_where_it_says_and_measured_by_a_command(row):
    assert re.search(r"\d", row["stated"]) and re.search(r"\d", row["measured"]), row
    cmd = row["command"].strip("`")
    if cmd.startswith("python benchmarks/"):
        assert (ROOT / cmd.split()[1]).is_file(), cmd
    else:
        assert cmd.startswith("magstack ") and cmd.split()[1] in help_texts().get("magstack --help", ""), cmd
    helps, pages = help_texts(), page_texts()
    for place in _places(row):
        text = helps.get(place) if place.startswith("magstack ") else pages.get(place)
        assert text is not None, f"{row['id']}: unknown place {place!r} (a --help text or one of {PAGES})"
        assert _norm(row["stated"]) in text, f"{row['id']}: {row['stated']!r} is not in {place}"


def test_every_figure_in_the_help_texts_is_registered():
    assert unregistered(help_texts(), ROWS) == []


def test_every_figure_on_the_pages_is_registered():
    assert unregistered(page_texts(), ROWS) == []


def test_the_check_catches_an_unregistered_figure():
    texts = {"docs/flight.md": "A simulated day takes 3 minutes. Downlink 12.5 MB per day, 80 B/s.",
             "magstack run --help": "a simulated day takes minutes at most"}
    found = unregistered(texts, ROWS)
    assert len(found) == 4 and all("docs/flight.md" in f or "--help" in f for f in found)
