"""``magstack tm xtce|decode|command``: the CCSDS side of the flight application (docs/ccsds.md)."""
from __future__ import annotations

import argparse
import logging
import os
import socket
import struct
import time
from pathlib import Path

from magstack.cli.options import int_range, nonempty_dir, nonempty_path
from magstack.cli.output import CommandResult
from magstack.data.dictionary import APP_APID, COMMAND, TC_FUNCTION, TC_PING, arg_problem
from magstack.data.dictionary_doc import BEGIN, END, dictionary_markdown
from magstack.data.io import atomic_write_text, open_exclusive, read_bytes_bounded
from magstack.data.packets import SEQ_MODULO, encode_command_args, pack_tc
from magstack.data.xtce import xtce_document
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.errors import FlightConfigError
from magstack.firmware.flight.ccsds import apid_map
from magstack.firmware.flight.config import load_config
from magstack.firmware.flight.intake import check_private_dir
from magstack.ground.tm_decode import decode_files

log = logging.getLogger(__name__)


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
    d.add_argument("--out", required=True, type=nonempty_dir,
                   help="output directory (new, empty or an earlier decode's; never the packet file's own)")
    d.add_argument("--strict", action="store_true",
                   help="a bad packet or a channel row no identification vouches for is an error (exit 3, nothing "
                        "written); without it they are counted and reported on stderr")
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
                   help="sequence count (default: one more than the last sent, kept in <telemetry_dir>/.tc-sequence; "
                        "0 without it); after resync_tc seq=N the next is N")
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
    rep = decode_files(args.packets, args.out, strict=args.strict)
    if rep.bad_packets or rep.unattributed:
        log.warning("tm decode: %d bad packets, %d channel rows not attributed to a run and channel (counted, not "
                    "written; --strict makes this an error)", rep.bad_packets, rep.unattributed)
    lines = [f"{rep.packets_ok} packets decoded from {rep.bytes} bytes: "
             + ", ".join(f"{n} {k}" for k, n in sorted(rep.by_packet.items())),
             f"bad packets {rep.bad_packets} (crc {rep.bad_crc}, length {rep.bad_length}, truncated {rep.truncated}, "
             f"unknown {rep.unknown}, malformed {rep.malformed}; {rep.skipped_bytes} bytes skipped); "
             f"sequence: {rep.seq_missing} missing, {rep.seq_repeated} repeated",
             f"runs {', '.join(map(str, rep.runs)) or 'none'}; {rep.unattributed} channel rows unattributed, "
             f"{rep.identity_conflicts} identity conflicts (split)",
             *(f"  wrote {f}" for f in rep.files)]
    return CommandResult("tm", {"action": "decode", **rep.to_dict()}, lines)


def _seq_file(cfg) -> Path:
    return cfg.telemetry_dir / ".tc-sequence"


def _next_seq(cfg) -> int:
    """The ground's next sequence count: one more than the last one sent (0 without a record)."""
    try:
        return (int(read_bytes_bounded(_seq_file(cfg), 64, "sequence file").decode().strip()) + 1) % SEQ_MODULO
    except (ValueError, UnicodeDecodeError):     # InputDataError is a ValueError: missing, unreadable, corrupt
        return 0


def _record_seq(cfg, n: int) -> None:
    """Remember ``n`` as the last count sent (atomic, 0600)."""
    path = _seq_file(cfg)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, f"{n % SEQ_MODULO}\n", perm=0o600)


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
        for a in cmd.args:                 # the receiver's own check: what it would refuse is not built
            why = arg_problem(a, kv[a.name])
            if why:
                raise ConfigurationError(f"{cmd.name}: {why}")
        try:
            app_data = struct.pack(">H", cmd.opcode) + encode_command_args([kv[n] for n in names])
        except ValueError as exc:
            raise ConfigurationError(f"{cmd.name}: {exc}") from None
        service = TC_FUNCTION
    seq = args.seq if args.seq is not None else _next_seq(cfg)
    source = args.source_id if args.source_id is not None else cc.tc_source_ids[0]
    if args.name == "resync_tc" and int(kv["source_id"]) != source:
        raise ConfigurationError(f"resync_tc source_id={kv['source_id']} but the packet's source id is {source}: "
                                 "a source resynchronises only itself (--source-id)")
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
        if args.out is None:
            why = check_private_dir(cc.tc_dir)      # created 0700, as the receiver creates it
            if why:
                raise FlightConfigError(f"{args.config}: ccsds.tc_dir: {why}")
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
        _write_packet(out, packet)
        where = f"written to {out}"
        data["path"] = str(out)
    _record_seq(cfg, seq if args.name != "resync_tc" else int(kv["seq"]) - 1)
    return CommandResult("tm", data, [f"{args.name}: {len(packet)}-byte PUS-C TC, seq {seq}, source {source}, {where}"])


def _write_packet(out: Path, packet: bytes) -> None:
    """The packet file, 0600 whatever the umask (the receiver refuses a file others may write), appearing
    whole under its name (written under a fresh hidden name, then renamed)."""
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    created = False
    try:
        with open_exclusive(tmp, "wb", perm=0o600) as fh:    # a planted file or symlink there: FileExistsError
            created = True
            fh.write(packet)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, out)
        created = False
    finally:
        if created:
            tmp.unlink(missing_ok=True)
