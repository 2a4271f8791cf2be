"""docs/tutorial.md, run as a new user would: every command line of its code blocks, in order, in an empty directory,
each with exit 0, and the outcomes the prose states (the flight run calibrates every HMC1053 sample, the refit
proposes a candidate, the diagnosis names `time_skew`), and every figure the prose quotes after a command is what
that command printed, within 3 % (:data:`FIGURES`). No command says the same line on stdout and on stderr.

Adaptations, each explicit: the install line (`python3 -m pip install ...`) is not run (the suite runs in an
installed environment); `mkdir` is done by Python; the example configuration's telecommand port is replaced by a
free one after `run --example-config` wrote it, as tests run in parallel."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from magstack.cli.main import main
from tests.netutil import own_tc_port

ROOT = Path(__file__).resolve().parents[1]
TUTORIAL = ROOT / "docs" / "tutorial.md"


def command_lines() -> list[tuple[str, str]]:
    """(where, line) of every line in the tutorial's code blocks, in order."""
    out, block = [], False
    for n, line in enumerate(TUTORIAL.read_text(encoding="utf-8").splitlines(), 1):
        if line.startswith("```"):
            block = not block
            continue
        if block and line.strip():
            out.append((f"tutorial.md:{n}", line.strip()))
    return out


LINES = command_lines()

#: (command, regex of its output, regex of the tutorial's prose, scale output -> prose unit): each figure the
#: tutorial quotes and where the command prints it.
NUM = r"([0-9.]+(?:e-?[0-9]+)?)"
FIGURES = [
    ("fit bench.csv", r"raw ref-dut RMS(?:\s+[0-9.]+){3}\s+" + NUM, r"the raw error \(" + NUM + " uT", 1e-3),
    ("fit bench.csv", r"held-out time blocks(?:\s+[0-9.]+){3}\s+" + NUM, r"\(" + NUM + " nT on held-out 60 s", 1.0),
    ("apply tables/hmc1053.json", r"all rows \(\d+ rows\):.* norm " + NUM, r"RMS \(" + NUM + " nT over all rows", 1.0),
    ("apply tables/hmc1053.json", r"away from steps .* norm " + NUM, NUM + r" nT away from the field steps", 1.0),
    ("refit orbit.csv", r"PROPOSED: held-out RMS " + NUM, r"here " + NUM + " nT against", 1.0),
    ("refit orbit.csv", r"PROPOSED: .* vs active " + NUM, r" nT against " + NUM + " nT", 1.0),
    ("diagnose heldout.csv", r"gap \(held-out, norm of per-axis RMS\): " + NUM, r"of the " + NUM + " nT gap", 1.0),
    ("diagnose heldout.csv", r"time_skew closes " + NUM + "%", r"closes " + NUM + " % of the", 1.0),
    ("diagnose heldout.csv", r"gap \(p = " + NUM, r" gap \(p = " + NUM + r"\)", 1.0),
    ("diagnose heldout.csv", r"dt\[y\]\s+" + NUM, r"0, " + NUM + " and [0-9]+ ms apart", 1e3),
    ("diagnose heldout.csv", r"dt\[z\]\s+" + NUM, r"0, [0-9]+ and " + NUM + " ms apart", 1e3),
]


def test_the_tutorial_goes_from_demo_to_diagnosis():
    text = [line for _, line in LINES]
    firsts = [t.split()[1] for t in text if t.startswith("magstack ")]
    for step in ("demo", "simulate", "fit", "table", "apply", "run", "tm", "refit", "diagnose"):
        assert step in firsts, step
    assert all(t.startswith(("magstack ", "mkdir ", "python3 -m pip install ")) for t in text), text


@pytest.mark.slow
def test_every_command_line_of_the_tutorial_runs_in_order(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    outputs = {}
    for where, line in LINES:
        words = shlex.split(line)
        if words[:4] == ["python3", "-m", "pip", "install"]:
            continue
        if words[0] == "mkdir":
            Path(words[-1]).mkdir(parents=True, exist_ok=True)
            continue
        target = None
        if ">" in words:
            i = words.index(">")
            words, target = words[:i], words[i + 1]
        capsys.readouterr()
        code = main(words[1:])
        out, err = capsys.readouterr()
        assert code == 0, f"{where}: `{line}` exited {code}: {err.strip()[-600:]}"
        both = {s.strip() for s in out.splitlines()} & {s.strip() for s in err.splitlines()} - {""}
        assert not both, f"{where}: `{line}` says the same on stdout and stderr: {sorted(both)[:3]}"
        if target is not None:
            Path(target).write_text(out)
        if words[1:3] == ["run", "--example-config"]:
            Path(target).write_text(own_tc_port(Path(target).read_text()))
        outputs[" ".join(words[1:3])] = out
    assert Path("demo/report.html").is_file() and Path("hmc1053.mcal").stat().st_size == 336
    run_out = outputs["run --config"]
    assert "120 cycles: 120 good, 120 calibrated" in run_out, run_out
    assert Path("candidate.json").is_file() and "PROPOSED" in outputs["refit orbit.csv"]
    assert "verdict: time_skew" in outputs["diagnose heldout.csv"]
    prose = " ".join(TUTORIAL.read_text(encoding="utf-8").split())
    for command, printed, quoted, scale in FIGURES:
        m, q = re.search(printed, outputs[command]), re.search(quoted, prose)
        assert m and q, (command, printed if not m else quoted)
        measured, stated = float(m.group(1)) * scale, float(q.group(1))
        assert abs(measured - stated) <= 0.03 * stated, f"{command}: prints {measured:g}, the tutorial says {stated:g}"


def test_every_figure_check_finds_its_figure_in_the_prose():
    prose = " ".join(TUTORIAL.read_text(encoding="utf-8").split())
    assert [quoted for _, _, quoted, _ in FIGURES if not re.search(quoted, prose)] == []
