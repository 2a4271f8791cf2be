"""The fit against the simulator's forward error model (magstack.sim.error_model): the distortion the
simulator applies is undone by the fitted calibration to the simulated noise level."""
from __future__ import annotations

import numpy as np
import pytest

from magstack.firmware.cal_table import table_from_fit, validate
from magstack.firmware.calibration import FitData, FitOptions, fit
from magstack.firmware.float_applier import apply_float

em = pytest.importorskip("magstack.sim.error_model")

N = 6000
DT_S = 0.25


class _Truth:
    """Tumbling 50 uT field, a temperature ramp, a switched current, three sessions."""

    def field_series_uT(self, t):
        k = t / (N * DT_S)
        return 50.0 * np.column_stack([np.sin(2 * np.pi * 3.1 * k), np.cos(2 * np.pi * 4.7 * k + 0.3),
                                       np.sin(2 * np.pi * 2.3 * k + 1.1)])

    def temp_series_c(self, t):
        return 25.0 + 30.0 * np.sin(2 * np.pi * t / (N * DT_S) * 1.3)

    def currents_series_A(self, t):
        return {"solar": 0.8 * (np.sin(2 * np.pi * t / 97.0) > 0)}

    def session_series(self, t):
        return np.minimum((t / (N * DT_S) * 3).astype(np.int64), 2) + 1


def _simulate(effects, **params):
    p = em.ErrorParams(**params)
    model = em.ErrorModel(p, seed=3, effects=effects)
    t = np.arange(N) * DT_S
    truth = _Truth()
    ts = em.sample_truth(truth, t)
    y = model.sense_series(t, truth)
    return FitData(y, ts.b_uT, ts.temp_c, t, ts.session, dict(ts.currents_A))


def test_fit_undoes_the_simulated_eq4_distortion():
    effects = ("interference", "misalignment", "gain", "temperature_gain", "offset", "temperature_offset",
               "session_offset", "noise")
    d = _simulate(effects, interference_uT_per_A={"solar": (3.0, -1.0, 0.5)},
                  misalignment_rad=(0.01, -0.02, 0.005), rotation_rad=(0.01, 0.0, -0.01),
                  gain_matrix=((1.09, 0.09, -0.03), (0.05, 1.12, -0.07), (0.02, 0.03, 1.11)),
                  k_s_per_c=((-3e-4, 0, 0), (0, -2e-4, 0), (0, 0, -2.5e-4)),
                  offset_uT=(0.33, 0.03, -0.47), k_o_uT_per_c=(-0.14, 0.02, 0.05),
                  session_offset_sigma_uT=(0.1, 0.1, 0.1), noise_white_uT=(0.02, 0.02, 0.02))
    r = fit(d, "eq3", ["session_offset"], ["solar"], options=FitOptions(holdout=False))
    assert r.held == []
    # residual = white noise (20 nT per axis) + the second-order temperature terms Eq. 3 linearises
    assert np.all(r.rmse_uT < 0.025), r.rmse_uT
    assert r.noise_floor_uT == pytest.approx([0.02] * 3, rel=0.15)
    # a bound wide enough for the data's own region (with the generic priors the default region is narrow: the
    # unmodelled second-order tempco's prior is 1e-5 /degC^2 where no chip is named)
    table = table_from_fit(r, "sim", validity_sd_uT=1.0)
    assert validate(table).ok
    out, flags = apply_float(table, d.b_meas_uT, d.temp_c, d.currents_A)
    assert np.all(flags == 0)
    # applied on board (no session offsets): the residual is the session-offset spread (0.1 uT sigma)
    rms = np.sqrt(np.mean((out - d.b_ref_uT) ** 2, axis=0))
    assert np.all(rms < 0.2)
    assert np.all(np.sqrt(np.mean((d.b_meas_uT - d.b_ref_uT) ** 2, axis=0)) > 10 * rms)


def test_nonlinearity_needs_the_cubic_term():
    effects = ("gain", "nonlinearity", "noise")
    d = _simulate(effects, gain_matrix=((1.1, 0, 0), (0, 1.0, 0), (0, 0, 0.95)),
                  cubic_per_uT2=(2e-5, 0, -1e-5), noise_white_uT=(0.01, 0.01, 0.01))
    lin = fit(d, "gain_offset", options=FitOptions(holdout=False))
    cub = fit(d, "gain_offset", ["cubic"], options=FitOptions(holdout=False))
    assert lin.rmse_uT[0] > 5 * cub.rmse_uT[0]
    # the cubic column inverts the forward cubic to first order: what is left on X is < 1 % of the
    # nonlinearity's peak (c3 (G B)^3, 3.3 uT here); Y, which has none, stays at the 10 nT noise
    peak_x = 2e-5 * (1.1 * 50.0) ** 3
    assert cub.rmse_uT[0] < 0.01 * peak_x
    assert cub.rmse_uT[1] == pytest.approx(0.01, rel=0.1)
