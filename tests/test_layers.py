"""The layer contract is live: a back-import (a lower layer importing a higher one) fails `.ci/layers.py`."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


LINT = shutil.which("lint-imports") or (Path(sys.executable).parent / "lint-imports").exists()


@pytest.mark.skipif(not LINT, reason="import-linter is in the test extra")
def test_a_deliberate_back_import_breaks_the_contract(tmp_path):
    tree = tmp_path / "repo"
    shutil.copytree(ROOT, tree, ignore=shutil.ignore_patterns(".git", "tests", "docs", "benchmarks", "*.egg-info",
                                                              "__pycache__", "build", ".hypothesis"))
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    ok = subprocess.run([sys.executable, str(tree / ".ci" / "layers.py")], capture_output=True, text=True, env=env,
                        timeout=300)
    assert ok.returncode == 0, ok.stdout[-2000:]
    with open(tree / "drivers" / "clock.py", "a", encoding="utf-8") as fh:
        fh.write("\nfrom magstack.ground import alignment  # noqa: E402,F401  (deliberate back-import)\n")
    bad = subprocess.run([sys.executable, str(tree / ".ci" / "layers.py")], capture_output=True, text=True, env=env,
                         timeout=300)
    assert bad.returncode != 0
    assert "magstack.drivers is not allowed to import magstack.ground" in bad.stdout
