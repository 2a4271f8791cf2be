"""``magstack table show|validate cal.json|cal.mcal`` and ``magstack table export``.

A table file is a JSON table or its binary image (:mod:`magstack.firmware.cal_image`), told apart by
the image's magic; ``export`` writes the image, and with ``--c DIR`` the C applier beside it."""
from __future__ import annotations

import argparse
import io
import logging

import numpy as np

from magstack.cli.inputs import TABLE_MAX_BYTES, check_table_file
from magstack.cli.options import nonempty_dir, nonempty_path, nonempty_text
from magstack.cli.output import CommandResult
from magstack.data.io import read_bytes_bounded
from magstack.drivers.errors import ConfigurationError
from magstack.errors import EXIT_NEGATIVE
from magstack.firmware import cal_image
from magstack.firmware.cal_table import load_table, validate
from magstack.firmware.errors import CalTableInvalid


def register(subparsers) -> None:
    p = subparsers.add_parser("table", help="show, validate or export a calibration table")
    sub = p.add_subparsers(dest="table_command", metavar="ACTION", required=True)
    for name, hlp in (("show", "print a table's header, parameters, validity and fit statistics"),
                      ("validate", "check CRC, schema, bounds, conditioning and fixed-point headroom")):
        q = sub.add_parser(name, help=hlp)
        q.add_argument("table", metavar="cal.json", help="calibration table file (JSON, or its binary image)")
        q.add_argument("--device-id", default=None, type=nonempty_text, help="also require this device id")
        q.set_defaults(func=run, action=name)
    q = sub.add_parser("export", help="write a table's binary image and the C applier",
                       description="Write the table's binary image (docs/cal-table.md) and/or the C99 applier "
                                   "(magstack_cal.c/.h, docs/c-applier.md) with the image into a folder. The table "
                                   "is validated first.")
    q.add_argument("table", metavar="cal.json", help="calibration table file (JSON, or its binary image)")
    q.add_argument("--image", type=nonempty_path, default=None, metavar="OUT.mcal", help="binary image to write")
    q.add_argument("--c", dest="c_dir", type=nonempty_dir, default=None, metavar="DIR",
                   help="write magstack_cal.c, magstack_cal.h and the image (table.mcal) into DIR")
    q.add_argument("--c-array", action="store_true",
                   help="with --c: also magstack_cal_image.h, the image as a const byte array (no file system)")
    q.add_argument("--device-id", default=None, type=nonempty_text, help="also require this device id")
    q.set_defaults(func=run_export, action="export")


log = logging.getLogger(__name__)


def run(args: argparse.Namespace) -> CommandResult:
    """``show``: an unreadable or invalid table is bad input (exit 3). ``validate``: a file that is not a
    table document at all (not a regular file, too large, not JSON, too deep, huge integers) is bad
    input (exit 3); for a table document the verdict is the answer, so an invalid one prints why and
    exits 1."""
    data = {"table": str(args.table), "action": args.action, "valid": False, "problems": [], "crc32": None,
            "device_id": None, "model": None, "terms": None, "worst_output_uT": None, "max_cond": None,
            "document": None, "format": "json", "image": None}
    raw = read_bytes_bounded(args.table, TABLE_MAX_BYTES, "calibration table")
    image = cal_image.is_image(raw)
    if image:
        data["format"] = "image"
    else:
        check_table_file(args.table)
    try:
        t = cal_image.table_from_image(raw, str(args.table)) if image else load_table(args.table)
        if args.device_id is not None and t.device_id != args.device_id:
            raise CalTableInvalid(f"{args.table}: table is for device {t.device_id!r}, not {args.device_id!r}")
    except CalTableInvalid as exc:
        if args.action != "validate":
            raise
        log.error("INVALID: %s", exc)
        return CommandResult("table", {**data, "problems": [str(exc)]}, [f"INVALID: {exc}"], EXIT_NEGATIVE)
    v = validate(t)
    data.update(valid=v.ok, problems=list(v.problems), crc32=f"0x{t.crc32:08x}", device_id=t.device_id,
                model=t.model_name, terms=list(t.terms), worst_output_uT=v.worst_output_uT, max_cond=v.max_cond)
    lines = _show_lines(t) if args.action == "show" else []
    if image:
        data["image"] = _image_data(raw)
        if args.action == "show":
            lines += _image_lines(raw)
    elif args.action == "show" and v.ok:
        data["document"] = t.to_document()
    if v.ok:
        lines.append(f"valid: worst-case output {v.worst_output_uT:.1f} uT, max condition number {v.max_cond:.3g}")
        return CommandResult("table", data, lines)
    lines.append("INVALID: " + "; ".join(v.problems))
    if args.action == "validate":
        log.error("INVALID: %s: %s", args.table, "; ".join(v.problems))
        return CommandResult("table", data, lines, EXIT_NEGATIVE)
    from magstack.cli.output import say

    say("\n".join(lines))   # the contents first, then the typed error (exit 3)
    v.raise_if_bad(str(args.table))
    return CommandResult("table", data, lines, EXIT_NEGATIVE)


def _show_lines(t) -> list[str]:
    buf = io.StringIO()

    def p(*a) -> None:
        print(*a, file=buf)

    p(f"table {t.table_name} schema v{t.schema_version} device {t.device_id} crc32 0x{t.crc32:08x}")
    p(f"created {t.created_utc}; {t.description}")
    p(f"model {t.model_name}: terms {', '.join(t.terms)}; t0 = {t.t0_c:g} degC")
    with np.printoptions(precision=6, suppress=False):
        p(f"S (1) =\n{t.S}\nK_S (1/degC) =\n{t.K_S}\nO (uT) = {t.O}\nK_O (uT/degC) = {t.K_O}")
        if "temperature_gain2" in t.terms:
            p(f"K_S2 (1/degC^2) = {t.K_S2}")
        for k, d in t.D:
            p(f"D_{k} (uT/A) = {d}")
        if "cubic" in t.terms:
            p(f"c3 (1/uT^2) = {t.c3}")
        if "cross_products" in t.terms:
            p(f"P (1/uT; columns xy, xz, yz) =\n{t.P}")
    if t.ground_only:
        p(f"ground-only terms (not applied): {', '.join(t.ground_only)}")
    p(f"validity: temp_c {t.validity_temp_c}, calibrated field per axis within +-{list(t.field_limits_uT)} uT"
      + ("" if t.validity_field_norm_uT is None else f", |B| <= {t.validity_field_norm_uT:g} uT")
      + "".join(f", I_{k} in {r} A" for k, r in t.validity_currents_A))
    fs = t.fit_stats
    for key in ("n_used", "raw_rmse_norm_uT", "rmse_norm_uT", "holdout_blocks_rmse_norm_uT",
                "holdout_sessions_rmse_norm_uT", "noise_floor_norm_uT"):
        if key in fs:
            p(f"fit {key}: {fs[key]}")
    for h in fs.get("held", []) if isinstance(fs.get("held"), list) else ():
        if isinstance(h, dict):
            p(f"prior-determined {h.get('param')} = {h.get('value')}: {h.get('reason')}")
    for line in _posterior_lines(t):
        p(line)
    return buf.getvalue().rstrip("\n").split("\n")


def _posterior_lines(t) -> list[str]:
    """The posterior block: per parameter its sd, per axis the strongest correlations (|r| >= 0.5)."""
    post = t.posterior
    if post is None:
        return ["posterior: none (table without the optional block)"]
    out = [f"posterior (parameter covariance; validity bound {post.get('bound_uT', float('nan')) * 1e3:.0f} nT, "
           f"priors: {post.get('prior', '?')}):"]
    for a in ("x", "y", "z"):
        names = post[a]["names"]
        C = np.asarray(post[a]["cov"], dtype=float)
        sd = np.sqrt(np.maximum(np.diag(C), 0.0))
        out.append(f"  axis {a}: " + ", ".join(f"{n} sd {s:.3g}" for n, s in zip(names, sd, strict=True)))
        with np.errstate(invalid="ignore", divide="ignore"):
            R = C / np.outer(sd, sd)
        strong = [(abs(R[i, j]), names[i], names[j], R[i, j]) for i in range(len(names)) for j in range(i)
                  if np.isfinite(R[i, j]) and abs(R[i, j]) >= 0.5]
        if strong:
            out.append("    correlations: " + ", ".join(f"{x}~{y} {r:+.2f}" for _, x, y, r in sorted(strong)[::-1][:6]))
    return out


def _image_data(raw: bytes) -> dict:
    img = cal_image.decode_image(raw)
    fx = img.fixed
    return {"version": cal_image.VERSION, "size": len(raw), "image_crc32": f"0x{img.image_crc32:08x}",
            "source_crc32": f"0x{img.source_crc32:08x}", "current_names": list(img.current_names),
            "integers": {"S": fx.S, "K_S": fx.K_S, "K_S2": fx.K_S2, "O": fx.O, "K_O": fx.K_O, "D": fx.D,
                         "t0_cdeg": fx.t0_cdeg, "field_limit_nT": fx.field_limit_nT,
                         "field_limits_nT": fx.axis_limits_nT, "field_norm_nT": fx.field_norm_nT,
                         "temp_range_cdeg": fx.temp_range_cdeg, "current_ranges_mA": fx.current_ranges_mA}}


def _image_lines(raw: bytes) -> list[str]:
    img = cal_image.decode_image(raw)
    fx = img.fixed
    return [f"image v{cal_image.VERSION}, {len(raw)} bytes, image crc32 0x{img.image_crc32:08x}, made from the table "
            f"with crc32 0x{img.source_crc32:08x} (not carried: description, creation time, fit statistics, "
            "posterior, ground-only terms)",
            f"integers: S (2^-27) {list(fx.S)}", f"  K_S (2^-34 /degC) {list(fx.K_S)}",
            f"  K_S2 (2^-40 /degC^2) {list(fx.K_S2)}", f"  O (2^-8 nT) {list(fx.O)}",
            f"  K_O (2^-16 nT/degC) {list(fx.K_O)}",
            *(f"  D_{n} (2^-20 nT/mA) {list(d)}" for n, d in zip(img.current_names, fx.D, strict=True)),
            f"  t0 {fx.t0_cdeg} centi-degC, field limit {fx.field_limit_nT} nT, calibrated field per axis within "
            f"+-{list(fx.axis_limits_nT)} nT, "
            + ("no magnitude limit" if fx.field_norm_nT is None else f"|B| <= {fx.field_norm_nT} nT")
            + f", temperature {fx.temp_range_cdeg} centi-degC"
            + "".join(f", I_{n} in {r} mA" for n, r in zip(img.current_names, fx.current_ranges_mA, strict=True))]


#: The files ``export --c DIR`` writes besides the C sources.
C_IMAGE_NAME = "table.mcal"
C_ARRAY_HEADER = "magstack_cal_image.h"


def run_export(args: argparse.Namespace) -> CommandResult:
    """Validate the table (JSON or image) and write its image and/or the C applier; nothing is written when
    the table is invalid (exit 3) or cannot be carried by an image."""
    from magstack.data.io import atomic_write_bytes, staged_directory

    if args.image is None and args.c_dir is None:
        raise ConfigurationError("table export: give --image OUT.mcal and/or --c DIR")
    if args.c_array and args.c_dir is None:
        raise ConfigurationError("table export: --c-array needs --c DIR")
    raw_in = read_bytes_bounded(args.table, TABLE_MAX_BYTES, "calibration table")
    if cal_image.is_image(raw_in):
        t = cal_image.table_from_image(raw_in, str(args.table))
        validate(t).raise_if_bad(str(args.table))
        raw = raw_in
    else:
        check_table_file(args.table)
        t = load_table(args.table)
        raw = cal_image.image_from_table(t)
    if args.device_id is not None and t.device_id != args.device_id:
        raise CalTableInvalid(f"{args.table}: table is for device {t.device_id!r}, not {args.device_id!r}")
    img = cal_image.decode_image(raw)
    written = []
    if args.image is not None:
        atomic_write_bytes(args.image, raw)
        written.append(str(args.image))
    if args.c_dir is not None:
        files = {**cal_image.c_sources(), C_IMAGE_NAME: raw}
        if args.c_array:
            files[C_ARRAY_HEADER] = cal_image.c_array_header(raw).encode()
        with staged_directory(args.c_dir) as stage:
            for name, content in files.items():
                (stage / name).write_bytes(content)
        written += [str(args.c_dir / name) for name in files]
    lines = [f"image v{cal_image.VERSION} of table 0x{img.source_crc32:08x} for {img.device_id}: {len(raw)} bytes, "
             f"image crc32 0x{img.image_crc32:08x}"] + [f"wrote {w}" for w in written]
    data = {"table": str(args.table), "action": "export", "device_id": img.device_id,
            "source_crc32": f"0x{img.source_crc32:08x}", "image_crc32": f"0x{img.image_crc32:08x}",
            "image_bytes": len(raw), "written": written}
    return CommandResult("table", data, lines)
