"""hil/pi-emulated-check.sh: on a machine that cannot run it, it stops at once
with one line naming what is missing, exit 4. (The check itself needs root, mmdebstrap and a qemu-aarch64
binfmt_misc handler and takes tens of minutes: it is run by hand, hil/README.md.)"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "hil" / "pi-emulated-check.sh"


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_missing_prerequisites_are_named_in_one_line(tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in ("grep", "sed"):                       # what the check itself uses; no mmdebstrap, qemu, git
        (bin_dir / tool).symlink_to(shutil.which(tool))
    env = {"PATH": str(bin_dir), "MAGSTACK_HOST": "no-such-magstack", "HOME": str(tmp_path)}
    r = subprocess.run([shutil.which("bash"), str(SCRIPT), "--check"], env=env, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 4 and r.stdout == ""
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("pi-emulated-check: cannot run, missing: "), r.stderr
    for what in ("mmdebstrap", "qemu-aarch64-static", "git", "a magstack on this host ('no-such-magstack'"):
        assert what in lines[0]
    assert ("root (" in lines[0]) == (os.geteuid() != 0)


def test_unknown_argument_is_a_usage_error():
    r = subprocess.run([shutil.which("bash") or "bash", str(SCRIPT), "--frobnicate"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and r.stderr.startswith("pi-emulated-check: unknown argument '--frobnicate'")
