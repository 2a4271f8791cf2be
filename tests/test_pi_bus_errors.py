"""On the Raspberry Pi: without lgpio, or with a gpiochip that cannot be opened, the GPIO path
is one BusError (exit 4), not a ModuleNotFoundError or lgpio's own exception; the SPI open error names
/dev/spidevB.C. Fake ``lgpio``/``spidev`` modules stand in for the Pi's."""
from __future__ import annotations

import sys
import types

import pytest

from magstack.drivers.errors import BusError
from magstack.errors import EXIT_DEVICE


@pytest.fixture(autouse=True)
def _fresh_handles():
    from magstack.drivers.bus import gpio

    gpio._Lgpio._handles.clear()
    yield
    gpio._Lgpio._handles.clear()


def test_missing_lgpio_is_a_bus_error(monkeypatch):
    from magstack.drivers.bus.gpio import LgpioInputLine, LgpioOutputLine

    monkeypatch.setitem(sys.modules, "lgpio", None)   # import lgpio -> ImportError
    for make in (lambda: LgpioOutputLine(6), lambda: LgpioInputLine(19)):
        with pytest.raises(BusError, match="lgpio is not installed") as exc:
            make()
        assert exc.value.exit_code == EXIT_DEVICE


def test_lgpio_errors_name_the_gpiochip(monkeypatch):
    from magstack.drivers.bus.gpio import LgpioOutputLine

    fake = types.ModuleType("lgpio")

    class error(Exception):   # lgpio.error is not an OSError
        pass

    def gpiochip_open(chip):
        raise error("can not open gpiochip")
    fake.error, fake.gpiochip_open = error, gpiochip_open
    monkeypatch.setitem(sys.modules, "lgpio", fake)
    with pytest.raises(BusError, match="/dev/gpiochip0: open failed: can not open gpiochip"):
        LgpioOutputLine(6)


def test_spi_open_error_names_the_device_node(monkeypatch):
    from magstack.drivers.bus.spi import SpidevSpiBus

    fake = types.ModuleType("spidev")

    class SpiDev:
        def open(self, bus, device):
            raise FileNotFoundError(2, "No such file or directory")
    fake.SpiDev = SpiDev
    monkeypatch.setitem(sys.modules, "spidev", fake)
    with pytest.raises(BusError, match=r"cannot open /dev/spidev0\.1: No such file or directory") as exc:
        SpidevSpiBus(0, 1, mode=1, max_speed_hz=500_000)
    assert exc.value.exit_code == EXIT_DEVICE


def test_lgpio_gets_a_writable_work_dir_when_the_current_one_is_not(monkeypatch, tmp_path):
    """lgpio creates its notification pipe in $LG_WD or the current directory; started in an unwritable one (a
    service in /) its import failed with FileNotFoundError (found by hil/pi-emulated-check.sh)."""
    import os

    from magstack.drivers.bus import gpio

    monkeypatch.delenv("LG_WD", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    cwd = os.getcwd()
    monkeypatch.setattr(gpio.os, "access", lambda p, mode: p != cwd)
    assert gpio.lgpio_work_dir() == str(tmp_path)
    monkeypatch.setitem(sys.modules, "lgpio", types.ModuleType("lgpio"))
    gpio._lgpio_module(0)
    assert os.environ["LG_WD"] == str(tmp_path)
    # a writable current directory, or LG_WD already set: left alone
    monkeypatch.setattr(gpio.os, "access", lambda p, mode: True)
    monkeypatch.delenv("LG_WD")
    assert gpio.lgpio_work_dir() is None
    monkeypatch.setenv("LG_WD", "/somewhere")
    assert gpio.lgpio_work_dir() is None


def test_lgpio_that_cannot_start_is_a_bus_error(monkeypatch):
    import builtins

    from magstack.drivers.bus import gpio

    real = builtins.__import__

    def fail(name, *a, **k):
        if name == "lgpio":
            raise FileNotFoundError(2, "No such file or directory", ".lgd-nfy0")
        return real(name, *a, **k)

    monkeypatch.delitem(sys.modules, "lgpio", raising=False)
    monkeypatch.setattr(builtins, "__import__", fail)
    with pytest.raises(BusError, match="lgpio cannot start.*LG_WD") as exc:
        gpio._lgpio_module(0)
    assert exc.value.exit_code == EXIT_DEVICE
