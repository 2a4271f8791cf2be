"""One import root: the folders map onto ``magstack.*`` and nothing else is installed at top level."""
from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_package_folder_is_listed():
    """A new sub-package must be added to pyproject's ``packages`` or it is missing from the wheel."""
    listed = set(CONFIG["packages"])
    found = set()
    for package, folder in CONFIG["package-dir"].items():
        base = ROOT / folder
        for init in base.rglob("__init__.py"):
            rel = init.parent.relative_to(base)
            found.add(".".join([package, *rel.parts]))
    assert found == listed


def test_python_dash_m_magstack_runs(tmp_path):
    """Run from a neutral directory: from the checkout's parent a folder named ``magstack`` (the
    checkout itself, when cloned under that name) would shadow the installed package."""
    out = subprocess.run([sys.executable, "-m", "magstack", "--version"], capture_output=True, text=True,
                         cwd=tmp_path, timeout=60)
    assert out.returncode == 0 and out.stdout.startswith("magstack ")


@pytest.mark.slow
def test_wheel_installs_only_magstack(tmp_path):
    """``pip wheel .`` holds only ``magstack/`` and its dist-info at top level."""
    pytest.importorskip("setuptools")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(ROOT)],
                       capture_output=True, text=True, timeout=600)
    if r.returncode != 0:
        pytest.skip(f"cannot build a wheel here: {r.stderr.strip()[-200:]}")
    wheel = next(tmp_path.glob("magstack-*.whl"))
    tops = {name.split("/")[0] for name in zipfile.ZipFile(wheel).namelist()}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"magstack"}
    names = zipfile.ZipFile(wheel).namelist()
    for module in ("magstack/drivers/registry.py", "magstack/data/session.py", "magstack/firmware/cal_table.py",
                   "magstack/sim/backends.py", "magstack/ground/alignment.py", "magstack/hil/bench.py",
                   "magstack/cli/main.py", "magstack/cli/commands/demo.py",
                   "magstack/firmware/c_applier/magstack_cal.c", "magstack/firmware/c_applier/magstack_cal.h"):
        assert module in names


def test_license_typing_marker_changelog_and_extras():
    """The MIT licence pyproject names ships, the package is marked typed, there is no empty `plot`
    extra."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == {"text": "MIT"}
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "magstack developers" in text
    assert (ROOT / "magstack" / "py.typed").is_file() and "py.typed" in CONFIG["package-data"]["magstack"]
    assert "plot" not in project["optional-dependencies"]
    assert (ROOT / "CHANGELOG.md").read_text().startswith("# Changelog")


def test_the_demos_default_output_folder_is_git_ignored():
    """`magstack demo` run in the checkout (the README's first command) leaves `git status` clean."""
    from magstack.cli.main import build_parser

    default = Path(build_parser(load="demo").parse_args(["demo"]).out)
    assert not default.is_absolute() and len(default.parts) == 1
    patterns = [p.strip() for p in (ROOT / ".gitignore").read_text().splitlines()]
    assert f"/{default}/" in patterns
    git = shutil.which("git")
    if git and (ROOT / ".git").exists():
        r = subprocess.run([git, "-C", str(ROOT), "check-ignore", "-q", f"{default}/report.html"], timeout=60)
        assert r.returncode == 0


def _fenced_blocks(text: str) -> list[list[str]]:
    blocks, cur = [], None
    for line in text.splitlines():
        if line.startswith("```"):
            if cur is None:
                cur = []
            else:
                blocks.append(cur)
                cur = None
        elif cur is not None:
            cur.append(line)
    return blocks


def test_readme_sets_up_in_two_commands_and_ci_runs_its_test_command():
    """The first screen: one command installs what the demo needs and runs it, one installs the test tools and
    runs the suite in parallel; .ci/run runs that same test command (plus the slowest-tests list)."""
    setup = _fenced_blocks((ROOT / "README.md").read_text())[0]
    assert len(setup) == 2
    demo, tests = setup
    assert demo == "python3 -m pip install -e '.[ground]' && magstack demo"
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert "magstack[ground]" in extras["test"] and any(r.startswith("pytest-xdist") for r in extras["test"])
    install, run = tests.split(" && ")
    assert install == "python3 -m pip install -e '.[test]'" and run.startswith("python3 -m pytest ")
    assert "-n auto" in run
    ci = (ROOT / ".ci" / "run").read_text()
    assert f"{run} --durations=25" in ci.splitlines() and "-e '.[test]'" in ci
