"""The OMG XTCE 1.2 document of the TM packets one configuration produces, generated from the dictionary.

Containers: ``CCSDSPacket`` (abstract: the 133.0-B primary header) -> ``PUSTM`` (abstract: the PUS-C
TM data field header with the CUC timestamp, as ``CUC_COARSE`` + ``CUC_FINE``) -> one concrete
container per (APID, packet) restricted on APID, service and subtype, whose entries are the payload
fields and the packet error control ``PUS_PEC``. Scaled integers are FloatParameterTypes with an
IntegerDataEncoding and a polynomial calibrator (``value = raw * lsb``); a dictionary string field is
a length parameter ``<name>_len`` (octets) and a string sized by it.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

from magstack.data.dictionary import APP_APID, CUC, FieldDef
from magstack.data.packets import ApidMap

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
    ET.indent(d.root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(d.root, encoding="unicode") + "\n"
