"""Recording a hand-calibration session: the DUT alone (no reference), at a fixed read rate, into a session file.

:func:`record_hand_session` opens the chip (``bus`` "sim": the simulated I2C bench driven by a hand-rotation
truth programme, :mod:`magstack.sim.hand_rotation`; otherwise a real bus, e.g. "1" on a Raspberry Pi), sets an
output data rate above the read rate, and runs :func:`magstack.hil.bench.run_bench` with ``ref=None``: one
thread reads the DUT, the caller's thread writes rows and may draw a view (``on_sample``, ``progress``).
In simulation the clock is a :class:`~magstack.sim.paced_clock.PacedClock` (virtual time kept at ``speed`` x
the wall clock) or, with ``speed`` 0, a plain virtual clock (as fast as the host runs). ``stop`` ends the
recording with a complete file. :class:`SampleStats` counts what a live view needs to prove nothing was lost:
gaps in the sample times and the chip's overrun flags.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from magstack.drivers.clock import SystemClock, VirtualClock
from magstack.drivers.errors import ConfigurationError
from magstack.hil.bench import BenchResult, run_bench

#: Output data rate set for each chip so that reads at up to 150 Hz always find a new sample.
FAST_ODR_HZ = {"lis3mdl": 155.0, "hmc5983": 220.0, "lsm303dlhc": 220.0}


@dataclass
class SampleStats:
    """Samples seen, gaps (an interval over 1.5 read periods: a read the stream lost), first/last sample time
    (s), and ``overwritten``: reads whose chip flagged an overrun, i.e. the chip produced samples between two
    reads (expected: the output data rate is set above the read rate so every read finds a new sample)."""

    period_s: float
    n: int = 0
    gaps: int = 0
    overwritten: int = 0
    first_s: float = math.nan
    last_s: float = math.nan
    largest_gap_s: float = 0.0

    def add(self, sample) -> None:
        t = float(sample.t_s)
        if self.n:
            dt = t - self.last_s
            if dt > 1.5 * self.period_s:
                self.gaps += 1
            self.largest_gap_s = max(self.largest_gap_s, dt)
        else:
            self.first_s = t
        self.last_s = t
        self.n += 1
        self.overwritten += bool(getattr(sample, "extra", {}).get("overrun", False))

    def rate_hz(self) -> float:
        span = self.last_s - self.first_s
        return (self.n - 1) / span if self.n > 1 and span > 0 else math.nan

    def to_dict(self) -> dict:
        return {"samples": self.n, "rate_hz": self.rate_hz(), "gaps": self.gaps, "chip_overwritten": self.overwritten,
                "largest_interval_s": self.largest_gap_s}


@dataclass
class HandSession:
    """What :func:`record_hand_session` produced: the bench result, the sample statistics, the truth
    programme in simulation (None on hardware) and the clock used."""

    result: BenchResult
    stats: SampleStats
    truth: object = None
    clock: object = None
    metadata: dict = field(default_factory=dict)


def record_hand_session(chip: str, bus: str, out: str | Path, *, seconds: float, rate_hz: float = 100.0,
                        program: str = "hand", seed: int = 0, speed: float = 1.0, site=None,
                        epoch_unix_s: float | None = None, on_sample=None, progress=None, stop=None,
                        metadata: dict | None = None, wall=None, stats: SampleStats | None = None) -> HandSession:
    """Record ``seconds`` of DUT samples at ``rate_hz`` into ``out`` (module docstring). ``stats``: a
    :class:`SampleStats` to fill (the caller's view reads it while recording); a new one by default."""
    from magstack.drivers.registry import is_simulated, open_chip

    if chip not in FAST_ODR_HZ:
        raise ConfigurationError(f"hand calibration records an I2C chip ({', '.join(FAST_ODR_HZ)}), not {chip!r}")
    if not (0 < rate_hz <= 150.0):
        raise ConfigurationError(f"rate_hz must be in (0, 150], got {rate_hz!r}")
    stats = stats if stats is not None else SampleStats(1.0 / rate_hz)

    def seen(sample) -> None:
        stats.add(sample)
        if on_sample is not None:
            on_sample(sample)

    meta = {"purpose": "hand calibration (no reference)", **dict(metadata or {})}
    truth = None
    if is_simulated(bus):
        from magstack.sim.hand_rotation import HAND_PROGRAMS, hand_program
        from magstack.sim.i2c_bench import default_bench
        from magstack.sim.paced_clock import PacedClock

        if program not in HAND_PROGRAMS:
            raise ConfigurationError(f"unknown hand programme {program!r}; valid: {', '.join(HAND_PROGRAMS)}")
        kw = {}
        if site is not None:
            kw["site"] = tuple(site)
        if epoch_unix_s is not None:
            kw["epoch_unix_s"] = float(epoch_unix_s)
        truth = hand_program(program, max(float(seconds), 1.0), seed=seed, **kw)
        clock = VirtualClock() if speed == 0 else PacedClock(wall or SystemClock(), speed)
        bench = default_bench(clock, truth, seed=seed)
        dut = open_chip(chip, "sim", clock, bench=bench, odr_hz=FAST_ODR_HZ[chip])
        meta.update({"bus": "sim", "program": program, "seed": str(seed), "clock": "virtual" if speed == 0 else
                     f"virtual paced at {speed:g}x wall time"})
        threaded = speed != 0
    else:
        clock = SystemClock()
        dut = open_chip(chip, bus, clock, odr_hz=FAST_ODR_HZ[chip])
        meta.update({"bus": str(bus), "clock": "system"})
        threaded = True
    res = run_bench(dut, None, clock, out, seconds=seconds, dut_rate_hz=rate_hz, metadata=meta, progress=progress,
                    stop=stop, on_sample=seen, threaded=threaded)
    return HandSession(res, stats, truth, clock, meta)
