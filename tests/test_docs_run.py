"""The command lines of docs/flight.md and docs/ccsds.md, run in order in an empty directory as a new user would,
each with exit 0: from `magstack run --init .` through the end-to-end scenario (bench table, orbit flight paused
for the ground, refit, telecommands, decode, merge, diagnose).

Two adaptations, both explicit: the line that runs on the Pi's real buses until stopped is not run, and a
simulated `--duration` longer than 600 s runs 60 s (a simulated day is measured by benchmarks/bench_flight_day.py,
docs/benchmarks.md). The example's telecommand port is replaced by a free one, as tests run in parallel."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from magstack.cli.main import main
from tests.netutil import own_tc_port

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "docs" / "flight.md", ROOT / "docs" / "ccsds.md"]
#: Longest simulated duration run as written; longer ones run LONG_RUN_S.
MAX_DURATION_S, LONG_RUN_S = 600.0, "60"


def command_lines() -> list[tuple[str, str]]:
    """(where, line) of every `magstack` line in the plain code blocks of the two pages, in order."""
    out = []
    for doc in DOCS:
        block = None
        for n, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
            if line.startswith("```"):
                block = None if block is not None else line[3:].strip()
                continue
            if block == "" and line.startswith("magstack "):
                out.append((f"{doc.name}:{n}", line))
    return out


def _steps(line: str) -> list[tuple[list[str], str | None]]:
    """The commands of one line (split at &&), each (argv after 'magstack', stdout redirect target or None)."""
    line = re.split(r"\s+#\s", line)[0]
    steps = []
    for part in line.split("&&"):
        words = shlex.split(part)
        target = None
        if ">" in words:
            i = words.index(">")
            words, target = words[:i], words[i + 1]
        assert words[0] == "magstack", part
        args = words[1:]
        if "--duration" in args:
            k = args.index("--duration") + 1
            if float(args[k]) > MAX_DURATION_S:
                args[k] = LONG_RUN_S
        steps.append((args, target))
    return steps


LINES = command_lines()


def test_the_pages_quote_the_path_from_init_to_diagnose():
    text = [line for _, line in LINES]
    assert text[0].startswith("magstack run --init .") and any("--scenario ground.toml" in t for t in text)
    assert any(t.startswith("magstack tm command") and "--send" in t for t in text) and len(text) >= 14


@pytest.mark.slow
def test_every_command_line_of_flight_and_ccsds_runs_in_order_with_exit_0(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ran = 0
    for where, line in LINES:
        if "on the Pi" in line:
            continue
        for args, target in _steps(line):
            capsys.readouterr()
            code = main(args)
            out, err = capsys.readouterr()
            assert code == 0, f"{where}: `magstack {' '.join(args)}` exited {code}: {err.strip()[-600:]}"
            if target is not None:
                Path(target).write_text(out)
            ran += 1
        if args[:2] == ["run", "--init"]:
            Path("flight.toml").write_text(own_tc_port(Path("flight.toml").read_text()))
    assert ran >= 14
    assert Path("e2e/packets-0001.bin").is_file() and Path("tables/candidate.json").is_file()
