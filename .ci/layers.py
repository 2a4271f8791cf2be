"""Check the import-linter layer contract on the package as it installs.

The repository folders map onto ``magstack.*`` through ``[tool.setuptools.package-dir]``;
import-linter walks a package's directory, so this stages the mapped tree (Python files
only) in a temporary directory and runs ``lint-imports`` against it with the contracts from
pyproject.toml. Exit status is lint-imports' own.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

root = Path(__file__).resolve().parent.parent
config = tomllib.loads((root / "pyproject.toml").read_text())
package_dir = config["tool"]["setuptools"]["package-dir"]

with tempfile.TemporaryDirectory(prefix="magstack-layers-") as tmp:
    for package, folder in package_dir.items():
        dest = Path(tmp, *package.split("."))
        src = root / folder
        for path in src.rglob("*.py"):
            rel = path.relative_to(src)
            if any(part in package_dir.values() for part in rel.parts[:1]) and folder != ".":
                continue
            target = dest / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, target)
    env = dict(os.environ, PYTHONPATH=tmp)
    sys.exit(subprocess.call(["lint-imports", "--config", str(root / "pyproject.toml"), "--no-cache"], env=env,
                             cwd=tmp))
