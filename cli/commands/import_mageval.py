"""``magstack import-mageval DATA.csv REF.csv --out session.csv``: real AV-MagEval bench files -> session."""
from __future__ import annotations

import argparse
import logging
import math

from magstack.cli.options import finite_float, int_range, nonempty_path
from magstack.cli.output import CommandResult
from magstack.cli.progress import fraction_bar
from magstack.data.session import refuse_overwriting_inputs, write_session
from magstack.data.windows import add_window_options, describe, select_rows
from magstack.drivers.errors import ConfigurationError
from magstack.ground.mageval_import import AUTHORS_OFFSET_S, import_mageval

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"


def register(subparsers) -> None:
    p = subparsers.add_parser("import-mageval", help="import AV-MagEval dataN.csv + refN.csv as a session file",
                              description="Pair an AV-MagEval DUT log with its FVM400 reference file: authors' "
                                          "axis map, kelvin -> degC, clock offset estimated from the data, "
                                          "interpolation without extrapolation, gaps marked or dropped.")
    p.add_argument("data_csv", help="dataN.csv (DUT logger)")
    p.add_argument("ref_csv", help="refN.csv (reference fluxgate)")
    p.add_argument("--out", required=True, type=nonempty_path, help="session file to write")
    p.add_argument("--temp-column", choices=("temp_pi", "temp_mag"), default="temp_pi",
                   help="kelvin column used as temp_c (default temp_pi, as the authors)")
    p.add_argument("--clock-offset-s", type=finite_float(-1e6, 1e6, unit="s"), default=None,
                   help="seconds added to the reference clock (default: estimate from the data)")
    p.add_argument("--authors-offset", action="store_true",
                   help=f"use the authors' manual correction {AUTHORS_OFFSET_S} s instead of estimating")
    p.add_argument("--strict-offset", action="store_true",
                   help="fail if the data do not determine the offset (default: fall back to the authors' value)")
    p.add_argument("--onto", default="dut",
                   help="'dut' (default), 'ref', or a uniform grid step in s, 0.001..3600 (authors: 0.25)")
    p.add_argument("--max-gap-s", type=finite_float(0, 1e6, lo_open=True, unit="s"), default=1.0,
                   help="never interpolate across a longer gap (s)")
    p.add_argument("--drop-gaps", action="store_true", help="drop rows without a partner instead of NaN + flag")
    p.add_argument("--skip-bad-lines", action="store_true", help="skip (and count) unparsable lines")
    p.add_argument("--session-id", type=int_range(0, 2 ** 31 - 1), default=0,
                   help="integer run id for the session column")
    add_window_options(p)
    p.set_defaults(func=run)


log = logging.getLogger(__name__)

#: Accepted uniform grid step for --onto (s).
ONTO_STEP_RANGE_S = (0.001, 3600.0)


def _onto(text: str) -> str | float:
    if text in ("dut", "ref"):
        return text
    try:
        return finite_float(*ONTO_STEP_RANGE_S, unit="s")(text)
    except argparse.ArgumentTypeError as exc:
        raise ConfigurationError(f"--onto must be 'dut', 'ref' or a grid step in s: {exc}") from None


def _number(text):
    """A numeric metadata value as JSON wants it: a number, ``nan`` -> None."""
    if not isinstance(text, str):
        return text
    try:
        v = float(text)
    except ValueError:
        return text
    if not math.isfinite(v):
        return None
    return int(v) if v.is_integer() and text.strip().lstrip("+-").isdigit() else v


def run(args: argparse.Namespace) -> CommandResult:
    onto = _onto(args.onto)
    refuse_overwriting_inputs(args.out, [args.data_csv, args.ref_csv])
    offset = AUTHORS_OFFSET_S if args.authors_offset else args.clock_offset_s
    with fraction_bar("import-mageval") as progress:
        s = import_mageval(args.data_csv, args.ref_csv, temp_column=args.temp_column, clock_offset_s=offset,
                           on_undetermined="raise" if args.strict_offset else "prior", onto=onto,
                           max_gap_s=args.max_gap_s, gaps="drop" if args.drop_gaps else "nan",
                           bad_lines="skip" if args.skip_bad_lines else "raise", session_id=args.session_id,
                           progress=progress)
        if args.window or args.drop_window:
            keep = select_rows(s.t_s, s.session, args.window, args.drop_window)
            if not keep.any():
                raise ConfigurationError("the time windows select no rows")
            s.metadata["rows_selected"] = describe(args.window, args.drop_window, int(keep.sum()), len(s))
            s = s.select(keep)
        progress("write", 0.0)
        write_session(args.out, s)
    m = s.metadata
    keys = ("clock_offset_s", "clock_offset_vs_authors_s", "clock_offset_sigma_s", "clock_offset_method", "gap_rows",
            "gap_policy")
    numeric = {"clock_offset_s", "clock_offset_vs_authors_s", "clock_offset_sigma_s", "gap_rows"}
    data = {"out": str(args.out), "rows": len(s),
            **{k: _number(m.get(k)) if k in numeric else m.get(k) for k in keys},
            "rows_selected": m.get("rows_selected")}
    method = m["clock_offset_method"]
    warning = None
    if method.startswith("prior"):
        reason = method[len("prior ("):-1] if method.startswith("prior (") and method.endswith(")") else method
        warning = (f"clock offset NOT estimated, the authors' value {AUTHORS_OFFSET_S} s was used: {reason} "
                   "(use --strict-offset to fail instead)")
        log.warning("import-mageval: %s", warning)
    data["warning"] = warning
    return CommandResult("import-mageval", data, [
        f"wrote {args.out}: {len(s)} rows; clock offset {m['clock_offset_s']} s ({_offset_source(m)}); "
        + _gap_text(data["gap_rows"], m["gap_policy"])])


def _offset_source(m) -> str:
    """How the clock offset was chosen, for the one-line summary (the reason of a fallback is the warning's)."""
    method = m["clock_offset_method"]
    if method.startswith("prior"):
        return "the authors' value: the data do not determine it, see the warning"
    if method == "given":
        return f"given, {m['clock_offset_vs_authors_s']} s vs the authors'"
    sigma = _number(m.get("clock_offset_sigma_s"))
    return (f"{method}, {m['clock_offset_vs_authors_s']} s vs the authors'"
            + (f", sigma {sigma:.4f} s" if isinstance(sigma, float | int) else ""))


def _gap_text(n_gap, policy: str) -> str:
    """The DUT rows without a reference partner within --max-gap-s, and what became of them."""
    if policy == "drop":
        return f"{n_gap} rows without a reference partner dropped"
    return f"{n_gap} rows without a reference partner kept (reference empty, flagged)"
