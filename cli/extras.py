"""Optional extras of the ``magstack`` package and the one line a command answers when one is missing.

``pip install magstack`` installs what the flight application needs (``run``, also ``--sim``, ``probe``,
``read``, ``bench``, ``table``, ``tm``). The ground tools (fit, refit, diagnosis, reports, the demo, the
bulk simulator and the session tools) need ``pip install 'magstack[ground]'``. A command module that
needs an extra says so with a module-level ``EXTRA = "ground"``, which ``magstack`` reads from its source
before importing it (cli/main.py); a missing library of an extra met anywhere else (an import inside a
function) gives the same one line. Exit status 4 (a system error: the installation lacks a part).
"""
from __future__ import annotations

import importlib.util

from magstack.errors import EXIT_DEVICE, MagError

#: Import names of the libraries each extra adds to the core (pyproject.toml, [project.optional-dependencies];
#: tests/test_lean_install.py checks the two agree).
EXTRA_MODULES: dict[str, tuple[str, ...]] = {
    "ground": ("scipy", "pandas", "matplotlib", "ppigrf", "erfa", "threadpoolctl"),
    "dask": ("dask",),
}
#: The extra that brings each import name.
EXTRA_OF: dict[str, str] = {m: extra for extra, mods in EXTRA_MODULES.items() for m in mods}


class MissingExtra(MagError):
    """A command needs an optional extra that is not installed (exit 4)."""

    exit_code = EXIT_DEVICE

    def __init__(self, extra: str, module: str) -> None:
        self.extra, self.module = extra, module
        super().__init__(f"needs the '{extra}' extra, which is not installed (no module '{module}'): "
                         f"pip install 'magstack[{extra}]'")


def missing_module(extra: str) -> str | None:
    """The first library of ``extra`` that cannot be imported here, or None when all can."""
    for module in EXTRA_MODULES.get(extra, ()):
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):   # a broken installation of it counts as missing
            found = False
        if not found:
            return module
    return None


def require(extra: str | None) -> None:
    """Raise :class:`MissingExtra` when a library of ``extra`` is missing (nothing for None)."""
    module = missing_module(extra) if extra else None
    if module is not None:
        raise MissingExtra(extra, module)


def as_missing_extra(exc: ModuleNotFoundError) -> MissingExtra | None:
    """The :class:`MissingExtra` behind ``exc`` when the module it did not find belongs to an extra."""
    top = (exc.name or "").split(".")[0]
    extra = EXTRA_OF.get(top)
    return MissingExtra(extra, top) if extra else None
