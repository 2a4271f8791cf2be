"""Issue 26 "On the Raspberry Pi": without lgpio, or with a gpiochip that cannot be opened, the GPIO path
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
