"""An interrupted command keeps what it finished and leaves no half-made output.

`validate-diagnosis` stopped by Ctrl-C (or SIGTERM) writes the sessions completed so far, marked interrupted;
`diagnose --report` stopped by SIGTERM leaves neither an empty nor a partial report folder. The signals are
sent once the work has reached a known point (a progress line, a staging folder), never after a guessed delay.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading

import pytest


def _default_sigint() -> None:
    # a suite started in the background by a non-interactive shell inherits SIGINT ignored, and Python then keeps
    # it ignored: the child gets the default disposition (Ctrl-C raises KeyboardInterrupt) whatever the parent had
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _magstack(*args: str, cwd) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "magstack", *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupted_validation_writes_the_sessions_done_so_far(tmp_path, signum, code):
    from magstack.ground.diagnose.validate import jobs_count

    out = tmp_path / "vd"
    proc = _magstack("validate-diagnosis", "--seconds", "600", "--nulls", "1", "--out", str(out),
                     "--json", str(tmp_path / "vd.json"), "-v", cwd=tmp_path)
    err = []
    for line in proc.stderr:           # the first session's progress line, then the signal
        err.append(line)
        if "session 1 of" in line:
            proc.send_signal(signum)
            break
    stdout, rest = proc.communicate(timeout=300)
    name = signal.Signals(signum).name
    assert proc.returncode == code, "".join(err) + rest
    doc = json.loads((out / "results.json").read_text())
    s, rows = doc["summary"], doc["sessions"]
    assert s["interrupted"] is True and s["stopped_by"] == name
    assert s["sessions_completed"] == len(rows) >= 1 and s["sessions_planned"] == jobs_count(1, 1) > len(rows)
    assert rows[0]["kind"] == "withheld" and set(s["targets"].values()) == {None}
    assert "**Interrupted**" in (out / "summary.md").read_text()
    assert (out / "confusion.csv").read_text().startswith("withheld\\verdict,")
    assert sorted(p.name for p in out.iterdir()) == ["confusion.csv", "results.json", "summary.md"]
    # the table it prints, then one line saying what happened and what was saved
    assert "| effect | found (realistic)" in stdout
    assert stdout.rstrip().splitlines()[-1] == (f"interrupted by {name} after {len(rows)} of {s['sessions_planned']} "
                                                f"sessions: wrote the partial results.json, confusion.csv and "
                                                f"summary.md to {out}")
    j = json.loads((tmp_path / "vd.json").read_text())
    assert j["exit_code"] == code and j["interrupted"] is True and j["sessions_completed"] == len(rows)
    assert "Traceback" not in "".join(err) + rest


def test_validation_interrupted_in_its_first_session_writes_nothing(tmp_path, monkeypatch):
    import magstack.ground.diagnose.validate as v

    def ctrl_c(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(v, "simulate", ctrl_c)
    s = v.run_validation(tmp_path / "vd", n_null=1, duration_s=600.0)
    assert s["interrupted"] and s["stopped_by"] == "SIGINT" and s["sessions_completed"] == 0
    assert not (tmp_path / "vd").exists()


def test_validation_interrupted_after_one_session_summarises_it(tmp_path):
    from magstack.cli.interrupt import Stopped
    from magstack.ground.diagnose.validate import run_validation

    def sigterm():
        raise Stopped("SIGTERM")
    s = run_validation(tmp_path / "vd", n_null=1, duration_s=600.0, on_session=sigterm)
    doc = json.loads((tmp_path / "vd" / "results.json").read_text())
    assert s["sessions_completed"] == len(doc["sessions"]) == 1 and doc["summary"]["stopped_by"] == "SIGTERM"
    assert s["per_effect"]["time_skew"]["scale_1"]["n"] == 1 and "scale_0.5" not in s["per_effect"]["time_skew"]


def test_sigterm_during_diagnose_report_leaves_no_folder(tmp_path):
    """Before: SIGTERM killed the process while the page was written, leaving an empty folder or one holding
    only a hidden temporary file; now the page is made in a staging folder that is removed on SIGTERM."""
    from magstack.cli.main import main

    assert main(["simulate", "--program", "steps_xyz", "--seconds", "600", "--out", str(tmp_path / "s.csv"),
                 "-q"]) == 0
    rep = tmp_path / "rep"
    proc = _magstack("diagnose", "s.csv", "--block-s", "30", "--report", str(rep), "-q", cwd=tmp_path)
    while proc.poll() is None and not list(tmp_path.glob(".rep.tmp-*")):
        threading.Event().wait(0.005)   # poll for the staging folder: the report is being drawn
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and err == "magstack diagnose: stopped by SIGTERM\n"
    assert not rep.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["s.csv"]


def test_staged_directory_appears_whole_or_not_at_all(tmp_path):
    from magstack.data.io import staged_directory

    new = tmp_path / "new"
    with staged_directory(new) as st:
        (st / "a.txt").write_text("a")
        assert not new.exists()
    umask = os.umask(0o022)
    os.umask(umask)
    assert (new / "a.txt").read_text() == "a" and new.stat().st_mode & 0o777 == 0o777 & ~umask   # not mkdtemp's
    (new / "keep.txt").write_text("k")
    with staged_directory(new) as st:
        (st / "a.txt").write_text("b")
    assert (new / "a.txt").read_text() == "b" and (new / "keep.txt").exists()
    with pytest.raises(KeyboardInterrupt), staged_directory(tmp_path / "never") as st:
        (st / "a.txt").write_text("a")
        raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new"]
