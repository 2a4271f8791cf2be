"""The OMG XTCE 1.2 document of the TM packets one configuration produces, generated from the dictionary.

Containers: ``CCSDSPacket`` (abstract: the 133.0-B primary header) -> ``PUSTM`` (abstract: the PUS-C
TM data field header with the CUC timestamp, as ``CUC_COARSE`` + ``CUC_FINE``) -> one concrete
container per (APID, packet) restricted on APID, service and subtype, whose entries are the payload
fields and the packet error control ``PUS_PEC``. Scaled integers are FloatParameterTypes with an
IntegerDataEncoding and a polynomial calibrator (``value = raw * lsb``); a dictionary string field is
a length parameter ``<name>_len`` (octets) and a string sized by it.

Commanding (``CommandMetaData``, when the configuration takes telecommands): the abstract MetaCommand ``PUS_TC``
is the Space Packet primary header of a telecommand to ``APP_APID`` (fixed values: version 0, type 1, secondary
header, the APID, unsegmented) and the PUS-C TC data field header (PUS version 2, acknowledgement flags 0xF,
service, subtype, source id); ``PUS_PEC`` is its packet error control, a 16-bit argument whose encoding carries
the CRC (CRC-16/CCITT-FALSE from the packet's first bit); ``CCSDS_LENGTH`` is the packet length less 7 octets
(ancillary data ``derived = packet_length_minus_7``: the encoder fills it in). ``PING`` is 17,1; the abstract
``PUS_TC_8_1`` adds ``FUNCTION_ID``; every command of the flight dictionary is a MetaCommand derived from it with its
function id assigned and, per argument, ``<arg>_len`` (uint8, valid 1..max octets) and ``<arg>`` (UTF-8 of that
many octets), in dictionary order, then ``PUS_PEC``.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

from magstack.data.dictionary import APP_APID, COMMANDS, CUC, TC_FUNCTION, TC_PING, FieldDef
from magstack.data.packets import SEQ_MODULO, ApidMap

NS = "http://www.omg.org/spec/XTCE/20180204"
_HEADER = (("CCSDS_VERSION", 3), ("CCSDS_TYPE", 1), ("CCSDS_SEC_HDR", 1), ("CCSDS_APID", 11),
           ("CCSDS_SEQ_FLAGS", 2), ("CCSDS_SEQ_COUNT", 14), ("CCSDS_LENGTH", 16))
_PUS = (("PUS_VERSION", 4), ("PUS_TIME_REF", 4), ("PUS_SERVICE", 8), ("PUS_SUBTYPE", 8), ("PUS_MSG_COUNTER", 16),
        ("PUS_DEST_ID", 16), ("CUC_COARSE", 8 * CUC.coarse_octets), ("CUC_FINE", 8 * CUC.fine_octets))


def _el(parent, tag: str, **attrib) -> ET.Element:
    return ET.SubElement(parent, f"{{{NS}}}{tag}", {k: str(v) for k, v in attrib.items()})


class _Doc:
    def __init__(self, name: str) -> None:
        ET.register_namespace("xtce", NS)
        self.root = ET.Element(f"{{{NS}}}SpaceSystem", {"name": name})
        tm = _el(self.root, "TelemetryMetaData")
        self.types = _el(tm, "ParameterTypeSet")
        self.params = _el(tm, "ParameterSet")
        self.containers = _el(tm, "ContainerSet")
        self._types: set[str] = set()

    def int_type(self, bits: int, signed: bool) -> str:
        name = f"{'I' if signed else 'U'}{bits}"
        if name not in self._types:
            self._types.add(name)
            t = _el(self.types, "IntegerParameterType", name=name, signed=str(signed).lower(), sizeInBits=bits)
            _el(t, "UnitSet")
            _el(t, "IntegerDataEncoding", sizeInBits=bits, encoding="twosComplement" if signed else "unsigned")
        return name

    def field_type(self, f: FieldDef) -> str:
        if f.kind == "string":
            return "STRING"
        if f.lsb == 1.0:
            return self.int_type(f.bits, f.kind == "int")
        lsb = f"{f.lsb:g}".replace(".", "p").replace("-", "m")      # XTCE names take no "."
        name = f"{'I' if f.kind == 'int' else 'U'}{f.bits}_x{lsb}_{f.unit or 'one'}"
        if name not in self._types:
            self._types.add(name)
            t = _el(self.types, "FloatParameterType", name=name, sizeInBits=64)
            units = _el(t, "UnitSet")
            if f.unit:
                _el(units, "Unit").text = f.unit
            enc = _el(t, "IntegerDataEncoding", sizeInBits=f.bits,
                      encoding="twosComplement" if f.kind == "int" else "unsigned")
            poly = _el(_el(enc, "DefaultCalibrator"), "PolynomialCalibrator")
            _el(poly, "Term", coefficient=repr(f.lsb), exponent=1)
        return name

    def param(self, name: str, type_ref: str, text: str = "") -> None:
        p = _el(self.params, "Parameter", name=name, parameterTypeRef=type_ref)
        if text:
            p.set("shortDescription", text[:120])

    def string_param(self, name: str, length_param: str, text: str) -> None:
        t = _el(self.types, "StringParameterType", name=f"{name}_T")
        _el(t, "UnitSet")
        enc = _el(t, "StringDataEncoding", encoding="UTF-8")
        var = _el(enc, "Variable", maxSizeInBits=255 * 8)
        dyn = _el(var, "DynamicValue")
        _el(dyn, "ParameterInstanceRef", parameterRef=length_param, useCalibratedValue="false")
        _el(dyn, "LinearAdjustment", slope=8, intercept=0)
        self.param(name, f"{name}_T", text)

    def container(self, name: str, entries: list[str], *, base: str | None = None,
                  restrict: dict[str, int] | None = None, abstract: bool = False) -> None:
        c = _el(self.containers, "SequenceContainer", name=name, **({"abstract": "true"} if abstract else {}))
        el = _el(c, "EntryList")
        for e in entries:
            _el(el, "ParameterRefEntry", parameterRef=e)
        if base is not None:
            b = _el(c, "BaseContainer", containerRef=base)
            if restrict:
                cl = _el(_el(b, "RestrictionCriteria"), "ComparisonList")
                for k, v in restrict.items():
                    _el(cl, "Comparison", parameterRef=k, value=v, useCalibratedValue="false")


_TC_FIXED = (("CCSDS_VERSION", 3, 0), ("CCSDS_TYPE", 1, 1), ("CCSDS_SEC_HDR", 1, 1), ("CCSDS_APID", 11, APP_APID),
             ("CCSDS_SEQ_FLAGS", 2, 0b11))
_TC_ARGS = (("CCSDS_SEQ_COUNT", 14, "sequence count: newer than the last accepted from this source (mod 2^14)"),
            ("CCSDS_LENGTH", 16, "packet length in octets minus 7"),
            ("PUS_SERVICE", 8, "PUS service type"), ("PUS_SUBTYPE", 8, "PUS message subtype"),
            ("PUS_SOURCE_ID", 16, "PUS source id: one of [ccsds] tc_source_ids"),
            ("PUS_PEC", 16, "packet error control: CRC-16/CCITT-FALSE over the packet before it"))


class _Commands:
    """The CommandMetaData part of a document."""

    def __init__(self, root: ET.Element) -> None:
        cm = _el(root, "CommandMetaData")
        self.types = _el(cm, "ArgumentTypeSet")
        self.set = _el(cm, "MetaCommandSet")
        self._types: set[str] = set()

    def int_type(self, bits: int, lo: int = 0, hi: int | None = None, crc: bool = False) -> str:
        hi = (1 << bits) - 1 if hi is None else hi
        name = f"TC_U{bits}" + ("" if (lo, hi) == (0, (1 << bits) - 1) else f"_{lo}_{hi}") + ("_CRC" if crc else "")
        if name not in self._types:
            self._types.add(name)
            t = _el(self.types, "IntegerArgumentType", name=name, signed="false", sizeInBits=bits)
            enc = _el(t, "IntegerDataEncoding", sizeInBits=bits, encoding="unsigned")
            if crc:
                c = _el(_el(enc, "ErrorDetectCorrect"), "CRC", width=16, bitsFromReference=0, reference="start")
                _el(c, "Polynomial").text = "1021"
                _el(c, "InitRemainder").text = "FFFF"
                _el(c, "FinalXOR").text = "0000"
            _el(_el(t, "ValidRangeSet"), "ValidRange", minInclusive=lo, maxInclusive=hi)
        return name

    def string_type(self, arg) -> str:
        name = f"TC_STR_{arg.name}_{arg.max_len}"
        if name not in self._types:
            self._types.add(name)
            t = _el(self.types, "StringArgumentType", name=name, shortDescription=arg.meaning[:120])
            enc = _el(t, "StringDataEncoding", encoding="UTF-8")
            var = _el(enc, "Variable", maxSizeInBits=8 * arg.max_len)
            dyn = _el(var, "DynamicValue")
            _el(dyn, "ArgumentInstanceRef", argumentRef=f"{arg.name}_len", useCalibratedValue="false")
            _el(dyn, "LinearAdjustment", slope=8, intercept=0)
        return name

    def meta(self, name: str, text: str, *, base: str | None = None, assign: dict[str, int] | None = None,
             args: list[tuple[str, str, str]] = (), entries: list[str] = (), container_base: str | None = None,
             fixed: tuple = (), abstract: bool = False) -> None:
        m = _el(self.set, "MetaCommand", name=name, shortDescription=text[:120],
                **({"abstract": "true"} if abstract else {}))
        if base is not None:
            b = _el(m, "BaseMetaCommand", metaCommandRef=base)
            if assign:
                al = _el(b, "ArgumentAssignmentList")
                for k, v in assign.items():
                    _el(al, "ArgumentAssignment", argumentName=k, argumentValue=v)
        if args:
            al = _el(m, "ArgumentList")
            for aname, tref, atext in args:
                a = _el(al, "Argument", name=aname, argumentTypeRef=tref, shortDescription=atext[:120])
                if aname == "CCSDS_LENGTH":
                    _el(_el(a, "AncillaryDataSet"), "AncillaryData", name="derived").text = "packet_length_minus_7"
        cc = _el(m, "CommandContainer", name=f"{name}_CC")
        el = _el(cc, "EntryList")
        for fname, bits, value in fixed:
            _el(el, "FixedValueEntry", name=fname, binaryValue=f"{value:0{2 * ((bits + 7) // 8)}X}", sizeInBits=bits)
        for e in entries:
            _el(el, "ArgumentRefEntry", argumentRef=e)
        if container_base is not None:
            _el(cc, "BaseContainer", containerRef=container_base)


def _command_metadata(root: ET.Element) -> None:
    c = _Commands(root)
    header_args = [(n, c.int_type(b, crc=n == "PUS_PEC") if n != "CCSDS_SEQ_COUNT" else
                    c.int_type(b, 0, SEQ_MODULO - 1), t) for n, b, t in _TC_ARGS]
    # primary header, then the PUS-C TC data field header (version 2, acknowledgement flags 0b1111)
    c.meta("PUS_TC", "ECSS PUS-C telecommand in a CCSDS Space Packet (133.0-B) to this application",
           args=header_args, abstract=True, fixed=_TC_FIXED,
           entries=["CCSDS_SEQ_COUNT", "CCSDS_LENGTH"])
    # the data field header: a second block of fixed values and arguments, appended by a derived abstract command
    c.meta("PUS_TC_HEADER", "PUS-C TC data field header", base="PUS_TC", abstract=True,
           fixed=(("PUS_VERSION", 4, 2), ("PUS_ACK_FLAGS", 4, 0xF)),
           entries=["PUS_SERVICE", "PUS_SUBTYPE", "PUS_SOURCE_ID"], container_base="PUS_TC_CC")
    c.meta("PING", "17,1 are-you-alive: answered with 17,2", base="PUS_TC_HEADER",
           assign={"PUS_SERVICE": TC_PING[0], "PUS_SUBTYPE": TC_PING[1]}, entries=["PUS_PEC"],
           container_base="PUS_TC_HEADER_CC")
    c.meta("PUS_TC_8_1", "8,1 perform function: function id, then the function's arguments", base="PUS_TC_HEADER",
           assign={"PUS_SERVICE": TC_FUNCTION[0], "PUS_SUBTYPE": TC_FUNCTION[1]}, abstract=True,
           args=[("FUNCTION_ID", c.int_type(16), "the command's function id (flight dictionary opcode)")],
           entries=["FUNCTION_ID"], container_base="PUS_TC_HEADER_CC")
    for cmd in COMMANDS:
        args, entries = [], []
        for a in cmd.args:
            args += [(f"{a.name}_len", c.int_type(8, 1, a.max_len), f"octets of {a.name} (1..{a.max_len})"),
                     (a.name, c.string_type(a), a.meaning)]
            entries += [f"{a.name}_len", a.name]
        c.meta(cmd.name, cmd.meaning, base="PUS_TC_8_1", assign={"FUNCTION_ID": cmd.opcode}, args=args,
               entries=[*entries, "PUS_PEC"], container_base="PUS_TC_8_1_CC")


def xtce_document(apids: ApidMap, name: str = "magstack") -> str:
    """The XTCE document (UTF-8 text) for every packet ``apids`` produces."""
    d = _Doc(name)
    for pname, bits in (*_HEADER, *_PUS):
        d.param(pname, d.int_type(bits, False))
    d.param("PUS_PEC", d.int_type(16, False), "packet error control, CRC-16/CCITT-FALSE")
    d.container("CCSDSPacket", [p for p, _ in _HEADER], abstract=True)
    d.container("PUSTM", [p for p, _ in _PUS], base="CCSDSPacket", restrict={"CCSDS_TYPE": 0, "CCSDS_SEC_HDR": 1},
                abstract=True)
    for apid, packet, label in apids.packets():
        prefix = f"{packet.name.upper()}" if apid == APP_APID else f"{packet.name.upper()}_{label}"
        entries = []
        for f in packet.fields:
            pname = f"{prefix}_{f.name}"
            if f.kind == "string":
                d.param(f"{pname}_len", d.int_type(f.bits, False), f"octets of {f.name}")
                d.string_param(pname, f"{pname}_len", f.meaning)
                entries += [f"{pname}_len", pname]
            else:
                d.param(pname, d.field_type(f), f.meaning)
                entries.append(pname)
        restrict = {"CCSDS_APID": apid, "PUS_SERVICE": packet.service}
        if packet.service != 5:               # events: subtype 1..4 carries the severity
            restrict["PUS_SUBTYPE"] = packet.subtype
        d.container(f"TM_{prefix}", [*entries, "PUS_PEC"], base="PUSTM", restrict=restrict)
    if apids.telecommands:
        _command_metadata(d.root)
    ET.indent(d.root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(d.root, encoding="unicode") + "\n"
