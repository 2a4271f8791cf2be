"""``magstack table show|validate cal.json``."""
from __future__ import annotations

import argparse
import io
import logging

import numpy as np

from magstack.cli.inputs import check_table_file
from magstack.cli.options import nonempty_text
from magstack.cli.output import CommandResult
from magstack.errors import EXIT_NEGATIVE
from magstack.firmware.cal_table import load_table, validate
from magstack.firmware.errors import CalTableInvalid


def register(subparsers) -> None:
    p = subparsers.add_parser("table", help="show or validate a calibration table")
    sub = p.add_subparsers(dest="table_command", metavar="ACTION", required=True)
    for name, hlp in (("show", "print a table's header, parameters, validity and fit statistics"),
                      ("validate", "check CRC, schema, bounds, conditioning and fixed-point headroom")):
        q = sub.add_parser(name, help=hlp)
        q.add_argument("table", metavar="cal.json", help="calibration table file")
        q.add_argument("--device-id", default=None, type=nonempty_text, help="also require this device id")
        q.set_defaults(func=run, action=name)


log = logging.getLogger(__name__)


def run(args: argparse.Namespace) -> CommandResult:
    """``show``: an unreadable or invalid table is bad input (exit 3). ``validate``: a file that is not a
    table document at all (not a regular file, too large, not JSON, too deep, huge integers) is bad
    input (exit 3); for a table document the verdict is the answer, so an invalid one prints why and
    exits 1."""
    data = {"table": str(args.table), "action": args.action, "valid": False, "problems": [], "crc32": None,
            "device_id": None, "model": None, "terms": None, "worst_output_uT": None, "max_cond": None,
            "document": None}
    check_table_file(args.table)
    try:
        t = load_table(args.table)
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
    if args.action == "show" and v.ok:
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
        for k, d in t.D:
            p(f"D_{k} (uT/A) = {d}")
        if "cubic" in t.terms:
            p(f"c3 (1/uT^2) = {t.c3}")
        if "cross_products" in t.terms:
            p(f"P (1/uT; columns xy, xz, yz) =\n{t.P}")
    if t.ground_only:
        p(f"ground-only terms (not applied): {', '.join(t.ground_only)}")
    p(f"validity: temp_c {t.validity_temp_c}, |B| <= {t.validity_field_uT:g} uT"
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
