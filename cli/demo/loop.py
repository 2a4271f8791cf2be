"""Demo step 7: the flight sampling loop on a simulated HMC1053 with the active table.

:class:`~magstack.firmware.sampling_loop.SamplingLoop` with the on-board
:class:`~magstack.firmware.corrector.FixedPointCorrector`; an SPI fault and a stuck DRDY are
injected and must show up in the health counters, and the loop must keep publishing.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magstack.cli.demo.config import LOOP_TEMP_C, LOOP_FIELD_uT, Say, norm_rms_uT, vec_text
from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import MagError
from magstack.firmware.corrector import FixedPointCorrector
from magstack.firmware.sampling_loop import SamplingLoop
from magstack.sim.hmc1053_bridge import build_sim_hmc1053
from magstack.sim.truth_source import StaticTruth

#: Columns of flight-loop.csv.
LOOP_CSV_COLUMNS = ("cycle", "t_s", "raw_x_uT", "raw_y_uT", "raw_z_uT", "x_uT", "y_uT", "z_uT", "temp_c",
                    "calibrated", "error_count", "fault")


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


def _write_csv(path: Path, published: list[dict]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(LOOP_CSV_COLUMNS)
        for p in published:
            raw = p["raw_uT"] or ("",) * 3
            b = p["b_uT"] or ("",) * 3
            w.writerow([p["cycle"], f"{p['t_s']:.6f}", *raw, *b, "" if p["temp_c"] is None else p["temp_c"],
                        int(p["calibrated"]), p["error_count"], p["fault"] or ""])


def flight_loop(store, out_path: Path, *, seed: int, cycles: int, period_s: float, say: Say = print) -> LoopFigures:
    """Run the flight sampling loop on a simulated HMC1053, inject an SPI fault and a stuck DRDY."""
    clock = VirtualClock()
    truth = StaticTruth(LOOP_FIELD_uT, LOOP_TEMP_C)
    board = build_sim_hmc1053(clock, truth=truth, seed=seed)   # the typed board handle, for fault injection
    corrector = FixedPointCorrector(store)
    loop = SamplingLoop(board.front_end, clock, period_s=period_s, corrector=corrector)
    bus_fault_at, drdy_fault_at = cycles // 4, (2 * cycles) // 3
    injected = {"bus_errors": 0, "timeouts": 0}
    published = []
    say(f"  truth B = {vec_text(LOOP_FIELD_uT, '7.2f')} uT at {LOOP_TEMP_C:.1f} degC; period {period_s:g} s; "
        f"SPI fault injected at cycle {bus_fault_at}, DRDY stuck high during cycle {drdy_fault_at}")
    say(f"    {'cycle':>5} {'t_s':>8}  {'raw B (uT)':^27}  {'calibrated B (uT)':^27} {'|err| nT':>9} {'errors':>6}")
    for k in range(cycles):
        store.cycle_boundary()  # the scheduler's table-swap point (nothing staged here)
        if k == bus_fault_at:
            board.spi.inject_fault(1)
            injected["bus_errors"] += 1
        board.adc_model.drdy_stuck_high = k == drdy_fault_at
        if k == drdy_fault_at:
            injected["timeouts"] += 1
        p = loop.step()
        err = (float(np.linalg.norm(np.subtract(p.b_uT, LOOP_FIELD_uT))) * 1e3) if p.b_uT is not None else math.nan
        published.append({"cycle": k, "t_s": p.t_s, "raw_uT": p.raw_uT, "b_uT": p.b_uT, "temp_c": p.temp_c,
                          "calibrated": p.calibrated, "error_count": p.error_count, "fault": p.fault})
        raw = vec_text(p.raw_uT) if p.raw_uT is not None else f"{'-':^26}"
        calv = vec_text(p.b_uT) if p.b_uT is not None else f"{'-':^26}"
        tail = f"  FAULT {p.fault}" if p.fault else ""
        errs = f"{err:9.1f}" if math.isfinite(err) else f"{'-':>9}"
        say(f"    {k:5d} {p.t_s:8.3f}  {raw}  {calv} {errs} {p.error_count:6d}{tail}")
    board.adc_model.drdy_stuck_high = False
    health = loop.health.snapshot()
    good = [p for p in published if p["b_uT"] is not None]
    raw_err = norm_rms_uT(np.array([np.subtract(p["raw_uT"], LOOP_FIELD_uT) for p in good]).reshape(-1, 3))
    cal_err = norm_rms_uT(np.array([np.subtract(p["b_uT"], LOOP_FIELD_uT) for p in good]).reshape(-1, 3))
    _write_csv(out_path, published)
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
