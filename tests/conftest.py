"""Shared fixtures and the hardware selection options.

``pytest --hil --i2c-bus 1`` runs the tests marked ``hil`` against real hardware;
without ``--hil`` they are skipped. See hil/README.md for wiring.
"""
from __future__ import annotations

import logging
import os

import pytest
from hypothesis import settings

from magstack.drivers.clock import VirtualClock

# CI replays a fixed set of examples (no database, derandomised) so a run is reproducible;
# developers' runs keep exploring new examples. Property tests set their own example counts.
settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


def pytest_addoption(parser):
    g = parser.getgroup("magstack hardware-in-the-loop")
    g.addoption("--hil", action="store_true", default=os.environ.get("MAGSTACK_HIL") == "1",
                help="run hil-marked tests on real hardware (or MAGSTACK_HIL=1)")
    g.addoption("--i2c-bus", default=os.environ.get("MAGSTACK_I2C_BUS", "1"), help="I2C bus number for --hil")
    g.addoption("--spi-bus", default=os.environ.get("MAGSTACK_SPI", "0.0"), help="SPI bus.cs for --hil")
    g.addoption("--fvm-port", default=os.environ.get("MAGSTACK_FVM_PORT", "/dev/ttyUSB0"),
                help="FVM400 serial port for --hil")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--hil"):
        return
    skip = pytest.mark.skip(reason="hardware test: run with --hil (see hil/README.md)")
    for item in items:
        if "hil" in item.keywords:
            item.add_marker(skip)


_MAGSTACK_LOGGER = logging.getLogger("magstack")
#: The ``magstack`` logger as the test session found it (a module- or session-scoped fixture that runs a
#: CLI command sets it up before a test's own fixtures run, so a per-test snapshot could catch it
#: configured, e.g. at ERROR by ``-q``).
_PRISTINE = (list(_MAGSTACK_LOGGER.handlers), _MAGSTACK_LOGGER.level, _MAGSTACK_LOGGER.propagate)


def _restore_pristine_logger() -> None:
    _MAGSTACK_LOGGER.handlers[:] = _PRISTINE[0]
    _MAGSTACK_LOGGER.setLevel(_PRISTINE[1])
    _MAGSTACK_LOGGER.propagate = _PRISTINE[2]


@pytest.fixture(autouse=True)
def _restore_magstack_logger():
    """``magstack`` CLI runs in-process configure the ``magstack`` logger (own handler, no
    propagation, a level from -v/-q); each test starts and ends with the pristine logger so its
    ``caplog`` or own handler sees records whatever ran before."""
    _restore_pristine_logger()
    yield
    _restore_pristine_logger()


@pytest.fixture
def clock() -> VirtualClock:
    return VirtualClock()


@pytest.fixture(params=["part", "strict"])
def sim_profile(request):
    """Run a test against the part-faithful simulator defaults and again with every opt-in lint on
    (``magstack.sim.i2c_register_model.STRICT``): the project's drivers must pass both."""
    from magstack.sim.i2c_register_model import PART_FAITHFUL, STRICT, default_lints

    with default_lints(STRICT if request.param == "strict" else PART_FAITHFUL) as lints:
        yield lints
