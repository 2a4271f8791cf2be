"""flight.toml loader: the shipped example, clear errors naming the key, and fuzzed files (only typed errors)."""
from __future__ import annotations

import tomllib

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magstack.firmware.errors import FlightConfigError
from magstack.firmware.flight.config import example_config_text, load_config, parse_config


def _write(tmp_path, text):
    p = tmp_path / "flight.toml"
    p.write_text(text)
    return p


def test_example_config_loads(tmp_path):
    cfg = load_config(_write(tmp_path, example_config_text()))
    assert [s.chip for s in cfg.sensors] == ["hmc1053", "lis3mdl"]
    assert cfg.group("slow").period_s == 1.0 and cfg.sensors[0].table == str(tmp_path / "tables/hmc1053.json")
    assert cfg.telemetry_dir == tmp_path / "telemetry" and cfg.rotate_bytes == 16 << 20
    assert not cfg.simulated


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace('rotate_mb = 16', 'rotate_mb = 16\nrotate_gb = 1'),
     r"flight: unknown key\(s\) \['rotate_gb'\]"),
    (lambda t: t.replace('bus = "1"', 'buss = "1"'), r"sensor\[1\]: missing required key\(s\) \['bus'\]"),
    (lambda t: t.replace('rate_hz = 10.0', 'rate_hz = 500.0'), r"sensor\[1\].rate_group: lis3mdl delivers"),
    (lambda t: t.replace('rate_hz = 1.0', 'rate_hz = 5.0'), r"sensor\[0\].rate_group: hmc1053 delivers"),
    (lambda t: t.replace('rate_hz = 1.0', 'rate_hz = -1.0'), r"rate_group\[0\].rate_hz: must be a number"),
    (lambda t: t.replace('rate_hz = 1.0', 'rate_hz = "fast"'), r"rate_group\[0\].rate_hz: must be a number"),
    (lambda t: t.replace('rate_group = "fast"', 'rate_group = "medium"'), r"sensor\[1\].rate_group: no rate group"),
    (lambda t: t.replace('chip = "lis3mdl"', 'chip = "rm3100"'), r"sensor\[1\].chip: unknown chip 'rm3100'"),
    (lambda t: t.replace('name = "lis3mdl"', 'name = "hmc1053"'), "names must be unique"),
    (lambda t: t.replace('odr_hz = 20.0', 'odr_hz = 21.0'), r"sensor\[1\].options: invalid driver options"),
    (lambda t: t.replace('spi0.0,start=6,reset=13,drdy=19,sr=5', '1'), "sensors on one bus must share a rate group"),
    (lambda t: t + "\n[extra]\nx = 1\n", r"document: unknown key\(s\) \['extra'\]"),
    (lambda t: t.replace('[flight]', '[flight\n'), "not valid TOML"),
])
def test_bad_configs_name_the_key(tmp_path, edit, match):
    with pytest.raises(FlightConfigError, match=match):
        load_config(_write(tmp_path, edit(example_config_text())))


def test_missing_file_and_binary(tmp_path):
    with pytest.raises(FlightConfigError, match="cannot read"):
        load_config(tmp_path / "nope.toml")
    p = tmp_path / "b.toml"
    p.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(FlightConfigError, match="not UTF-8"):
        load_config(p)


_values = st.recursive(st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True)
                       | st.text(max_size=12), lambda c: st.lists(c, max_size=3)
                       | st.dictionaries(st.text(max_size=8), c, max_size=3), max_leaves=8)


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_fuzzed_configs_raise_only_config_errors(tmp_path, data):
    """Replace or delete random keys of the example: the loader returns a config or FlightConfigError."""
    doc = tomllib.loads(example_config_text())
    for _ in range(data.draw(st.integers(1, 3))):
        section = data.draw(st.sampled_from(["flight", "rate_group", "sensor"]))
        target = doc[section] if section == "flight" else data.draw(st.sampled_from(doc[section]))
        key = data.draw(st.sampled_from(sorted(target) + ["bogus"]))
        if data.draw(st.booleans()):
            target.pop(key, None)
        else:
            target[key] = data.draw(_values)
    try:
        parse_config(doc, tmp_path / "flight.toml")
    except FlightConfigError:
        pass


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace("rotate_mb = 16", "rotate_mb = " + "9" * 400), "invalid value"),     # float() overflows
    (lambda t: t.replace("rotate_mb = 16", "rotate_mb = " + "9" * 5000), "not a usable TOML document"),
    (lambda t: t.replace("rotate_mb = 16", "rotate_mb = " + "[" * 5000 + "]" * 5000), "not a usable TOML"),
    (lambda t: t.replace('telemetry_dir = "telemetry"', 'telemetry_dir = "telemetry"\ntable_roots = []'),
     r"flight.table_roots: must be a non-empty array"),
    (lambda t: t.replace('telemetry_dir = "telemetry"', 'telemetry_dir = "telemetry"\ncommands_per_cycle = 0'),
     r"flight.commands_per_cycle: must be an integer"),
])
def test_hostile_configs_are_one_line_errors(tmp_path, edit, match):
    """Fuzzed configs: huge integers and deep nesting in flight.toml are config errors, not crashes."""
    with pytest.raises(FlightConfigError, match=match):
        load_config(_write(tmp_path, edit(example_config_text())))


def test_a_config_that_is_not_a_regular_file_never_blocks(tmp_path):
    import os

    fifo = tmp_path / "flight.toml"
    os.mkfifo(fifo)
    with pytest.raises(FlightConfigError, match="not a regular file"):
        load_config(fifo)
    with pytest.raises(FlightConfigError, match="not a regular file"):
        load_config("/dev/zero")


def test_roots_default_to_the_config_directory(tmp_path):
    cfg = load_config(_write(tmp_path, example_config_text()))
    assert cfg.table_roots == (tmp_path,) and cfg.refit_roots == (tmp_path,)
    assert cfg.command_rate_hz == 2.0 and cfg.commands_per_cycle == 8
