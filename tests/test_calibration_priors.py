"""One MAP estimator with datasheet priors, the posterior in the table, validity from it."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from magstack.drivers.cal_priors import GENERIC, PRIORS, priors_for
from magstack.firmware.cal_table import CalTableStore, load_table, save_table, table_from_fit, validate
from magstack.firmware.cal_uncertainty import norm_sd_uT, predictive_sd_uT
from magstack.firmware.calibration import FitData, FitOptions, fit
from magstack.firmware.calibration.estimator import Prior, autocorr_inflation, map_solve, model_prior, parse_override
from magstack.firmware.calibration.linalg import qr_r
from magstack.firmware.calibration.model import CalModel, resolve_terms
from magstack.firmware.corrector import TableCorrector
from magstack.firmware.errors import CalTableInvalid, FitError
from magstack.sim.calibration_benches import preset_thermal_bench
from magstack.sim.coil_programs import ProgramTruth
from magstack.sim.error_model import ErrorModel
from magstack.sim.presets import preset

DATA = Path(__file__).parent / "data" / "av-mageval"


# ------------------------------------------------------------------ the chip tables
def test_every_chip_has_priors_with_sources_and_the_hmc1053_tempco_is_the_datasheet_value():
    for name, p in PRIORS.items():
        assert p.chip == name and p.source
        for f in ("gain_diag", "gain_offdiag", "offset_uT", "k_s_rel_per_c", "k_o_uT_per_c"):
            v = getattr(p, f)
            assert v.sd > 0 and v.source.startswith("[")
    # hardware-facts 5.1: -2700 ppm/degC (Vbridge drive) -> +2.7e-3 in the calibration direction, sd widened for [U]
    hp = PRIORS["hmc1053"]
    assert hp.k_s_rel_per_c.mean == 2.7e-3 and "[U]" in hp.k_s_rel_per_c.source and hp.k_s_rel_per_c.sd >= 3e-4
    assert hp.operating_temp_c == (-40.0, 125.0) and hp.field_range_uT == 600.0
    assert priors_for("hmc1053:sn1") is hp and priors_for("HMC5983") is PRIORS["hmc5983"]
    assert priors_for(None) is GENERIC and priors_for("bogus") is GENERIC


# ------------------------------------------------------------------ the estimator
def test_map_equals_the_closed_form_posterior():
    rng = np.random.default_rng(0)
    m = CalModel(("gain_matrix", "offset"))
    b = rng.normal(0, 30, (300, 3))
    X = m.design(b)
    th = np.hstack([np.eye(3) * 1.1, np.array([[0.3], [-0.2], [0.1]])])
    Y = X @ th.T + rng.normal(0, 0.05, (300, 3))
    R = qr_r(np.hstack([X, Y]))
    pr = model_prior(m, PRIORS["hmc1053"])
    post = map_solve(R, 300, m, pr, sigma_uT=np.full(3, 0.05))
    for i in range(3):
        P0 = np.linalg.inv(pr.cov[i])
        A = X.T @ X / 0.05 ** 2 + P0
        mean = np.linalg.solve(A, X.T @ Y[:, i] / 0.05 ** 2 + P0 @ pr.mean[i])
        np.testing.assert_allclose(post.theta[i], mean, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(post.cov[i], np.linalg.inv(A), rtol=1e-6, atol=1e-14)


def test_flat_prior_is_least_squares_and_no_data_is_the_prior():
    rng = np.random.default_rng(1)
    m = CalModel(("gain_matrix", "offset"))
    X = m.design(rng.normal(0, 30, (200, 3)))
    Y = X @ rng.normal(0, 1, (4, 3)) + rng.normal(0, 0.01, (200, 3))
    R = qr_r(np.hstack([X, Y]))
    post = map_solve(R, 200, m, Prior.flat(4))
    np.testing.assert_allclose(post.theta.T, np.linalg.lstsq(X, Y, rcond=None)[0], atol=1e-9)
    pr = model_prior(m, PRIORS["lis3mdl"])
    empty = map_solve(np.zeros((7, 7)), 1, m, pr, sigma_uT=np.ones(3))
    np.testing.assert_allclose(empty.theta, pr.mean, atol=1e-12)
    np.testing.assert_allclose(empty.sd, pr.sd, rtol=1e-9)
    assert all(empty.determined_by(i, c) == "prior" for i in range(3) for c in range(4))


def test_autocorrelated_residuals_inflate_the_data_variance():
    rng = np.random.default_rng(2)
    n = 4000
    white = rng.normal(0, 1, (n, 3))
    slow = np.cumsum(rng.normal(0, 1, (n, 3)), axis=0)
    slow -= np.convolve(slow[:, 0], np.ones(200) / 200, "same")[:, None]
    k_white = autocorr_inflation(white, np.arange(n), np.zeros(n))
    k_slow = autocorr_inflation(slow, np.arange(n), np.zeros(n))
    assert np.all(k_white < 2.0) and np.all(k_slow > 10.0)


def test_prior_override_syntax():
    assert parse_override("K_S[x,x]=-2.7e-3+-0.5e-3") == ("K_S[x,x]", -2.7e-3, 0.5e-3)
    assert parse_override("O[z]=0.3") == ("O[z]", 0.3, 0.0)
    name, mean, sd = parse_override("O[z]=flat")
    assert name == "O[z]" and np.isinf(sd)
    for bad in ("K_S[x,x]", "O[z]=a+-1", "O[z]=1+-nan", "O[z]=1+--2"):
        with pytest.raises(FitError):
            parse_override(bad)


# ------------------------------------------------------------------ acceptance: one-field thermal run
def _error_at(result, level, lo_c, hi_c, seed=5):
    tr = ProgramTruth("check", 1000.0, lambda t: np.tile(np.asarray(level, float), (np.atleast_1d(t).size, 1)),
                      lambda t: lo_c + (hi_c - lo_c) * np.atleast_1d(t) / 1000.0)
    t = np.arange(0.0, 1000.0, 0.5)
    bm = ErrorModel(preset("hmc1053"), seed=seed).sense_series(t, tr)
    err = tr.field_series_uT(t) - result.model.predict(result.theta, result.model.design(bm, tr.temp_series_c(t)))
    return float(np.linalg.norm(np.sqrt(np.mean(err ** 2, axis=0))))


@pytest.fixture(scope="module")
def preset_thermal():
    # HMC1053 error model (preset: -2700 ppm/degC in the truth); room-temperature sweeps + X held at 44 uT
    # while the unit cools 36 -> 28 degC (within Eq. 3's linear range, see docs/calibration.md)
    return preset_thermal_bench(seed=1, cool_c=(36.0, 28.0))


def test_one_field_thermal_run_with_the_hmc1053_preset(preset_thermal):
    d = preset_thermal
    r = fit(d, "eq3", options=FitOptions(exclude_ref_steps_uT=0.5, holdout=False, chip="hmc1053"))
    floor = float(np.linalg.norm(r.noise_floor_uT))
    S = r.params["S"]
    ks = next(c for c, col in enumerate(r.model.columns) if col.param == "K_S" and col.index == 0)
    truth = 2.7e-3 * S[0, 0]            # -alpha x S to first order (preset alpha = -2700 ppm/degC)
    assert abs(r.theta[0, ks] - truth) < 2 * r.se[0, ks]
    for level in [(0.0, 0.0, 0.0), (-30.0, 0.0, 0.0), (0.0, 0.0, 40.0), (20.0, -25.0, 30.0)]:
        assert _error_at(r, level, 28.0, 36.0) <= 1.5 * floor, level
    # without priors the one-field data split the tempco wrongly: microtesla at zero field
    bare = fit(d, "eq3", options=FitOptions(exclude_ref_steps_uT=0.5, holdout=False, use_priors=False))
    assert _error_at(bare, (0.0, 0.0, 0.0), 28.0, 36.0) > 10 * floor


# ------------------------------------------------------------------ the table's posterior and validity
@pytest.fixture(scope="module")
def bench_table(tmp_path_factory):
    from magstack.data.session import Session
    from magstack.ground import mageval_import as mi
    pairs = {3: ("data2.csv", "ref3.csv"), 4: ("data3.csv", "ref4.csv"), 5: ("data5.csv", "ref5.csv"),
             6: ("data6.csv", "ref6.csv"), 7: ("data7.csv", "ref7.csv")}
    parts = [mi.import_mageval(DATA / d, DATA / r, session_id=k, onto=0.25, clock_offset_s=mi.AUTHORS_OFFSET_S)
             for k, (d, r) in pairs.items()]
    data = FitData.from_session(Session.concatenate(parts))
    r = fit(data, "eq3", options=FitOptions(exclude_ref_steps_uT=0.1, holdout=False, chip="hmc1053"))
    path = tmp_path_factory.mktemp("tab") / "cal.json"
    save_table(table_from_fit(r, "hmc1053"), path)
    return r, path


def test_posterior_block_is_crc_covered_and_round_trips(bench_table, tmp_path):
    r, path = bench_table
    t = load_table(path)
    assert validate(t).ok and t.posterior is not None
    names = t.posterior["x"]["names"]
    assert names[:8] == ["S[x,x]", "S[x,y]", "S[x,z]", "K_S[x,x]", "K_S[x,y]", "K_S[x,z]", "O[x]", "K_O[x]"]
    left = t.posterior["left_out"]          # the terms eq3 leaves out, valued 0 in the table
    assert names[8:] == [n for n in left if n.endswith("[x]") or n.startswith("P[x,")]
    assert {"K_S2[x]", "K_S3[x]", "c3[x]", "P[x,xy]"} <= set(left)
    C = np.asarray(t.posterior["x"]["cov"])
    # never below the posterior: the slow-noise sandwich and the gated parameters' absorption only add
    assert np.all(np.sqrt(np.diag(C))[:8] >= r.se[0, :8] * (1 - 1e-9))
    assert np.all(np.linalg.eigvalsh(C) > -1e-12 * np.abs(C).max())
    doc = json.loads(path.read_text())
    doc["posterior"]["x"]["cov"][0][0] *= 2.0                       # edited: the CRC catches it
    bad = tmp_path / "edited.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(CalTableInvalid, match="CRC"):
        load_table(bad)
    # a table without the block stays valid (older tables)
    plain = tmp_path / "plain.json"
    doc = json.loads(path.read_text())
    del doc["posterior"]
    from magstack.firmware.cal_table import _crc
    doc["crc32"] = f"0x{_crc(doc):08x}"
    plain.write_text(json.dumps(doc))
    assert load_table(plain).posterior is None and validate(load_table(plain)).ok


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d["posterior"]["x"]["names"].__setitem__(0, "S[y,x]"), "not a parameter of output axis x"),
    (lambda d: d["posterior"]["y"]["cov"][0].__setitem__(1, 5.0), "not symmetric"),
    (lambda d: [row.__setitem__(k, -1.0) for k, row in enumerate(d["posterior"]["z"]["cov"])], "negative variance"),
    (lambda d: d["posterior"].__setitem__("extra", 1), "unknown key"),
])
def test_a_malformed_posterior_is_refused_naming_the_path(bench_table, tmp_path, mutate, match):
    from magstack.firmware.cal_table import _crc
    doc = json.loads(bench_table[1].read_text())
    mutate(doc)
    doc["crc32"] = f"0x{_crc(doc):08x}"
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(CalTableInvalid, match=match):
        load_table(p)


def test_bench_table_calibrates_at_25_degc_and_flags_60_degc(bench_table):
    """Tests 3-7 ran at 23.8-24.5 degC; the validity region follows the predictive sd (the tempcos are the
    datasheet's priors there), so a flight sample at 25 degC is calibrated and one at 60 degC is not."""
    _, path = bench_table
    t = load_table(path)
    lo, hi = t.validity_temp_c
    assert lo <= 23.9 and hi >= 25.0 and hi < 60.0
    store = CalTableStore("hmc1053")
    store.load_and_activate(path)
    corr = TableCorrector(store)
    assert corr.correct((20.0, -10.0, 35.0), 25.0).status == "ok"
    assert corr.correct((20.0, -10.0, 35.0), 60.0).status == "out_of_validity"
    b = np.array([[20.0, -10.0, 35.0], [20.0, -10.0, 35.0]])
    sd = predictive_sd_uT(t.posterior, t.t0_c, b, [25.0, 60.0])
    s25, s60 = norm_sd_uT(sd, b)
    assert s25 <= t.posterior["bound_uT"] < s60


def test_refuse_unidentifiable_names_the_prior_determined_parameters():
    rng = np.random.default_rng(3)
    m = CalModel(resolve_terms("eq3"))
    from magstack.sim.synthetic_calibration import make_data, random_theta
    d = make_data(m, random_theta(m, rng), 2000, rng, temp_span_c=(24.0, 24.0))
    with pytest.raises(FitError, match="the prior would"):
        fit(d, options=FitOptions(holdout=False, chip="hmc1053", on_unidentifiable="refuse"))
