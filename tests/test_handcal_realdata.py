"""AV-MagEval tests 3-7 fitted with only the reference's magnitude per row, beside the vector fit."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

DATA = Path(__file__).parent / "data" / "av-mageval"
PAIRS = {3: ("data2.csv", "ref3.csv"), 4: ("data3.csv", "ref4.csv"), 5: ("data5.csv", "ref5.csv"),
         6: ("data6.csv", "ref6.csv"), 7: ("data7.csv", "ref7.csv")}


def _vrms(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))) * 1e3)


def _mrms(a, b):
    return float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - np.linalg.norm(b, axis=1)) ** 2)) * 1e3)


@pytest.mark.slow
def test_magnitude_only_fit_of_the_real_bench_names_what_it_cannot_see():
    from magstack.data.session import Session
    from magstack.firmware.calibration import FitData, FitOptions, fit
    from magstack.firmware.calibration.fit import reference_steps
    from magstack.firmware.calibration.handcal import HandCalData, HandCalOptions, calibrate
    from magstack.ground import mageval_import as mi

    parts = [mi.import_mageval(DATA / d, DATA / r, session_id=n, onto=0.25, clock_offset_s=mi.AUTHORS_OFFSET_S)
             for n, (d, r) in PAIRS.items()]
    s = Session.concatenate(parts)
    ok = np.all(np.isfinite(s.ref_uT), axis=1) & np.all(np.isfinite(s.dut_uT), axis=1)
    s = s.select(ok & ~reference_steps(s.ref_uT, s.session, 0.1))
    vec = fit(FitData.from_session(s), "gain_offset", options=FitOptions(chip="hmc1053", holdout=False))
    pv = vec.model.predict(vec.theta, vec.model.design(s.dut_uT, s.temp_c))
    res = calibrate(HandCalData(s.dut_uT, s.temp_c, s.t_s, np.linalg.norm(s.ref_uT, axis=1), s.session),
                    HandCalOptions(chip="hmc1053", temperature="off", frame="sensor", block_s=60.0))
    cal = res.apply(s.dut_uT, s.temp_c)
    # on the magnitude, the magnitude-only fit is as good as the vector fit (both near the 43 nT noise floor)
    assert _mrms(cal, s.ref_uT) < 60.0 and _mrms(pv, s.ref_uT) < 65.0
    # as vectors it is not: the sweeps run along the coil axes, so the cross terms are mostly the prior's and
    # a rotation is undetermined; the report says both instead of claiming a vector calibration
    rot, _ = Rotation.align_vectors(s.ref_uT, cal)
    assert _vrms(pv, s.ref_uT) < 100.0 < _vrms(rot.apply(cal), s.ref_uT) <= _vrms(cal, s.ref_uT)
    assert "3 angles" in res.frame.undetermined
    who = {r["param"]: r["determined_by"] for r in res.parameter_rows()}
    assert {who["S[x,y]"], who["S[x,z]"], who["S[y,z]"]} <= {"data+prior", "prior"}
    assert res.refused and "cover" in res.refused[0]          # 29 % of the cells: refused without the override
