"""Probe/identify on the simulated bench, the chip registry and the probe/read CLI commands."""
from __future__ import annotations

from itertools import pairwise

import pytest

from magstack.cli.main import main
from magstack.drivers import registry as chip_registry
from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import BusError, ConfigurationError, DeviceNotFound
from magstack.drivers.i2c_probe import identify, probe, scan
from magstack.drivers.lis3mdl import LIS3MDL
from magstack.drivers.magnetometer import Magnetometer
from magstack.sim.i2c_bench import default_bench
from magstack.sim.i2c_bus import SimI2CBus
from magstack.sim.i2c_register_model import RO, IdealSensor, Reg, RegisterFileModel
from magstack.sim.lis3mdl_model import LIS3MDLModel
from magstack.sim.truth_source import StaticTruth

#: every test runs against the part-faithful simulator and against the strict lints
pytestmark = pytest.mark.usefixtures("sim_profile")


def test_default_bench_layout_and_probe():
    bench = default_bench()
    assert set(bench.buses) == {"sim-i2c-1", "sim-i2c-2"}
    assert bench.buses["sim-i2c-1"].addresses() == [0x1C, 0x1E]
    assert bench.buses["sim-i2c-2"].addresses() == [0x1E]
    got = {(name, r.address): (r.chip, r.identity) for name, bus in bench.buses.items() for r in probe(bus)}
    assert got == {("sim-i2c-1", 0x1C): ("lis3mdl", b"\x3d"),
                   # freshly powered HMC5983: temperature word 0, as an HMC5883L reads: not guessed
                   ("sim-i2c-1", 0x1E): ("hmc5883l_or_hmc5983", b"H43\x00\x00"),
                   ("sim-i2c-2", 0x1E): ("lsm303dlhc", b"H43\x3c")}


def test_default_bench_chips_draw_independent_noise():
    """Each chip's error model has its own random stream (one shared seed made the chips' noise
    identical draw for draw: correlation 1.0); still deterministic in the bench seed."""
    import numpy as np

    truth = StaticTruth()

    def noise(bench, chip):
        s = bench.model(chip).sensor
        return np.array([s.sense(0.01 * i, truth) for i in range(500)])[:, 0]

    a, b = default_bench(seed=4), default_bench(seed=4)
    h, d = noise(a, "hmc5983"), noise(a, "lsm303dlhc")
    assert abs(np.corrcoef(h, d)[0, 1]) < 0.2
    np.testing.assert_array_equal(h, noise(b, "hmc5983"))
    assert not np.array_equal(h, noise(default_bench(seed=5), "hmc5983"))


def test_lis3mdl_at_shared_address_is_identified():
    clock = VirtualClock()
    bus = SimI2CBus()
    bus.attach(0x1E, LIS3MDLModel(clock, StaticTruth(), IdealSensor(), address=0x1E))
    assert identify(bus, 0x1E).chip == "lis3mdl"
    d = LIS3MDL(bus, clock, address=0x1E, stuck_limit=None)
    assert d.read().valid


def test_absent_and_unknown_devices():
    bus = SimI2CBus()
    assert scan(bus) == []
    with pytest.raises(DeviceNotFound):
        identify(bus, 0x1E)
    bus.attach(0x50, RegisterFileModel([Reg(0x00, "X", RO, 0x77)], name="eeprom"))
    (r,) = probe(bus)
    assert r.address == 0x50 and r.chip is None


def _hmc5883l(lints=()):
    regs = [Reg(a, f"R{a}", RO, 0) for a in range(0x00, 0x0A)] + [Reg(0x0A, "IRA", RO, 0x48),
                                                                    Reg(0x0B, "IRB", RO, 0x34),
                                                                    Reg(0x0C, "IRC", RO, 0x33)]
    return RegisterFileModel(regs, name="hmc5883l", lints=lints)


def test_hmc5883l_is_never_reported_as_an_hmc5983():
    """HMC5883L p.11: an invalid address reads 0 and the part ACKs, so 0x31 answers 0 on a real
    HMC5883L. It is not identified as an HMC5983 (whose driver would set the reserved CRA7 and
    report a constant fake 25 degC)."""
    bus = SimI2CBus()
    bus.attach(0x1E, _hmc5883l())
    r = identify(bus, 0x1E)
    assert r.chip == "hmc5883l_or_hmc5983" and "temperature=False" in r.notes
    # with the opt-in lint the unmapped register NACKs (not datasheet behaviour): then it is no HMC5983
    bus2 = SimI2CBus()
    bus2.attach(0x1E, _hmc5883l(lints=("nack_invalid_address",)))
    assert identify(bus2, 0x1E).chip == "hmc5883l"


def test_hmc5983_with_a_temperature_reading_is_identified():
    """A nonzero temperature word cannot come from an HMC5883L: positive evidence of an HMC5983."""
    from magstack.drivers.hmc5983 import HMC5983

    clock = VirtualClock()
    bench = default_bench(clock, StaticTruth(temp_c=21.0))
    bus = bench.buses["sim-i2c-1"]
    assert identify(bus, 0x1E).chip == "hmc5883l_or_hmc5983"
    HMC5983(bus, clock, stuck_limit=None).read()      # TS on, one conversion: 21 degC is a nonzero word
    r = identify(bus, 0x1E)
    assert r.chip == "hmc5983" and r.identity == b"H43\xfe\x00"


def test_probe_survives_nacks():
    bench = default_bench()
    bus = bench.buses["sim-i2c-1"]
    bus.inject_nack(0x1C, 1)      # the scan's quick write is NACKed: the register-read fallback finds it
    assert [r.chip for r in probe(bus)] == ["lis3mdl", "hmc5883l_or_hmc5983"]
    bus.inject_nack(0x1C, 3)      # scan, identify's quick write and its WHO_AM_I read all NACKed: absent
    assert [r.chip for r in probe(bus)] == ["hmc5883l_or_hmc5983"]


def test_registry_entries_and_factories():
    assert chip_registry.backend_name("sim") == "sim" and chip_registry.backend_name("1") == "linux"
    assert chip_registry.is_simulated("SIM") and not chip_registry.is_simulated("/dev/i2c-1")
    assert {"lis3mdl", "hmc5983", "lsm303dlhc", "hmc1053"} <= set(chip_registry.chip_names())
    clock = VirtualClock()
    bench = default_bench(clock)
    for chip in ("lis3mdl", "hmc5983", "lsm303dlhc"):
        mag = chip_registry.open_chip(chip, "sim", clock, bench=bench)
        assert isinstance(mag, Magnetometer) and mag.name == chip
        s = mag.read()
        assert len(s.b_uT) == 3 and s.temp_c is not None
    with pytest.raises(ConfigurationError, match="valid"):
        chip_registry.open_chip("rm3100", "sim", clock)
    assert chip_registry.parse_i2c_bus("/dev/i2c-1") == 1 and chip_registry.parse_i2c_bus("3") == 3
    with pytest.raises(ConfigurationError):
        chip_registry.parse_i2c_bus("i2c1")


def test_registry_real_bus_missing_gives_bus_error():
    with pytest.raises(BusError, match="cannot open"):
        chip_registry.open_chip("lis3mdl", "/dev/i2c-97", VirtualClock())


def test_cli_probe_sim(capsys):
    assert main(["probe", "--bus", "sim"]) == 0
    out = capsys.readouterr().out
    import re
    assert re.search(r"sim-i2c-1 +0x1c +lis3mdl", out)
    assert re.search(r"sim-i2c-1 +0x1e +hmc5883l_or_hmc5983", out)
    assert re.search(r"sim-i2c-2 +0x1e +lsm303dlhc", out)
    assert "48 34 33 3c 'H43<'" in out


@pytest.mark.parametrize("chip", ["lis3mdl", "hmc5983", "lsm303dlhc"])
def test_cli_read_sim(capsys, chip):
    assert main(["read", "--chip", chip, "--bus", "sim", "-n", "4"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln and not ln.startswith("#")]
    assert lines[0].split() == ["t_s", "x_uT", "y_uT", "z_uT", "temp_c"]
    rows = [list(map(float, ln.split())) for ln in lines[1:]]
    assert len(rows) == 4
    assert all(b[0] > a[0] for a, b in pairwise(rows))


def test_cli_read_options_and_errors(capsys):
    assert main(["read", "--chip", "lis3mdl", "-n", "2", "--range", "1600", "--rate", "1000"]) == 0
    assert "range_uT=1600 odr_hz=1000" in capsys.readouterr().out
    assert main(["read", "--chip", "hmc5983", "-n", "1", "--range", "500"]) == 2
    err = capsys.readouterr().err
    assert "error: invalid hmc5983 range_uT 500" in err and "88, 130" in err
    assert main(["read", "--chip", "nosuchchip"]) == 2   # usage error: exit 2, no SystemExit out of main()
    assert "argument --chip: invalid choice: 'nosuchchip'" in capsys.readouterr().err
    for bad in (["-n", "0"], ["--range", "nan"], ["--rate", "-1"]):
        assert main(["read", "--chip", "lis3mdl", *bad]) == 2
        assert f"argument {bad[0]}: " in capsys.readouterr().err
