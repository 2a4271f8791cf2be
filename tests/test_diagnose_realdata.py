"""Real bench data (AV-MagEval tests 3-7, tests/data/av-mageval) through the diagnosis: the figures of
docs/diagnosis.md's real-data table stay what they are when the diagnosis is made faster.

Tests 3-7 carry two tones 1.6 mHz apart near 1.08 Hz (less than 2 periodogram bins): the tone refinement
must find the stronger one's peak on its 0.1-bin grid (a coarse-then-fine scan moved the second tone and the
noise floor). Both are at the Nyquist frequency of the DUT's 0.461 s sampling: an even/odd alternation."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magstack.data.session import Session
from magstack.ground import mageval_import as mi
from magstack.ground.diagnose import Options, diagnose_model

PAIRS = {3: ("data2.csv", "ref3.csv"), 4: ("data3.csv", "ref4.csv"), 5: ("data5.csv", "ref5.csv"),
         6: ("data6.csv", "ref6.csv"), 7: ("data7.csv", "ref7.csv")}
DATA = Path(__file__).parent / "data" / "av-mageval"


@pytest.fixture(scope="module")
def tests_3_to_7() -> Session:
    """The pairs as `magstack import-mageval` imports them by default (clock offset estimated)."""
    return Session.concatenate([mi.import_mageval(DATA / d, DATA / r, session_id=n) for n, (d, r) in PAIRS.items()])


def test_tests_3_to_7_gain_offset_30_s_blocks(tests_3_to_7):
    d = diagnose_model(tests_3_to_7, "gain_offset", Options(block_s=30.0)).to_dict()
    assert d["n_rows"] == 1060 and d["verdict"] == "none"
    assert abs(d["baseline_rmse_nT"] - 77.6) < 0.1 and abs(d["noise_floor_nT"] - 41.2) < 0.1
    assert d["ranking"][0]["effect"] == "session_offset" and abs(d["ranking"][0]["rmse_nT"] - 66.3) < 0.1
    tones = sorted(t["freq_hz"] for t in d["where"]["tones"])
    assert np.allclose(tones, [1.0829, 1.0845], atol=1e-4), tones
    # both sit at the Nyquist frequency of the 0.461 s DUT sampling: an even/odd alternation, named so, and the
    # explicit parity test finds it (its constant part is not significant here: nothing is removed from the floor)
    assert all(t["kind"] == "even_odd_alternation" for t in d["where"]["tones"])
    alt = d["where"]["alternation"]
    assert alt["significant"] and alt["p_value"] < 0.01 and not alt["removed_before_floor"]
    assert abs(alt["nyquist_hz"] - 1.0846) < 1e-3
