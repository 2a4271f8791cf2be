"""`magstack run --init DIR`: the example configuration with the table it names runs simulated with exit 0."""
from __future__ import annotations

import json

from magstack.cli.main import main
from magstack.firmware import cal_table as ct
from magstack.firmware.flight.config import example_config_text
from tests.netutil import own_tc_port


def test_init_writes_a_configuration_that_runs_calibrated_with_exit_0(tmp_path, capsys, monkeypatch):
    d = tmp_path / "board"
    assert main(["run", "--init", str(d), "--json"]) == 0
    made = json.loads(capsys.readouterr().out)["init"]
    assert (d / "flight.toml").read_text() == example_config_text()
    table = ct.load_table(d / "tables" / "hmc1053.json")
    assert table.device_id == "hmc1053:sn1" and f"0x{table.crc32:08x}" == made["table_crc32"]
    assert ct.validate(table).ok and (d / "bench" / "hmc1053-bench.csv").is_file()
    (d / "flight.toml").write_text(own_tc_port((d / "flight.toml").read_text()))
    monkeypatch.chdir(d)
    assert main(["run", "--config", "flight.toml", "--sim", "--duration", "30", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    hmc = out["channels"]["hmc1053"]
    assert out["degraded"] == [] and hmc["samples_ok"] == 30 and hmc["corrector"]["ok"] == 30
    assert main(["tm", "command", "--config", "flight.toml", "ping", "--send", "-q"]) == 0


def test_init_refuses_a_directory_that_holds_its_files(tmp_path, capsys):
    (tmp_path / "flight.toml").write_text("keep me")
    assert main(["run", "--init", str(tmp_path)]) == 2
    assert "exist" in capsys.readouterr().err and (tmp_path / "flight.toml").read_text() == "keep me"


def test_a_missing_table_names_the_way_to_make_one(tmp_path, capsys, monkeypatch):
    (tmp_path / "flight.toml").write_text(own_tc_port(example_config_text()))
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--config", "flight.toml", "--sim", "--duration", "2"]) == 1
    assert "magstack run --init DIR" in capsys.readouterr().out
