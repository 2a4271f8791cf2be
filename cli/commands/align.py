"""``magstack align``: clock offset, per-axis skew and axis map of a DUT/reference pair."""
from __future__ import annotations

import argparse
import logging

import numpy as np

from magstack.cli.options import finite_float, nonempty_path
from magstack.cli.output import CommandResult
from magstack.cli.progress import fraction_bar
from magstack.data.pairing import split_streams
from magstack.data.session import read_session, refuse_overwriting_inputs, write_session
from magstack.drivers.errors import ConfigurationError
from magstack.ground.alignment import align_streams, aligned_session
from magstack.ground.mageval_import import AUTHORS_OFFSET_S, KELVIN_OFFSET, read_mageval_data, read_mageval_ref

#: The optional extra this command needs (cli/extras.py): checked before this module is imported.
EXTRA = "ground"

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    p = subparsers.add_parser("align", help="estimate clock offset, per-axis time skew and axis map",
                              description="Inputs: one session file (its ref_* columns are aligned against its "
                                          "dut_* columns), or an AV-MagEval pair DATA.csv REF.csv. Exit 3 (bad "
                                          "input data, one-line error) when the data cannot determine the clock "
                                          "offset.")
    p.add_argument("inputs", nargs="+", help="SESSION.csv | DATA.csv REF.csv")
    p.add_argument("--prior-s", type=finite_float(-1e7, 1e7, unit="s"), default=None,
                   help="expected offset (s added to reference time); with --halfwidth-s limits the search")
    p.add_argument("--halfwidth-s", type=finite_float(0, 1e7, lo_open=True, unit="s"), default=None,
                   help="search prior +- this (s). Default for a session file: 0 +- 10 s (both streams carry "
                        "host timestamps); for a DATA/REF pair: every offset with >= 50%% overlap")
    p.add_argument("--max-gap-s", type=finite_float(0, 1e6, lo_open=True, unit="s"), default=None,
                   help="never interpolate across a longer gap (s)")
    p.add_argument("--min-r2", type=finite_float(0, 1), default=0.9,
                   help="minimum explained variance to accept the offset, 0..1 (default 0.9)")
    p.add_argument("--temp-model", choices=("auto", "on", "off"), default="auto",
                   help="add the Eq. 3 temperature columns (field*dT, dT) to the regressions: auto = when the "
                        "DUT temperature spans at least --min-temp-span-c (default auto)")
    p.add_argument("--min-temp-span-c", type=finite_float(0, 200, unit="degC"), default=1.0,
                   help="temperature span (degC, 2..98 %% percentiles) above which auto uses the temperature model")
    p.add_argument("--temp-order", type=int, choices=(1, 2), default=2,
                   help="temperature terms: 1 = belsten Eq. 3 (field*dT, dT); 2 = also field*dT^2, dT^2 (default)")
    p.add_argument("--out", default=None, type=nonempty_path,
                   help="write the paired session: reference interpolated onto the DUT timestamps at the "
                        "estimated offset (session input only; for DATA/REF use import-mageval)")
    p.add_argument("--correct-skew", action="store_true", help="with --out: also re-sample determined DUT axes")
    p.add_argument("--drop-gaps", action="store_true", help="with --out: drop rows without a reference")
    p.set_defaults(func=run)


def _load(inputs: list[str], prior: float | None, halfwidth: float | None):
    if len(inputs) == 1:
        st = split_streams(read_session(inputs[0]))
        st.require_increasing()   # as --out does: out-of-order rows are bad input, never sorted silently
        if prior is None and halfwidth is None:
            prior, halfwidth = 0.0, 10.0
        return st.t_dut_s, st.dut_uT, st.t_ref_s, st.ref_uT, prior, halfwidth, st.temp_dut_c
    if len(inputs) == 2:
        cols, _ = read_mageval_data(inputs[0])
        t_ref, ref, _ = read_mageval_ref(inputs[1])
        dut = np.column_stack([cols["x_test"], cols["y_test"], cols["z_test"]])
        temp_c = cols["temp_pi"] - KELVIN_OFFSET  # the authors' calibration temperature
        return cols["time"], dut, t_ref, ref, AUTHORS_OFFSET_S if prior is None else prior, halfwidth, temp_c
    raise ConfigurationError(f"give one session file or DATA.csv REF.csv, got {len(inputs)} paths")


def run(args: argparse.Namespace) -> CommandResult:
    if args.out and len(args.inputs) != 1:
        raise ConfigurationError("--out needs a session file input; for DATA.csv REF.csv use import-mageval")
    if args.out:
        refuse_overwriting_inputs(args.out, args.inputs)
    t_dut, dut, t_ref, ref, prior, halfwidth, temp_c = _load(args.inputs, args.prior_s, args.halfwidth_s)
    log.info("align: %d DUT rows, %d reference rows; offset search %s; temperature model %s (order %d)", len(t_dut),
             len(t_ref), "every offset with >= 50% overlap" if halfwidth is None else f"{prior:g} +- {halfwidth:g} s",
             args.temp_model, args.temp_order)
    with fraction_bar("align") as progress:
        rep = align_streams(t_dut, dut, t_ref, ref, prior_s=prior, search_halfwidth_s=halfwidth,
                            max_gap_s=args.max_gap_s, min_r2=args.min_r2, temp_c=temp_c, temp_model=args.temp_model,
                            min_temp_span_c=args.min_temp_span_c, temp_order=args.temp_order, progress=progress)
        lines = _report_lines(rep)
        log.info("align: model %s; offset %.4f s +- %.4f s, R2 %.6f from %d pairs", rep.model, rep.offset.offset_s,
                 rep.offset.sigma_s, rep.offset.r2, rep.offset.n_pairs)
        data = {**rep.as_dict(), "out": None, "paired_rows": None, "gap_rows": None}
        if args.out:
            progress("write paired session", 0.0)
            paired = aligned_session(read_session(args.inputs[0]), rep, correct_skew=args.correct_skew,
                                     max_gap_s=args.max_gap_s, gaps="drop" if args.drop_gaps else "nan")
            write_session(args.out, paired)
            gaps = int(paired.metadata["gap_rows"])
            data.update(out=str(args.out), paired_rows=len(paired), gap_rows=gaps)
            lines.append(f"wrote {args.out}: {len(paired)} paired rows ({gaps} without reference, "
                         f"{paired.metadata['gap_policy']})")
    return CommandResult("align", data, lines)


def _report_lines(rep) -> list[str]:
    o = rep.offset
    runner_up = ("no other minimum in the search window" if not np.isfinite(o.runner_up_ratio)
                 else f"next minimum {o.runner_up_ratio:.1f}x worse")
    lines = [f"model: {rep.model}",
             f"clock offset: {o.offset_s:.4f} s +- {o.sigma_s:.4f} s (add to reference time); "
             f"R2 {o.r2:.6f}; {o.n_pairs} pairs; {runner_up}"]
    for ax, e in zip("xyz", rep.skew_s, strict=True):
        state = "" if e.determined else f"  UNDETERMINED: {e.reason}"
        lines.append(f"skew {ax}: {e.value:+.4f} s +- {e.sigma:.4f} s{state}")
    lines.append(f"axis map: {rep.axis_map.describe()}")
    for name, r in (("linear-fit", rep.rmse_uT), ("temperature-model", rep.rmse_model_uT)):
        if r is not None:
            lines.append(f"{name} RMSE after alignment: x {r['x'] * 1e3:.1f} nT, y {r['y'] * 1e3:.1f} nT, "
                         f"z {r['z'] * 1e3:.1f} nT, vector {r['vector'] * 1e3:.1f} nT (n={r['n']})")
    lines += [f"note: {n}" for n in rep.notes]
    return lines
