"""``magstack demo``: the whole stack end to end on the simulated bench, no hardware needed.

Seven steps, each a function returning its measured figures (tests assert on them), each
printing a short headline through ``say``:

1. :func:`probe_bench` - scan the simulated I2C buses (LIS3MDL, HMC5983, LSM303DLHC; two
   chips share 0x1E and are told apart by their identity registers), bring up the HMC1053
   front end (ADS1248 over simulated SPI) and read every chip through
   :func:`magstack.drivers.registry.open_chip` (the common ``Magnetometer`` interface).
2. :func:`record_session` - a bench session with :func:`magstack.hil.bench.run_bench`: HMC1053 DUT
   through the register-level ADC + bridge + shared error model, FVM400 reference through the
   real driver over ``fvm400sim://``; coil program ``full`` (steps, sweeps, rotation and
   +-150 uT excursions on every axis, one thermal cycle 5..55 degC).
3. :func:`align_session` - clock offset, per-axis skew, axis map (:mod:`magstack.ground.alignment`) and
   the paired session.
4. :func:`fit_calibration` - belsten Eq. 3 (24 parameters) and optional terms, held-out
   errors, the identifiability report, and the same fit on a thermally flat slice to show
   what is held / refused when the data cannot determine a parameter.
5. :func:`table_lifecycle` - save, validate, load + activate in a
   :class:`~magstack.firmware.cal_table.CalTableStore`; corrupted copies are refused with
   :class:`~magstack.drivers.errors.CalTableInvalid` while the active table stays in force.
6. :func:`holdout_check` - a second, independent session (other seed, other length), aligned
   and calibrated with the fixed-point applier (``magstack apply`` logic); residual before/after.
7. :func:`flight_loop` - :class:`~magstack.firmware.sampling_loop.SamplingLoop` on a simulated
   HMC1053 with a corrector backed by the active table's fixed-point applier; an SPI fault and
   a stuck DRDY are injected and must show up in the health counters.

Everything runs in virtual time and is deterministic for a seed (wall times aside). Units:
field uT, temperature degC, time s (suffixes in names).
"""
from __future__ import annotations

import csv
import datetime as _dt
import json
import math
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from magstack.data.io import to_json
from magstack.drivers.errors import ConfigurationError, MagError
from magstack.firmware.errors import CalTableInvalid, FitError

#: Device id of the simulated HMC1053 board (tables and sessions carry it).
DEVICE_ID = "hmc1053:sim-bench"
#: Static field and temperature for the probe / read step (uT, degC).
PROBE_FIELD_uT = (20.0, -5.0, 40.0)
PROBE_TEMP_C = 25.0
#: Static field and temperature the flight loop sees (inside the table's validity box).
LOOP_FIELD_uT = (-12.0, 27.0, 35.0)
LOOP_TEMP_C = 40.0
#: Shortest bench session the demo accepts (s): below this the coil program's plateaus are
#: shorter than a few DUT cycles and the temperature cycle too fast to pair reliably.
MIN_SECONDS = 300.0
MAX_SECONDS = 36000.0
#: Files the demo writes (their stale ``.part`` siblings from an interrupted run are removed).
ARTEFACTS = ("probe.json", "session.csv", "session-paired.csv", "fit-report.txt", "cal.json",
             "cal-corrupted.json", "cal-truncated.json", "holdout-session.csv", "holdout-paired.csv",
             "holdout-calibrated.csv", "flight-loop.csv", "summary.json")

Say = Callable[[str], None]


@dataclass(frozen=True)
class DemoConfig:
    """What the demo runs. ``seconds``: calibration session length (virtual s); the held-out
    session lasts ``holdout_seconds`` (default seconds / 2) with seed ``seed + 1``."""

    out_dir: Path = Path("magstack-demo")
    seed: int = 0
    seconds: float = 1200.0
    program: str = "full"
    holdout_program: str = "full"
    holdout_seconds: float | None = None
    #: fit and held-out figures leave out rows next to a reference change above this (uT between
    #: consecutive DUT rows, ~0.36 s): coil steps and excursion ramps, where pairing a 4 Hz
    #: reference with a 2.8 Hz DUT by interpolation, not the sensor, dominates the error.
    exclude_steps_uT: float = 2.0
    #: probability of a garbled FVM400 reply (the driver must skip and count them)
    ref_garble: float = 0.005
    loop_cycles: int = 16
    loop_period_s: float = 0.5
    samples_per_chip: int = 3

    def __post_init__(self) -> None:
        object.__setattr__(self, "out_dir", Path(self.out_dir))
        if int(self.seed) != self.seed or self.seed < 0:
            raise ConfigurationError(f"seed must be an integer >= 0, got {self.seed!r}")
        for name in ("seconds", "holdout_seconds"):
            v = getattr(self, name)
            if v is None:
                continue
            if not (math.isfinite(v) and MIN_SECONDS <= v <= MAX_SECONDS):
                raise ConfigurationError(f"{name} must be in [{MIN_SECONDS:g}, {MAX_SECONDS:g}] s, got {v!r}")
        if not (self.exclude_steps_uT > 0 and math.isfinite(self.exclude_steps_uT)):
            raise ConfigurationError(f"exclude_steps_uT must be > 0, got {self.exclude_steps_uT!r}")
        if not 0.0 <= self.ref_garble <= 0.2:
            raise ConfigurationError(f"ref_garble must be in [0, 0.2], got {self.ref_garble!r}")
        if self.loop_cycles < 12:
            raise ConfigurationError(f"loop_cycles must be >= 12 (two faults are injected), got {self.loop_cycles}")
        if not (self.loop_period_s > 0 and math.isfinite(self.loop_period_s)):
            raise ConfigurationError(f"loop_period_s must be > 0, got {self.loop_period_s!r}")
        if self.samples_per_chip < 1:
            raise ConfigurationError("samples_per_chip must be >= 1")

    @property
    def holdout_s(self) -> float:
        return self.holdout_seconds if self.holdout_seconds is not None else max(MIN_SECONDS, self.seconds / 2.0)


# ------------------------------------------------------------------------------ helpers
def _vec(v, fmt: str = "8.3f") -> str:
    return "(" + ", ".join(format(float(x), fmt) for x in v) + ")"


def _norm_rms_uT(err_uT: np.ndarray) -> float:
    """Vector norm of the per-axis RMS of (N,3) errors (uT); NaN rows must be removed first."""
    if err_uT.shape[0] == 0:
        return math.nan
    return float(np.linalg.norm(np.sqrt(np.mean(err_uT ** 2, axis=0))))


def _iso_utc(epoch_s: float) -> str:
    return _dt.datetime.fromtimestamp(round(epoch_s), _dt.UTC).isoformat().replace("+00:00", "Z")


def _finite_or_none(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


# ------------------------------------------------------------------------------ step 1
@dataclass
class ProbeFigures:
    devices: list[dict]                      # bus, address, chip, identity_hex, notes
    shared_address_chips: dict[str, str]     # bus -> chip identified at 0x1E
    ads1248_id: int                          # IDAC0 ID nibble read over simulated SPI
    front_end_table: str
    samples: dict[str, list[dict]]           # chip -> [{t_s, b_uT, temp_c}]
    truth_uT: tuple[float, float, float]
    truth_temp_c: float


def probe_bench(seed: int, *, samples_per_chip: int = 3, say: Say = print) -> ProbeFigures:
    """Probe the simulated I2C buses and the HMC1053 front end; read each chip."""
    from magstack.cli.commands.probe import format_result
    from magstack.drivers.clock import VirtualClock
    from magstack.drivers.i2c_probe import probe
    from magstack.drivers.registry import open_chip
    from magstack.sim.i2c_bench import CHIPS, default_bench
    from magstack.sim.truth_source import StaticTruth

    clock = VirtualClock()
    truth = StaticTruth(PROBE_FIELD_uT, PROBE_TEMP_C)
    bench = default_bench(clock, truth, seed=seed)
    devices, shared = [], {}
    for bus_name, bus in bench.buses.items():
        for r in probe(bus):
            devices.append({"bus": bus_name, "address": r.address, "chip": r.chip, "identity_hex": r.identity.hex(),
                            "notes": r.notes})
            if r.address == 0x1E:
                shared[bus_name] = r.chip
            say("  " + format_result(bus_name, r))
    found = {d["chip"] for d in devices}
    missing = [c for c in CHIPS if c not in found]
    if missing:
        raise MagError(f"probe did not identify {missing} on the simulated bench")
    fe = open_chip("hmc1053", "sim", clock, truth=truth, seed=seed)
    ads_id = fe.adc.read_register("IDAC0") >> 4
    say(f"  {fe.adc.spi.name:<12} CS0   hmc1053     ADS1248 IDAC0 ID nibble {ads_id:#x}; front-end table "
        f"{fe.table.name} (PGA {fe.table.pga}, {fe.table.data_rate_sps} SPS, set/reset strap)")
    samples: dict[str, list[dict]] = {}
    say(f"  truth: B = {_vec(truth.b_uT, '7.2f')} uT, T = {PROBE_TEMP_C:.1f} degC; raw readings "
        f"(offsets and gains not yet calibrated):")
    for chip in (*CHIPS, "hmc1053"):
        mag = fe if chip == "hmc1053" else open_chip(chip, "sim", clock, bench=bench)
        rows = []
        for _ in range(samples_per_chip):
            s = mag.read()
            rows.append({"t_s": s.t_s, "b_uT": list(s.b_uT), "temp_c": s.temp_c})
            temp = "   n/a" if s.temp_c is None else f"{s.temp_c:6.2f}"
            say(f"    {chip:<11} t {s.t_s:8.4f} s  B = {_vec(s.b_uT)} uT  T = {temp} degC"
                + (f"  OVERFLOW {s.overflow}" if s.overflow else ""))
        samples[chip] = rows
    return ProbeFigures(devices, shared, int(ads_id), fe.table.name, samples,
                        tuple(float(x) for x in truth.b_uT), PROBE_TEMP_C)


# ------------------------------------------------------------------------------ step 2
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
    from magstack.data.pairing import split_streams
    from magstack.data.session import read_session
    from magstack.hil.bench import build_sim_bench, run_bench, truth_currents
    from magstack.sim.measurement_sim import FVM400_NOISE_uT

    ref_noise_uT = float(np.sqrt(np.mean(np.square(FVM400_NOISE_uT))))
    sb = build_sim_bench("hmc1053", program=program, seconds=seconds, seed=seed,
                         ref_faults={"garble": ref_garble} if ref_garble else None, ref_noise_uT=ref_noise_uT,
                         instrument_name=instrument_name)
    names, cur = truth_currents(sb.truth)
    meta = {"bus": "sim", "program": program, "seed": str(seed), "ref_port": sb.ref_url, "clock": "virtual",
            "device_id": DEVICE_ID, "source": "magstack demo",
            "ref_noise_uT": f"{ref_noise_uT:g}", "ref_faults": f"garble={ref_garble:g}"}
    try:
        res = run_bench(sb.dut, sb.ref, sb.clock, path, seconds=seconds, ref_clock=sb.ref_clock,
                        session_id=session_id, metadata=meta, currents=cur, current_names=names)
    finally:
        from magstack.sim.fvm400_model import unregister_instrument

        sb.ref.close()
        unregister_instrument(instrument_name)
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


# ------------------------------------------------------------------------------ step 3
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
    from magstack.data.pairing import split_streams
    from magstack.data.session import read_session, write_session
    from magstack.ground.alignment import align_streams, aligned_session

    raw = read_session(raw_path)
    st = split_streams(raw)
    # both streams carry the host clock: search 0 +- 10 s as `magstack align` does for a session file
    rep = align_streams(st.t_dut_s, st.dut_uT, st.t_ref_s, st.ref_uT, prior_s=0.0, search_halfwidth_s=10.0,
                        temp_c=st.temp_dut_c)
    paired = aligned_session(raw, rep, correct_skew=True)
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


# ------------------------------------------------------------------------------ step 4
@dataclass
class FitFigures:
    model: str
    terms: list[str]
    candidates: list[dict]
    recovery: dict[str, float]       # fitted vs the simulator's preset (see recovery_vs_preset)
    n_used: int
    n_excluded: int
    raw_rmse_uT: list[float]
    raw_rmse_norm_uT: float
    rmse_uT: list[float]
    rmse_norm_uT: float
    holdout_blocks_norm_uT: float | None
    noise_floor_norm_uT: float
    held: list[dict]
    temp_span_with_field_c: list[float]
    slice_window_s: tuple[float, float]
    slice_temp_span_c: float
    slice_held: list[dict]
    slice_refused: str
    report_path: Path
    result: Any = field(repr=False, default=None)


#: Optional terms tried on top of Eq. 3 (the best held-out fixed-point-compatible set is adopted).
CANDIDATE_TERMS: tuple[tuple[str, ...], ...] = ((), ("time_skew",), ("time_skew", "cubic"))


def _fixed_point_ok(terms) -> bool:
    from magstack.firmware.cal_table import GROUND_ONLY_TERMS
    from magstack.firmware.fixed_point import FIXED_POINT_TERMS

    return all(t in FIXED_POINT_TERMS or t in GROUND_ONLY_TERMS for t in terms)


def recovery_vs_preset(result, preset_name: str = "hmc1053") -> dict[str, float]:
    """How far the fitted S, K_S, O are from the inverse of the simulated sensor's forward model.

    The error model applies ``b = (I + dT K) G b_true + o`` (gain matrix G, temperature gain K,
    offset o; ``dT = T - temp_ref_c``), so to first order in dT the calibration that undoes it is
    ``S = G^-1``, ``K_S = -G^-1 K``, ``O = -G^-1 o`` at ``t0_c = temp_ref_c``.
    """
    from magstack.sim.presets import preset

    p = preset(preset_name)
    g_inv = np.linalg.inv(np.asarray(p.gain_matrix, float))
    fitted = result.params
    if abs(result.model.t0_c - float(p.temp_ref_c)) > 1e-9:
        raise FitError(f"fit t0 {result.model.t0_c} degC differs from the preset's {p.temp_ref_c} degC")
    return {"S_max_abs": float(np.max(np.abs(fitted["S"] - g_inv))),
            "K_S_max_abs_per_c": float(np.max(np.abs(fitted["K_S"] + g_inv @ np.asarray(p.k_s_per_c, float)))),
            "O_max_abs_uT": float(np.max(np.abs(fitted["O"] + g_inv @ np.asarray(p.offset_uT, float))))}


def _flat_slice(fd, fraction: float = 0.1, min_rows: int = 300) -> tuple[np.ndarray, float]:
    """Rows of the contiguous window (``fraction`` of the rows, at least ``min_rows``) with the
    smallest temperature span, and that span (degC)."""
    t = fd.temp_c
    n = len(t)
    w = max(min_rows, int(fraction * n))
    if n <= w:
        return np.ones(n, bool), float(np.nanmax(t) - np.nanmin(t))
    from numpy.lib.stride_tricks import sliding_window_view

    win = sliding_window_view(np.nan_to_num(t, nan=np.nanmean(t)), w)
    span = win.max(axis=1) - win.min(axis=1)
    k = int(np.argmin(span))
    m = np.zeros(n, bool)
    m[k:k + w] = True
    return m, float(span[k])


def fit_calibration(paired_path: Path, report_path: Path, *, exclude_steps_uT: float,
                    say: Say = print) -> FitFigures:
    """Fit Eq. 3 (+ the optional terms that help held out) to the paired session."""
    from magstack.data.session import read_session
    from magstack.firmware.calibration import FitData, FitOptions, fit

    paired = read_session(paired_path)
    fd = FitData.from_session(paired)
    opts = FitOptions(exclude_ref_steps_uT=exclude_steps_uT)
    cands, results = [], {}
    for terms in CANDIDATE_TERMS:
        r = fit(fd, "eq3", list(terms), (), 25.0, opts)
        st = r.stats()
        results[terms] = r
        cands.append({"terms": list(terms), "model": r.model.name, "fixed_point": _fixed_point_ok(terms),
                      "rmse_norm_uT": st["rmse_norm_uT"], "holdout_blocks_norm_uT": st["holdout_blocks_rmse_norm_uT"],
                      "held": len(st["held"])})
    usable = [c for c in cands if c["fixed_point"] and c["holdout_blocks_norm_uT"] is not None]
    if not usable:
        raise FitError("no fixed-point-compatible model could be evaluated held out")
    best = min(usable, key=lambda c: c["holdout_blocks_norm_uT"])
    res = results[tuple(best["terms"])]
    st = res.stats()
    for c in cands:
        mark = "<- adopted" if c is best else ("" if c["fixed_point"] else "(float-only: not loadable on board)")
        say(f"  {c['model']:<22} in-sample {c['rmse_norm_uT'] * 1e3:7.1f} nT   held-out time blocks "
            f"{(c['holdout_blocks_norm_uT'] or math.nan) * 1e3:7.1f} nT  {mark}".rstrip())
    cov = res.coverage
    spans = [float(cov.temp_span_with_field(j)) for j in range(3)]
    say(f"  rows used {res.n_used}, excluded {res.n_excluded} (coil transitions > {exclude_steps_uT:g} uT "
        f"between rows, gaps); temperature span with field present per axis "
        f"{', '.join(f'{s:.1f}' for s in spans)} degC (need {opts.min_temp_span_c:g})")
    held = [{"param": h.name, "value": h.value, "reason": h.reason} for h in res.held]
    if held:
        say(f"  identifiability: {len(held)} parameters held at their prior: "
            + "; ".join(f"{h['param']} ({h['reason']})" for h in held[:4]) + (" ..." if len(held) > 4 else ""))
    else:
        n_par = int(res.model.axis_mask().sum())
        say(f"  identifiability: all {n_par} parameters of {res.model.name} determined (none held)")
    rec = recovery_vs_preset(res)
    say(f"  vs the simulated sensor (preset hmc1053, first order in dT): max |S - G^-1| {rec['S_max_abs']:.2g}, "
        f"max |K_S - (-G^-1 k_s)| {rec['K_S_max_abs_per_c']:.2g} /degC, max |O - (-G^-1 o)| "
        f"{rec['O_max_abs_uT'] * 1e3:.1f} nT")
    # the same fit on the thermally flattest slice of the session: what the report does when the
    # data cannot determine the temperature terms
    m, span = _flat_slice(fd)
    sl = fd.select(m)
    t0 = float(np.nanmin(paired.t_s))
    window = (float(sl.t_s.min() - t0), float(sl.t_s.max() - t0))
    try:
        rs = fit(sl, "eq3", list(best["terms"]), (), 25.0, FitOptions(exclude_ref_steps_uT=exclude_steps_uT,
                                                                       holdout=False))
        slice_held = [{"param": h.name, "value": h.value, "reason": h.reason} for h in rs.held]
    except FitError as exc:  # too few rows in a short session: the report says so
        slice_held = [{"param": "(all)", "value": math.nan, "reason": str(exc)}]
    try:
        fit(sl, "eq3", list(best["terms"]), (), 25.0, FitOptions(exclude_ref_steps_uT=exclude_steps_uT,
                                                                 holdout=False, on_unidentifiable="refuse"))
        refused = ""
    except FitError as exc:
        refused = str(exc)
    names = sorted({h["param"].split("[")[0] for h in slice_held})
    say(f"  same fit on the thermally flattest {len(sl)} rows (t {window[0]:.0f}..{window[1]:.0f} s, "
        f"T span {span:.2f} degC): "
        f"{len(slice_held)} parameters held ({', '.join(names) or 'none'})"
        + (f"; with --refuse-unidentifiable: FitError ({len(refused)} chars naming them)" if refused else
           "; nothing to refuse"))
    Path(report_path).write_text(res.report() + "\n\nCandidates (held-out by time blocks, uT):\n"
                                 + "\n".join(json.dumps(c) for c in cands) + "\n\nFlat-slice refusal:\n"
                                 + (refused or "none") + "\n", encoding="utf-8")
    return FitFigures(res.model.name, list(best["terms"]), cands, rec, res.n_used, res.n_excluded,
                      [float(x) for x in res.raw_rmse_uT], st["raw_rmse_norm_uT"], [float(x) for x in res.rmse_uT],
                      st["rmse_norm_uT"], st["holdout_blocks_rmse_norm_uT"], st["noise_floor_norm_uT"], held, spans,
                      window, span, slice_held, refused, Path(report_path), res)


# ------------------------------------------------------------------------------ step 5
@dataclass
class TableFigures:
    path: Path
    crc32: str
    valid: bool
    worst_output_uT: float
    max_cond: float
    validity_temp_c: tuple[float, float] | None
    validity_field_uT: float
    refused: list[dict]            # {kind, path, error}
    active_crc32_after: str
    reject_count: int
    store: Any = field(repr=False, default=None)
    table: Any = field(repr=False, default=None)


def _corrupt_one_digit(text: str) -> str:
    """The table text with one digit of the first gain value changed (still valid JSON)."""
    start = text.index('"S"')
    start = text.index('"value"', start)
    for i in range(start, len(text)):
        if text[i].isdigit() and text[i] != "0":
            return text[:i] + ("1" if text[i] != "1" else "2") + text[i + 1:]
    raise MagError("no digit to corrupt in the table text")  # pragma: no cover - a table always has S


def table_lifecycle(fit_result, out_dir: Path, *, created_epoch_s: float, description: str,
                    say: Say = print) -> TableFigures:
    """cal.json: save, validate, load + activate; two corrupted copies must be refused."""
    from magstack.firmware.cal_table import CalTableStore, save_table, table_from_fit, validate

    table = table_from_fit(fit_result, DEVICE_ID, description=description, created_utc=_iso_utc(created_epoch_s))
    v = validate(table)
    if not v.ok:
        raise CalTableInvalid("fitted table does not validate: " + "; ".join(v.problems))
    path = save_table(table, out_dir / "cal.json")
    store = CalTableStore(DEVICE_ID)
    active = store.load_and_activate(path)
    crc = f"0x{active.crc32:08x}"
    if store.active_fixed is None:
        raise CalTableInvalid("activated table has no fixed-point form")
    say(f"  {path.name}: {active.model_name}, crc32 {crc}, validity {active.validity_temp_c} degC, "
        f"|B_i| <= {active.validity_field_uT:g} uT")
    say(f"  validates: worst-case output {v.worst_output_uT:.1f} uT (fixed-point range "
        f"{_out_limit_uT():.0f} uT), max condition number {v.max_cond:.3g}; loaded and activated in "
        f"CalTableStore({DEVICE_ID!r})")
    text = Path(path).read_text(encoding="utf-8")
    copies = (("one digit changed", out_dir / "cal-corrupted.json", _corrupt_one_digit(text)),
              ("truncated", out_dir / "cal-truncated.json", text[: len(text) // 2]))
    refused = []
    fixed_before = store.active_fixed
    for kind, p, body in copies:
        p.write_text(body, encoding="utf-8")
        try:
            store.load_and_activate(p)
        except CalTableInvalid as exc:
            refused.append({"kind": kind, "path": p, "error": str(exc)})
            say(f"  {p.name} ({kind}): refused, CalTableInvalid: {exc}")
            continue
        raise MagError(f"{p.name} ({kind}) was accepted by the table store")
    after = store.active
    if after is not active or store.active_fixed is not fixed_before:
        raise MagError("a refused table replaced the active one")
    after_crc = f"0x{after.crc32:08x}"
    say(f"  active table still crc32 {after_crc}; store telemetry: rejects {store.reject_count}, "
        f"loads {store.load_count}")
    return TableFigures(Path(path), crc, v.ok, v.worst_output_uT, v.max_cond, active.validity_temp_c,
                        active.validity_field_uT, refused, after_crc, store.reject_count, store, active)


def _out_limit_uT() -> float:
    from magstack.firmware.fixed_point import OUT_LIMIT_uT

    return OUT_LIMIT_uT


# ------------------------------------------------------------------------------ step 6
@dataclass
class HoldoutFigures:
    bench: BenchFigures
    align: AlignFigures
    calibrated_path: Path
    n_rows: int
    n_steady: int
    raw_rmse_norm_uT: float          # rows outside coil transitions (the fit's rule)
    cal_rmse_norm_uT: float
    raw_rmse_uT: list[float]
    cal_rmse_uT: list[float]
    raw_rmse_all_norm_uT: float      # every paired row, transitions included
    cal_rmse_all_norm_uT: float
    out_of_validity_rows: int
    saturated_rows: int
    fixed_vs_float_max_nT: float     # same quantised inputs: the integer arithmetic alone
    fixed_vs_float_unquantised_max_nT: float  # float64 on the unrounded inputs (adds input rounding)


def holdout_check(table, out_dir: Path, *, program: str, seconds: float, seed: int, ref_garble: float,
                  exclude_steps_uT: float, say: Say = print) -> HoldoutFigures:
    """Record an independent session, pair it, calibrate it with the fixed-point applier."""
    from magstack.data.session import read_session, write_session
    from magstack.firmware.calibration.fit import reference_steps
    from magstack.firmware.fixed_point import to_fixed_inputs
    from magstack.firmware.float_applier import ApplyFlag, apply_float
    from magstack.ground.apply_session import FLAG_SHIFT, calibrate_session

    bench = record_session(out_dir / "holdout-session.csv", program=program, seconds=seconds, seed=seed,
                           session_id=2, ref_garble=ref_garble, instrument_name="demo-holdout", say=say)
    al = align_session(bench.path, out_dir / "holdout-paired.csv", say=say, verbose=False)
    say(f"  aligned: offset {al.offset_s:+.4f} +- {al.offset_sigma_s:.4f} s, axis map "
        f"{'identity' if al.axis_map_identity else al.axis_map}; {al.paired_rows} paired rows")
    paired = read_session(al.paired_path)
    dev = paired.metadata.get("device_id")
    if dev is not None and dev != table.device_id:  # the check `magstack apply` makes
        raise CalTableInvalid(f"table is for device {table.device_id!r}, session is from {dev!r}")
    cal = calibrate_session(table, paired, "fixed")
    cal_path = write_session(out_dir / "holdout-calibrated.csv", cal)
    apply_flags = cal.flag >> FLAG_SHIFT
    ok = (paired.flag == 0) & ~(apply_flags & int(ApplyFlag.MISSING_INPUT)).astype(bool)
    ok &= np.all(np.isfinite(cal.dut_uT), axis=1) & np.all(np.isfinite(paired.ref_uT), axis=1)
    steady = ok & ~reference_steps(paired.ref_uT, paired.session, exclude_steps_uT)
    raw_e = paired.ref_uT - paired.dut_uT
    cal_e = paired.ref_uT - cal.dut_uT
    per_axis = lambda e, m: [float(x) for x in np.sqrt(np.mean(e[m] ** 2, axis=0))]  # noqa: E731
    bi, ti, _, _ = to_fixed_inputs(paired.dut_uT, paired.temp_c)
    flt_q, _ = apply_float(table, bi / 1e3, ti / 1e2)
    flt, _ = apply_float(table, paired.dut_uT, paired.temp_c)
    diff = lambda x: float(np.max(np.abs(x[ok] - cal.dut_uT[ok]))) * 1e3 if ok.any() else math.nan  # noqa: E731
    diff_nT, diff_unq_nT = diff(flt_q), diff(flt)
    fig = HoldoutFigures(bench, al, Path(cal_path), int(ok.sum()), int(steady.sum()),
                         _norm_rms_uT(raw_e[steady]), _norm_rms_uT(cal_e[steady]), per_axis(raw_e, steady),
                         per_axis(cal_e, steady), _norm_rms_uT(raw_e[ok]), _norm_rms_uT(cal_e[ok]),
                         int(np.count_nonzero(apply_flags & int(ApplyFlag.OUT_OF_VALIDITY))),
                         int(np.count_nonzero(apply_flags & int(ApplyFlag.SATURATED))), diff_nT, diff_unq_nT)
    say(f"  fixed-point applier (magstack apply --applier fixed) on {fig.n_rows} rows: outside validity "
        f"{fig.out_of_validity_rows}, saturated {fig.saturated_rows}; |fixed - float64| <= {diff_nT:.4f} nT on the "
        f"same 1 nT / 0.01 degC inputs ({diff_unq_nT:.2f} nT against float64 on unrounded inputs)")
    per = ", ".join(f"{v * 1e3:.1f}" for v in fig.cal_rmse_uT)
    say(f"  residual vs reference, {fig.n_steady} rows outside coil transitions: raw {fig.raw_rmse_norm_uT:.3f} uT"
        f" -> calibrated {fig.cal_rmse_norm_uT * 1e3:.1f} nT (x/y/z {per} nT)")
    say(f"  all {fig.n_rows} rows incl. transitions: raw {fig.raw_rmse_all_norm_uT:.3f} uT -> calibrated "
        f"{fig.cal_rmse_all_norm_uT * 1e3:.1f} nT (the excess sits next to coil steps and ramps, where a 0.36 s DUT "
        f"cycle and a 4 Hz reference cannot be paired sample-exactly)")
    return fig


# ------------------------------------------------------------------------------ step 7
class FixedPointCorrector:
    """Sampling-loop corrector backed by a :class:`CalTableStore`'s active fixed-point table.

    The float reading is converted once at the boundary (uT -> int nT, degC -> int centi-degC),
    the integer applier runs, and its Q23.8 nT output is published in uT. Returns None (the loop
    counts it as uncalibrated) when no table is active, the temperature a table needs is missing,
    the table needs current inputs this loop does not measure, or the output saturated.
    """

    def __init__(self, store) -> None:
        self.store = store
        self.status = Counter()

    def __call__(self, sample) -> tuple[float, float, float] | None:
        from magstack.firmware.fixed_point import OUT_FRAC
        from magstack.firmware.float_applier import ApplyFlag

        fx = self.store.active_fixed
        if fx is None or fx.D or not all(math.isfinite(v) for v in sample.b_uT):
            self.status["not_applied"] += 1
            return None
        if sample.temp_c is None or not math.isfinite(sample.temp_c):
            if fx.temp_range_cdeg is not None:
                self.status["no_temperature"] += 1
                return None
            t_cdeg = fx.t0_cdeg
        else:
            t_cdeg = int(round(sample.temp_c * 100.0))
        q, status = fx.apply_sample([int(round(v * 1000.0)) for v in sample.b_uT], t_cdeg)
        if status & ApplyFlag.OUT_OF_VALIDITY:
            self.status["out_of_validity"] += 1
        if status & ApplyFlag.SATURATED:
            self.status["saturated"] += 1
            return None
        self.status["ok"] += 1
        scale = float(2 ** OUT_FRAC) * 1e3
        return (q[0] / scale, q[1] / scale, q[2] / scale)


@dataclass
class LoopFigures:
    cycles: int
    published: list[dict]
    health: dict[str, int]
    injected: dict[str, int]
    corrector_status: dict[str, int]
    truth_uT: tuple[float, float, float]
    truth_temp_c: float
    raw_error_norm_uT: float         # RMS over the good cycles of |raw - truth|
    cal_error_norm_uT: float         # same for the calibrated field
    path: Path


def flight_loop(store, out_path: Path, *, seed: int, cycles: int, period_s: float, say: Say = print) -> LoopFigures:
    """Run the flight sampling loop on a simulated HMC1053, inject an SPI fault and a stuck DRDY."""
    from magstack.drivers.clock import VirtualClock
    from magstack.firmware.sampling_loop import SamplingLoop
    from magstack.sim.hmc1053_bridge import build_sim_hmc1053
    from magstack.sim.truth_source import StaticTruth

    clock = VirtualClock()
    truth = StaticTruth(LOOP_FIELD_uT, LOOP_TEMP_C)
    rig = build_sim_hmc1053(clock, truth=truth, seed=seed)   # the typed board handle, for fault injection
    fe = rig.front_end
    corrector = FixedPointCorrector(store)
    loop = SamplingLoop(fe, clock, period_s=period_s, corrector=corrector)
    bus_fault_at, drdy_fault_at = cycles // 4, (2 * cycles) // 3
    injected = {"bus_errors": 0, "timeouts": 0}
    published = []
    say(f"  truth B = {_vec(LOOP_FIELD_uT, '7.2f')} uT at {LOOP_TEMP_C:.1f} degC; period {period_s:g} s; "
        f"SPI fault injected at cycle {bus_fault_at}, DRDY stuck high during cycle {drdy_fault_at}")
    say(f"    {'cycle':>5} {'t_s':>8}  {'raw B (uT)':^27}  {'calibrated B (uT)':^27} {'|err| nT':>9} {'errors':>6}")
    for k in range(cycles):
        store.cycle_boundary()  # the scheduler's table-swap point (nothing staged here)
        if k == bus_fault_at:
            rig.spi.inject_fault(1)
            injected["bus_errors"] += 1
        rig.adc_model.drdy_stuck_high = k == drdy_fault_at
        if k == drdy_fault_at:
            injected["timeouts"] += 1
        p = loop.step()
        err = (float(np.linalg.norm(np.subtract(p.b_uT, LOOP_FIELD_uT))) * 1e3) if p.b_uT is not None else math.nan
        published.append({"cycle": k, "t_s": p.t_s, "raw_uT": p.raw_uT, "b_uT": p.b_uT, "temp_c": p.temp_c,
                          "calibrated": p.calibrated, "error_count": p.error_count, "fault": p.fault})
        raw = _vec(p.raw_uT) if p.raw_uT is not None else f"{'-':^26}"
        calv = _vec(p.b_uT) if p.b_uT is not None else f"{'-':^26}"
        tail = f"  FAULT {p.fault}" if p.fault else ""
        errs = f"{err:9.1f}" if math.isfinite(err) else f"{'-':>9}"
        say(f"    {k:5d} {p.t_s:8.3f}  {raw}  {calv} {errs} {p.error_count:6d}{tail}")
    rig.adc_model.drdy_stuck_high = False
    health = loop.health.snapshot()
    good = [p for p in published if p["b_uT"] is not None]
    raw_err = _norm_rms_uT(np.array([np.subtract(p["raw_uT"], LOOP_FIELD_uT) for p in good]).reshape(-1, 3))
    cal_err = _norm_rms_uT(np.array([np.subtract(p["b_uT"], LOOP_FIELD_uT) for p in good]).reshape(-1, 3))
    with open(out_path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["cycle", "t_s", "raw_x_uT", "raw_y_uT", "raw_z_uT", "x_uT", "y_uT", "z_uT", "temp_c",
                    "calibrated", "error_count", "fault"])
        for p in published:
            raw = p["raw_uT"] or ("",) * 3
            b = p["b_uT"] or ("",) * 3
            w.writerow([p["cycle"], f"{p['t_s']:.6f}", *raw, *b, "" if p["temp_c"] is None else p["temp_c"],
                        int(p["calibrated"]), p["error_count"], p["fault"] or ""])
    fig = LoopFigures(cycles, published, health, injected, dict(corrector.status), LOOP_FIELD_uT, LOOP_TEMP_C,
                      raw_err, cal_err, Path(out_path))
    say(f"  health: ok {health['samples_ok']}, bus_errors {health['bus_errors']}, timeouts {health['timeouts']}, "
        f"overflows {health['overflows']}, uncalibrated {health['uncalibrated']}, error_count "
        f"{health['error_count']}; loop published all {cycles} cycles")
    say(f"  field error vs truth over the good cycles: raw {raw_err:.3f} uT -> calibrated {cal_err * 1e3:.1f} nT")
    if health["bus_errors"] != injected["bus_errors"] or health["timeouts"] != injected["timeouts"]:
        raise MagError(f"health counters {health} do not match the injected faults {injected}")
    if len(published) != cycles or published[-1]["b_uT"] is None:
        raise MagError("the loop did not keep publishing calibrated samples after the faults")
    return fig


# ------------------------------------------------------------------------------ the whole demo
@dataclass
class DemoResult:
    config: DemoConfig
    probe: ProbeFigures | None = None
    bench: BenchFigures | None = None
    align: AlignFigures | None = None
    fit: FitFigures | None = None
    table: TableFigures | None = None
    holdout: HoldoutFigures | None = None
    loop: LoopFigures | None = None
    step_wall_s: dict[str, float] = field(default_factory=dict)
    wall_s: float = 0.0
    files: list[Path] = field(default_factory=list)

    def figures(self) -> dict:
        """The headline figures (JSON-friendly)."""
        f, h, b, a, t, lp = self.fit, self.holdout, self.bench, self.align, self.table, self.loop
        return {
            "seed": self.config.seed, "seconds": self.config.seconds, "program": self.config.program,
            "probe": {"devices": [f"{d['bus']}@{d['address']:#04x}={d['chip']}" for d in self.probe.devices],
                      "ads1248_id": self.probe.ads1248_id},
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
                        "fixed_vs_float_max_nT": _finite_or_none(h.fixed_vs_float_max_nT),
                        "fixed_vs_float_unquantised_max_nT": _finite_or_none(h.fixed_vs_float_unquantised_max_nT),
                        "offset_s": h.align.offset_s},
            "loop": {"cycles": lp.cycles, "health": lp.health, "injected": lp.injected,
                     "raw_error_norm_uT": lp.raw_error_norm_uT, "cal_error_norm_uT": lp.cal_error_norm_uT},
            "wall_s": {"total": self.wall_s, **self.step_wall_s},
        }


STEPS = ("probe", "bench", "align", "fit", "table", "holdout", "loop")


@contextmanager
def _step(n: int, key: str, title: str, result: DemoResult, say: Say) -> Iterator[None]:
    say(f"\n[{n}/7] {title}")
    t0 = time.perf_counter()
    try:
        yield
    except (MagError, ValueError, OSError, ArithmeticError, KeyError) as exc:
        # one clear line naming the step; the original exception stays attached as __cause__
        raise MagError(f"step {n} ({key}) failed: {type(exc).__name__}: {exc}") from exc
    dt = time.perf_counter() - t0
    result.step_wall_s[key] = dt
    say(f"  ({dt:.1f} s wall)")


def _clean_stale_parts(out_dir: Path, say: Say) -> None:
    for name in ARTEFACTS:
        part = out_dir / (name + ".part")
        if part.exists():
            part.unlink()
            say(f"note: removed {part} left by an interrupted demo run")


def run_demo(config: DemoConfig | None = None, *, say: Say = print) -> DemoResult:
    """Run the seven steps; returns every figure. Raises MagError naming the step that failed."""
    cfg = config or DemoConfig()
    res = DemoResult(cfg)
    out = cfg.out_dir
    t_start = time.perf_counter()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigurationError(f"cannot create output directory {out}: {exc}") from exc
    _clean_stale_parts(out, say)
    say(f"magstack demo: simulated bench, seed {cfg.seed}, calibration session {cfg.seconds:g} s of coil program "
        f"'{cfg.program}', held-out session {cfg.holdout_s:g} s (seed {cfg.seed + 1}); output in {out}/")

    with _step(1, "probe", "probe the simulated bench and read every chip (magstack.drivers.registry)", res, say):
        res.probe = probe_bench(cfg.seed, samples_per_chip=cfg.samples_per_chip, say=say)
        (out / "probe.json").write_text(to_json(res.probe.__dict__, indent=1) + "\n",
                                        encoding="utf-8")
        sh = ", ".join(f"{c} on {b}" for b, c in res.probe.shared_address_chips.items())
        say(f"  -> {len(res.probe.devices)} I2C magnetometers identified (0x1E: {sh}) + HMC1053/ADS1248 on SPI")

    with _step(2, "bench", f"record a bench session: hmc1053 DUT + FVM400 reference, program '{cfg.program}'",
               res, say):
        res.bench = record_session(out / "session.csv", program=cfg.program, seconds=cfg.seconds, seed=cfg.seed,
                                   session_id=1, ref_garble=cfg.ref_garble, instrument_name="demo-bench", say=say)
        say(f"  -> {res.bench.path.name}: {res.bench.rows} rows")

    with _step(3, "align", "align DUT and reference streams (magstack.ground.alignment)", res, say):
        res.align = align_session(res.bench.path, out / "session-paired.csv", say=say)
        say(f"  -> {res.align.paired_path.name}")

    with _step(4, "fit", "fit the calibration (belsten Eq. 3 + optional terms) on the paired session", res, say):
        res.fit = fit_calibration(res.align.paired_path, out / "fit-report.txt",
                                  exclude_steps_uT=cfg.exclude_steps_uT, say=say)
        f = res.fit
        if not f.rmse_norm_uT < f.raw_rmse_norm_uT:
            raise FitError(f"calibrated RMSE {f.rmse_norm_uT:.4f} uT is not below raw {f.raw_rmse_norm_uT:.4f} uT")
        say(f"  -> raw {f.raw_rmse_norm_uT:.3f} uT -> calibrated {f.rmse_norm_uT * 1e3:.1f} nT in-sample, "
            f"{(f.holdout_blocks_norm_uT or math.nan) * 1e3:.1f} nT held out (time blocks); noise floor "
            f"{f.noise_floor_norm_uT * 1e3:.1f} nT  (vector norm of per-axis RMSE) -> {f.report_path.name}")

    with _step(5, "table", "calibration table: save, validate, activate; corrupted copies refused", res, say):
        res.table = table_lifecycle(res.fit.result, out, created_epoch_s=res.bench.end_epoch_s,
                                    description=f"magstack demo fit of {res.bench.path.name} (seed {cfg.seed})",
                                    say=say)

    with _step(6, "holdout", "held-out session: apply the table with the fixed-point applier", res, say):
        res.holdout = holdout_check(res.table.table, out, program=cfg.holdout_program, seconds=cfg.holdout_s,
                                    seed=cfg.seed + 1, ref_garble=cfg.ref_garble,
                                    exclude_steps_uT=cfg.exclude_steps_uT, say=say)

    with _step(7, "loop", "flight sampling loop with the active table, faults injected", res, say):
        res.loop = flight_loop(res.table.store, out / "flight-loop.csv", seed=cfg.seed + 2, cycles=cfg.loop_cycles,
                               period_s=cfg.loop_period_s, say=say)

    res.wall_s = time.perf_counter() - t_start
    res.files = [out / n for n in ARTEFACTS if n != "summary.json"] + [out / "summary.json"]
    (out / "summary.json").write_text(to_json(res.figures(), indent=1) + "\n",
                                      encoding="utf-8")
    for line in summary_lines(res):
        say(line)
    return res


def summary_lines(res: DemoResult) -> list[str]:
    """The closing summary table and the list of files written."""
    f, h, a, t, lp, b = res.fit, res.holdout, res.align, res.table, res.loop, res.bench
    nT = lambda v: "n/a" if v is None or not math.isfinite(v) else f"{v * 1e3:.1f} nT"  # noqa: E731
    rows = [
        ("I2C chips identified / HMC1053 ADC ID", f"{len(res.probe.devices)} / {res.probe.ads1248_id:#x}"),
        ("bench: DUT / reference samples", f"{b.dut_samples} @ {b.dut_rate_hz:.2f} Hz / "
                                           f"{b.ref_samples} @ {b.ref_rate_hz:.2f} Hz"),
        ("clock offset", f"{a.offset_s:+.4f} +- {a.offset_sigma_s:.4f} s"),
        ("axis skew x / y / z", " / ".join(f"{v:+.3f}" for v in a.skew_s) + " s"),
        ("axis map", "identity" if a.axis_map_identity else a.axis_map),
        ("fit model", f"{f.model} ({len(f.held)} held)"),
        ("raw RMSE (fit session)", f"{f.raw_rmse_norm_uT:.3f} uT"),
        ("calibrated RMSE, in-sample", nT(f.rmse_norm_uT)),
        ("calibrated RMSE, held-out time blocks", nT(f.holdout_blocks_norm_uT)),
        ("noise floor (from residuals)", nT(f.noise_floor_norm_uT)),
        ("table crc32 / corrupted copies refused", f"{t.crc32} / {len(t.refused)} of 2"),
        ("held-out session raw -> calibrated", f"{h.raw_rmse_norm_uT:.3f} uT -> {nT(h.cal_rmse_norm_uT)}"),
        ("held-out incl. transitions", f"{h.raw_rmse_all_norm_uT:.3f} uT -> {nT(h.cal_rmse_all_norm_uT)}"),
        ("fixed-point vs float64 applier", f"{h.fixed_vs_float_max_nT:.4f} nT max (same inputs)"),
        ("flight loop: faults injected / counted", f"{sum(lp.injected.values())} / {lp.health['error_count']} "
                                                   f"(bus {lp.health['bus_errors']}, timeout {lp.health['timeouts']})"),
        ("flight loop error vs truth raw -> cal", f"{lp.raw_error_norm_uT:.3f} uT -> {nT(lp.cal_error_norm_uT)}"),
        ("wall time", f"{res.wall_s:.1f} s"),
    ]
    w = max(len(k) for k, _ in rows)
    out = ["", "summary (RMSE = vector norm of per-axis RMSE; measured in this run)", "-" * (w + 40)]
    out += [f"{k:<{w}}  {v}" for k, v in rows]
    out += ["", f"files written to {res.config.out_dir}/:"]
    for p in res.files:
        size = p.stat().st_size if p.exists() else 0
        out.append(f"  {p.name:<24} {size:>9} bytes")
    return out
