"""Every ``magstack ...`` command line quoted in README.md, hil/README.md
and every page under docs/ (inline code and code blocks) names a command that exists and only options that command
has; its ``--help`` runs, so the docs cannot drift from the parser."""
from __future__ import annotations

import argparse
import functools
import re
import shlex
from pathlib import Path

import pytest

from magstack.cli.main import ALL, build_parser, main

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", ROOT / "hil" / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
INLINE = re.compile(r"`([^`\n]*\bmagstack [a-z][^`\n]*)`")


def quoted_command_lines() -> list[tuple[str, str]]:
    """(where, text from 'magstack ' on) of every quoted command line."""
    out = []
    for doc in DOCS:
        in_block = False
        for n, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
            if line.lstrip().startswith("```"):
                in_block = not in_block
                continue
            texts = [line] if in_block else INLINE.findall(line)
            for t in texts:
                for m in re.finditer(r"(?:^|[\s&;(`$])(magstack [a-z][^\n]*)", t):
                    out.append((f"{doc.relative_to(ROOT)}:{n}", m.group(1)))
    return out


def _tokens(text: str) -> list[str]:
    """The arguments of a quoted command line ([] for output or prose quoted after 'magstack ')."""
    text = re.split(r"\s(?:&&|\|\||;|>|#|\|)\s|\s\|\s*$", text)[0]   # the command itself, not what follows
    words = text.split()
    if len(words) > 1 and words[1].endswith((":", ",")):   # `magstack fit: error: ...`, prose
        return []
    toks = []
    for tok in text.replace("\\|", "|").split()[1:]:
        tok = tok.strip("[]()`,")
        if not tok or tok.endswith(":") or tok in ("...", "…"):
            continue
        toks.append(tok.split("|")[0])
    return toks


@functools.cache
def _commands() -> dict[str, argparse.ArgumentParser]:
    """Every command's parser (built once: the checks only read the parsers)."""
    return _subparsers(build_parser(ALL))


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return dict(a.choices)
    return {}


LINES = quoted_command_lines()


def test_docs_quote_command_lines():
    assert len(LINES) > 40


@pytest.mark.parametrize("where, text", LINES, ids=[w for w, _ in LINES])
def test_quoted_command_line_matches_the_parser(where, text, capsys):
    toks = _tokens(text)
    commands = _commands()
    if not toks or toks[0].startswith("-"):
        assert not toks or toks[0] in ("--help", "-h", "--version"), (where, text)
        return
    name = toks[0]
    if name in ("and", "command", "commands"):   # prose: "the magstack command ..."
        return
    assert name in commands, f"{where}: `{text}`: no command {name!r}"
    parser, argv = commands[name], [name]
    subs = _subparsers(parser)
    if subs and len(toks) > 1 and toks[1] in subs:
        parser, argv = subs[toks[1]], [name, toks[1]]
    options = {o for a in parser._actions for o in a.option_strings}
    used = {t.split("=")[0] for t in toks if t.startswith("-") and len(t) > 1 and not re.match(r"-\d", t)}
    assert used <= options, f"{where}: `{text}`: {sorted(used - options)} not options of {' '.join(argv)}"
    assert main([*argv, "--help"]) == 0
    capsys.readouterr()


def test_the_check_catches_a_stale_option_and_a_missing_command(capsys):
    """The drift guard itself: a removed option or command in a quoted line fails it."""
    with pytest.raises(AssertionError, match="--bogus"):
        test_quoted_command_line_matches_the_parser("x.md:1", "magstack fit s.csv --bogus", capsys)
    with pytest.raises(AssertionError, match="no command 'fitt'"):
        test_quoted_command_line_matches_the_parser("x.md:1", "magstack fitt s.csv", capsys)


#: The guides whose code blocks a reader copies: every `magstack` line there parses with the real parser, values
#: included (choices, numbers, paths' kinds), not only its option names.
GUIDES = [*sorted((ROOT / "docs" / "how-to").glob("*.md")), ROOT / "docs" / "tutorial.md",
          ROOT / "docs" / "calibrate-by-hand.md"]


def guide_command_lines() -> list[tuple[str, list[str], tuple[str, ...]]]:
    """(where, argv after 'magstack', folders made by the guide's `mkdir` lines before it) of each command in the
    plain code blocks of the guides (split at &&, without a trailing comment or stdout redirect; output lines such
    as `magstack calibrate: ...` left out)."""
    out = []
    for doc in GUIDES:
        block, made = None, ()
        for n, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
            if line.startswith("```"):
                block = None if block is not None else line[3:].strip()
                continue
            if block == "" and line.startswith("mkdir "):
                made += tuple(w for w in shlex.split(line)[1:] if not w.startswith("-"))
            if block != "" or not line.startswith("magstack "):
                continue
            for part in re.split(r"\s+#\s", line)[0].split("&&"):
                words = shlex.split(part)
                if ">" in words:
                    words = words[:words.index(">")]
                if words[0] == "magstack" and not words[1].endswith(":"):
                    out.append((f"{doc.relative_to(ROOT)}:{n}", words[1:], made))
    return out


GUIDE_LINES = guide_command_lines()


def test_every_how_to_guide_quotes_commands():
    pages = {where.split(":")[0] for where, _, _ in GUIDE_LINES}
    assert {f"docs/how-to/{p.name}" for p in (ROOT / "docs" / "how-to").glob("*.md")} - pages <= {
        "docs/how-to/add-a-sensor.md"}   # a guide to the code, no command line
    assert "docs/tutorial.md" in pages and len(GUIDE_LINES) > 30


@pytest.mark.parametrize("where, argv, made", GUIDE_LINES, ids=[w for w, _, _ in GUIDE_LINES])
def test_guide_command_line_parses(where, argv, made, capsys, tmp_path, monkeypatch):
    """Parsed in an empty directory holding the folders the guide has made by then (`mkdir -p merged`)."""
    monkeypatch.chdir(tmp_path)
    for folder in made:
        Path(folder).mkdir(parents=True, exist_ok=True)
    try:
        build_parser(ALL).parse_args(argv)
    except SystemExit as e:
        pytest.fail(f"{where}: `magstack {shlex.join(argv)}` does not parse (exit {e.code}): "
                    f"{capsys.readouterr().err.strip()[-300:]}")
