"""The TM encoder's packets are the bytes spacepackets' PusTm gives for the same fields (every service, APID,
sequence count and payload)."""
from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st
from spacepackets.ecss.tm import PusTm

from magstack.data.dictionary import TM_PACKETS
from magstack.data.packets import SEQ_MODULO, TmEncoder, cuc_bytes, encode_fields


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(TM_PACKETS), st.integers(0, 0x7FF), st.integers(0, SEQ_MODULO + 5),
       st.floats(0, 4e9), st.integers(1, 4), st.data())
def test_pack_equals_spacepackets(packet, apid, n, t_s, sub, data):
    values = {}
    for f in packet.fields:
        if f.kind == "string":
            values[f.name] = data.draw(st.text(max_size=40))
        else:
            values[f.name] = data.draw(st.one_of(st.none(), st.floats(-1e12, 1e12), st.integers(-2**40, 2**40)))
    subtype = sub if packet.service == 5 else None
    enc = TmEncoder({apid: n % SEQ_MODULO})
    got = enc.pack(packet, apid, t_s, values, subtype)
    want = bytes(PusTm(service=packet.service, message_subtype=packet.subtype if subtype is None else subtype,
                       timestamp=cuc_bytes(t_s), source_data=encode_fields(packet.fields, values), apid=apid,
                       seq_count=n % SEQ_MODULO, message_counter=n % SEQ_MODULO).pack())
    assert got == want
    assert enc.seq[apid] == (n % SEQ_MODULO + 1) % SEQ_MODULO
