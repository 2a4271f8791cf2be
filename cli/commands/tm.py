"""``magstack tm xtce|decode|command``: the CCSDS side of the flight application (docs/ccsds.md)."""
from __future__ import annotations

import argparse
import os
import socket
import struct
import time
from pathlib import Path

from magstack.cli.options import int_range, nonempty_dir, nonempty_path
from magstack.cli.output import CommandResult
from magstack.data.dictionary import APP_APID, COMMAND, TC_FUNCTION, TC_PING
from magstack.data.dictionary_doc import BEGIN, END, dictionary_markdown
from magstack.data.errors import SessionFileError
from magstack.data.packets import SEQ_MODULO, encode_command_args, pack_tc
from magstack.data.xtce import xtce_document
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.errors import FlightConfigError
from magstack.firmware.flight.ccsds import apid_map
from magstack.firmware.flight.config import load_config
from magstack.ground.tm_decode import decode_files


def register(subparsers) -> None:
    p = subparsers.add_parser("tm", help="CCSDS packets: XTCE document, decode a packet stream, build telecommands")
    sub = p.add_subparsers(dest="tm_command", metavar="ACTION", required=True)
    x = sub.add_parser("xtce", help="print the XTCE 1.2 document of the packets a flight configuration produces")
    x.add_argument("--config", required=True, type=nonempty_path, help="flight.toml")
    x.set_defaults(func=run_xtce)
    m = sub.add_parser("dictionary", help="print the flight dictionary's tables (docs/ccsds.md) as Markdown")
    m.set_defaults(func=run_dictionary)
    d = sub.add_parser("decode", help="packet stream(s) -> session files, events.jsonl, housekeeping.jsonl")
    d.add_argument("packets", nargs="+", type=Path, help="packet files (e.g. telemetry/packets-0001.bin)")
    d.add_argument("--out", required=True, type=nonempty_dir, help="output directory")
    d.set_defaults(func=run_decode)
    c = sub.add_parser("command", help="build a PUS-C telecommand; write it to a file or send it over UDP",
                       description=f"NAME is ping or one of: {', '.join(COMMAND)}; arguments as key=value.")
    c.add_argument("name", help="ping or a command name")
    c.add_argument("args", nargs="*", metavar="key=value", help="command arguments")
    c.add_argument("--config", required=True, type=nonempty_path, help="flight.toml (addresses, tc_dir)")
    where = c.add_mutually_exclusive_group()
    where.add_argument("--out", type=nonempty_path, default=None, help="write the packet to this file")
    where.add_argument("--send", action="store_true", help="send it to [ccsds] tc_udp")
    c.add_argument("--seq", type=int_range(0, SEQ_MODULO - 1), default=None,
                   help="sequence count (default: the next from <telemetry_dir>/.tc-sequence)")
    c.add_argument("--source-id", type=int_range(0, 65535), default=None,
                   help="PUS source id (default: the first of [ccsds] tc_source_ids)")
    c.set_defaults(func=run_command)


def run_xtce(args: argparse.Namespace) -> CommandResult:
    cfg = load_config(args.config)
    if cfg.ccsds is None:
        raise FlightConfigError(f"{args.config}: no [ccsds] table: this configuration produces no packets")
    doc = xtce_document(apid_map(cfg), name=cfg.name)
    return CommandResult("tm", {"action": "xtce", "xtce": doc}, [doc.rstrip("\n")])


def run_dictionary(args: argparse.Namespace) -> CommandResult:
    text = dictionary_markdown()
    return CommandResult("tm", {"action": "dictionary", "markdown": text}, [BEGIN, text.rstrip("\n"), END])


def run_decode(args: argparse.Namespace) -> CommandResult:
    for p in args.packets:
        if not Path(p).is_file():
            raise SessionFileError(f"{p}: no such packet file")
    try:
        rep = decode_files(args.packets, args.out)
    except OSError as exc:
        raise SessionFileError(f"{args.out}: cannot write ({exc.strerror or exc})") from None
    if rep.packets_ok == 0:
        raise SessionFileError(f"{', '.join(map(str, args.packets))}: no valid packet in {rep.bytes} bytes "
                               f"({rep.bad_packets} bad)")
    lines = [f"{rep.packets_ok} packets decoded from {rep.bytes} bytes: "
             + ", ".join(f"{n} {k}" for k, n in sorted(rep.by_packet.items())),
             f"bad packets {rep.bad_packets} (crc {rep.bad_crc}, length {rep.bad_length}, truncated {rep.truncated}, "
             f"unknown {rep.unknown}, malformed {rep.malformed}; {rep.skipped_bytes} bytes skipped); "
             f"sequence: {rep.seq_missing} missing, {rep.seq_repeated} repeated",
             *(f"  wrote {f}" for f in rep.files)]
    return CommandResult("tm", {"action": "decode", **rep.to_dict()}, lines)


def _next_seq(cfg) -> int:
    path = cfg.telemetry_dir / ".tc-sequence"
    try:
        n = (int(path.read_text().strip()) + 1) % SEQ_MODULO
    except (OSError, ValueError):
        n = int(time.time()) % SEQ_MODULO
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(".tc-sequence.tmp")
    tmp.write_text(f"{n}\n")
    os.replace(tmp, path)
    return n


def run_command(args: argparse.Namespace) -> CommandResult:
    cfg = load_config(args.config)
    cc = cfg.ccsds
    if cc is None:
        raise FlightConfigError(f"{args.config}: no [ccsds] table: the application takes no telecommands")
    kv = {}
    for a in args.args:
        k, sep, v = a.partition("=")
        if not sep or not k or not v:
            raise ConfigurationError(f"argument {a!r}: use key=value")
        kv[k] = v
    if args.name == "ping":
        if kv:
            raise ConfigurationError("ping takes no arguments")
        service, app_data = TC_PING, b""
    else:
        cmd = COMMAND.get(args.name)
        if cmd is None:
            raise ConfigurationError(f"unknown command {args.name!r}; valid: ping, {', '.join(COMMAND)}")
        names = [a.name for a in cmd.args]
        if set(kv) != set(names):
            raise ConfigurationError(f"{cmd.name} takes {', '.join(names) or 'no arguments'}; got {', '.join(kv)}")
        try:
            app_data = struct.pack(">H", cmd.opcode) + encode_command_args([kv[n] for n in names])
        except ValueError as exc:
            raise ConfigurationError(f"{cmd.name}: {exc}") from None
        service = TC_FUNCTION
    seq = args.seq if args.seq is not None else _next_seq(cfg)
    source = args.source_id if args.source_id is not None else cc.tc_source_ids[0]
    packet = pack_tc(*service, app_data, apid=APP_APID, seq_count=seq, source_id=source)
    data = {"action": "command", "name": args.name, "seq_count": seq, "source_id": source, "packet": packet.hex()}
    if args.send:
        if cc.tc_udp is None:
            raise FlightConfigError(f"{args.config}: [ccsds] has no tc_udp address to send to")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(packet, cc.tc_udp)
        where = f"sent to {cc.tc_udp[0]}:{cc.tc_udp[1]}"
    else:
        if args.out is not None:
            out = Path(args.out)
        elif cc.tc_dir is not None:
            out = cc.tc_dir / f"{int(time.time() * 1000)}-{seq:05d}.tc"
        else:
            raise FlightConfigError(f"{args.config}: [ccsds] has no tc_dir; give --out FILE or --send")
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp")
        tmp.write_bytes(packet)
        os.replace(tmp, out)
        where = f"written to {out}"
        data["path"] = str(out)
    return CommandResult("tm", data, [f"{args.name}: {len(packet)}-byte PUS-C TC, seq {seq}, source {source}, {where}"])
