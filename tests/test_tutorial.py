"""docs/tutorial.md, run as a new user would: every command line of its code blocks, in order, in an empty directory,
each with exit 0, and the outcomes the prose states (the flight run calibrates every HMC1053 sample, the refit
proposes a candidate, the diagnosis names `time_skew`).

Adaptations, each explicit: the install line (`python3 -m pip install ...`) is not run (the suite runs in an
installed environment); `mkdir` is done by Python; the example configuration's telecommand port is replaced by a
free one after `run --example-config` wrote it, as tests run in parallel."""
from __future__ import annotations

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
