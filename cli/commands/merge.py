"""``magstack merge TELEMETRY.csv [...] --adcs ADCS.csv [...] --out PATH``: ADCS position and attitude
into flight telemetry, written as refit input (:mod:`magstack.ground.merge_adcs`, docs/refit.md)."""
from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

from magstack.cli.options import finite_float, nonempty_path
from magstack.cli.output import CommandResult
from magstack.data.telemetry import NO_ADCS_FLAG
from magstack.ground.merge_adcs import METHODS, TOLERANCE_S, merge_files

log = logging.getLogger(__name__)

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"

#: Gaps printed in the text report (all of them are in --json).
SHOWN_GAPS = 10


def file_or_directory(text: str) -> Path:
    """argparse type of ``--out``: an output file, or an existing directory (one output per input, same name)."""
    if text.strip() and Path(text).is_dir():
        return Path(text)
    if text.endswith(("/", os.sep)):
        raise argparse.ArgumentTypeError(f"directory {text!r} does not exist: create it first (mkdir -p {text})")
    return nonempty_path(text)


file_or_directory.is_output = True  # type: ignore[attr-defined]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "merge", help="merge ADCS position/attitude into flight telemetry (refit input)",
        description="Give every telemetry row the ADCS position and attitude at its time (interpolated, or the "
                    "nearest sample), within a tolerance. Rows without ADCS are kept, flagged "
                    f"({NO_ADCS_FLAG}=no_adcs) and listed as gaps. Output: telemetry that `magstack refit` reads.")
    p.add_argument("telemetry", nargs="+", metavar="TELEMETRY.csv", help="flight telemetry session files")
    p.add_argument("--adcs", required=True, action="append", metavar="ADCS.csv",
                   help="ADCS file (t_s, pos_ecef_x/y/z_km, q_body_eci_w/x/y/z); repeat for several")
    p.add_argument("--out", required=True, type=file_or_directory, metavar="PATH",
                   help="output file (one telemetry file) or existing directory (one output per input, same name)")
    p.add_argument("--method", choices=METHODS, default="interpolate",
                   help="interpolate (position linear, attitude slerp; default) or nearest sample")
    p.add_argument("--tolerance", type=finite_float(0, 86400, lo_open=True, unit="s"), default=TOLERANCE_S,
                   metavar="S", help="interpolate: largest spacing of the two ADCS samples around a row; "
                                     f"nearest: largest distance to the sample (default {TOLERANCE_S:g} s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> CommandResult:
    reports, track = merge_files(args.telemetry, args.adcs, args.out, args.method, args.tolerance)
    lines = [f"ADCS: {track.t_s.size} samples from {len(args.adcs)} file(s), {track.dropped} samples with an empty "
             f"or non-finite cell skipped"
             + (f" (lines {', '.join(map(str, track.dropped_lines))}{' ...' if track.dropped > 5 else ''})"
                if track.dropped else "")
             + f"; {args.method}, tolerance {args.tolerance:g} s"]
    if track.dropped:
        log.warning("merge: %d ADCS samples with an empty or non-finite cell skipped (first at line %d)",
                    track.dropped, track.dropped_lines[0])
    for r in reports:
        lines.append(f"wrote {r.out}: {r.rows} rows, {r.merged} with ADCS, {r.flagged} without "
                     f"(flag {NO_ADCS_FLAG}) in {len(r.gaps)} gap(s)")
        for g in sorted(r.gaps, key=lambda g: -g.rows)[:SHOWN_GAPS]:
            lines.append(f"  gap {g.t_first_s:.3f}..{g.t_last_s:.3f} s: {g.rows} rows")
        if len(r.gaps) > SHOWN_GAPS:
            lines.append(f"  ... {len(r.gaps) - SHOWN_GAPS} shorter gaps (all in --json)")
    data = {"method": args.method, "tolerance_s": args.tolerance, "adcs_samples": int(track.t_s.size),
            "adcs_rows_skipped": track.dropped, "adcs_skipped_lines": list(track.dropped_lines),
            "no_adcs_flag": NO_ADCS_FLAG,
            "files": [{"telemetry": r.telemetry, "out": r.out, "rows": r.rows, "merged": r.merged,
                       "without_adcs": r.flagged,
                       "gaps": [{"t_first_s": g.t_first_s, "t_last_s": g.t_last_s, "rows": g.rows} for g in r.gaps]}
                      for r in reports]}
    return CommandResult("merge", data, lines)
