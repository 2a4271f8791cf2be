"""``magstack demo``: the end-to-end run on the simulated bench (cli/demo/, cli/commands/demo.py).

One demo run (600 s calibration session, 300 s held-out session) is shared by the figure
tests; bounds come from the simulated sensor, not from a previous run: the HMC1053 preset's
white noise (belsten Table 1) and the simulator's own axis timing.
"""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from magstack.cli.demo import ARTEFACTS, DEVICE_ID, DemoConfig, run_demo
from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import ConfigurationError, MagError
from magstack.firmware.cal_table import CalTableStore, load_table
from magstack.firmware.corrector import TableCorrector
from magstack.firmware.fixed_point import to_fixed_inputs
from magstack.firmware.float_applier import apply_float
from magstack.ground.apply_session import FLAG_SHIFT
from magstack.ground.errors import AlignmentError
from magstack.sim.presets import preset

#: Norm of the HMC1053 preset's white noise per axis (uT): the floor no calibration can beat.
NOISE_NORM_uT = float(np.linalg.norm(preset("hmc1053").noise_white_uT))
#: Unmodelled-by-Eq.3 effects of the simulated sensor (hysteresis +-25 nT, second-order
#: cross-axis, pairing of a 4 Hz reference with a 2.8 Hz DUT) stay within a few noise sigmas.
RESIDUAL_BOUND_uT = 4.0 * NOISE_NORM_uT


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    lines: list[str] = []
    res = run_demo(DemoConfig(out_dir=out, seed=3, seconds=600.0), say=lines.append)
    return res, lines


def _sim_axis_spacing_s() -> tuple[float, float]:
    """(Y - X, Z - X) conversion-instant spacing of the simulated HMC1053, measured from a sample."""
    from magstack.drivers.registry import open_chip

    s = open_chip("hmc1053", "sim", VirtualClock()).read()
    return s.axis_t_s[1] - s.axis_t_s[0], s.axis_t_s[2] - s.axis_t_s[0]


def test_probe_identifies_every_chip_and_reads_them(demo):
    res, lines = demo
    p = res.probe
    # a freshly powered HMC5983 reads like an HMC5883L at 0x31/0x32: the probe says so
    assert sorted(d["chip"] for d in p.devices) == ["hmc5883l_or_hmc5983", "lis3mdl", "lsm303dlhc"]
    # the shared 0x1E address resolved to different chips on the two buses
    assert p.shared_address_chips == {"sim-i2c-1": "hmc5883l_or_hmc5983", "sim-i2c-2": "lsm303dlhc"}
    assert set(p.samples) == {"lis3mdl", "hmc5983", "lsm303dlhc", "hmc1053"}
    for chip, rows in p.samples.items():
        assert len(rows) == 3
        for r in rows:
            assert all(math.isfinite(v) for v in r["b_uT"]), chip
            assert r["temp_c"] is not None and abs(r["temp_c"] - p.truth_temp_c) < 2.0, chip
    # the HMC1053 reads the truth within its gain/offset errors (<= 12 % gain in belsten Table 3)
    b = np.mean([r["b_uT"] for r in p.samples["hmc1053"]], axis=0)
    assert np.linalg.norm(b - p.truth_uT) < 0.2 * np.linalg.norm(p.truth_uT)
    assert any("0x1e" in ln and "lsm303dlhc" in ln for ln in lines)


def test_bench_session_file_and_rates(demo):
    res, _ = demo
    b = res.bench
    s = read_session(b.path)
    assert len(s) == b.rows == b.dut_samples + b.ref_samples
    assert s.metadata["device_id"] == DEVICE_ID and s.metadata["dut_chip"] == "hmc1053"
    assert s.metadata["program"] == "full_in_range"
    assert int(np.all(np.isfinite(s.dut_uT), axis=1).sum()) == b.dut_samples
    _, dz = _sim_axis_spacing_s()
    # one vector = 7 conversions; the Z-X spacing is 2 conversions (hf8.2 table)
    assert b.dut_rate_hz == pytest.approx(2.0 / (7.0 * dz), rel=0.01)
    assert b.ref_rate_hz == pytest.approx(4.0, rel=0.01)
    assert b.ref_skipped.get("garbled", 0) > 0  # injected at 0.5 %, skipped and counted by the driver
    assert b.temp_range_c[1] - b.temp_range_c[0] > 40.0  # the thermal cycle of program 'full'


def test_alignment_recovers_simulated_timing_and_identity_map(demo):
    res, _ = demo
    a = res.align
    assert abs(a.offset_s) < max(0.1, 4 * a.offset_sigma_s) and a.offset_sigma_s < 0.05
    dy, dz = _sim_axis_spacing_s()
    sx, sy, sz = a.skew_sigma_s
    assert all(a.skew_determined)
    assert abs((a.skew_s[2] - a.skew_s[0]) - dz) < 3 * math.hypot(sx, sz)
    assert abs((a.skew_s[1] - a.skew_s[0]) - dy) < 3 * math.hypot(sx, sy)
    assert a.axis_map_identity and all(a.axis_map_determined)
    paired = read_session(a.paired_path)
    assert len(paired) == a.paired_rows and "clock offset" in paired.metadata["alignment_applied"]


def test_fit_calibrates_well_below_raw_and_near_the_noise(demo):
    res, _ = demo
    f = res.fit
    assert f.raw_rmse_norm_uT > 5.0  # the preset's gains/offsets: several uT before calibration
    assert f.rmse_norm_uT < f.raw_rmse_norm_uT / 50
    assert NOISE_NORM_uT * 0.5 < f.rmse_norm_uT < RESIDUAL_BOUND_uT
    assert f.holdout_blocks_norm_uT is not None and f.holdout_blocks_norm_uT < f.raw_rmse_norm_uT / 10
    assert 0 < f.noise_floor_norm_uT < f.rmse_norm_uT
    assert f.held == [] and min(f.temp_span_with_field_c) > 5.0
    adopted = [c for c in f.candidates if c["terms"] == f.terms][0]
    assert adopted["fixed_point"]
    assert adopted["holdout_blocks_norm_uT"] == min(c["holdout_blocks_norm_uT"] for c in f.candidates
                                                     if c["fixed_point"])
    # the fit undoes the simulated sensor: to first order in dT the exact inverse of the preset;
    # the neglected second-order term of 1/(1 + k dT) is (k dT_max)^2 with |dT| <= 30 degC
    p = preset("hmc1053")
    second_order = (float(np.max(np.abs(p.k_s_per_c))) * 30.0) ** 2
    assert f.recovery["S_max_abs"] < 1.5 * second_order
    assert f.recovery["K_S_max_abs_per_c"] < 0.05 * float(np.max(np.abs(p.k_s_per_c)))
    assert f.recovery["O_max_abs_uT"] < 0.05
    # the thermally flat slice cannot determine temperature terms: held, and refused on request
    assert f.slice_held and all(h["param"].startswith(("K_S", "K_O", "S[")) for h in f.slice_held)
    assert f.slice_refused and f.slice_held[0]["param"] in f.slice_refused
    assert f.report_path.read_text().startswith("model ")


def test_table_saved_validated_and_corrupt_copies_refused(demo):
    res, _ = demo
    t = res.table
    assert t.valid and t.worst_output_uT < 1000
    assert [r["kind"] for r in t.refused] == ["one digit changed", "truncated"]
    assert "CRC-32 mismatch" in t.refused[0]["error"] and "truncated" in t.refused[1]["error"]
    assert t.active_crc32_after == t.crc32 and t.reject_count == 2
    assert t.store.active is t.table
    loaded = load_table(t.path)
    assert f"0x{loaded.crc32:08x}" == t.crc32 and loaded.device_id == DEVICE_ID


def test_holdout_session_residual_before_after(demo):
    res, _ = demo
    h = res.holdout
    assert h.bench.seed == res.config.seed + 1
    assert h.n_steady > 100
    assert h.cal_rmse_norm_uT < h.raw_rmse_norm_uT / 50
    assert NOISE_NORM_uT * 0.8 < h.cal_rmse_norm_uT < RESIDUAL_BOUND_uT
    assert h.cal_rmse_all_norm_uT < h.raw_rmse_all_norm_uT / 5
    assert h.fixed_vs_float_max_nT < 0.5  # docs/fixed-point.md requirement
    assert h.saturated_rows == 0
    cal = read_session(h.calibrated_path)
    # rows outside the table's validity region are flagged and carry no value (as on board): the held-out
    # session's excursions take the calibrated field beyond the largest |B| at which the table can bound its
    # error in every direction; every other row is calibrated
    t = res.table.table
    paired = read_session(h.align.paired_path)
    b_cal, _ = apply_float(t, paired.dut_uT, paired.temp_c)
    beyond = ((np.linalg.norm(b_cal, axis=1) > t.validity_field_norm_uT)
              | (paired.temp_c < t.validity_temp_c[0]) | (paired.temp_c > t.validity_temp_c[1])
              | np.any(np.abs(b_cal) > np.asarray(t.field_limits_uT), axis=1))
    flagged = ((cal.flag >> FLAG_SHIFT) & 2) != 0
    assert h.out_of_validity_rows == int(flagged.sum())
    assert np.array_equal(flagged, beyond & np.all(np.isfinite(paired.dut_uT), axis=1))
    assert cal.metadata["cal_applier"] == "fixed" and cal.metadata["cal_table_crc32"] == res.table.crc32


def test_flight_loop_counts_injected_faults_and_keeps_running(demo):
    res, _ = demo
    lp = res.loop
    assert lp.health["bus_errors"] == lp.injected["bus_errors"] == 1
    assert lp.health["timeouts"] == lp.injected["timeouts"] == 1
    assert lp.health["error_count"] == 2 and lp.health["samples_ok"] == lp.cycles - 2
    assert lp.health["uncalibrated"] == 0
    faults = [p for p in lp.published if p["fault"]]
    assert [p["fault"].split(":")[0] for p in faults] == ["BusError", "BusTimeout"]
    after = [p for p in lp.published if p["cycle"] > faults[-1]["cycle"]]
    assert after and all(p["calibrated"] for p in after)
    assert lp.cal_error_norm_uT < RESIDUAL_BOUND_uT < lp.raw_error_norm_uT
    tlm = read_session(lp.path)                  # the channel's telemetry is a session file
    assert len(tlm) == lp.cycles and int(np.count_nonzero(tlm.flag)) == 2
    assert lp.events["CHAN_BUS_ERROR/hmc1053"] == 1 and lp.events["CHAN_TIMEOUT/hmc1053"] == 1
    assert lp.events_path.read_text().count('"CHAN_') == 2


def test_corrector_matches_float_applier_and_needs_an_active_table(demo):
    res, _ = demo
    from magstack.drivers.magnetometer import MagSample

    empty = TableCorrector(CalTableStore(DEVICE_ID))
    s = MagSample(0.0, (10.0, -20.0, 30.0), 30.0)
    assert empty.correct(s.b_uT, s.temp_c).b_uT is None
    corr = TableCorrector(res.table.store)
    b = corr.correct(s.b_uT, s.temp_c).b_uT
    bi, ti, _, _ = to_fixed_inputs([s.b_uT], [s.temp_c])
    ref, _ = apply_float(res.table.table, bi / 1e3, ti / 1e2)
    assert np.max(np.abs(np.array(b) - ref[0])) * 1e3 < 0.5
    assert corr.correct((10.0, -20.0, 30.0), None).b_uT is None  # the table needs temperature


def test_files_exist_and_parse(demo):
    res, _ = demo
    out = res.config.out_dir
    for name in ARTEFACTS:
        assert (out / name).is_file(), name
    for name in ("session.csv", "session-paired.csv", "holdout-session.csv", "holdout-paired.csv",
                 "holdout-calibrated.csv"):
        assert len(read_session(out / name)) > 100, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["holdout"]["cal_rmse_norm_uT"] == pytest.approx(res.holdout.cal_rmse_norm_uT)
    assert summary["loop"]["health"]["error_count"] == 2
    assert json.loads((out / "probe.json").read_text())["ads1248_id"] == res.probe.ads1248_id


@pytest.mark.slow
def test_cli_demo_runs_and_is_deterministic(tmp_path, capsys, shared_demo):
    a, b = tmp_path / "a", shared_demo["out"]
    assert main(["demo", "--out-dir", str(a), "--seconds", "300", "--seed", "1"]) == 0
    text = capsys.readouterr().out
    for n in range(1, 9):
        assert f"[{n}/8]" in text
    assert "summary" in text and "files written" in text
    # the same run with --json (the shared run, tests/conftest.py): stdout holds only the summary figures as
    # strict JSON

    def refuse(c):
        raise ValueError(f"non-standard JSON constant {c}")

    assert shared_demo["code"] == 0
    doc = json.loads(shared_demo["stdout"], parse_constant=refuse)
    assert doc["command"] == "demo" and doc["exit_code"] == 0 and doc["out_dir"] == str(b)
    assert {"probe", "bench", "align", "fit", "table", "holdout", "loop", "wall_s", "files"} <= set(doc)
    assert doc["loop"]["health"]["error_count"] == 2 and shared_demo["stderr"] == ""
    for name in ("session.csv", "session-paired.csv", "cal.json", "holdout-calibrated.csv", "flight-loop.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    html = (a / "report.html").read_text()
    assert html.startswith("<!DOCTYPE html>") and html.count("data:image/png;base64,") == 6
    assert "Flight executive" in html and "Held-out session" in html


def test_cli_rejects_bad_parameters(tmp_path, capsys):
    assert main(["demo", "--out-dir", str(tmp_path), "--seconds", "10"]) == 2
    assert "argument --seconds: must be within [300, 36000] s, got '10'" in capsys.readouterr().err
    assert main(["demo", "--out-dir", str(tmp_path), "--seed", "-1"]) == 2
    assert "argument --seed: must be within [0, 4294967295], got '-1'" in capsys.readouterr().err
    assert main(["demo", "--out-dir", ""]) == 2
    assert "argument --out/--out-dir: expected a directory name" in capsys.readouterr().err
    (tmp_path / "file").write_text("x")
    assert main(["demo", "--out-dir", str(tmp_path / "file")]) == 2
    assert "exists and is not a directory" in capsys.readouterr().err
    with pytest.raises(ConfigurationError):
        DemoConfig(seconds=math.nan)


@pytest.mark.slow
def test_failing_step_names_itself_and_exits_nonzero(tmp_path, monkeypatch, capsys):
    import magstack.ground.alignment

    def refuse(*args, **kwargs):
        raise AlignmentError("the data do not determine the clock offset (injected by the test)")

    monkeypatch.setattr(magstack.ground.alignment, "align_streams", refuse)
    with pytest.raises(MagError, match=r"step 3 \(align\) failed: AlignmentError: .*injected"):
        run_demo(DemoConfig(out_dir=tmp_path / "x", seconds=300.0), say=lambda s: None)
    assert main(["demo", "--out-dir", str(tmp_path / "y"), "--seconds", "300"]) == 3
    assert "step 3 (align) failed" in capsys.readouterr().err


def test_demo_reference_stays_inside_the_fvm400_range(demo, tmp_path, capsys):
    """The demo's simulated FVM400 stays inside its +-100 uT range, so `fit` on the demo's own session
    excludes no rows as saturated."""
    res, _ = demo
    s = read_session(res.bench.path)
    assert np.nanmax(np.abs(s.ref_uT)) < 99.0
    assert main(["fit", str(res.align.paired_path), "--no-holdout", "--out", str(tmp_path / "c.json"), "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)["stats"]
    assert stats["saturated_rows"] == 0 and stats["n_used"] > 0


def test_report_and_console_show_the_same_wall_time(demo):
    res, lines = demo
    console = next(ln for ln in lines if ln.startswith("wall time"))
    html = (res.config.out_dir / "report.html").read_text()
    page = re.search(r"<td>wall time[^<]*</td><td>([^<]*)</td>", html).group(1)
    assert console.endswith(f"  {page}") and page == f"{res.wall_s:.1f} s"
    doc = json.loads((res.config.out_dir / "summary.json").read_text())
    assert doc["wall_s"]["steps_1_to_7"] == pytest.approx(res.wall_s)
    assert doc["wall_s"]["total"] >= res.wall_s
