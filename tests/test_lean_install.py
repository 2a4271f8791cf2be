"""``pip install magstack`` (no extras) is the flight install: the flight commands run without the libraries of
any extra, the core's dependencies are exactly what the core's code imports, and a ground command in a lean
install answers one line naming the extra (exit 4).

A lean install is imitated in a fresh interpreter by an import hook that refuses every library of every extra
(cli/extras.py ``EXTRA_MODULES``), as a missing distribution would; the hook is the first import finder, so a
library the code tries to import anywhere fails loudly instead of going unnoticed.
"""
from __future__ import annotations

import ast
import functools
import json
import re
import subprocess
import sys
import tomllib
from importlib.metadata import packages_distributions as _packages_distributions
from pathlib import Path

import pytest

from magstack.cli.extras import EXTRA_MODULES
from magstack.cli.main import command_index

ROOT = Path(__file__).resolve().parent.parent
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
#: The commands of the flight install (README, hil/README.md): they must run without any extra.
FLIGHT_COMMANDS = {"run", "probe", "read", "bench", "table", "tm"}

_HOOK = """
import sys
REFUSED = {refused!r}
class _Lean:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in REFUSED:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None
sys.meta_path.insert(0, _Lean())
"""


def lean_python(code: str, cwd: Path, refused: set[str] | None = None) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter in which the libraries of every extra cannot be imported."""
    if refused is None:
        refused = {m for mods in EXTRA_MODULES.values() for m in mods}
    return subprocess.run([sys.executable, "-c", _HOOK.format(refused=sorted(refused)) + code], cwd=cwd,
                          capture_output=True, text=True, timeout=600)


@functools.cache
def packages_distributions() -> dict[str, list[str]]:
    """Import name -> distributions providing it (scanning the installed metadata once)."""
    return _packages_distributions()


def _dist_name(requirement: str) -> str:
    return re.split(r"[ <>=!~;\[]", requirement, maxsplit=1)[0].lower().replace("_", "-")


def _with_requirements(dists: set[str]) -> set[str]:
    """``dists`` and, transitively, what their installed metadata requires (not the extras' requirements)."""
    from importlib.metadata import PackageNotFoundError, requires

    todo, seen = list(dists), set()
    while todo:
        d = todo.pop()
        if d in seen:
            continue
        seen.add(d)
        try:
            reqs = requires(d) or []
        except PackageNotFoundError:
            continue
        todo += [_dist_name(r) for r in reqs if "extra ==" not in r.replace('"', "'").replace("extra=", "extra ==")]
    return seen


def _import_names(dist: str) -> set[str]:
    """The top-level import names the installed distribution ``dist`` provides."""
    return {top for top, dists in packages_distributions().items()
            if any(d.lower().replace("_", "-") == dist for d in dists)}


_FLIGHT_RUN = """
import sys
BEFORE = {m.split(".")[0] for m in sys.modules}
import contextlib, io, json
from pathlib import Path
import numpy as np
from magstack.cli.main import main
from magstack.firmware import cal_table as ct
from magstack.firmware.flight.config import example_config_text

text = example_config_text().replace("spi0.0,start=6,reset=13,drdy=19,sr=5", "sim").replace('bus = "1"', 'bus = "sim"')
Path("tables").mkdir()
ct.save_table(ct.CalTable(device_id="hmc1053:sn1", terms=("gain_matrix", "offset"), S=np.eye(3), O=[0.1, 0.2, 0.3],
                          validity_field_uT=100.0), "tables/hmc1053.json")
Path("flight.toml").write_text(text)
commands = [
    ["run", "--example-config"],
    ["run", "--config", "flight.toml", "--sim", "--duration", "20", "--out", "tlm"],
    ["probe", "--bus", "sim"],
    ["read", "--chip", "lis3mdl", "--bus", "sim", "-n", "3"],
    ["read", "--chip", "hmc1053", "--bus", "sim", "-n", "2"],
    ["bench", "--dut", "lis3mdl", "--ref", "fvm400", "--bus", "sim", "--seconds", "5", "--out", "bench.csv"],
    ["table", "show", "tables/hmc1053.json"],
    ["table", "validate", "tables/hmc1053.json"],
    ["tm", "xtce", "--config", "flight.toml"],
    ["tm", "dictionary"],
    ["tm", "decode", "tlm/packets-0001.bin", "--out", "decoded"],
    ["tm", "command", "--config", "flight.toml", "ping", "--out", "ping.bin"],
]
codes = []
for argv in commands:
    with contextlib.redirect_stdout(io.StringIO()):
        codes.append(main(argv + ["-q"]))
print(json.dumps({"codes": codes, "modules": sorted({m.split(".")[0] for m in sys.modules} - BEFORE)}))
"""


def test_flight_commands_run_without_any_extra_and_use_only_core_dependencies(tmp_path):
    r = lean_python(_FLIGHT_RUN, tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["codes"] == [0] * len(out["codes"]), (out["codes"], r.stderr[-2000:])
    assert (tmp_path / "tlm" / "packets-0001.bin").stat().st_size > 0 and (tmp_path / "bench.csv").is_file()
    # every third-party library the flight commands loaded comes from a core dependency
    core = _with_requirements({_dist_name(d) for d in PROJECT["dependencies"]})
    dists = packages_distributions()
    third_party = {m for m in out["modules"] if m in dists and m != "magstack"}
    loaded_from = {m: {d.lower().replace("_", "-") for d in dists[m]} for m in third_party}
    assert {m for m, ds in loaded_from.items() if not ds & core} == set(), loaded_from


def test_the_core_depends_on_no_library_of_an_extra_and_uses_every_dependency():
    """The core's dependencies are the flight's: none brings a library of an extra, and the package imports
    each of them (spidev, on a Pi only, in the SPI adapter)."""
    extra_modules = {m for mods in EXTRA_MODULES.values() for m in mods}
    sources = [p for folder in PROJECT_FOLDERS for p in (ROOT / folder).rglob("*.py")]
    imported = set()
    for src in sources:
        for node in ast.walk(ast.parse(src.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                imported |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported.add(node.module.split(".")[0])
    for requirement in PROJECT["dependencies"]:
        dist = _dist_name(requirement)
        names = _import_names(dist) or {dist}      # spidev is not installed off a Pi: its import name is its name
        assert not names & extra_modules, f"core dependency {dist} is a library of an extra"
        assert names & imported, f"core dependency {dist} is imported nowhere in the package"


PROJECT_FOLDERS = ("magstack", "drivers", "data", "firmware_py", "sim", "ground", "hil", "cli")


def test_the_extras_in_pyproject_and_in_cli_extras_agree():
    """EXTRA_MODULES lists the import names of exactly the libraries each extra adds; `test` installs ground."""
    extras = PROJECT["optional-dependencies"]
    assert "magstack[ground]" in extras["test"]
    for extra, modules in EXTRA_MODULES.items():
        names = set()
        for requirement in extras[extra]:
            dist = _dist_name(requirement)
            if dist == "magstack":
                continue
            provided = _import_names(dist) or {dist}
            assert provided & set(modules), f"extra {extra}: no import name of {dist} in EXTRA_MODULES"
            names |= provided
        assert set(modules) <= names, (extra, modules, names)


def test_every_command_outside_the_flight_install_declares_the_ground_extra():
    declared = {name: extra for name, (_module, _help, extra) in command_index().items()}
    assert {n for n, e in declared.items() if e is None} == FLIGHT_COMMANDS, (
        "a command either declares EXTRA = 'ground' in its module (cli/extras.py) or belongs to the flight install "
        f"(FLIGHT_COMMANDS here, and README.md / hil/README.md say so): {declared}")
    assert {e for n, e in declared.items() if n not in FLIGHT_COMMANDS} == {"ground"}


def test_every_command_without_an_extra_loads_and_shows_its_help_without_the_extras(tmp_path):
    """A command that declares no extra is loaded (its module and its parser) where no extra is installed."""
    names = sorted(n for n, (_m, _h, extra) in command_index().items() if extra is None)
    code = ("import contextlib, io, json\nfrom magstack.cli.main import main\ncodes = {}\n"
            f"for name in {names!r}:\n"
            "    with contextlib.redirect_stdout(io.StringIO()):\n        codes[name] = main([name, '--help'])\n"
            "print(json.dumps(codes))")
    r = lean_python(code, tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]) == dict.fromkeys(names, 0), r.stderr[-2000:]


@pytest.mark.parametrize("argv", [["fit", "s.csv", "--out", "cal.json"], ["demo", "--out", "demo"],
                                  ["diagnose", "s.csv"], ["fit", "--help"]])
def test_a_ground_command_without_the_extra_is_one_line_exit_4(tmp_path, argv):
    (tmp_path / "s.csv").write_text("")
    r = lean_python(f"import sys\nfrom magstack.cli.main import main\nsys.exit(main({argv!r}))", tmp_path)
    assert r.returncode == 4 and r.stdout == ""
    assert r.stderr.splitlines() == [f"magstack {argv[0]}: error: needs the 'ground' extra, which is not installed "
                                     "(no module 'scipy'): pip install 'magstack[ground]'"]
    assert not (tmp_path / "cal.json").exists() and not (tmp_path / "demo").exists()


def test_a_library_of_an_extra_missing_inside_a_flight_command_is_one_line_exit_4(tmp_path):
    """An orbit programme needs IGRF (the ground extra): met where it is imported, not when the command loads."""
    from magstack.firmware.flight.config import example_config_text

    (tmp_path / "flight.toml").write_text(example_config_text())
    argv = ["run", "--config", "flight.toml", "--sim", "--duration", "5", "--sim-program", "orbit_nadir",
            "--out", "tlm", "--json=-"]
    r = lean_python(f"import sys\nfrom magstack.cli.main import main\nsys.exit(main({argv!r}))", tmp_path)
    assert r.returncode == 4, r.stderr
    (line,) = r.stderr.splitlines()
    assert re.fullmatch(r"magstack run: error: needs the 'ground' extra, which is not installed \(no module "
                        r"'(scipy|erfa|ppigrf)'\): pip install 'magstack\[ground\]'", line), line
    assert json.loads(r.stdout)["exit_code"] == 4
