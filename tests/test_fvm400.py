"""FVM400 driver + simulator: framing table, robust parsing, faults, timeouts, URL handler, pty."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.drivers.bus.serial_port import open_serial
from magstack.drivers.clock import SystemClock, VirtualClock
from magstack.drivers.errors import BusError, BusTimeout, ProtocolError, ReadbackMismatch
from magstack.drivers.fvm400 import (
    COMMANDS,
    DEFAULT_MAX_ABS_NT,
    EOT,
    FVM400,
    SERIAL_SETTINGS,
    RecordError,
    parse_record,
)
from magstack.sim.fvm400_model import (
    FVM400Faults,
    FVM400Model,
    PtyInstrument,
    register_instrument,
    unregister_instrument,
)
from magstack.sim.truth_source import StaticTruth


class RampTruth(StaticTruth):
    """Field that changes linearly in time (uT, s)."""

    def field_uT(self, t_s):
        return np.array([10.0 + 2.0 * t_s, -3.0 * t_s, 45.0])


@pytest.fixture
def bench_instrument():
    clock = VirtualClock()
    model = FVM400Model(RampTruth(), clock)
    register_instrument("t_bench", model)
    yield model, clock
    unregister_instrument("t_bench")


def test_framing_table_golden_values():
    # hardware-facts 6.2: 9600 baud 8N1, 2 s timeout; '?' query, GM/GX, SM0/1, SX0/1, '*', SC0..2
    assert dict(SERIAL_SETTINGS) == {"baudrate": 9600, "bytesize": 8, "parity": "N", "stopbits": 1,
                                     "timeout_s": 2.0}
    assert EOT == b"\x04"
    sends = {k: c.send for k, c in COMMANDS.items()}
    assert sends == {"query": b"?", "defaults": b"*", "get_mode": b"GM", "get_representation": b"GX",
                     "set_absolute": b"SM0", "set_relative": b"SM1", "set_rectangular": b"SX0",
                     "set_polar": b"SX1", "channel_x": b"SC0", "channel_y": b"SC1", "channel_z": b"SC2"}
    assert COMMANDS["query"].reply == "record"


def test_parse_record_rig_sample_and_reasons():
    assert parse_record(" -8989,-108638,-107863") == (-8989, -108638, -107863)
    assert parse_record("1,2,3 ") == (1, 2, 3)
    cases = {"": "partial", " 12,34": "partial", " 1,2,3,4": "garbled", " 1,#2,3": "garbled",
             " 0.000004,1,2": "wrong_units", " 1,2,9999999": "out_of_range", "1,\x012,3": "garbled"}
    for text, reason in cases.items():
        with pytest.raises(RecordError) as ei:
            parse_record(text)
        assert ei.value.reason == reason, text


@settings(max_examples=150, deadline=None)
@given(st.tuples(*[st.integers(-DEFAULT_MAX_ABS_NT, DEFAULT_MAX_ABS_NT)] * 3))
def test_parse_record_roundtrip(vals):
    assert parse_record(" " + ",".join(str(v) for v in vals)) == vals


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=40))
def test_parse_record_never_crashes_on_garbage(text):
    try:
        vals = parse_record(text)
    except RecordError as exc:
        assert exc.reason in {"partial", "garbled", "wrong_units", "out_of_range"}
    else:
        assert len(vals) == 3 and all(abs(v) <= DEFAULT_MAX_ABS_NT for v in vals)


def test_reads_truth_in_nT_resolution_with_host_timestamp(bench_instrument):
    model, clock = bench_instrument
    drv = FVM400.open("fvm400sim://t_bench", clock)
    for _ in range(5):
        clock.sleep_s(0.25)
        s = drv.read()
        truth = RampTruth().field_uT(s.t_s)
        # serial transfer time at 9600 baud (~30 bytes ~ 31 ms) is modelled: field within the slope * transfer
        assert np.allclose(s.b_uT, truth, atol=0.001 + 3.0 * 0.04)
        assert s.extra["epoch_s"] == pytest.approx(clock.epoch_s() - (clock.monotonic_s() - s.t_s))
    assert drv.samples == 5 and not drv.skipped
    assert model.protocol_errors == []


def test_static_field_exact(clock):
    model = FVM400Model(StaticTruth((12.3456, -0.0004, 99.9999)), clock)
    register_instrument("t_static", model)
    try:
        s = FVM400.open("fvm400sim://t_static", clock).read()
    finally:
        unregister_instrument("t_static")
    assert s.b_uT == (12.346, -0.0, 100.0)


@pytest.mark.parametrize("fault,reason", [("garble", "garbled"), ("partial", "partial"),
                                          ("wrong_units", "wrong_units"), ("over_range", "out_of_range")])
def test_each_fault_counted_and_skipped(fault, reason, clock):
    model = FVM400Model(StaticTruth(), clock, seed=3, faults=FVM400Faults(**{fault: 0.3}))
    register_instrument("t_fault", model)
    try:
        drv = FVM400.open("fvm400sim://t_fault", clock, max_attempts=10)
        got = [drv.read() for _ in range(60)]
    finally:
        unregister_instrument("t_fault")
    assert all(np.allclose(s.b_uT, (20.0, -5.0, 40.0)) for s in got)
    assert model.injected[fault] > 5
    assert drv.skipped == {reason: model.injected[fault]}
    assert model.queries == 60 + model.injected[fault]


def test_dropout_raises_bus_timeout_after_port_timeout(clock):
    model = FVM400Model(StaticTruth(), clock, faults=FVM400Faults(dropout=1.0))
    register_instrument("t_drop", model)
    try:
        drv = FVM400.open("fvm400sim://t_drop", clock, timeout_s=0.5)
        t0 = clock.monotonic_s()
        with pytest.raises(BusTimeout):
            drv.read()
    finally:
        unregister_instrument("t_drop")
    assert clock.monotonic_s() - t0 == pytest.approx(0.5, abs=0.01)
    assert drv.skipped["timeout"] == 1


def test_too_many_bad_replies_is_protocol_error(clock):
    model = FVM400Model(StaticTruth(), clock, faults=FVM400Faults(garble=1.0))
    register_instrument("t_bad", model)
    try:
        drv = FVM400.open("fvm400sim://t_bad", clock, max_attempts=4)
        with pytest.raises(ProtocolError, match="4 bad replies"):
            drv.read()
    finally:
        unregister_instrument("t_bad")
    assert drv.skipped["garbled"] == 4


def test_configure_reads_back_and_detects_stuck_polar(clock):
    class StuckPolar(FVM400Model):
        def _set(self, attr, value):
            if attr == "representation":
                self.representation = 1
                return b"A" + EOT
            return super()._set(attr, value)

    model = FVM400Model(StaticTruth(), clock)
    model.representation, model.mode = 1, 1
    register_instrument("t_cfg", model)
    register_instrument("t_stuck", StuckPolar(StaticTruth(), clock))
    try:
        FVM400.open("fvm400sim://t_cfg", clock)
        assert (model.representation, model.mode) == (0, 0)
        with pytest.raises(ReadbackMismatch):
            FVM400.open("fvm400sim://t_stuck", clock)
    finally:
        unregister_instrument("t_cfg")
        unregister_instrument("t_stuck")


def test_front_panel_change_detected_by_periodic_verify(clock):
    model = FVM400Model(StaticTruth(), clock)
    register_instrument("t_pol", model)
    try:
        drv = FVM400.open("fvm400sim://t_pol", clock, verify_every=5)
        for _ in range(5):
            drv.read()
        model.representation = 1  # polar records are three integers too: syntax cannot tell
        with pytest.raises(ReadbackMismatch, match="get_representation = 1"):
            drv.read()
    finally:
        unregister_instrument("t_pol")


def test_relative_mode_zeroes_selected_channel(clock):
    model = FVM400Model(StaticTruth((20.0, -5.0, 40.0)), clock)
    register_instrument("t_rel", model)
    try:
        drv = FVM400.open("fvm400sim://t_rel", clock)
        drv.command("channel_y")
        drv.command("set_relative")
        assert drv.read().b_uT == (20.0, 0.0, 40.0)
        drv.command("set_absolute")
        assert drv.read().b_uT == (20.0, -5.0, 40.0)
    finally:
        unregister_instrument("t_rel")


def test_unknown_command_is_loud_in_the_model(clock):
    model = FVM400Model(StaticTruth(), clock)
    model.receive(b"Q")
    assert model.protocol_errors == ["unknown command b'Q'"]
    assert model.take(10) == b"N" + EOT
    with pytest.raises(ValueError, match="valid"):
        FVM400(open_serial("fvm400sim://?seed=0"), clock).command("bogus")


def test_url_options_and_errors():
    drv = FVM400.open("fvm400sim://?seed=2&noise_uT=0.5")
    s = drv.read()
    assert not np.allclose(s.b_uT, (20.0, -5.0, 40.0), atol=0.01)
    with pytest.raises(BusError, match="unknown fvm400sim option"):
        open_serial("fvm400sim://?garbel=0.1")
    with pytest.raises(BusError, match="no simulated FVM400 named"):
        open_serial("fvm400sim://nosuch")
    with pytest.raises(BusError, match="9600 baud"):
        open_serial("fvm400sim://?seed=1", baudrate=19200)
    with pytest.raises(BusError, match=r"must be in \[0, 1\]"):
        open_serial("fvm400sim://?dropout=2")


def test_through_a_real_pseudo_terminal():
    """The simulated instrument behind os.openpty; the driver opens the slave like /dev/ttyUSB0."""
    model = FVM400Model(StaticTruth((1.234, -56.789, 100.5)), SystemClock(), seed=5,
                        faults=FVM400Faults(garble=0.2))
    with PtyInstrument(model) as pty:
        assert pty.port.startswith("/dev/")
        drv = FVM400.open(pty.port, SystemClock(), timeout_s=0.5, max_attempts=10)
        try:
            samples = [drv.read() for _ in range(20)]
        finally:
            drv.close()
    assert all(s.b_uT == (1.234, -56.789, 100.5) for s in samples)
    assert drv.skipped.get("garbled", 0) == model.injected["garble"]
    assert all(b.t_s > a.t_s for a, b in zip(samples, samples[1:], strict=False))


def test_pty_timeout_is_bus_timeout():
    model = FVM400Model(StaticTruth(), SystemClock(), faults=FVM400Faults(dropout=1.0))
    with PtyInstrument(model) as pty:
        drv = FVM400(open_serial(pty.port, timeout_s=0.2), SystemClock(), configure=False)
        with pytest.raises(BusTimeout):
            drv.read()
        drv.close()


@pytest.mark.hil
def test_real_fvm400_on_serial_port(request):
    """Bench: a powered FVM400 on --fvm-port (default /dev/ttyUSB0), probe in the lab field."""
    drv = FVM400.open(request.config.getoption("--fvm-port"), SystemClock())
    try:
        samples = [drv.read() for _ in range(20)]
    finally:
        drv.close()
    b = np.array([s.b_uT for s in samples])
    # Earth's field plus lab disturbances: well inside the accepted range, and not all identical
    assert np.all(np.abs(b) < DEFAULT_MAX_ABS_NT / 1000.0)
    assert 1.0 < np.median(np.linalg.norm(b, axis=1)) < 150.0
    assert np.all(np.diff([s.t_s for s in samples]) > 0)
    assert sum(drv.skipped.values()) <= 2
