"""The XTCE document commands the application: it is valid against the OMG XTCE 1.2 schema (tests/data/xtce/), it has
a MetaCommand for every telecommand of the flight dictionary, and packets encoded from the XTCE alone (a small
encoder below that reads only the MetaCommand definitions: no magstack encoder) are the bytes `tm command` builds
and are accepted by the UDP receiver of a running `magstack run`."""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from magstack.cli.main import main
from magstack.data.dictionary import COMMANDS
from tests.test_ccsds_packets import sim_config

xmlschema = pytest.importorskip("xmlschema")

NS = {"x": "http://www.omg.org/spec/XTCE/20180204"}
X = "{http://www.omg.org/spec/XTCE/20180204}"
XSD = Path(__file__).parent / "data" / "xtce" / "SpaceSystem.xsd"
#: Argument values the test commands with (acceptance checks the packet, not whether the command can succeed).
VALUES = {"channel": "hmc1053", "path": "tables/none.json", "group": "slow", "files": "telemetry/*.csv",
          "source_id": "1", "seq": "9000"}


def _document(tmp_path, capsys) -> tuple[Path, str]:
    cfg = sim_config(tmp_path)
    assert main(["tm", "xtce", "--config", str(cfg)]) == 0
    doc = capsys.readouterr().out
    (tmp_path / "magstack.xtce.xml").write_text(doc)
    return cfg, doc


# --------------------------------------------------------------------------- an encoder reading only the XTCE
class XtceCommands:
    def __init__(self, text: str) -> None:
        root = ET.fromstring(text)
        cm = root.find("x:CommandMetaData", NS)
        self.types = {t.get("name"): t for t in cm.find("x:ArgumentTypeSet", NS)}
        self.metas = {m.get("name"): m for m in cm.find("x:MetaCommandSet", NS)}
        self.containers = {m.find("x:CommandContainer", NS).get("name"): m.find("x:CommandContainer", NS)
                           for m in self.metas.values()}

    def chain(self, name: str) -> list[ET.Element]:
        """The MetaCommand and its bases, base first."""
        out, m = [], self.metas[name]
        while m is not None:
            out.insert(0, m)
            b = m.find("x:BaseMetaCommand", NS)
            m = self.metas[b.get("metaCommandRef")] if b is not None else None
        return out

    def entries(self, container: ET.Element) -> list[ET.Element]:
        base = container.find("x:BaseContainer", NS)
        head = self.entries(self.containers[base.get("containerRef")]) if base is not None else []
        return head + list(container.find("x:EntryList", NS))

    def arguments(self, name: str) -> tuple[dict[str, ET.Element], dict[str, int], dict[str, str]]:
        """(argument name -> its type, assigned values, argument name -> ancillary 'derived')."""
        types, assigned, derived = {}, {}, {}
        for m in self.chain(name):
            for a in m.iterfind("x:ArgumentList/x:Argument", NS):
                types[a.get("name")] = self.types[a.get("argumentTypeRef")]
                for anc in a.iterfind("x:AncillaryDataSet/x:AncillaryData", NS):
                    if anc.get("name") == "derived":
                        derived[a.get("name")] = anc.text
            for s in m.iterfind("x:BaseMetaCommand/x:ArgumentAssignmentList/x:ArgumentAssignment", NS):
                assigned[s.get("argumentName")] = int(s.get("argumentValue"), 0)
        return types, assigned, derived

    def encode(self, name: str, given: dict[str, object]) -> bytes:
        meta = self.metas[name]
        assert meta.get("abstract") != "true", name
        types, assigned, derived = self.arguments(name)
        values = {**assigned, **given}
        for arg, t in types.items():               # string lengths: the argument a string's size refers to
            ref = t.find("x:StringDataEncoding/x:Variable/x:DynamicValue", NS)
            if ref is not None:
                slope = int(ref.find("x:LinearAdjustment", NS).get("slope"))
                values[ref.find("x:ArgumentInstanceRef", NS).get("argumentRef")] = \
                    len(str(values[arg]).encode("utf-8")) * 8 // slope
        for arg in derived:
            values.setdefault(arg, 0)
        bits = self._bits(name, types, values)
        if "packet_length_minus_7" in derived.values():
            n = len(bits) // 8
            values[next(a for a, d in derived.items() if d == "packet_length_minus_7")] = n - 7
            bits = self._bits(name, types, values)
        assert len(bits) % 8 == 0
        return int(bits, 2).to_bytes(len(bits) // 8, "big")

    def _bits(self, name: str, types, values) -> str:
        out = ""
        for e in self.entries(self.metas[name].find("x:CommandContainer", NS)):
            if e.tag == X + "FixedValueEntry":
                n = int(e.get("sizeInBits"))
                out += format(int(e.get("binaryValue"), 16) & ((1 << n) - 1), f"0{n}b")
                continue
            arg = e.get("argumentRef")
            t = types[arg]
            if t.tag == X + "StringArgumentType":
                out += "".join(format(b, "08b") for b in str(values[arg]).encode("utf-8"))
                continue
            enc = t.find("x:IntegerDataEncoding", NS)
            n = int(enc.get("sizeInBits"))
            crc = enc.find("x:ErrorDetectCorrect/x:CRC", NS)
            if crc is not None:
                v = _crc(out, int(crc.get("width")), int(crc.find("x:Polynomial", NS).text, 16),
                         int(crc.find("x:InitRemainder", NS).text, 16), int(crc.find("x:FinalXOR", NS).text, 16))
            else:
                v = int(values[arg])
            r = t.find("x:ValidRangeSet/x:ValidRange", NS)
            if r is not None:
                assert int(r.get("minInclusive")) <= v <= int(r.get("maxInclusive")), (name, arg, v)
            out += format(v, f"0{n}b")
        return out


def _crc(bits: str, width: int, poly: int, init: int, xorout: int) -> int:
    """Plain bitwise CRC (MSB first, no reflection) over a bit string."""
    reg, top, mask = init, 1 << (width - 1), (1 << width) - 1
    for b in bits:
        reg ^= int(b) << (width - 1)
        reg = ((reg << 1) ^ poly) & mask if reg & top else (reg << 1) & mask
    return reg ^ xorout


# --------------------------------------------------------------------------- tests
def test_the_document_is_valid_against_the_omg_xtce_1_2_schema(tmp_path, capsys):
    _, doc = _document(tmp_path, capsys)
    schema = xmlschema.XMLSchema(str(XSD), allow="local")     # offline: no remote location is fetched
    errors = [str(e)[:300] for e in schema.iter_errors(ET.fromstring(doc))]
    assert errors == []
    broken = doc.replace("<xtce:MetaCommandSet>", "<xtce:MetaCommandSet><xtce:Bogus/>", 1)
    assert not schema.is_valid(ET.fromstring(broken))               # the check can fail


def test_every_dictionary_command_is_a_metacommand_with_its_arguments_and_ranges(tmp_path, capsys):
    _, doc = _document(tmp_path, capsys)
    x = XtceCommands(doc)
    for cmd in COMMANDS:
        types, assigned, _ = x.arguments(cmd.name)
        assert assigned["FUNCTION_ID"] == cmd.opcode and assigned["PUS_SERVICE"] == 8 and assigned["PUS_SUBTYPE"] == 1
        own = [a.get("name") for a in x.metas[cmd.name].iterfind("x:ArgumentList/x:Argument", NS)]
        assert own == [n for a in cmd.args for n in (f"{a.name}_len", a.name)]
        for a in cmd.args:
            r = types[f"{a.name}_len"].find("x:ValidRangeSet/x:ValidRange", NS)
            assert (int(r.get("minInclusive")), int(r.get("maxInclusive"))) == (1, a.max_len)
    assert x.arguments("PING")[1] == {"PUS_SERVICE": 17, "PUS_SUBTYPE": 1}


def test_commands_encoded_from_the_xtce_are_the_bytes_tm_command_builds(tmp_path, capsys):
    cfg, doc = _document(tmp_path, capsys)
    x = XtceCommands(doc)
    for seq, cmd in enumerate([None, *COMMANDS], start=100):
        name = "PING" if cmd is None else cmd.name
        args = {} if cmd is None else {a.name: VALUES[a.name] for a in cmd.args}
        ours = x.encode(name, {"CCSDS_SEQ_COUNT": seq, "PUS_SOURCE_ID": 1, **args})
        out = tmp_path / f"{name}.tc"
        argv = ["tm", "command", "ping" if cmd is None else cmd.name, *(f"{k}={v}" for k, v in args.items()),
                "--config", str(cfg), "--seq", str(seq), "--out", str(out), "-q"]
        assert main(argv) == 0
        assert ours == out.read_bytes(), name
    with pytest.raises(AssertionError):                 # out of its valid range: refused by the encoder
        x.encode("activate_table", {"CCSDS_SEQ_COUNT": 1, "PUS_SOURCE_ID": 1, "channel": "c" * 65})


@pytest.mark.slow
def test_the_receiver_of_a_running_magstack_run_accepts_every_command_encoded_from_the_xtce(tmp_path, capsys):
    cfg, doc = _document(tmp_path, capsys)
    x = XtceCommands(doc)
    port = int(re.search(r'tc_udp = "127\.0\.0\.1:(\d+)"', cfg.read_text()).group(1))
    packets = [x.encode("PING" if c is None else c.name,
                        {"CCSDS_SEQ_COUNT": seq, "PUS_SOURCE_ID": 1,
                         **({} if c is None else {a.name: VALUES[a.name] for a in c.args})})
               for seq, c in enumerate([None, *COMMANDS], start=1)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "magstack", "run", "--config", str(cfg), "--sim", "--out",
                             str(tmp_path / "tlm")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        t_end = time.monotonic() + 30
        while not (tmp_path / "tlm" / "packets-0001.bin").exists() and time.monotonic() < t_end:
            time.sleep(0.1)
        time.sleep(0.5)                              # the receiver is bound once the application is built
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for p in packets:
                s.sendto(p, ("127.0.0.1", port))
        time.sleep(2.0)                              # polled at the command group's 2 Hz boundaries
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert proc.returncode == 143
    assert main(["tm", "decode", str(tmp_path / "tlm" / "packets-0001.bin"), "--out", str(tmp_path / "dec"),
                 "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["by_packet"]["accept_ok"] == len(packets) and "accept_fail" not in rep["by_packet"]
    assert rep["by_packet"]["ping_reply"] == 1
