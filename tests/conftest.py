"""Shared fixtures and the hardware selection options.

``pytest --hil --i2c-bus 1`` runs the tests marked ``hil`` against real hardware;
without ``--hil`` they are skipped. See hil/README.md for wiring.
"""
from __future__ import annotations

import os

# One BLAS / OpenMP thread per test process, set before numpy or scipy load their BLAS (workers of pytest-xdist
# and the subprocesses tests start inherit it): OpenBLAS starts a spinning thread per core for each call, so
# two test workers on two cores would oversubscribe the machine and make small solves many times slower
# (firmware_py/blas.py). Thread counts change speed, not results.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import logging  # noqa: E402
import re  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

from magstack.drivers.clock import VirtualClock  # noqa: E402

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
    """Hardware tests are skipped without ``--hil``."""
    if config.getoption("--hil"):
        return
    skip = pytest.mark.skip(reason="hardware test: run with --hil (see hil/README.md)")
    for item in items:
        if "hil" in item.keywords:
            item.add_marker(skip)


#: A test module that defines a module- or session-scoped fixture (a simulated session, a demo run built once
#: for its tests).
_SHARED_FIXTURE = re.compile(r"@pytest\.fixture\([^)]*scope\s*=\s*[\"'](module|session)[\"']")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``pytest -n N --dist loadgroup`` (pyproject addopts): tests go to whichever worker is free, one by one,
    except that the tests of a module defining a module- or session-scoped fixture stay together on one worker,
    so the fixture is built once, and tests marked ``xdist_group(name)`` share a worker as in pytest-xdist's
    own loadgroup. The grouping is decided here on the controller from the test ids and the module sources
    (pytest-xdist's own loadgroup appends the group to the test id on the workers, which pytest 9.2 ignores:
    https://github.com/pytest-dev/pytest-xdist/issues/1386)."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    root = Path(str(config.rootpath))
    shared: dict[str, bool] = {}

    class ModuleFixtureScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            if nodeid.rfind("@") > nodeid.rfind("]"):     # an xdist_group mark that reached the test id
                return nodeid.split("@")[-1]
            module = nodeid.split("::", 1)[0]
            if module not in shared:
                try:
                    shared[module] = bool(_SHARED_FIXTURE.search((root / module).read_text(encoding="utf-8")))
                except OSError:
                    shared[module] = False
            return module if shared[module] else nodeid

    return ModuleFixtureScheduling(config, log)


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


def shared_artifact(tmp_path_factory, name: str, build) -> Path:
    """A directory ``build(path)`` fills once per test run and every test (and every pytest-xdist worker) reads.

    The first caller builds it under a file lock in the run's common temporary folder, the others wait for
    the lock and reuse it; a build that raises leaves nothing behind (the next caller tries again). Tests must
    not change what they get: copy a file before changing it."""
    import fcntl
    import shutil

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent               # the workers' folders share this parent
    path, done = base / f"shared-{name}", base / f"shared-{name}.done"
    with open(base / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(path, ignore_errors=True)
            path.mkdir()
            try:
                build(path)
            except BaseException:
                shutil.rmtree(path, ignore_errors=True)
                raise
            done.touch()
    return path


@pytest.fixture(scope="session")
def shared_demo(tmp_path_factory) -> dict:
    """One ``magstack demo --out DIR --seconds 300 --seed 1 --json`` run for every test that only reads it:
    ``{"out": DIR, "stdout": the JSON text, "stderr": text, "code": exit status, "layout_problems": [...]}``
    (the layout problems every report page of the run recorded, ``Report.layout_problems``)."""
    import contextlib
    import io
    import json

    def build(d: Path) -> None:
        from magstack.cli.main import main
        from magstack.ground.report import Report

        problems: list = []
        real_write = Report.write

        def write(self, path):
            problems.extend(self.layout_problems)
            return real_write(self, path)

        out, err = io.StringIO(), io.StringIO()
        mp = pytest.MonkeyPatch()
        mp.setattr(Report, "write", write)
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = main(["demo", "--out", str(d / "demo"), "--seconds", "300", "--seed", "1", "--json"])
        finally:
            mp.undo()
        (d / "run.json").write_text(json.dumps({"stdout": out.getvalue(), "stderr": err.getvalue(), "code": code,
                                                "layout_problems": [list(p) for p in problems]}))

    d = shared_artifact(tmp_path_factory, "demo-300s-seed1", build)
    return {"out": d / "demo", **json.loads((d / "run.json").read_text())}
