"""The flight dictionary (data/dictionary.py) is the one definition the flight code and ground tools use."""
from __future__ import annotations

import numpy as np

from magstack.data import dictionary as d
from magstack.firmware.flight import commands
from magstack.firmware.flight.channel import BAD, TlmFlag
from magstack.firmware.flight.events import SEVERITY, EventId
from magstack.firmware.float_applier import ApplyFlag
from magstack.ground import mageval_import
from magstack.ground.apply_session import FLAG_SHIFT


def test_flag_bits_are_distinct_powers_of_two_with_one_owner_each():
    values = [b.value for b in d.FLAG_BITS]
    assert all(v > 0 and v & (v - 1) == 0 for v in values)
    assert len(set(values)) == len(values) and len({b.name for b in d.FLAG_BITS}) == len(values)
    assert {b.owner for b in d.FLAG_BITS} == {d.FLIGHT, d.APPLY, d.IMPORT, d.MERGE}


def test_the_three_flag_schemes_no_longer_collide():
    flight = sum(TlmFlag)
    apply_bits = sum(int(f) << FLAG_SHIFT for f in ApplyFlag if f)
    imported = mageval_import.FLAG_NO_REF | mageval_import.FLAG_NO_DUT
    assert flight & apply_bits == 0 and flight & imported == 0 and apply_bits & imported == 0
    # REPEATED (informational) is not MISSING_INPUT after the shift any more (it was: 256 == 1 << 8)
    assert int(TlmFlag.REPEATED) != int(ApplyFlag.MISSING_INPUT) << FLAG_SHIFT
    assert int(ApplyFlag.MISSING_INPUT) << FLAG_SHIFT == d.FLAG["APPLY_MISSING_INPUT"].value
    assert int(ApplyFlag.OUT_OF_VALIDITY) << FLAG_SHIFT == d.FLAG["APPLY_OUT_OF_VALIDITY"].value
    assert int(ApplyFlag.SATURATED) << FLAG_SHIFT == d.FLAG["APPLY_SATURATED"].value


def test_tlmflag_and_bad_come_from_the_dictionary():
    assert {f.name: int(f) for f in TlmFlag} == d.flags_of(d.FLIGHT)
    assert int(BAD) == sum(b.value for b in d.FLAG_BITS if b.owner == d.FLIGHT and b.disqualifies)
    flags = np.array([0, int(TlmFlag.REPEATED | TlmFlag.UNCALIBRATED), int(TlmFlag.STALE), d.FLAG["NO_REF"].value])
    assert d.usable(flags).tolist() == [True, True, False, False]


def test_events_and_commands_come_from_the_dictionary():
    assert {e.name: int(e) for e in EventId} == {e.name: e.id for e in d.EVENTS}
    assert all(SEVERITY[EventId(e.id)] == e.severity for e in d.EVENTS)
    assert EventId.CHAN_STALE == 0x0202 and EventId.TLM_WRITE_ERROR == 0x0601   # released ids keep their value
    assert commands.COMMANDS == {c.name: {a.name for a in c.args} for c in d.COMMANDS}
    assert len({c.opcode for c in d.COMMANDS}) == len(d.COMMANDS)


def test_packet_fields_fit_their_encodings():
    for p in d.TM_PACKETS:
        assert sum(f.bits for f in p.fields if f.kind != "string") % 8 == 0, p.name
        for f in p.fields:
            assert f.kind in ("int", "uint", "string") and f.bits in (8, 16, 32)
    assert d.CUC.p_field == 0b0_010_11_10
