"""``magstack calibrate`` from files and live (simulated, under a pseudo-terminal); PX4/ArduPilot exports."""
from __future__ import annotations

import json
import os
import pty
import re
import select
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.firmware.cal_table import load_table
from magstack.ground.export import ardupilot, load_exporters, px4, read_params, table_output
from magstack.sim.hand_rotation import site_field_ned_uT

F = float(np.linalg.norm(site_field_ned_uT()))


@pytest.fixture(scope="module")
def hand_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("hand")
    out = {}
    for prog, secs in (("hand", 80), ("hand_flat", 40)):
        p = d / f"{prog}.csv"
        assert main(["simulate", "--chip", "hmc5983", "--program", prog, "--seconds", str(secs), "--sessions", "1",
                     "--rate-hz", "50", "--out", str(p), "--quiet"]) == 0
        out[prog] = p
    return out


def test_calibrate_files_writes_table_and_exports_that_round_trip(hand_file, tmp_path, capsys):
    cal, px, ap = tmp_path / "cal.json", tmp_path / "cal.params", tmp_path / "cal.parm"
    code = main(["calibrate", str(hand_file["hand"]), "--field-uT", f"{F:.4f}", "--out", str(cal), "--px4", str(px),
                 "--ardupilot", str(ap), "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0 and doc["written"] and cal.exists()
    assert set(doc["exports"]) == {"px4", "ardupilot"}
    table = load_table(cal)
    s = read_session(hand_file["hand"])
    b = s.dut_uT[np.all(np.isfinite(s.dut_uT), axis=1)]
    # each convention's documented formula applied to raw samples, from the written file, equals the table's own
    # output on the terms it holds (the table evaluated at the session's temperature, rotation part dropped)
    from magstack.ground.export import held_linear

    M, c, _, _, _ = held_linear(table, None, s.temp_c, symmetric=True, sensor_bounds="x")
    want = b @ M.T + c
    for mod, path in ((px4, px), (ardupilot, ap)):
        got = mod.apply_params(read_params(path.read_text()), b)
        assert np.abs(got - want).max() * 1e3 < 0.1
    assert "CAL_MAG0_XODIAG" in px.read_text() and "COMPASS_ODI_X" in ap.read_text()
    # what they drop is said, with its cost on the session
    dropped = doc["exports"]["px4"]["dropped"]
    assert any("temperature" in d["term"] for d in dropped)


def test_round_trip_of_a_symmetric_table_is_exact(hand_file, tmp_path):
    assert main(["calibrate", str(hand_file["hand"]), "--field-uT", f"{F:.4f}", "--frame", "sensor",
                 "--temperature", "off", "--out", str(tmp_path / "c.json"), "--quiet"]) == 0
    table = load_table(tmp_path / "c.json")
    b = read_session(hand_file["hand"]).dut_uT
    ref = table_output(table, b, None)
    for name, ex in load_exporters().items():
        e = ex.build(table, b, None)
        mod = px4 if name == "px4" else ardupilot
        got = mod.apply_params(read_params(e.text), b)
        assert np.abs(got - ref).max() * 1e3 < 0.1, name
        assert not e.dropped


def test_flat_session_is_refused_without_a_table(hand_file, tmp_path, capsys):
    out = tmp_path / "flat.json"
    assert main(["calibrate", str(hand_file["hand_flat"]), "--field-uT", f"{F:.4f}", "--out", str(out)]) == 3
    cap = capsys.readouterr()
    assert "refused" in cap.err and not out.exists()
    assert "cover" in cap.err


def test_usage_errors(tmp_path):
    assert main(["calibrate", "--out", str(tmp_path / "c.json")]) == 2
    assert main(["calibrate", "--bus", "sim", "--out", str(tmp_path / "c.json")]) == 2       # no --chip
    assert main(["calibrate", "--chip", "lis3mdl", "--bus", "sim", "--site", "52,4", "--field-uT", "49",
                 "--out", str(tmp_path / "c.json")]) == 2


def _run_in_pty(argv, stop_after_s=None, timeout_s=120.0):
    """Run ``argv`` with a pseudo-terminal as stdout/stderr; optionally send Ctrl-C after ``stop_after_s``."""
    master, slave = pty.openpty()
    os.set_blocking(master, False)
    env = dict(os.environ, COLUMNS="100", LINES="40", TERM="xterm")
    proc = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, env=env, start_new_session=True)
    os.close(slave)
    out = bytearray()
    t0 = time.monotonic()
    sent = False
    while True:
        r, _, _ = select.select([master], [], [], 0.2)
        chunk = b""
        if r:
            try:
                chunk = os.read(master, 65536)
            except OSError:          # the child closed the terminal
                chunk = b""
            out += chunk
        if stop_after_s is not None and not sent and time.monotonic() - t0 > stop_after_s:
            os.killpg(proc.pid, signal.SIGINT)
            sent = True
        if proc.poll() is not None and not chunk:
            break
        if time.monotonic() - t0 > timeout_s:
            proc.kill()
            break
    os.close(master)
    return proc.wait(), out.decode("utf-8", "replace")


@pytest.mark.slow
def test_live_view_under_a_pty_redraws_and_ctrl_c_keeps_the_recording(tmp_path):
    cal = tmp_path / "cal.json"
    code, text = _run_in_pty([sys.executable, "-m", "magstack", "calibrate", "--chip", "hmc5983", "--bus", "sim",
                              "--seconds", "60", "--no-holdout", "--field-uT", f"{F:.4f}", "--allow-poor-coverage",
                              "--out", str(cal)], stop_after_s=9.0)
    assert code == 0, text[-2000:]
    frames = text.count("field sphere (board frame)")
    m = re.search(r"recorded (\d+) samples at ([\d.]+) Hz .* \((\d+) gaps.*view redrawn (\d+) times \(([\d.]+) Hz\)",
                  text.replace("\r\n", " ").replace("\n", " "))
    assert m, text[-3000:]
    n, rate, gaps, redraws, redraw_hz = int(m[1]), float(m[2]), int(m[3]), int(m[4]), float(m[5])
    assert gaps == 0 and abs(rate - 100.0) < 1.0 and n > 500
    assert redraw_hz >= 5.0 and frames >= redraws - 1
    assert "stopped by SIGINT" in text and cal.exists()
    assert "\x1b[H\x1b[J" in text                                       # plain ANSI redraw, no curses
