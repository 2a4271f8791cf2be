"""The bounded fault and hostile-input campaign (benchmarks/campaign_reliability.py, 127.0.0.1 only) at a reduced
scale: every category, 0 tracebacks, 0 hangs, 0 silent wrong outputs, every lost record counted."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_campaign_has_no_traceback_hang_wrong_output_or_uncounted_loss():
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "campaign_reliability.py"), "--scale", "0.2",
                        "--seed", "1", "--json"], capture_output=True, text=True, timeout=900, cwd=ROOT)
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert r.returncode == 0, res["failures"]
    t = res["totals"]
    assert t["traceback"] == t["hang"] == t["wrong"] == t["uncounted"] == 0
    assert set(res["categories"]) == {"udp_tc", "tc_dir", "command_dir", "config", "tc_sequence", "tables", "stream",
                                      "decode_out", "readers", "merge", "full_disk", "kill9"}
    assert res["trials"] >= 90 and t["refused"] > 50 and t["correct"] > 10
