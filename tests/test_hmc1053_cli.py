"""`magstack read --chip hmc1053`, the factory's bus specs, and the hardware (hil) smoke test."""
from __future__ import annotations

import math

import pytest

from magstack.cli.main import main
from magstack.drivers.errors import ConfigurationError
from magstack.drivers.registry import DEFAULT_PINS, open_chip, parse_spi_spec


def test_cli_read_hmc1053_on_sim(capsys):
    assert main(["read", "--chip", "hmc1053", "--bus", "sim", "-n", "3"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == "# hmc1053 on sim"
    rows = [list(map(float, ln.split())) for ln in lines[2:]]
    assert len(rows) == 3
    # 7 conversions at 20 SPS per vector: rows 0.356 s apart in virtual time
    assert rows[1][0] - rows[0][0] == pytest.approx(0.355854, abs=2e-6)
    for r in rows:
        assert all(math.isfinite(v) for v in r) and 20 < math.hypot(*r[1:4]) < 100


def test_cli_bad_bus_is_a_clean_error(capsys):
    assert main(["read", "--chip", "hmc1053", "--bus", "spi0", "-n", "1"]) == 2
    assert "bad HMC1053 bus" in capsys.readouterr().err


def test_parse_spi_spec_defaults_and_overrides():
    assert parse_spi_spec("spi0.0") == (0, 0, {**DEFAULT_PINS, "chip": 0, "hz": 1_000_000})
    assert DEFAULT_PINS["start"] == 6 and DEFAULT_PINS["reset"] == 13 and DEFAULT_PINS["drdy"] == 19
    b, c, opts = parse_spi_spec("spi1.2,sr=26,hz=500000")
    assert (b, c, opts["sr"], opts["hz"]) == (1, 2, 26, 500000)
    with pytest.raises(ConfigurationError, match="unknown option"):
        parse_spi_spec("spi0.0,foo=1")
    with pytest.raises(ConfigurationError, match="distinct"):
        parse_spi_spec("spi0.0,sr=6")


def test_sim_factory_passes_options_and_rejects_them_on_hardware():
    from magstack.sim.hmc1053_bridge import IdealSensor, build_sim_hmc1053
    from magstack.sim.truth_source import StaticTruth

    fe = open_chip("hmc1053", "sim", None, truth=StaticTruth((1.0, 2.0, 3.0)), sensor=IdealSensor(),
                   table="hf8.2-8conv")
    assert fe.read().b_uT == pytest.approx((1.0, 2.0, 3.0), abs=1e-3)
    rig = build_sim_hmc1053(None, truth=StaticTruth((1.0, 2.0, 3.0)), sensor=IdealSensor(), table="hf8.2-8conv")
    assert rig.front_end.read().b_uT == pytest.approx((1.0, 2.0, 3.0), abs=1e-3)
    assert rig.adc_model.reads_before_drdy == 0
    with pytest.raises(ConfigurationError, match="simulated bus"):
        open_chip("hmc1053", "spi0.0", None, adc_kwargs={})


@pytest.mark.hil
def test_hil_hmc1053_reads_plausible_field(request):
    """On the bench (see docs/hmc1053-front-end.md): Earth-field-sized vector, sane telemetry."""
    fe = open_chip("hmc1053", f"spi{request.config.getoption('--spi-bus')}", None)
    samples = [fe.read() for _ in range(5)]
    for s in samples:
        assert s.valid
        assert 5.0 < math.hypot(*s.b_uT) < 600.0  # the +-6 G range of the part
        assert all(abs(o) <= 2.0 for o in s.extra["bridge_offset_mV_per_V"])  # spec max 1.25 mV/V
        assert s.temp_c is not None and -40.0 < s.temp_c < 85.0
    dts = [b.t_s - a.t_s for a, b in zip(samples[:-1], samples[1:], strict=True)]
    assert all(abs(dt - fe.table.nominal_cycle_s()) < 0.05 for dt in dts)
