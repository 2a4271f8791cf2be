"""`magstack run --sim --duration S --scenario ground.toml`: ground actions at virtual times, with the flight
standing still; the executive's pauses; the scenario file's checks."""
from __future__ import annotations

import json

import pytest

from magstack.cli.main import main
from magstack.cli.scenario import example_scenario_text, load_scenario
from magstack.firmware.errors import FlightConfigError
from tests.test_ccsds_packets import sim_config


def _scenario(tmp_path, text: str):
    p = tmp_path / "ground.toml"
    p.write_text(text)
    return p


def test_actions_run_at_their_virtual_time_and_see_every_packet_so_far(tmp_path, capsys, monkeypatch):
    sim_config(tmp_path)
    monkeypatch.chdir(tmp_path)
    _scenario(tmp_path, '[[at]]\nt_s = 5\nrun = "magstack tm command --config flight.toml ping --send"\n\n'
                        '[[at]]\nt_s = 10\nrun = "magstack tm decode tlm/packets-0001.bin --out dec10/"\n')
    assert main(["run", "--config", "flight.toml", "--duration", "12", "--out", "tlm", "--scenario", "ground.toml",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [(a["t_s"], a["exit_code"]) for a in out["scenario"]["actions"]] == [(5.0, 0), (10.0, 0)]
    assert out["scenario"]["failed"] is None and out["degraded"] == []
    rep = json.loads((tmp_path / "dec10" / "decode-report.json").read_text())
    # at 10 s: the hmc1053 rows of 10 slots and the lis3mdl rows of 100 (101: the 10 Hz grid, summed in floats,
    # puts its 101st slot a hair before 10 s), all in the file; the ping answered
    assert 10 + 100 <= rep["by_packet"]["channel"] <= 10 + 101 and rep["by_packet"]["ping_reply"] == 1
    assert rep["bad_packets"] == 0


def test_a_failing_action_stops_the_run_with_exit_1(tmp_path, capsys, monkeypatch):
    sim_config(tmp_path)
    monkeypatch.chdir(tmp_path)
    _scenario(tmp_path, '[[at]]\nt_s = 3\nrun = "magstack tm decode missing.bin --out d/"\n\n'
                        '[[at]]\nt_s = 6\nrun = "magstack tm dictionary"\n')
    assert main(["run", "--config", "flight.toml", "--duration", "20", "--out", "tlm", "--scenario", "ground.toml",
                 "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert len(out["scenario"]["actions"]) == 1 and "exited 3 (expected 0)" in out["scenario"]["failed"]
    assert out["rate_groups"]["slow"]["runs"] == 3             # stopped at the pause: no slot after it
    assert any("missing.bin" in d for d in out["degraded"])


@pytest.mark.parametrize("text, msg", [
    ('[[at]]\nt_s = 50\nrun = "magstack tm dictionary"\n', "t_s: a time in 0..20"),
    ('[[at]]\nt_s = 1\nrun = "ls -l"\n', "a magstack command line"),
    ('[[at]]\nt_s = 1\nrun = "magstack tm dictionary > x.md"\n', "no shell"),
    ('[[at]]\nt_s = 1\nrun = "magstack tm dictionary"\nexpect = "0"\n', "expect: an exit status"),
    ('[[at]]\nt_s = 1\n', "keys t_s, run"),
    ('wait = 3\n', "needs [[at]] entries"),
])
def test_bad_scenarios_are_refused_naming_the_entry(tmp_path, text, msg):
    with pytest.raises(FlightConfigError, match=msg.replace("[", r"\[")):
        load_scenario(_scenario(tmp_path, text), 20.0)


def test_scenario_needs_virtual_time_and_the_example_parses(tmp_path, capsys):
    cfg = sim_config(tmp_path)
    _scenario(tmp_path, '[[at]]\nt_s = 1\nrun = "magstack tm dictionary"\n')
    assert main(["run", "--config", str(cfg), "--sim", "--scenario", str(tmp_path / "ground.toml")]) == 2
    assert "needs virtual time" in capsys.readouterr().err
    s = load_scenario(_scenario(tmp_path, example_scenario_text()), 430.0)
    assert [a.argv[0] for a in s.actions] == ["tm", "merge", "refit", "tm", "tm"]
    assert main(["run", "--example-scenario"]) == 0 and "[[at]]" in capsys.readouterr().out
