"""The demo's closing summary: headline figures as JSON-friendly data and as a table for a person."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from magstack.cli.demo.run import DemoResult


def figures(res: DemoResult) -> dict:
    """The headline figures (stable keys; summary.json and ``magstack demo --json``)."""
    f, h, b, a, t, lp = res.fit, res.holdout, res.bench, res.align, res.table, res.loop
    return {
        "seed": res.config.seed, "seconds": res.config.seconds, "program": res.config.program,
        "probe": {"devices": [f"{d['bus']}@{d['address']:#04x}={d['chip']}" for d in res.probe.devices],
                  "ads1248_id": res.probe.ads1248_id},
        "bench": {"dut_samples": b.dut_samples, "ref_samples": b.ref_samples, "dut_rate_hz": b.dut_rate_hz,
                  "ref_rate_hz": b.ref_rate_hz, "ref_skipped": b.ref_skipped, "temp_range_c": b.temp_range_c},
        "align": {"offset_s": a.offset_s, "offset_sigma_s": a.offset_sigma_s, "skew_s": a.skew_s,
                  "skew_sigma_s": a.skew_sigma_s, "axis_map": a.axis_map,
                  "linear_fit_rmse_uT": a.linear_fit_rmse_uT},
        "fit": {"model": f.model, "raw_rmse_norm_uT": f.raw_rmse_norm_uT, "rmse_norm_uT": f.rmse_norm_uT,
                "holdout_blocks_norm_uT": f.holdout_blocks_norm_uT, "noise_floor_norm_uT": f.noise_floor_norm_uT,
                "n_used": f.n_used, "held": f.held, "candidates": f.candidates, "recovery": f.recovery,
                "slice_held": [x["param"] for x in f.slice_held], "slice_refused": bool(f.slice_refused)},
        "table": {"crc32": t.crc32, "valid": t.valid, "worst_output_uT": t.worst_output_uT, "max_cond": t.max_cond,
                  "refused": [{"kind": r["kind"], "error": r["error"]} for r in t.refused],
                  "active_crc32_after": t.active_crc32_after},
        "holdout": {"seed": h.bench.seed, "seconds": h.bench.seconds, "n_rows": h.n_rows, "n_steady": h.n_steady,
                    "raw_rmse_norm_uT": h.raw_rmse_norm_uT, "cal_rmse_norm_uT": h.cal_rmse_norm_uT,
                    "raw_rmse_all_norm_uT": h.raw_rmse_all_norm_uT, "cal_rmse_all_norm_uT": h.cal_rmse_all_norm_uT,
                    "fixed_vs_float_max_nT": h.fixed_vs_float_max_nT,
                    "fixed_vs_float_unquantised_max_nT": h.fixed_vs_float_unquantised_max_nT,
                    "offset_s": h.align.offset_s},
        "loop": {"cycles": lp.cycles, "health": lp.health, "injected": lp.injected,
                 "corrector_status": lp.corrector_status,
                 "raw_error_norm_uT": lp.raw_error_norm_uT, "cal_error_norm_uT": lp.cal_error_norm_uT},
        "wall_s": {"total": res.total_wall_s, "steps_1_to_7": res.wall_s, **res.step_wall_s},
        "files": [str(p) for p in res.files],
    }


def _nT(v: float | None) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v * 1e3:.1f} nT"


def summary_rows(res: DemoResult) -> list[tuple[str, str]]:
    """(quantity, value) rows of the closing summary (also the report's summary table)."""
    f, h, a, t, lp, b = res.fit, res.holdout, res.align, res.table, res.loop, res.bench
    rows = [
        ("I2C chips identified / HMC1053 ADC ID", f"{len(res.probe.devices)} / {res.probe.ads1248_id:#x}"),
        ("bench: DUT / reference samples", f"{b.dut_samples} @ {b.dut_rate_hz:.2f} Hz / "
                                           f"{b.ref_samples} @ {b.ref_rate_hz:.2f} Hz"),
        ("clock offset", f"{a.offset_s:+.4f} +- {a.offset_sigma_s:.4f} s"),
        ("axis skew x / y / z", " / ".join(f"{v:+.3f}" for v in a.skew_s) + " s"),
        ("axis map", "identity" if a.axis_map_identity else a.axis_map),
        ("fit model", f"{f.model} ({len(f.held)} from the prior)"),
        ("raw RMSE (fit session)", f"{f.raw_rmse_norm_uT:.3f} uT"),
        ("calibrated RMSE, in-sample", _nT(f.rmse_norm_uT)),
        ("calibrated RMSE, held-out time blocks", _nT(f.holdout_blocks_norm_uT)),
        ("noise floor (from residuals)", _nT(f.noise_floor_norm_uT)),
        ("table crc32 / corrupted copies refused", f"{t.crc32} / {len(t.refused)} of 2"),
        ("held-out session raw -> calibrated", f"{h.raw_rmse_norm_uT:.3f} uT -> {_nT(h.cal_rmse_norm_uT)}"),
        ("held-out incl. transitions", f"{h.raw_rmse_all_norm_uT:.3f} uT -> {_nT(h.cal_rmse_all_norm_uT)}"),
        ("fixed-point vs float64 applier", f"{h.fixed_vs_float_max_nT:.4f} nT max (same inputs)"),
        ("flight loop: faults injected / counted", f"{sum(lp.injected.values())} / {lp.health['error_count']} "
                                                   f"(bus {lp.health['bus_errors']}, timeout {lp.health['timeouts']})"),
        ("flight loop error vs truth raw -> cal", f"{lp.raw_error_norm_uT:.3f} uT -> {_nT(lp.cal_error_norm_uT)}"),
        ("wall time, steps 1-7 (the report's own: step 8)", f"{res.wall_s:.1f} s"),
    ]
    return rows


def summary_lines(res: DemoResult) -> list[str]:
    """The closing summary table and the list of files written."""
    rows = summary_rows(res)
    w = max(len(k) for k, _ in rows)
    out = ["", "summary (RMSE = vector norm of per-axis RMSE; measured in this run)", "-" * (w + 40)]
    out += [f"{k:<{w}}  {v}" for k, v in rows]
    out += ["", f"files written to {res.config.out_dir}/:"]
    for p in res.files:
        size = p.stat().st_size if p.exists() else 0
        out.append(f"  {p.name:<24} {size:>9} bytes")
    return out
