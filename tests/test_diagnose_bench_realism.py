"""The diagnosis on cases where real benches differ from simulations: a clipped reference, a prior conflict
that must not keep the gap, thermal lag restarting after pauses, an even/odd alternation at the DUT's Nyquist
frequency, hysteresis whose state flips once per session, and the orbit floor's parts.

Each case comes from this file's own numpy generator (not the project's error model), built to show the
failure it guards against.
"""
from __future__ import annotations

import numpy as np
import pytest

from magstack.data.session import Session
from magstack.ground.diagnose import diagnose_model

G = np.array([[1.09, 0.05, -0.03], [0.04, 1.11, 0.02], [-0.02, 0.03, 1.10]])
O = np.array([0.3, -0.1, 0.45])


def _steps(levels, dwell_s, ramp_s):
    tk, v, t = [0.0], [levels[0]], 0.0
    for a in levels[1:]:
        t += dwell_s
        tk.append(t)
        v.append(v[-1])
        t += ramp_s
        tk.append(t)
        v.append(a)
    t += dwell_s
    tk.append(t)
    v.append(v[-1])
    return np.array(tk), np.array(v, float)


def _lowpass(x: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    a = np.exp(-dt_s / tau_s)
    y = np.empty_like(x)
    y[0] = x[0]
    for k in range(1, x.shape[0]):
        y[k] = a * y[k - 1] + (1 - a) * x[k]
    return y


def high_field_run(seed=0, clip_uT=107.1, peak_uT=119.0, ref_tau_s=0.4, noise_uT=0.03) -> Session:
    """Three sessions, one per axis, each stepping its axis through 0, +-40, +-80, +-``peak_uT`` (8 s dwells,
    0.1 s steps) over a small constant field; the fluxgate reference (4.1 Hz, 3 nT, 1 nT steps) clips at
    +-``clip_uT`` in its loop and its output follows a first-order filter (``ref_tau_s``), linearly
    interpolated onto the DUT rows (0.461 s); the DUT reads G B + O with 30 nT noise."""
    rng = np.random.default_rng(seed)
    levels = [0, 40, 80, peak_uT, 80, 40, 0, -40, -80, -peak_uT, -80, -40, 0] * 2
    parts, t0 = [], 1.7e9
    for ax in range(3):
        tk, v = _steps(levels, 8.0, 0.1)
        span = tk[-1]

        def truth(t, tk=tk, v=v, ax=ax):
            b = np.tile([4.0, -3.0, 2.0], (t.size, 1))
            b[:, ax] += np.interp(t, tk, v)
            return b
        tf = np.arange(0.0, span, 0.01)
        out = _lowpass(np.clip(truth(tf), -clip_uT, clip_uT), 0.01, ref_tau_s)
        t_ref = np.cumsum(0.244 + rng.uniform(-0.015, 0.015, int(span / 0.2)))
        t_ref = t_ref[t_ref < span]
        r = np.column_stack([np.interp(t_ref, tf, out[:, j]) for j in range(3)])
        r = np.round(r + rng.standard_normal(r.shape) * 0.003, 3)
        t = np.cumsum(0.461 + rng.uniform(-0.006, 0.006, int(span / 0.4)))
        t = t[(t > t_ref[0]) & (t < t_ref[-1])]
        ref = np.column_stack([np.interp(t, t_ref, r[:, j]) for j in range(3)])
        dut = truth(t) @ G.T + O + rng.standard_normal((t.size, 3)) * noise_uT
        parts.append(Session(t0 + t, ref, dut, 25.0 + 0.3 * np.sin(t / 50.0), np.full(t.size, ax + 1), {},
                             {"reference": "fvm400", "dut_chip": "hmc1053", "device_id": "hf"}))
        t0 += span + 100.0
    return Session.concatenate(parts)


# ----------------------------------------------------------------------------- a clipped reference
def test_a_reference_clipped_beyond_its_range_is_left_out_and_the_report_says_why():
    """The reference sits flat at +-107.1 uT (an FVM400 beyond its +-100 uT range) while the DUT reads
    ~119 uT; the reference's output filter makes the edge rows vary, which a spread test took for "following
    the DUT": those rows stayed and the gap read tens of times the floor at 100-200 uT."""
    s = high_field_run()
    d = diagnose_model(s, "gain_offset")
    j = d.to_dict()
    ref = j["reference"]
    assert ref["saturated_excluded"] and ref["saturated_rows"] > 150, ref
    assert {(c["axis"], c["sign"]) for c in ref["clipped"]} == {(a, g) for a in "xyz" for g in "+-"}
    assert all(abs(abs(c["level_uT"]) - 107.1) < 0.05 and c["excess_uT"] > 5 for c in ref["clipped"])
    why = ref["excluded_by_reason"]
    assert why["at_range"] > 100 and why["dut_beyond_range"] > 0 and why["next_to_clipped"] > 0
    assert sum(why.values()) == ref["saturated_rows"]
    assert any("clips" in n and "107.1" in n and "rows at its range" in n for n in j["notes"]), j["notes"]
    assert not j["unexplained"]["remains"], d.text()
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"], d.text()
    # the reference's output filter is a real lag (a bandwidth limit): time skew is the only name allowed
    assert j["verdict"] in ("none", "time_skew"), d.text()


def test_a_reference_plateau_the_dut_agrees_with_is_not_a_clip():
    """Coils held at 105 uT, within 10 % of the nominal range, on an unclipped reference: a plateau at an
    extreme, but the DUT agrees with it, so nothing is left out."""
    s = high_field_run(clip_uT=1000.0, peak_uT=105.0, ref_tau_s=0.01)
    j = diagnose_model(s, "gain_offset").to_dict()
    ref = j["reference"]
    assert ref["saturated_rows"] == 0 and not ref["clipped"], ref
    assert "DUT agrees" in ref["note"]


# ----------------------------------------------------------------------------- a prior conflict is evidence
def _thermal_run(seed=3, seconds=1800.0, tempco=-2.7e-3, k_o=(0.0, 0.1, 0.0)) -> Session:
    """X held at 44 uT while the unit cools 80 -> 38 degC (slower than exponential at the end: the run is
    stopped before it settles); every sensitivity falls with temperature (``tempco``) and Y carries an offset
    tempco ``k_o`` (0.1 uT/degC: beyond the HMC1053's datasheet prior, as a real board's can be); 30 nT noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 0.5)
    temp = 38.0 + 42.0 * np.exp(-t / seconds)
    dT = temp - 25.0
    b = np.tile([44.0, 0.0, 0.0], (t.size, 1))
    dut = (b @ G.T) * (1.0 + tempco * dT)[:, None] + O + np.outer(dT, k_o)
    dut = dut + rng.standard_normal(dut.shape) * 0.03
    ref = b + rng.standard_normal(b.shape) * 0.002
    return Session(1.7e9 + t, ref, dut, temp, np.zeros(t.size, int), {},
                   {"device_id": "thermal", "dut_chip": "hmc1053"})


def _sweep_only_table():
    """A gain + offset table fitted on a bench sweep at one temperature (no temperature column)."""
    from test_diagnose import make

    from magstack.firmware.cal_table import table_from_fit
    from magstack.firmware.calibration import FitData, FitOptions, fit
    clean = make(None, seed=5, temp=False)
    return table_from_fit(fit(FitData.from_session(clean), "gain_offset", options=FitOptions(holdout=False)), "test")


def test_a_thermal_run_against_a_sweep_only_table_keeps_the_temperature_gain_despite_a_prior_conflict():
    """temperature_gain closes the gap (needing Y's offset tempco K_O[y] a little beyond 3 prior sd of the hmc1053
    prior); drift is plausible but leaves three times the floor. A veto would hand the verdict to drift (whose
    held-out residual is not kept while searching: it must be evaluated again). Weighed, the conflict leaves
    temperature_gain named; held within the prior it still closes the gap, so the conflict costs nothing here."""
    from test_diagnose import _table_diagnosis
    j = _table_diagnosis(_thermal_run(), _sweep_only_table()).to_dict()
    assert j["verdict"] == "temperature_gain", j["notes"]
    assert j["after_rmse_nT"] <= 1.2 * j["noise_floor_nT"]
    checks = {c["effect"]: c for c in j["prior_check"]}
    assert not checks["temperature_gain"]["plausible"] and checks["drift"]["plausible"]
    assert checks["temperature_gain"]["constrained_rmse_nT"] <= 1.2 * j["noise_floor_nT"]
    assert checks["drift"]["constrained_rmse_nT"] > 2 * j["noise_floor_nT"]
    assert any("prior conflict weighed, not a veto" in n and "data's verdict stands" in n for n in j["notes"]), \
        j["notes"]


def test_two_explanations_beyond_the_prior_leave_the_data_s_verdict_with_both_fits_within_the_prior():
    """Forward, at one field level: temperature_offset (the data's pick, fewer parameters) needs K_O[x] ~20 sd out,
    temperature_gain its Y cross term ~7 sd out; neither closes the gap within its prior, so the data's verdict
    stands and the note gives what each leaves within its prior."""
    d = diagnose_model(_thermal_run(), "gain_offset")
    j = d.to_dict()
    assert j["verdict"] == "temperature_offset", j["notes"]
    checks = {c["effect"]: c for c in j["prior_check"]}
    assert not checks["temperature_offset"]["plausible"] and not checks["temperature_gain"]["plausible"]
    assert min(c["constrained_rmse_nT"] for c in checks.values()) > 3 * j["after_rmse_nT"]
    assert any("not a veto" in n and "temperature_gain" in n and "within its prior" in n for n in j["notes"])
    assert "fitted within 3 prior sd" in d.text()


# ----------------------------------------------------------------------------- thermal lag restarting after pauses
def lag_restart_run(seed=0, tau_s=260.0, session_s=900.0, pause_s=90.0, sessions=3, noise_uT=0.03) -> Session:
    """Power cycles of ``session_s`` with ``pause_s`` pauses; the board warms by 18 degC per cycle (heater) from a
    different start each time (it cooled while off), the die follows it with ``tau_s`` and restarts in
    equilibrium at each power-on (a powered-down bench); HMC1053-like temperature effects on the die
    temperature (-140 nT/degC on X, -2700 ppm/degC); a tumbling field."""
    rng = np.random.default_rng(seed)
    starts = 25.0 + np.array([0.0, 6.0, -2.0, 4.0, 1.0])
    t_all, board_all, die_all, sess = [], [], [], []
    t0 = 0.0
    for k in range(sessions):
        t = t0 + np.arange(0.0, session_s, 0.5)
        u = t - t0
        board = starts[k] + 18.0 * (1 - np.exp(-u / 300.0)) + 2.0 * np.sin(2 * np.pi * u / 420.0)
        die = np.empty_like(board)
        die[0] = board[0]
        a = np.exp(-0.5 / tau_s)
        for i in range(1, t.size):
            die[i] = a * die[i - 1] + (1 - a) * board[i]
        t_all.append(t)
        board_all.append(board)
        die_all.append(die)
        sess.append(np.full(t.size, k))
        t0 += session_s + pause_s
    t, board, die, s = (np.concatenate(x) for x in (t_all, board_all, die_all, sess))
    w = 2 * np.pi * np.array([1 / 97.0, 1 / 131.0, 1 / 173.0])
    b = np.column_stack([40 * np.sin(w[0] * t), 35 * np.cos(w[1] * t + 0.3), 30 * np.sin(w[2] * t + 1.1)])
    dT = die - 25.0
    dut = (b @ G.T) * (1 - 2.7e-3 * dT)[:, None] + O + np.outer(dT, [-0.14, 0.02, 0.03])
    dut = dut + rng.standard_normal(dut.shape) * noise_uT
    return Session(1.6e9 + t, b + rng.standard_normal(b.shape) * 0.001, dut, board, s, {},
                   {"device_id": "lag", "dut_chip": "hmc1053"})


@pytest.mark.parametrize("seed,sessions", [(0, 3), (1, 4)])
def test_thermal_lag_restarting_after_pauses_closes_the_gap_with_the_right_time_constant(seed, sessions):
    """90 s pauses, a 260 s lag restarting at each power-on: carried across the pauses, the die temperature was
    wrong for minutes after each start (after/floor 4.6-6.2, tau ~46 s); with each start fitted the gap closes."""
    s = lag_restart_run(seed=seed, sessions=sessions, session_s=900.0 if sessions == 3 else 700.0)
    d = diagnose_model(s, "gain_offset")
    j = d.to_dict()
    assert j["verdict"] == "thermal_lag", d.text()
    assert j["after_rmse_nT"] <= 1.1 * j["noise_floor_nT"], d.text()
    assert 230.0 <= j["parameters"]["tau_s"]["value"] <= 290.0, j["parameters"]["tau_s"]
    starts = [j["parameters"][f"T_die_start[{r}]"] for r in range(sessions)]
    truth = 25.0 + np.array([0.0, 6.0, -2.0, 4.0])[:sessions]       # the die starts at the board's temperature
    assert np.allclose([p["value"] for p in starts], truth, atol=0.5), starts
    assert all(p["unit"] == "degC" for p in starts)


# ----------------------------------------------------------------------------- even/odd alternation at Nyquist
def alternating_run(seed=0, offset_nT=(40.0, -15.0, 25.0), stamp_ms=0.0, seconds=1500.0, sessions=3,
                    period_s=0.461) -> Session:
    """A 0.461 s DUT (jitter +-6 ms, 1 % of cycles not logged) whose reading alternates with the set/reset strap
    by ``offset_nT`` (a bridge offset that the half-difference does not cancel: docs/hmc1053-front-end.md), or a
    logger stamping the rows alternately ``stamp_ms`` early and late; tumbling field, 30 nT noise."""
    rng = np.random.default_rng(seed)
    ts, ss, cyc = [], [], []
    t0 = 0.0
    for k in range(sessions):
        n = int(seconds / sessions / period_s)
        c = np.arange(n)
        keep = rng.random(n) > 0.01
        t = t0 + c * period_s + rng.uniform(-0.006, 0.006, n)
        ts.append(t[keep])
        ss.append(np.full(int(keep.sum()), k))
        cyc.append(c[keep])
        t0 = t[-1] + 60.0
    t, s, c = np.concatenate(ts), np.concatenate(ss), np.concatenate(cyc)
    par = np.where(c % 2 == 0, 1.0, -1.0)
    w = 2 * np.pi * np.array([1 / 97.0, 1 / 131.0, 1 / 173.0])

    def field(tt):
        return np.column_stack([40 * np.sin(w[0] * tt), 35 * np.cos(w[1] * tt + 0.3), 30 * np.sin(w[2] * tt + 1.1)])
    dut = field(t) @ G.T + O + rng.standard_normal((t.size, 3)) * 0.03 + np.outer(par, offset_nT) * 1e-3
    logged = t + par * stamp_ms * 1e-3
    ref = field(logged) + rng.standard_normal((t.size, 3)) * 0.002     # the reference at the logged instants
    return Session(1.6e9 + logged, ref, dut, np.full(t.size, 25.0), s, {}, {"device_id": "alt"})


def test_an_alternating_set_reset_offset_is_named_an_even_odd_alternation_at_nyquist():
    """Its power sits at the Nyquist frequency of the 0.461 s sampling, where a periodogram's last bin hides it
    and missed cycles smear it beside Nyquist: only the explicit parity test names it."""
    d = diagnose_model(alternating_run(), "gain_offset")
    j = d.to_dict()
    a = j["where"]["alternation"]
    assert a["significant"] and a["p_value"] < 1e-10
    assert np.allclose(a["amplitude_nT"], [40.0, 15.0, 25.0], atol=3.0), a["amplitude_nT"]
    assert abs(a["nyquist_hz"] - 1 / (2 * 0.461)) < 0.01
    assert any("set/reset polarity: an offset alternating" in c for c in a["causes"]) and len(a["causes"]) == 1
    assert "even/odd alternation at the Nyquist frequency" in d.text()
    near = [t for t in j["where"]["tones"] if abs(t["freq_hz"] - 1.0846) < 2e-3]
    assert all(t.get("kind") == "even_odd_alternation" for t in near)
    assert j["verdict"] == "none"


def test_time_stamps_alternating_early_and_late_are_named_as_such():
    j = diagnose_model(alternating_run(offset_nT=(0.0, 0.0, 0.0), stamp_ms=20.0), "gain_offset").to_dict()
    a = j["where"]["alternation"]
    assert a["significant"] and abs(a["stamp_alternation_ms"] - 20.0) < 1.0, a
    assert len(a["causes"]) == 1 and a["causes"][0].startswith("time stamps alternating early/late")


def test_no_alternation_is_named_without_one():
    j = diagnose_model(alternating_run(offset_nT=(0.0, 0.0, 0.0)), "gain_offset").to_dict()
    a = j["where"]["alternation"]
    assert not a["significant"] and a["p_value"] > 0.01
    assert not any(t.get("kind") == "even_odd_alternation" for t in j["where"]["tones"])


# ----------------------------------------------------------------------------- hysteresis flipping once per session
def once_per_session(seed=0, sessions=3, session_s=600.0, pause_s=60.0, lead_s=10.0, rem_nT=(50.0, 10.0, -8.0),
                     yz_peak_uT=90.0, noise_uT=0.03) -> Session:
    """One +-150 uT X excursion ``lead_s`` into each power cycle (sign alternating) sets a remanence vector
    ``rem_nT`` that holds until the next cycle's excursion, so the state flips once per session and only the first
    ``lead_s`` of each cycle tell it from a per-session offset; Y and Z step to +-``yz_peak_uT`` (no remanence)
    twice per cycle; tumbling field, 30 nT noise, 0.46 s rows."""
    rng = np.random.default_rng(seed)
    ts, ss = [], []
    t0 = 0.0
    for k in range(sessions):
        t = t0 + np.arange(0.0, session_s, 0.46)
        ts.append(t + rng.uniform(-0.005, 0.005, t.size))
        ss.append(np.full(t.size, k))
        t0 += session_s + pause_s
    t, s = np.concatenate(ts), np.concatenate(ss)
    w = 2 * np.pi * np.array([1 / 97.0, 1 / 131.0, 1 / 173.0])
    b = np.column_stack([40 * np.sin(w[0] * t), 35 * np.cos(w[1] * t + 0.3), 30 * np.sin(w[2] * t + 1.1)])
    state = np.zeros(t.size)
    cur = -1.0                              # the part's state before the file starts
    for k in range(sessions):
        sign = 1.0 if k % 2 == 0 else -1.0
        m = np.flatnonzero(s == k)
        u = t[m] - t[m][0]
        b[m[(u >= lead_s) & (u < lead_s + 15.0)]] = [sign * 150.0, 0.0, 0.0]
        for j, at in ((1, 200.0), (2, 380.0)):
            b[m[(u >= at) & (u < at + 12.0)], j] = (1 if (k + j) % 2 else -1) * yz_peak_uT
        state[m] = np.where(u < lead_s, cur, sign)
        cur = sign
    dut = b @ G.T + O + np.outer(state, rem_nT) * 1e-3 + rng.standard_normal(b.shape) * noise_uT
    return Session(1.6e9 + t, b + rng.standard_normal(b.shape) * 0.002, dut, np.full(t.size, 25.0), s, {},
                   {"device_id": "hyst"})


@pytest.mark.parametrize("seed", [0, 3])
def test_hysteresis_flipping_once_per_session_is_a_near_tie_that_parsimony_decides(seed):
    """Only the first 10 s of each cycle tell the remanence from per-session offsets: held out they tie. Counting
    a parameter vector for every axis with large fields (9) would make session_offset (6) the simpler; the fit
    uses one remanence vector (3): hysteresis is named, and the report says it is a near-tie."""
    d = diagnose_model(once_per_session(seed=seed), "gain_offset")
    j = d.to_dict()
    assert j["verdict"] == "hysteresis", j["notes"]
    cmp = j["hysteresis_vs_session_offset"]
    assert cmp["near_tie"] and cmp["decided_by"] == "parsimony"
    assert cmp["n_params"] == [3, 6]
    assert next(r for r in j["ranking"] if r["effect"] == "hysteresis")["significant"]
    assert any(n.startswith("near-tie: hysteresis") and "parsimony names hysteresis" in n for n in j["notes"])
    assert j["after_rmse_nT"] <= 1.1 * j["noise_floor_nT"]
