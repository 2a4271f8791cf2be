"""`magstack run`: example config, a simulated run in virtual time, SIGTERM and SIGKILL in real time."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.firmware import cal_table as ct
from tests.netutil import own_tc_port


def _sim_config(tmp_path: Path, *, table: bool = True) -> Path:
    from magstack.firmware.flight.config import example_config_text

    text = own_tc_port(example_config_text()).replace("spi0.0,start=6,reset=13,drdy=19,sr=5", "sim").replace(
        'bus = "1"', 'bus = "sim"')
    if table:
        (tmp_path / "tables").mkdir()
        ct.save_table(ct.CalTable(device_id="hmc1053:sn1", terms=("gain_matrix", "offset"), S=np.eye(3),
                                  O=[0.1, 0.2, 0.3], validity_field_uT=100.0), tmp_path / "tables/hmc1053.json")
    else:
        text = text.replace('table = "tables/hmc1053.json"', "")
    p = tmp_path / "flight.toml"
    p.write_text(text)
    return p


def test_example_config_is_printed(capsys):
    assert main(["run", "--example-config"]) == 0
    assert "[[rate_group]]" in capsys.readouterr().out


def test_simulated_run_in_virtual_time(tmp_path, capsys):
    cfg = _sim_config(tmp_path)
    t0 = time.perf_counter()
    assert main(["run", "--config", str(cfg), "--duration", "120", "--out", str(tmp_path / "tlm"), "--json"]) == 0
    wall = time.perf_counter() - t0
    out = json.loads(capsys.readouterr().out)
    assert out["command"] == "run" and out["exit_code"] == 0 and out["virtual_time"] is True
    assert out["rate_groups"]["slow"]["runs"] == 120 and out["rate_groups"]["fast"]["runs"] == 1200
    assert out["channels"]["hmc1053"]["samples_ok"] == 120 and out["channels"]["hmc1053"]["corrector"]["ok"] == 120
    assert wall < 60     # virtual time: two simulated minutes take seconds
    s = read_session(tmp_path / "tlm" / "hmc1053-0001-0001.csv")
    assert len(s) == 120 and np.all(s.flag == 0) and s.metadata["dut_field"] == "raw"
    events = [json.loads(x) for x in (tmp_path / "tlm" / "events-0001.jsonl").read_text().splitlines()]
    assert [e["name"] for e in events][:2] == ["TABLE_ACTIVATED", "EXEC_STARTED"]


def test_bad_config_is_a_one_line_error(tmp_path, capsys):
    cfg = _sim_config(tmp_path)
    cfg.write_text(cfg.read_text().replace("rotate_mb", "rotate_gb"))
    assert main(["run", "--config", str(cfg), "--duration", "1"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown key(s) ['rotate_gb']" in err[0]
    assert main(["run", "--config", str(cfg), "--duration", "-5"]) == 2


def _start(cfg: Path, out: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "magstack", "run", "--config", str(cfg), "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_rows(out: Path, n: int, timeout_s: float = 30.0) -> None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        parts = list(out.glob("lis3mdl-*.csv.part"))
        if parts and parts[0].read_text().count("\n") > n:
            return
        time.sleep(0.2)
    raise AssertionError("no telemetry rows appeared")


def _stop_cleanly(cfg: Path, out: Path, signum: int, code: int) -> None:
    """A real-time run stopped by ``signum``: the exit code, a message, every file closed and renamed."""
    proc = _start(cfg, out)
    _wait_rows(out, 40)
    proc.send_signal(signum)
    stdout, _ = proc.communicate(timeout=30)
    name = signal.Signals(signum).name
    assert proc.returncode == code and f"{name}: stopped after the cycles under way" in stdout
    assert not list(out.glob("*.part")) and read_session(next(out.glob("lis3mdl-*.csv")))


@pytest.mark.slow
def test_sigterm_stops_cleanly_and_kill_loses_nothing_flushed(tmp_path):
    cfg = _sim_config(tmp_path, table=False)
    cfg.write_text(cfg.read_text().replace("block_rows = 50", "block_rows = 5"))
    _stop_cleanly(cfg, tmp_path / "a", signal.SIGTERM, 143)
    # SIGKILL: every flushed block stays readable in the .part file
    out = tmp_path / "b"
    proc = _start(cfg, out)
    _wait_rows(out, 40)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=30)
    part = next(out.glob("lis3mdl-*.csv.part"))
    s = read_session(part)
    assert len(s) >= 15 and np.all(np.isfinite(s.dut_uT))


def test_refit_commands_over_recorded_telemetry(tmp_path):
    """start_refit runs the on-orbit refit over recorded telemetry in a worker while the rate groups run;
    the proposed candidate is then loaded and activated by the ordinary table commands."""
    from magstack.firmware.flight.app import FlightApp
    from magstack.firmware.flight.config import load_config
    from magstack.firmware.flight.events import EventId

    orbit = tmp_path / "orbit.csv"
    assert main(["simulate", "--program", "orbit_tumbling", "--seconds", "7200", "--rate-hz", "1", "--sessions", "1",
                 "--seed", "3", "--t0", "1780272000", "--effects",
                 "misalignment,gain,offset,noise", "--out", str(orbit)]) == 0
    cfg_path = _sim_config(tmp_path, table=False)
    dev = read_session(orbit).metadata.get("device_id") or "lis3mdl:sn1"
    cfg_path.write_text(cfg_path.read_text().replace('device_id = "lis3mdl:sn1"', f'device_id = "{dev}"'))
    cmd = tmp_path / "commands"
    cmd.mkdir()
    (cmd / "01.json").write_text(json.dumps({"cmd": "start_refit", "channel": "lis3mdl", "files": "orbit*.csv"}))
    app = FlightApp(load_config(cfg_path), virtual=True, simulate=True, telemetry_dir=tmp_path / "tlm")
    try:
        app.run(5.0)
        app.wait_refits(600)
        job = app.refits["lis3mdl"]
        assert job.result["ok"] and job.result.get("candidate_path"), job.result
        assert app.events.count(EventId.REFIT_STARTED, "lis3mdl") == 1
        assert app.events.count(EventId.REFIT_FINISHED, "lis3mdl") == 1
        (cmd / "02.json").write_text(json.dumps({"cmd": "load_table", "channel": "lis3mdl",
                                                 "path": job.result["candidate_path"]}))
        (cmd / "03.json").write_text(json.dumps({"cmd": "activate_table", "channel": "lis3mdl"}))
        (cmd / "04.json").write_text(json.dumps({"cmd": "stop_refit", "channel": "lis3mdl"}))
        app.run(2.0)
        assert app.slots["lis3mdl"].store.active is not None
        assert app.events.count(EventId.TABLE_ACTIVATED, "lis3mdl") == 1
        res = json.loads((cmd / "done" / "04.json.result.json").read_text())
        assert res["ok"] is False and "no refit running" in res["message"]
    finally:
        app.close()


# ---------------------------------------------------------------------------------------------------------
# Warnings on the console, an exit status that says "degraded", one device-id rule.
def test_a_table_for_another_device_id_is_rejected_loudly_and_the_run_exits_1(tmp_path, capsys):
    cfg = _sim_config(tmp_path, table=False)
    (tmp_path / "tables").mkdir()
    # what `magstack fit` writes without --device-id for a bench session: the chip name
    ct.save_table(ct.CalTable(device_id="hmc1053", terms=("gain_matrix", "offset"), S=np.eye(3), O=[0.1, 0.2, 0.3],
                              validity_field_uT=100.0), tmp_path / "tables/hmc1053.json")
    cfg.write_text(cfg.read_text().replace('rate_group = "slow"\n',
                                           'rate_group = "slow"\ntable = "tables/hmc1053.json"\n'))
    assert main(["run", "--config", str(cfg), "--duration", "5", "--out", str(tmp_path / "tlm")]) == 1
    out, err = capsys.readouterr()
    assert "TABLE_REJECTED hmc1053" in err and "table is for device 'hmc1053', channel hmc1053 serves " \
                                              "'hmc1053:sn1'" in err and "fit --device-id hmc1053:sn1" in err
    assert "table none (configured table rejected)" in out and "DEGRADED: channel hmc1053: configured table" in out
    # the documented recipe: fit with --device-id as the config names it -> accepted, exit 0
    ct.save_table(ct.CalTable(device_id="hmc1053:sn1", terms=("gain_matrix", "offset"), S=np.eye(3),
                              O=[0.1, 0.2, 0.3], validity_field_uT=100.0), tmp_path / "tables/hmc1053.json")
    assert main(["run", "--config", str(cfg), "--duration", "5", "--out", str(tmp_path / "tlm")]) == 0
    out, err = capsys.readouterr()
    assert "TABLE_REJECTED" not in err and "DEGRADED" not in out


def test_warning_events_reach_the_console_rate_limited(caplog):
    from magstack.firmware.flight.events import EventId, EventLog

    log = EventLog()
    with caplog.at_level("WARNING", logger="magstack.flight"):
        for _ in range(1000):
            log.emit(0.0, EventId.CHAN_EXCEPTION, "lis3mdl", "ValueError: boom")
            log.emit(0.0, EventId.CHAN_BUS_ERROR, "lis3mdl", "NACK")       # WARNING_LO: counted, not shown
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 6 and all(x.startswith("CHAN_EXCEPTION lis3mdl: ValueError: boom") for x in lines)
    assert lines[-1].endswith("(1000 so far)") and log.count(EventId.CHAN_BUS_ERROR) == 1000


# ---------------------------------------------------------------------------------------------------------
# SIGHUP like SIGTERM, stdout closed by the reader, Ctrl-C at start-up.
@pytest.mark.slow
def test_sighup_stops_run_with_complete_files(tmp_path):
    """SIGHUP (the SSH session went away) stops `run` with complete files, no .part files (`bench`: test_bench.py)."""
    cfg = _sim_config(tmp_path, table=False)
    cfg.write_text(cfg.read_text().replace("block_rows = 50", "block_rows = 5"))
    _stop_cleanly(cfg, tmp_path / "a", signal.SIGHUP, 129)


def test_a_reader_closing_stdout_ends_output_quietly(tmp_path):
    """`magstack ... | true` (the reader is gone before the first write): no BrokenPipeError, no traceback,
    the command completes (a run still writes every file) and exits with its own status, 0."""
    cfg = _sim_config(tmp_path)
    for args in (["run", "--example-config"],
                 ["run", "--config", str(cfg), "--duration", "3", "--out", str(tmp_path / "tlm")]):
        cmd = " ".join([sys.executable, "-m", "magstack", *args]) + " | true; echo rc=${PIPESTATUS[0]}"
        res = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=300)
        assert res.stdout.strip() == "rc=0" and res.stderr == "", (args, res.stdout, res.stderr)
    assert (tmp_path / "tlm" / "summary-0001.json").exists() and not list((tmp_path / "tlm").glob("*.part"))


def test_ctrl_c_while_the_command_line_loads_is_one_line(monkeypatch, capsys):
    import magstack.cli.main as cli_main

    def interrupted(*a, **kw):
        raise KeyboardInterrupt
    monkeypatch.setattr(cli_main, "build_parser", interrupted)
    assert cli_main.main(["run", "--example-config"]) == 130
    assert capsys.readouterr().err.strip() == "magstack: interrupted"


def test_a_configured_table_with_a_huge_integer_is_a_warning_not_a_crash(tmp_path, capsys):
    """A 400-digit integer in the start-up table is a warning, never an OverflowError out of `run`."""
    cfg = _sim_config(tmp_path)
    path = tmp_path / "tables/hmc1053.json"
    doc = json.loads(path.read_text())
    doc["parameters"]["O"]["value"][0] = 10 ** 400
    doc.pop("crc32")
    doc["crc32"] = f"0x{ct._crc(doc):08x}"          # a well-formed file: only the number is hostile
    path.write_text(json.dumps(doc))
    assert main(["run", "--config", str(cfg), "--duration", "3", "--out", str(tmp_path / "tlm")]) == 1
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "TABLE_REJECTED hmc1053" in err and "digits (at most 30)" in err
    assert "DEGRADED: channel hmc1053: configured table rejected" in out


def test_telemetry_table_crc32_is_an_integer(tmp_path, capsys):
    """Telemetry writes table_crc32 as an integer, not 3350503024.000000."""
    cfg = _sim_config(tmp_path)
    assert main(["run", "--config", str(cfg), "--duration", "5", "--out", str(tmp_path / "tlm"), "-q"]) == 0
    f = next(p for p in (tmp_path / "tlm").glob("hmc1053*.csv"))
    lines = f.read_text().splitlines()
    header = next(ln for ln in lines if ln.startswith("t_s")).split(",")
    k = header.index("table_crc32")
    cells = [ln.split(",")[k] for ln in lines[lines.index(",".join(header)) + 1:] if ln and not ln.startswith("#")]
    assert cells and all(c.isdigit() for c in cells if c), cells[:3]


def test_an_orbit_programme_drives_the_simulated_run_on_the_run_clock(tmp_path):
    """`run --sim --sim-program orbit_tumbling` was refused ("unknown program": only `simulate` registered the
    orbit programmes), and the orbit would have started at its own epoch, not the run clock's: the field the
    sensors saw would not belong to the position and attitude at the telemetry's t_s."""
    from magstack.cli.commands.run import _sim_options
    from magstack.drivers.clock import VirtualClock
    from magstack.firmware.flight.config import load_config

    cfg = _sim_config(tmp_path, table=False)
    res = subprocess.run([sys.executable, "-m", "magstack", "run", "--config", str(cfg), "--sim", "--sim-program",
                          "orbit_tumbling", "--duration", "3", "--out", str(tmp_path / "tlm"), "--json"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["simulated"] is True
    s = read_session(next((tmp_path / "tlm").glob("hmc1053-*.csv")))
    assert len(s) == 3 and np.all(s.flag & 0b1111 == 0)
    hmc = next(x for x in load_config(cfg).sensors if x.chip == "hmc1053")
    options = _sim_options("orbit_tumbling", 60.0, 0)
    for epoch in (1767225600.0, 1780000000.5):
        clock = VirtualClock(start_epoch_s=epoch, start_monotonic_s=10.0)
        truth = options(hmc, clock)["truth"]
        assert truth.epoch_unix_s == pytest.approx(epoch - 10.0)     # truth time = the clock's monotonic time
        assert options(hmc, clock)["truth"] is truth
