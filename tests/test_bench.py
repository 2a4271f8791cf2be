"""Bench runner: simulated sessions, each instrument at its own rate, faults, abort, threads, CLI."""
from __future__ import annotations

import io

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.drivers.clock import SystemClock
from magstack.drivers.errors import BusTimeout, ConfigurationError, MagError
from magstack.drivers.magnetometer import MagSample
from magstack.ground.alignment import align_streams
from magstack.hil.bench import build_sim_bench, paired_view, record_sim_session, run_bench


def _run(sb, path, **kw):
    return run_bench(sb.dut, sb.ref, sb.clock, path, ref_clock=sb.ref_clock, **kw)


def test_sim_session_rows_rates_and_metadata(tmp_path):
    sb = build_sim_bench("lis3mdl", program="steps_x", seconds=10.0, instrument_name="t_b1")
    res = _run(sb, tmp_path / "s.csv", seconds=10.0, metadata={"program": "steps_x"})
    assert res.completed and res.rows == res.dut_samples + res.ref_samples
    assert res.ref_samples / res.duration_s == pytest.approx(4.0, rel=0.05)
    assert res.dut_samples > 10 * res.ref_samples
    s = read_session(tmp_path / "s.csv")
    for key in ("dut_chip", "reference", "ref_rate_hz", "alignment_applied", "software_version", "program"):
        assert key in s.metadata
    assert s.metadata["dut_chip"] == "lis3mdl" and s.metadata["reference"] == "fvm400"
    t_dut, dut, t_ref, ref = paired_view(s)
    assert len(t_dut) == res.dut_samples and len(t_ref) == res.ref_samples
    assert np.all(np.diff(s.t_s) >= 0)  # one clock, rows in time order
    assert abs(s.t_s[0] - 1767225600.0) < 1.0  # VirtualClock epoch anchor
    # reference rows carry the coil program through the FVM400 model (integer nT)
    # the host stamps the midpoint of the ~30 ms serial exchange, so each reading lies between the
    # truth 30 ms before and at its timestamp (to the 1 nT resolution)
    before = np.array([sb.truth.field_uT(t - 1767225600.0 - 0.03) for t in t_ref])
    at = np.array([sb.truth.field_uT(t - 1767225600.0) for t in t_ref])
    lo, hi = np.minimum(before, at) - 0.0005, np.maximum(before, at) + 0.0005
    assert np.all((ref >= lo) & (ref <= hi))
    assert np.mean(np.all(ref == at.round(3), axis=1)) > 0.5  # on plateaus: exact to 1 nT


def test_faulty_reference_is_counted_and_session_continues(tmp_path):
    sb = build_sim_bench("hmc5983", program="sweep_y", seconds=20.0, seed=4, instrument_name="t_b2",
                         ref_faults={"garble": 0.1, "dropout": 0.05, "wrong_units": 0.05})
    res = _run(sb, tmp_path / "f.csv", seconds=20.0)
    assert res.completed
    assert res.ref_errors["BusTimeout"] == sb.ref_model.injected["dropout"] > 0
    assert res.ref_skipped["garbled"] + res.ref_skipped.get("wrong_units", 0) > 0
    assert "timeout" not in res.ref_skipped
    assert len(paired_view(read_session(tmp_path / "f.csv"))[2]) == res.ref_samples


def test_consecutive_failures_abort_and_keep_part(tmp_path):
    sb = build_sim_bench("lis3mdl", seconds=30.0, instrument_name="t_b3", ref_faults={"dropout": 1.0})
    with pytest.raises(MagError, match="ref failed 3 times in a row"):
        _run(sb, tmp_path / "a.csv", seconds=30.0, max_consecutive_errors=3)
    assert (tmp_path / "a.csv.part").exists() and not (tmp_path / "a.csv").exists()
    assert len(read_session(tmp_path / "a.csv.part")) > 0  # DUT rows recorded before the abort


def test_align_recovers_simulated_hmc1053_axis_timing(tmp_path):
    """End to end: coil sweep -> HMC1053 front end + FVM400 -> session -> alignment."""
    sb = build_sim_bench("hmc1053", program="sweep_x", seconds=120.0, instrument_name="t_b4")
    samples = []
    real_read = sb.dut.read

    def spy():
        s = real_read()
        samples.append(s)
        return s

    sb.dut.read = spy
    res = _run(sb, tmp_path / "h.csv", seconds=120.0)
    # one virtual clock per instrument: the 4 Hz reference is not held up by 0.36 s DUT cycles
    assert res.ref_samples / res.duration_s == pytest.approx(4.0, rel=0.02)
    assert np.all(np.diff(read_session(tmp_path / "h.csv").t_s) >= 0)
    t_dut, dut, t_ref, ref = paired_view(read_session(tmp_path / "h.csv"))
    rep = align_streams(t_dut, dut, t_ref, ref, prior_s=0.0, search_halfwidth_s=5.0)
    assert abs(rep.offset.offset_s) < 0.2
    # the simulator converts X, Y, Z in sequence: axis instants relative to the sample time
    axis_dt = np.mean([np.subtract(s.axis_t_s, s.t_s) for s in samples], axis=0)
    x = rep.skew_s[0]
    assert x.determined
    # DUT axis i reads the field at t + axis_dt[i]; a reference row is stamped mid-exchange, about
    # 15 ms (of a ~30 ms exchange) after the instrument sampled: effective offset -(axis_dt + 0.015)
    assert rep.offset.offset_s - x.value == pytest.approx(-axis_dt[0] - 0.015, abs=0.015 + 4 * x.sigma)
    for i in (1, 2):  # Y and Z see the X sweep only through cross-coupling; check them where determined
        e = rep.skew_s[i]
        if e.determined:
            assert e.value - x.value == pytest.approx(axis_dt[i] - axis_dt[0], abs=0.01 + 4 * e.sigma)
    assert rep.axis_map.perm[0] == 0 and rep.axis_map.sign[0] == 1 and rep.axis_map.determined[0]


class _SlowDut:
    """A DUT whose read blocks 0.3 s in real time (like a full HMC1053 conversion cycle)."""

    name = "slow"

    def __init__(self, clock):
        self.clock = clock

    def read(self):
        self.clock.sleep_s(0.3)
        return MagSample(self.clock.monotonic_s(), (1.0, 2.0, 3.0), 25.0)

    def data_ready(self):
        return True


class _FlakyRef:
    name = "fakeref"

    def __init__(self, clock):
        self.clock, self.n, self.skipped = clock, 0, {}

    def read(self):
        self.n += 1
        if self.n == 2:
            raise BusTimeout("no reply")
        return MagSample(self.clock.monotonic_s(), (1.0, 2.0, 3.0))

    def data_ready(self):
        return True


def test_threaded_real_clock_reference_not_held_up_by_slow_dut(tmp_path):
    clock = SystemClock()
    calls = []
    res = run_bench(_SlowDut(clock), _FlakyRef(clock), clock, tmp_path / "t.csv", seconds=1.2, ref_rate_hz=10.0,
                    progress=lambda elapsed_s, r, final=False: calls.append((elapsed_s, r.rows, final)))
    assert res.completed and res.ref_errors["BusTimeout"] == 1
    # 10 Hz reference vs. 0.3 s DUT reads (~11 vs ~4): not held up (relation, robust to machine load)
    assert res.dut_samples >= 2 and res.ref_samples >= 2 * res.dut_samples
    assert read_session(tmp_path / "t.csv").metadata["scheduler"] == "threads"
    # progress reported while running, then once more (final) with the whole duration
    assert len(calls) >= 3 and calls[-1][2] and not any(c[2] for c in calls[:-1])
    assert calls[-1][0] >= 1.2 and calls[-1][1] == res.rows


def test_bad_parameters():
    sb = build_sim_bench("lis3mdl", seconds=5.0, instrument_name="t_b5")
    for kw in ({"seconds": 0}, {"seconds": 1, "ref_rate_hz": 0}, {"seconds": 1, "dut_rate_hz": -1.0},
               {"seconds": float("nan")}):
        with pytest.raises(ConfigurationError):
            _run(sb, "/nonexistent/x.csv", **kw)
    with pytest.raises(ConfigurationError, match="unknown program"):
        build_sim_bench("lis3mdl", program="nope")
    with pytest.raises(ConfigurationError, match="unknown chip"):
        build_sim_bench("nochip")


def test_cli_bench_sim(tmp_path, capsys):
    out = tmp_path / "cli.csv"
    rc = main(["bench", "--dut", "lsm303dlhc", "--ref", "fvm400", "--bus", "sim", "--seconds", "5", "--out", str(out),
               "--program", "currents", "--sim-ref-faults", "garble=0.05"])
    assert rc == 0
    cap = capsys.readouterr()
    assert "rows in" in cap.out and cap.err == ""   # stderr is not a terminal: no progress bar
    s = read_session(out)
    assert set(s.currents_A) == {"solar", "torquer"} and s.metadata["program"] == "currents"
    assert main(["bench", "--dut", "lis3mdl", "--bus", "1", "--seconds", "1", "--out", str(out),
                 "--sim-ref-faults", "garble=0.1"]) == 2


def test_single_virtual_clock_interleave(tmp_path):
    from magstack.drivers.clock import VirtualClock
    from magstack.drivers.fvm400 import FVM400
    from magstack.drivers.registry import open_chip
    from magstack.sim.coil_programs import program
    from magstack.sim.fvm400_model import FVM400Model, register_instrument, unregister_instrument
    from magstack.sim.i2c_bench import default_bench

    clock = VirtualClock()
    truth = program("sweep_z", 10.0)
    register_instrument("t_one", FVM400Model(truth, clock))
    try:
        ref = FVM400.open("fvm400sim://t_one", clock)
        dut = open_chip("hmc5983", "sim", clock, bench=default_bench(clock, truth))
        res = run_bench(dut, ref, clock, tmp_path / "one.csv", seconds=10.0, dut_rate_hz=15.0)
    finally:
        unregister_instrument("t_one")
    s = read_session(tmp_path / "one.csv")
    assert s.metadata["scheduler"] == "single-thread interleave"
    assert res.ref_samples == pytest.approx(40, abs=2) and res.dut_samples == pytest.approx(150, abs=3)
    assert np.all(np.diff(s.t_s) >= 0)


def test_stop_request_ends_the_session_with_a_complete_file(tmp_path):
    import threading

    stop = threading.Event()

    def progress(elapsed_s, res, final=False):
        if elapsed_s >= 3.0:
            stop.set()   # what the CLI's SIGTERM handler does

    res, sb = record_sim_session("lis3mdl", tmp_path / "s.csv", program="steps_x", seconds=60.0, seed=1,
                                 instrument_name="t_stop", progress=progress, stop=stop)
    assert res.completed and res.stopped_early and 3.0 <= res.duration_s < 4.0
    assert not (tmp_path / "s.csv.part").exists()
    s = read_session(tmp_path / "s.csv")
    assert len(s) == res.rows > 0 and s.metadata["requested_s"] == "60"
    assert s.metadata["ref_faults"] == "none" and s.metadata["program"] == "steps_x"
    from magstack.sim.fvm400_model import get_instrument

    with pytest.raises(KeyError):   # the simulated instrument is unregistered afterwards
        get_instrument("t_stop")


@pytest.mark.parametrize("signame, code", [("SIGTERM", 143), ("SIGHUP", 129)])
def test_cli_bench_sigterm_stops_with_message_and_complete_file(tmp_path, signame, code):
    """SIGTERM and SIGHUP stop `bench` with a message and a complete file, not silently with only the
    .part file."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "long.csv"
    proc = subprocess.Popen([sys.executable, "-m", "magstack", "bench", "--dut", "lis3mdl", "--seconds", "86400",
                             "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    part = tmp_path / "long.csv.part"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (not part.exists() or part.stat().st_size < 5000):
        time.sleep(0.05)
    proc.send_signal(getattr(signal, signame))
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == code, stderr
    assert f"stopped by {signame} after" in stdout and "is complete with the" in stdout
    assert "stopped on request" in stderr   # the library's warning on the log
    assert out.exists() and not part.exists()
    s = read_session(out)
    assert len(s) > 50 and s.metadata["requested_s"] == "86400"


def test_cli_bench_progress_bar_on_a_terminal(tmp_path, capsys, monkeypatch):
    import sys

    class Tty(io.StringIO):
        def isatty(self):
            return True

    err = Tty()
    monkeypatch.setattr(sys, "stderr", err)
    assert main(["bench", "--dut", "lis3mdl", "--seconds", "5", "--out", str(tmp_path / "a.csv")]) == 0
    text = err.getvalue()
    assert "bench:" in text and "dut=" in text and "ref=" in text   # tqdm bar with the running counts
    monkeypatch.setattr(sys, "stderr", err := Tty())
    assert main(["bench", "--dut", "lis3mdl", "--seconds", "5", "--out", str(tmp_path / "b.csv"), "--json"]) == 0
    assert err.getvalue() == ""   # --json: no bar


@pytest.mark.parametrize("args,msg", [
    (["--ref-rate-hz", "1e9"], "argument --ref-rate-hz: must be within [0.01, 20] Hz"),
    (["--ref-rate-hz", "nan"], "argument --ref-rate-hz: expected a finite number"),
    (["--dut-rate-hz", "0"], "argument --dut-rate-hz: must be within [0.01, 1000] Hz"),
    (["--seconds", "inf"], "argument --seconds: expected a finite number"),
    (["--sim-ref-faults", "garble=2"], "argument --sim-ref-faults: must be within [0, 1]"),
    (["--program", "nope"], "argument --program: unknown program 'nope'"),
    (["--out", ""], "argument --out: expected a file name"),
])
def test_cli_bench_validates_options_at_parse_time(tmp_path, capsys, args, msg):
    base = {"--seconds": "1", "--out": str(tmp_path / "x.csv")}
    base.update(dict(zip(args[::2], args[1::2], strict=True)))
    argv = ["bench", "--dut", "lis3mdl"] + [x for kv in base.items() for x in kv]
    assert main(argv) == 2
    assert msg in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_threaded_session_stops_on_request(tmp_path):
    import threading

    clock = SystemClock()
    stop = threading.Event()
    timer = threading.Timer(0.5, stop.set)
    timer.start()
    try:
        res = run_bench(_SlowDut(clock), _FlakyRef(clock), clock, tmp_path / "t.csv", seconds=30.0, ref_rate_hz=10.0,
                        stop=stop)
    finally:
        timer.cancel()
    assert res.completed and res.stopped_early and res.duration_s < 5.0
    assert len(read_session(tmp_path / "t.csv")) == res.rows > 0


def test_graceful_stop_turns_sigterm_into_an_event_and_restores_handlers():
    import os
    import signal
    import time

    from magstack.cli.interrupt import graceful_stop

    before = signal.getsignal(signal.SIGTERM)
    with graceful_stop() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        deadline = time.monotonic() + 5
        while not stop.is_set() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert stop.is_set() and stop.signal_name == "SIGTERM"
    assert signal.getsignal(signal.SIGTERM) == before
