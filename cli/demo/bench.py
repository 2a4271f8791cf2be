"""Demo steps 2 and 3: record a simulated bench session, then align its two streams.

The session itself comes from :func:`magstack.hil.bench.record_sim_session` (the recipe
``magstack bench --bus sim`` uses); alignment from :mod:`magstack.ground.alignment` (as
``magstack align SESSION --out`` does). This module only gathers the figures the demo shows.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from magstack.cli.demo.config import DEVICE_ID, Say
from magstack.data.pairing import split_streams
from magstack.data.session import read_session, write_session
from magstack.ground import alignment
from magstack.hil.bench import record_sim_session
from magstack.sim.measurement_sim import FVM400_NOISE_uT


@dataclass
class BenchFigures:
    path: Path
    program: str
    seconds: float
    seed: int
    rows: int
    dut_samples: int
    ref_samples: int
    dut_rate_hz: float
    ref_rate_hz: float
    ref_skipped: dict[str, int]
    dut_errors: dict[str, int]
    ref_errors: dict[str, int]
    temp_range_c: tuple[float, float]
    max_abs_field_uT: float
    end_epoch_s: float


def record_session(path: Path, *, program: str, seconds: float, seed: int, session_id: int,
                   ref_garble: float, instrument_name: str, say: Say = print) -> BenchFigures:
    """Record one simulated bench session (HMC1053 DUT + FVM400 reference) into ``path``."""
    ref_noise_uT = float(np.sqrt(np.mean(np.square(FVM400_NOISE_uT))))
    res, sb = record_sim_session("hmc1053", path, program=program, seconds=seconds, seed=seed,
                                 session_id=session_id, ref_faults={"garble": ref_garble},
                                 ref_noise_uT=ref_noise_uT, instrument_name=instrument_name,
                                 metadata={"device_id": DEVICE_ID, "source": "magstack demo"})
    s = read_session(path)
    t = split_streams(s).temp_dut_c
    t = t[np.isfinite(t)]
    fig = BenchFigures(
        Path(path), program, float(seconds), seed, res.rows, res.dut_samples, res.ref_samples,
        res.dut_samples / res.duration_s, res.ref_samples / res.duration_s, dict(res.ref_skipped),
        dict(res.dut_errors), dict(res.ref_errors), (float(t.min()), float(t.max())),
        float(np.nanmax(np.abs(s.ref_uT))), sb.clock.epoch_s())
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(fig.ref_skipped.items())) or "none"
    errors = sum(fig.dut_errors.values()) + sum(fig.ref_errors.values())
    say(f"  DUT hmc1053 (ADS1248 + bridge + error model): {fig.dut_samples} samples at {fig.dut_rate_hz:.2f} Hz; "
        f"reference FVM400 via {sb.ref_url}: {fig.ref_samples} samples at {fig.ref_rate_hz:.2f} Hz")
    say(f"  reference replies skipped by the driver: {skipped}; read errors: {errors}; "
        f"DUT temperature {fig.temp_range_c[0]:.1f}..{fig.temp_range_c[1]:.1f} degC; "
        f"reference |B_i| up to {fig.max_abs_field_uT:.1f} uT")
    return fig


@dataclass
class AlignFigures:
    raw_path: Path
    paired_path: Path
    offset_s: float
    offset_sigma_s: float
    skew_s: list[float]
    skew_sigma_s: list[float]
    skew_determined: list[bool]
    axis_map: str
    axis_map_identity: bool
    axis_map_determined: list[bool]
    linear_fit_rmse_uT: float
    paired_rows: int
    gap_rows: int
    report: Any = field(repr=False, default=None)


def align_session(raw_path: Path, paired_path: Path, *, say: Say = print, verbose: bool = True) -> AlignFigures:
    """Estimate offset / skew / axis map from a raw bench session and write the paired session."""
    raw = read_session(raw_path)
    st = split_streams(raw)
    # both streams carry the host clock: search 0 +- 10 s as `magstack align` does for a session file
    rep = alignment.align_streams(st.t_dut_s, st.dut_uT, st.t_ref_s, st.ref_uT, prior_s=0.0,
                                  search_halfwidth_s=10.0, temp_c=st.temp_dut_c)
    paired = alignment.aligned_session(raw, rep, correct_skew=True)
    write_session(paired_path, paired)
    am = rep.axis_map
    fig = AlignFigures(Path(raw_path), Path(paired_path), rep.offset.offset_s, rep.offset.sigma_s,
                       [e.value for e in rep.skew_s], [e.sigma for e in rep.skew_s],
                       [e.determined for e in rep.skew_s], am.describe(),
                       am.perm == (0, 1, 2) and am.sign == (1, 1, 1), list(am.determined),
                       rep.rmse_uT["vector"], len(paired), int(paired.metadata["gap_rows"]), rep)
    if verbose:
        sk = ", ".join(f"{a} {v:+.3f}+-{s:.3f}" + ("" if d else " (undetermined)")
                       for a, v, s, d in zip("xyz", fig.skew_s, fig.skew_sigma_s, fig.skew_determined, strict=True))
        say(f"  clock offset {fig.offset_s:+.4f} +- {fig.offset_sigma_s:.4f} s (R2 {rep.offset.r2:.5f}, "
            f"{rep.offset.n_pairs} pairs); per-axis skew (s): {sk}")
        say(f"  axis map: {fig.axis_map}; linear-fit RMSE after alignment {fig.linear_fit_rmse_uT:.3f} uT")
        say(f"  paired session: {fig.paired_rows} DUT rows with the reference interpolated at t - offset, axes "
            f"re-sampled for their skew; {fig.gap_rows} rows without reference (flagged)")
    return fig
