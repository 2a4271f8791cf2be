"""Demo step 7: the flight application's executive on a simulated HMC1053 with the active table.

One rate group on its own virtual clock runs a fault injector and a
:class:`~magstack.firmware.flight.channel.MagChannel` (fixed-point
:class:`~magstack.firmware.corrector.TableCorrector`, session-file telemetry, event log): an SPI fault
and a stuck DRDY are injected and must show up once each in the health counters and the event log,
and the channel must keep publishing calibrated samples. ``flight-loop.csv`` is the channel's
telemetry file (a session file: raw field in ``dut_*``, calibrated in ``cal_*``); ``flight-events.jsonl``
the event log.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magstack.cli.demo.config import LOOP_TEMP_C, LOOP_FIELD_uT, Say, norm_rms_uT, vec_text
from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import MagError
from magstack.firmware.corrector import TableCorrector
from magstack.firmware.flight.channel import MagChannel
from magstack.firmware.flight.events import EventFileSink, EventId, EventLog
from magstack.firmware.flight.executive import Executive, RateGroup
from magstack.firmware.flight.telemetry import ChannelTelemetry
from magstack.sim.hmc1053_bridge import build_sim_hmc1053
from magstack.sim.truth_source import StaticTruth


@dataclass
class LoopFigures:
    cycles: int
    published: list[dict]
    health: dict[str, int]
    injected: dict[str, int]
    corrector_status: dict[str, int]
    events: dict[str, int]
    truth_uT: tuple[float, float, float]
    truth_temp_c: float
    raw_error_norm_uT: float         # RMS over the good cycles of |raw - truth|
    cal_error_norm_uT: float         # same for the calibrated field
    path: Path
    events_path: Path


class _FaultInjector:
    """A component run before the channel in the same rate group: SPI fault at one cycle, DRDY stuck at another."""

    name = "fault-injector"

    def __init__(self, board, bus_fault_at: int, drdy_fault_at: int) -> None:
        self.board, self.bus_fault_at, self.drdy_fault_at = board, bus_fault_at, drdy_fault_at
        self.cycle = -1
        self.injected = {"bus_errors": 0, "timeouts": 0}

    def run(self, now_s: float) -> None:
        self.cycle += 1
        if self.cycle == self.bus_fault_at:
            self.board.spi.inject_fault(1)
            self.injected["bus_errors"] += 1
        self.board.adc_model.drdy_stuck_high = self.cycle == self.drdy_fault_at
        if self.cycle == self.drdy_fault_at:
            self.injected["timeouts"] += 1


def flight_loop(store, out_path: Path, *, seed: int, cycles: int, period_s: float, say: Say = print) -> LoopFigures:
    """Run the flight executive for ``cycles`` periods on a simulated HMC1053; inject an SPI fault and a stuck DRDY."""
    clock = VirtualClock()
    truth = StaticTruth(LOOP_FIELD_uT, LOOP_TEMP_C)
    board = build_sim_hmc1053(clock, truth=truth, seed=seed)   # the typed board handle, for fault injection
    out_path = Path(out_path)
    events_path = out_path.with_name("flight-events.jsonl")
    events_path.unlink(missing_ok=True)
    sink = EventFileSink(events_path)
    events = EventLog(sink=sink)
    corrector = TableCorrector(store)
    published: list[dict] = []
    tlm = ChannelTelemetry(out_path.parent, "flight-loop", run_id=1,
                           metadata={"device_id": store.device_id, "dut_chip": "hmc1053", "bus": "sim",
                                     "source": "magstack demo"}, block_rows=20, events=events)
    offset_s = clock.epoch_s() - clock.monotonic_s()

    def epoch_of(t_s: float) -> float:
        return t_s + offset_s

    channel = MagChannel("hmc1053", board.front_end, corrector, events, epoch_of=epoch_of)
    injector = _FaultInjector(board, cycles // 4, (2 * cycles) // 3)
    group = RateGroup("demo", period_s, clock, [injector, channel])
    group.boundary.append(lambda now: store.cycle_boundary())   # the table-swap point, between cycles

    def tee(rec) -> None:
        k = len(published)
        err = (float(np.linalg.norm(np.subtract(rec.cal_uT, LOOP_FIELD_uT))) * 1e3) if rec.calibrated else math.nan
        published.append({"cycle": k, "t_s": rec.t_s, "raw_uT": rec.raw_uT, "b_uT": rec.cal_uT, "temp_c": rec.temp_c,
                          "calibrated": rec.calibrated, "error_count": rec.error_count, "fault": rec.fault if
                          not rec.good else None, "flags": rec.flags})
        raw = vec_text(rec.raw_uT) if rec.raw_uT is not None else f"{'-':^26}"
        calv = vec_text(rec.cal_uT) if rec.cal_uT is not None else f"{'-':^26}"
        tail = f"  FAULT {rec.fault}" if not rec.good else ""
        errs = f"{err:9.1f}" if math.isfinite(err) else f"{'-':>9}"
        say(f"    {k:5d} {rec.t_s - epoch_of(0.0):8.3f}  {raw}  {calv} {errs} {rec.error_count:6d}{tail}")
        tlm(rec)

    channel.sink = tee
    say(f"  truth B = {vec_text(LOOP_FIELD_uT, '7.2f')} uT at {LOOP_TEMP_C:.1f} degC; rate group {1 / period_s:g} Hz "
        f"(executive, virtual time); SPI fault injected at cycle {injector.bus_fault_at}, DRDY stuck high during "
        f"cycle {injector.drdy_fault_at}")
    say(f"    {'cycle':>5} {'t_s':>8}  {'raw B (uT)':^27}  {'calibrated B (uT)':^27} {'|err| nT':>9} {'errors':>6}")
    ex = Executive([group], events, epoch_of)
    try:
        ex.run_virtual(cycles * period_s)
    finally:
        board.adc_model.drdy_stuck_high = False
        tlm.close()
        sink.close()
    path = tlm.files[0]
    if path != out_path:
        path.replace(out_path)
    health = channel.counters()
    good = [p for p in published if p["b_uT"] is not None]
    raw_err = norm_rms_uT(np.array([np.subtract(p["raw_uT"], LOOP_FIELD_uT) for p in good]).reshape(-1, 3))
    cal_err = norm_rms_uT(np.array([np.subtract(p["b_uT"], LOOP_FIELD_uT) for p in good]).reshape(-1, 3))
    fig = LoopFigures(len(published), published, health, dict(injector.injected), dict(corrector.status),
                      events.snapshot(), LOOP_FIELD_uT, LOOP_TEMP_C, raw_err, cal_err, out_path, events_path)
    say(f"  health: ok {health['samples_ok']}, bus_errors {health['bus_errors']}, timeouts {health['timeouts']}, "
        f"overflows {health['overflows']}, uncalibrated {health['uncalibrated']}, error_count "
        f"{health['error_count']}; events CHAN_BUS_ERROR {events.count(EventId.CHAN_BUS_ERROR)}, CHAN_TIMEOUT "
        f"{events.count(EventId.CHAN_TIMEOUT)}; the channel published all {len(published)} cycles")
    say(f"  field error vs truth over the good cycles: raw {raw_err:.3f} uT -> calibrated {cal_err * 1e3:.1f} nT")
    if (health["bus_errors"] != injector.injected["bus_errors"] or health["timeouts"] != injector.injected["timeouts"]
            or events.count(EventId.CHAN_BUS_ERROR) != injector.injected["bus_errors"]
            or events.count(EventId.CHAN_TIMEOUT) != injector.injected["timeouts"]):
        raise MagError(f"health counters {health} / events do not match the injected faults {injector.injected}")
    if len(published) != cycles or published[-1]["b_uT"] is None:
        raise MagError("the channel did not keep publishing calibrated samples after the faults")
    return fig

