"""magstack: a flight-software-style sensor stack for small-spacecraft magnetometers.

One import root; the repository folders map onto sub-packages (pyproject ``package-dir``):

=====================  ==============================================================
``magstack.cli``       ``cli/``          the ``magstack`` command and the demo
``magstack.hil``       ``hil/``          bench runner and Raspberry Pi wiring
``magstack.ground``    ``ground/``       alignment, apply-to-session, importers, reports, diagnosis
``magstack.sim``       ``sim/``          simulated buses, chip models, error model, truth generators
``magstack.firmware``  ``firmware_py/``  on-board code: calibration, tables, appliers, flight loop
``magstack.data``      ``data/``         session / telemetry file format, merge, row split, atomic I/O
``magstack.drivers``   ``drivers/``      bus transports, chip tables and drivers, chip factory
=====================  ==============================================================

Layers are listed top to bottom as in ``docs/architecture.md`` (cli > hil > ground > sim > firmware >
data > drivers > errors): each imports only the layers below it (checked by import-linter in CI).
"""
from __future__ import annotations

__all__ = ["__version__"]


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("magstack")
    except Exception:  # running from a checkout without an install
        return "0.0.0+checkout"


def __getattr__(name: str) -> str:
    """``__version__``: the installed distribution version (``0.0.0+checkout`` when not installed),
    looked up on first use (importlib.metadata costs start-up time every command would pay)."""
    if name == "__version__":
        globals()["__version__"] = v = _version()
        return v
    raise AttributeError(f"module 'magstack' has no attribute {name!r}")
