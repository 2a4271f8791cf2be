"""FVM400 protocol points the manual does not settle and bad replies:
either GM reading accepted with a warning, no hang on a missing terminator, bounded replies and
fields, and a fuzz test: whatever the instrument sends, only typed errors leave the driver."""
from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import ConfigurationError, MagError, ProtocolError, ReadbackMismatch
from magstack.drivers.fvm400 import (
    FVM400,
    MAX_FIELD_CHARS,
    ProtocolAssumptionWarning,
    RecordError,
    parse_record,
)
from magstack.sim.fvm400_model import FVM400Model, register_instrument, unregister_instrument
from magstack.sim.truth_source import StaticTruth


def _open(model, name, clock, **kw):
    register_instrument(name, model)
    try:
        return FVM400.open(f"fvm400sim://{name}", clock, **kw)
    finally:
        unregister_instrument(name)


def test_gm_answering_1_in_absolute_mode_is_accepted_with_a_warning():
    """The public C++ driver's header implies GM = 1 means absolute; with the project's assumption
    (0) FVM400.open() could never succeed on such an instrument."""
    clock = VirtualClock()
    model = FVM400Model(StaticTruth((20.0, -5.0, 40.0)), clock, absolute_mode_digit=1)
    register_instrument("t_gm1", model)
    try:
        with pytest.warns(ProtocolAssumptionWarning, match="GM answers 1"):
            drv = FVM400.open("fvm400sim://t_gm1", clock, verify_every=3)
        assert drv.absolute_mode_digit == 1 and any("GM answers 1" in n for n in drv.notes)
        for _ in range(4):
            assert drv.read().b_uT == (20.0, -5.0, 40.0)
        model.mode = 1          # the front panel switched to relative: GM now answers 0
        with pytest.raises(ReadbackMismatch, match="get_mode = 0, expected 1"):
            for _ in range(4):
                drv.read()
    finally:
        unregister_instrument("t_gm1")


def test_gm_answering_0_opens_without_a_warning(recwarn):
    clock = VirtualClock()
    drv = _open(FVM400Model(StaticTruth(), clock), "t_gm0", clock)
    assert drv.absolute_mode_digit == 0 and drv.notes == []
    assert not [w for w in recwarn if issubclass(w.category, ProtocolAssumptionWarning)]


def test_set_replies_without_eot_open_in_bounded_time():
    """If the instrument sends no EOT after 'A' (unverified either way), the driver does not wait
    out the 2 s port timeout on every set/get command and fail with ProtocolError."""
    clock = VirtualClock()
    model = FVM400Model(StaticTruth((20.0, -5.0, 40.0)), clock, eot_after_reply=False)
    t0 = clock.monotonic_s()
    with pytest.warns(ProtocolAssumptionWarning, match="no EOT"):
        drv = _open(model, "t_noeot", clock)
    assert drv.set_replies_end_with_eot is False
    # 5 commands (SX0, SM0, GM, GX, GM), each at most eot_wait_s (0.1 s) for the absent EOT
    assert clock.monotonic_s() - t0 < 5 * 0.1 + 0.1
    register_instrument("t_noeot", model)
    try:
        assert drv.read().b_uT == (20.0, -5.0, 40.0)
        assert drv.command("get_representation") == 0
    finally:
        unregister_instrument("t_noeot")


def test_port_without_a_read_timeout_is_refused():
    class Port:
        timeout = None

    with pytest.raises(ConfigurationError, match="finite read timeout"):
        FVM400(Port(), VirtualClock(), configure=False)


def test_a_huge_integer_field_is_a_counted_skip_not_a_plain_value_error():
    """A record with a >4,300-digit integer made int() raise ValueError ('Exceeds the limit')."""
    with pytest.raises(RecordError) as ei:
        parse_record(" 1," + "9" * 5000 + ",3")
    assert ei.value.reason == "garbled" and isinstance(ei.value, ProtocolError)
    with pytest.raises(RecordError, match="garbled"):
        parse_record(" 1,2," + "7" * (MAX_FIELD_CHARS + 1))
    assert parse_record(" 1,2," + "0" * (MAX_FIELD_CHARS - 1) + "7") == (1, 2, 7)

    port = ScriptedPort([b"A\x04 1," + b"9" * 5000 + b",3\rD\x04", b"A\x04 1,2,3\rD\x04"])
    drv = FVM400(port, VirtualClock(), configure=False)
    assert drv.read().b_uT == (0.001, 0.002, 0.003)
    assert drv.skipped == {"garbled": 1}


class ScriptedPort:
    """A pyserial-like port: each write loads the next scripted reply; reads return what is there
    (fewer bytes than asked = a timeout, as pyserial does)."""

    def __init__(self, replies, timeout=2.0):
        self.replies = list(replies)
        self.timeout = timeout
        self.buf = bytearray()
        self.port = "scripted"

    def write(self, data):
        if self.replies:
            self.buf += self.replies.pop(0)
        return len(data)

    def flush(self):
        pass

    def reset_input_buffer(self):
        self.buf.clear()

    def read(self, n=1):
        out = bytes(self.buf[:n])
        del self.buf[:n]
        return out

    def read_until(self, expected=b"\n", size=None):
        out = bytearray()
        while self.buf and (size is None or len(out) < size):
            out.append(self.buf.pop(0))
            if out.endswith(expected):
                break
        return bytes(out)

    def close(self):
        pass


REPLY = st.one_of(
    st.binary(max_size=200),
    st.builds(lambda a, b, c, tail: b"A\x04" + b",".join([a, b, c]) + tail,
              *[st.from_regex(rb"\A[ +-]?[0-9]{0,5000}(\.[0-9]{0,3})?\Z", fullmatch=True)] * 3,
              st.sampled_from([b"\rD\x04", b"\r", b"", b"D\x04", b"\x04"])),
    st.sampled_from([b"A", b"A\x04", b"N\x04", b"A0", b"A1\x04", b"A9\x04", b"Ax\x04", b"\x04"]),
)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::magstack.drivers.fvm400.ProtocolAssumptionWarning")
@settings(max_examples=300, deadline=None)
@given(replies=st.lists(REPLY, min_size=1, max_size=8), configure=st.booleans())
def test_fuzz_reply_parser_only_typed_errors(replies, configure):
    """Whatever bytes the instrument sends, the driver returns a finite sample or raises a MagError."""
    port = ScriptedPort(replies)
    clock = VirtualClock()
    try:
        drv = FVM400(port, clock, configure=configure, max_attempts=3)
        for _ in range(3):
            s = drv.read()
            assert all(math.isfinite(v) for v in s.b_uT)
    except MagError:
        pass


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=300), st.from_regex(r"\A[ ,0-9+\-.eE]{0,6000}\Z", fullmatch=True)))
def test_fuzz_parse_record_only_record_errors(text):
    try:
        vals = parse_record(text)
    except RecordError:
        return
    assert len(vals) == 3 and all(isinstance(v, int) for v in vals)
