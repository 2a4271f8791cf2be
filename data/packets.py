"""CCSDS Space Packets (133.0-B) with ECSS PUS-C headers, laid out by the flight dictionary.

The headers, the packet error control (CRC-16/CCITT-FALSE) and the request ids come from
``spacepackets`` (:class:`~spacepackets.ecss.tm.PusTm`, :class:`~spacepackets.ecss.tc.PusTc`); this
module only turns dictionary fields into payload bytes and back, encodes the CUC timestamp (spacepackets
0.32 has CDS but no CUC: the CUC T-field is two big-endian unsigned integers) and assigns APIDs.

Integer fields are big-endian; a value is sent as ``round(value / lsb)`` clipped to the field's range
(the ``absent`` raw value excluded), ``None`` or NaN as ``absent``. Strings carry a one-octet byte count.
"""
from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from fastcrc import crc16
from spacepackets.ecss.tc import PusTc, generate_crc
from spacepackets.ecss.tm import PusTm

from magstack.data.dictionary import (
    APP_APID,
    CHANNEL_APID0,
    CUC,
    GROUP_APID0,
    MAX_CHANNELS,
    MAX_GROUPS,
    TM_PACKET,
    FieldDef,
    PacketDef,
)

SEQ_MODULO = 1 << 14
#: Primary header (packet id, sequence control, length) + PUS-C TM data field header up to the time field.
_TM_HEADER = struct.Struct(">HHHBBBHH")
_CRC = struct.Struct(">H")
_PUS_C = 2
PRIMARY_HEADER_BYTES = 6
TM_SECONDARY_BYTES = 7 + CUC.size        # PUS-C TM data field header with the CUC timestamp
TC_SECONDARY_BYTES = 5
CRC_BYTES = 2
MAX_PACKET_BYTES = 1024                  # the longest packet we send (events: 2 strings of <= 255 bytes)
_FINE = 1 << (8 * CUC.fine_octets)


class PacketError(ValueError):
    """A packet that cannot be decoded (counted by the caller, never raised out of a stream reader).

    ``kind``: "length" (length field vs bytes), "crc" (packet error control), "unknown" (APID/service not
    in the dictionary) or "malformed" (anything else)."""

    def __init__(self, message: str, kind: str = "malformed") -> None:
        super().__init__(message)
        self.kind = kind


# ------------------------------------------------------------------------------------------- time
def cuc_bytes(t_s: float) -> bytes:
    """CUC T-field of ``t_s`` (seconds since ``CUC.epoch``), fine part rounded to 2**-16 s."""
    ticks = round(max(0.0, float(t_s)) * _FINE) if math.isfinite(t_s) else 0
    coarse, fine = divmod(min(ticks, (1 << (8 * CUC.size)) - 1), _FINE)
    return coarse.to_bytes(CUC.coarse_octets, "big") + fine.to_bytes(CUC.fine_octets, "big")


def cuc_seconds(raw: bytes) -> float:
    coarse = int.from_bytes(raw[:CUC.coarse_octets], "big")
    return coarse + int.from_bytes(raw[CUC.coarse_octets:CUC.size], "big") / _FINE


# ------------------------------------------------------------------------------------------- fields
def _range(f: FieldDef) -> tuple[int, int]:
    lo, hi = (-(1 << (f.bits - 1)), (1 << (f.bits - 1)) - 1) if f.kind == "int" else (0, (1 << f.bits) - 1)
    if f.absent == lo:
        lo += 1
    elif f.absent == hi:
        hi -= 1
    return lo, hi


def to_raw(f: FieldDef, value) -> int:
    """Raw integer of an engineering value (``None``/NaN -> ``absent``, else rounded and clipped)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return 0 if f.absent is None else f.absent
    lo, hi = _range(f)
    raw = int(value) if f.lsb == 1.0 and isinstance(value, int) else round(float(value) / f.lsb)
    return min(hi, max(lo, raw))


def from_raw(f: FieldDef, raw: int) -> float:
    """Engineering value of a raw integer (``absent`` -> NaN)."""
    return math.nan if f.absent is not None and raw == f.absent else raw * f.lsb


def encode_fields(fields: Sequence[FieldDef], values: Mapping[str, object]) -> bytes:
    out = bytearray()
    for f in fields:
        v = values.get(f.name)
        if f.kind == "string":
            b = str(v or "").encode("utf-8")[:255]
            out.append(len(b))
            out += b
        else:
            out += to_raw(f, v).to_bytes(f.bits // 8, "big", signed=f.kind == "int")
    return bytes(out)


def decode_fields(fields: Sequence[FieldDef], data: bytes) -> dict[str, int | str]:
    """Raw field values; PacketError if ``data`` is not exactly the fields' length."""
    vals: dict[str, int | str] = {}
    i = 0
    for f in fields:
        if f.kind == "string":
            if i >= len(data):
                raise PacketError(f"payload ends before string {f.name!r}")
            n = data[i]
            if i + 1 + n > len(data):
                raise PacketError(f"string {f.name!r} of {n} bytes runs past the payload")
            vals[f.name] = data[i + 1:i + 1 + n].decode("utf-8", errors="replace")
            i += 1 + n
        else:
            n = f.bits // 8
            if i + n > len(data):
                raise PacketError(f"payload ends before field {f.name!r}")
            vals[f.name] = int.from_bytes(data[i:i + n], "big", signed=f.kind == "int")
            i += n
    if i != len(data):
        raise PacketError(f"payload has {len(data) - i} byte(s) after the last field")
    return vals


# ------------------------------------------------------------------------------------------- APIDs
@dataclass(frozen=True)
class ApidMap:
    """APIDs of one configuration: channel i -> CHANNEL_APID0 + i, group j -> GROUP_APID0 + j."""

    channels: tuple[str, ...]
    groups: tuple[str, ...]
    telecommands: bool = True          # the application takes telecommands (sends 1,x and 17,2 reports)

    def __post_init__(self) -> None:
        if len(self.channels) > MAX_CHANNELS or len(self.groups) > MAX_GROUPS:
            raise ValueError(f"at most {MAX_CHANNELS} channels and {MAX_GROUPS} rate groups have APIDs")

    def channel(self, name: str) -> int:
        return CHANNEL_APID0 + self.channels.index(name)

    def group(self, name: str) -> int:
        return GROUP_APID0 + self.groups.index(name)

    def packets(self) -> list[tuple[int, PacketDef, str]]:
        """Every (APID, packet, name) this configuration produces, in document order."""
        out = [(self.channel(c), TM_PACKET["channel"], c) for c in self.channels]
        out += [(self.group(g), TM_PACKET["group_hk"], g) for g in self.groups]
        out += [(APP_APID, p, "app") for p in TM_PACKET.values()
                if p.apid == "app" and (self.telecommands or p.service not in (1, 17))]
        return out


def kind_of_apid(apid: int) -> str | None:
    """"app", "channel", "group" or None (not one of ours)."""
    if apid == APP_APID:
        return "app"
    if CHANNEL_APID0 <= apid < CHANNEL_APID0 + MAX_CHANNELS:
        return "channel"
    if GROUP_APID0 <= apid < GROUP_APID0 + MAX_GROUPS:
        return "group"
    return None


def tm_packet_def(apid: int, service: int, subtype: int) -> PacketDef | None:
    """The dictionary packet a (APID, service, subtype) carries, or None."""
    kind = kind_of_apid(apid)
    for p in TM_PACKET.values():
        if p.apid == kind and p.service == service and (p.subtype == subtype or (p.service == 5 and 1 <= subtype <= 4)):
            return p
    return None


# ------------------------------------------------------------------------------------------- TM
@dataclass
class TmEncoder:
    """Packs TM packets; one 14-bit sequence count per APID (CCSDS) and a PUS message counter."""

    seq: dict[int, int] = field(default_factory=dict)

    def pack(self, packet: PacketDef, apid: int, t_s: float, values: Mapping[str, object],
             subtype: int | None = None) -> bytes:
        """The packet's bytes: those ``spacepackets.ecss.tm.PusTm(...).pack()`` gives for the same fields (a PUS-C
        TM, destination id 0, time reference status 0; ``tests/test_ccsds_packets.py`` compares the two), laid
        out here with ``struct`` because it runs for every telemetry record."""
        n = self.seq.get(apid, 0)
        self.seq[apid] = (n + 1) % SEQ_MODULO
        body = encode_fields(packet.fields, values)
        total = PRIMARY_HEADER_BYTES + TM_SECONDARY_BYTES + len(body) + CRC_BYTES
        head = _TM_HEADER.pack(0x0800 | apid, 0xC000 | n, total - 7, _PUS_C << 4, packet.service,
                               packet.subtype if subtype is None else subtype, n, 0) + cuc_bytes(t_s) + body
        return head + _CRC.pack(crc16.ibm_3740(head))


@dataclass(frozen=True)
class TmPacket:
    apid: int
    seq_count: int
    service: int
    subtype: int
    t_s: float
    packet: PacketDef
    raw: dict[str, int | str]


def pec_ok(packet: bytes) -> bool:
    """The PUS packet error control (CRC-16/CCITT-FALSE over all but the last 2 bytes) is right."""
    return len(packet) > CRC_BYTES and generate_crc(bytearray(packet[:-CRC_BYTES]))[-CRC_BYTES:] == packet[-CRC_BYTES:]


def tm_header(data: bytes, at: int = 0) -> tuple[int, int, int] | None:
    """(APID, sequence count, total length) if ``data[at:]`` starts with a plausible TM header of ours."""
    if len(data) - at < 6:
        return None
    w0, w1, n = struct.unpack_from(">HHH", data, at)
    if w0 >> 11 != 0b00001 or kind_of_apid(w0 & 0x7FF) is None:
        return None
    total = n + 7
    if not PRIMARY_HEADER_BYTES + TM_SECONDARY_BYTES + CRC_BYTES <= total <= MAX_PACKET_BYTES:
        return None
    return w0 & 0x7FF, w1 & 0x3FFF, total


def decode_tm(data: bytes) -> TmPacket:
    """One whole TM packet -> TmPacket; PacketError names what is wrong (length, CRC, type, layout)."""
    if len(data) < PRIMARY_HEADER_BYTES + TM_SECONDARY_BYTES + CRC_BYTES:
        raise PacketError(f"{len(data)} bytes: shorter than a PUS TM packet")
    hdr = struct.unpack(">HHH", data[:6])
    if hdr[0] >> 13 != 0 or (hdr[0] >> 12) & 1 != 0 or not (hdr[0] >> 11) & 1:
        raise PacketError("not a CCSDS version-1 TM packet with a secondary header")
    if hdr[2] + 7 != len(data):
        raise PacketError(f"length field says {hdr[2] + 7} bytes, packet has {len(data)}", "length")
    if not pec_ok(data):      # first: a corrupt header must count as a CRC error, not as malformed
        raise PacketError("packet error control (CRC-16) wrong", "crc")
    try:
        tm = PusTm.unpack(data, timestamp_len=CUC.size)
    except Exception as exc:  # noqa: BLE001 - spacepackets raises ValueError subclasses and its CRC error
        raise PacketError(f"{type(exc).__name__}: {exc}"[:160]) from None
    sh = tm.pus_tm_sec_header
    p = tm_packet_def(tm.apid, sh.service, sh.message_subtype)
    if p is None:
        raise PacketError(f"APID 0x{tm.apid:03x} service {sh.service},{sh.message_subtype} is not in the dictionary",
                          "unknown")
    return TmPacket(tm.apid, tm.seq_count, sh.service, sh.message_subtype, cuc_seconds(sh.timestamp), p,
                    decode_fields(p.fields, bytes(tm.source_data)))


# ------------------------------------------------------------------------------------------- TC
def encode_command_args(args: Sequence[str]) -> bytes:
    out = bytearray()
    for a in args:
        b = a.encode("utf-8")
        if not 0 < len(b) <= 255:
            raise ValueError(f"argument {a!r}: 1..255 UTF-8 bytes")
        out.append(len(b))
        out += b
    return bytes(out)


def pack_tc(service: int, subtype: int, app_data: bytes = b"", *, apid: int = APP_APID, seq_count: int = 0,
            source_id: int = 0) -> bytes:
    return bytes(PusTc(service=service, message_subtype=subtype, apid=apid, app_data=app_data,
                       seq_count=seq_count % SEQ_MODULO, source_id=source_id).pack())
