"""``apply`` merges housekeeping currents with refit's rule."""
from __future__ import annotations

import numpy as np

from magstack.data.session import Session
from magstack.data.telemetry import TelemetryBlock
from magstack.firmware.cal_table import CalTable
from magstack.firmware.calibration.housekeeping import interpolate_currents
from magstack.firmware.float_applier import ApplyFlag
from magstack.ground.apply_session import FLAG_SHIFT, calibrate_session


def test_apply_interpolates_sparse_currents_like_refit():
    n = 400
    t = 1.78e9 + np.arange(n, dtype=float)
    sess = np.where(np.arange(n) < 300, 0, 1)
    solar = np.where(np.arange(n) % 10 == 3, 1.0 + 0.001 * np.arange(n), np.nan)   # sampled every 10 s
    solar[120:200] = np.nan                                                          # an 80 s hole
    rng = np.random.default_rng(2)
    b = rng.normal(0, 30, (n, 3))
    table = CalTable(device_id="dev", terms=("gain_matrix", "offset", "currents"), S=np.eye(3), K_S=np.zeros((3, 3)),
                     O=np.zeros(3), K_O=np.zeros(3), D=(("solar", (100.0, -50.0, 20.0)),), t0_c=25.0,
                     validity_temp_c=None, validity_field_uT=1000.0, validity_currents_A=(("solar", (-5.0, 5.0)),))
    s = Session(t, np.zeros((n, 3)), b, np.full(n, 25.0), sess, {"solar": solar})
    out = calibrate_session(table, s)
    blk = TelemetryBlock("mem", 0, t, b, np.full(n, 25.0), sess, np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)),
                         {"solar": solar})
    refit_solar = np.concatenate([x.currents_A["solar"] for x in interpolate_currents([blk], ["solar"])])
    has = np.isfinite(refit_solar)
    assert has.sum() > 0.7 * n                             # most rows: before, every 10th row only
    missing = (out.flag >> FLAG_SHIFT) & int(ApplyFlag.MISSING_INPUT) != 0
    assert np.array_equal(missing, ~has)
    expect = b[has] + refit_solar[has, None] * np.array([100.0, -50.0, 20.0])   # D in uT/A
    assert np.allclose(out.dut_uT[has], expect, atol=1e-12)
    assert np.array_equal(out.currents_A["solar"], solar, equal_nan=True)   # the file's samples are kept as they were
