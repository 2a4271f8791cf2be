"""``magstack table show|validate cal.json``."""
from __future__ import annotations

import argparse
import sys

import numpy as np

from magstack.errors import EXIT_NEGATIVE
from magstack.firmware.cal_table import load_table, validate
from magstack.firmware.errors import CalTableInvalid


def register(subparsers) -> None:
    p = subparsers.add_parser("table", help="show or validate a calibration table")
    sub = p.add_subparsers(dest="table_command", metavar="ACTION", required=True)
    for name, hlp in (("show", "print a table's header, parameters, validity and fit statistics"),
                      ("validate", "check CRC, schema, bounds, conditioning and fixed-point headroom")):
        q = sub.add_parser(name, help=hlp)
        q.add_argument("table", metavar="cal.json")
        q.add_argument("--device-id", default=None, help="also require this device id")
        q.set_defaults(func=run, action=name)


def run(args: argparse.Namespace) -> int:
    """``show``: an unreadable or invalid table is bad input (exit 3). ``validate``: the verdict is the
    answer, so an invalid table prints why and exits 1."""
    try:
        t = load_table(args.table)
        if args.device_id is not None and t.device_id != args.device_id:
            raise CalTableInvalid(f"{args.table}: table is for device {t.device_id!r}, not {args.device_id!r}")
    except CalTableInvalid as exc:
        if args.action != "validate":
            raise
        print(f"INVALID: {exc}", file=sys.stderr)
        return EXIT_NEGATIVE
    v = validate(t)
    if args.action == "show":
        print(f"table {t.table_name} schema v{t.schema_version} device {t.device_id} crc32 0x{t.crc32:08x}")
        print(f"created {t.created_utc}; {t.description}")
        print(f"model {t.model_name}: terms {', '.join(t.terms)}; t0 = {t.t0_c:g} degC")
        np.set_printoptions(precision=6, suppress=False)
        print(f"S (1) =\n{t.S}\nK_S (1/degC) =\n{t.K_S}\nO (uT) = {t.O}\nK_O (uT/degC) = {t.K_O}")
        for k, d in t.D:
            print(f"D_{k} (uT/A) = {d}")
        if "cubic" in t.terms:
            print(f"c3 (1/uT^2) = {t.c3}")
        if "cross_products" in t.terms:
            print(f"P (1/uT; columns xy, xz, yz) =\n{t.P}")
        if t.ground_only:
            print(f"ground-only terms (not applied): {', '.join(t.ground_only)}")
        print(f"validity: temp_c {t.validity_temp_c}, |B| <= {t.validity_field_uT:g} uT"
              + "".join(f", I_{k} in {r} A" for k, r in t.validity_currents_A))
        fs = t.fit_stats
        for key in ("n_used", "raw_rmse_norm_uT", "rmse_norm_uT", "holdout_blocks_rmse_norm_uT",
                    "holdout_sessions_rmse_norm_uT", "noise_floor_norm_uT"):
            if key in fs:
                print(f"fit {key}: {fs[key]}")
        for h in fs.get("held", []) if isinstance(fs.get("held"), list) else ():
            if isinstance(h, dict):
                print(f"held {h.get('param')} = {h.get('value')}: {h.get('reason')}")
    if v.ok:
        print(f"valid: worst-case output {v.worst_output_uT:.1f} uT, max condition number {v.max_cond:.3g}")
        return 0
    print("INVALID: " + "; ".join(v.problems))
    if args.action == "validate":
        print(f"INVALID: {args.table}: " + "; ".join(v.problems), file=sys.stderr)
        return EXIT_NEGATIVE
    v.raise_if_bad(str(args.table))   # typed error, exit 3 (after ``show`` has printed the contents)
    return EXIT_NEGATIVE
