"""Bench session runner: a DUT magnetometer and the FVM400 reference, side by side, to a session file.

Each instrument runs at its own rate and every sample becomes one row of the session file
(:mod:`magstack.data.session`), host-timestamped (Unix epoch, UTC, through the injected clock): a DUT
row carries ``dut_*_uT`` and ``temp_c`` with empty ``ref_*`` cells, a reference row the
opposite. Nothing is resampled here; ``magstack align SESSION`` and ``import``-style pairing
work on the raw interleaved streams.

Scheduling: with a real clock each instrument is read by its own thread (the HMC1053 front end
blocks for a whole conversion cycle, which must not hold up the 4 Hz reference). In simulation a
single-thread discrete-event loop serves whichever instrument's next action comes first; with one
:class:`~magstack.drivers.clock.VirtualClock` per instrument (``ref_clock``, as :func:`build_sim_bench`
sets up) the lagging one catches up while the other blocks, so both keep their rates, and rows
pass through a time-ordered buffer. With one shared virtual clock a blocking DUT read delays the
reference (its timestamps stay exact).

Fault responses: a reference reply that is garbled, partial, out of range or in the wrong units
is skipped by the driver and counted; a reference timeout or DUT bus error is counted and the
session continues; ``max_consecutive_errors`` failures in a row on one instrument abort the
session, leaving the crash-safe ``.part`` file with every row so far.
"""
from __future__ import annotations

import heapq
import math
import queue
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magstack.data.pairing import split_streams
from magstack.data.session import SessionWriter
from magstack.drivers.clock import Clock, VirtualClock
from magstack.drivers.errors import ConfigurationError, MagError
from magstack.drivers.magnetometer import Magnetometer, MagSample

NAN3 = (math.nan, math.nan, math.nan)


@dataclass
class BenchResult:
    """What a session produced."""

    path: Path
    rows: int = 0
    dut_samples: int = 0
    ref_samples: int = 0
    dut_errors: Counter = field(default_factory=Counter)
    ref_errors: Counter = field(default_factory=Counter)
    ref_skipped: Counter = field(default_factory=Counter)
    dut_overflows: int = 0
    duration_s: float = 0.0
    completed: bool = False

    def summary(self) -> str:
        err = lambda c: ", ".join(f"{k} {v}" for k, v in sorted(c.items())) or "none"  # noqa: E731
        rate = lambda n: n / self.duration_s if self.duration_s > 0 else math.nan  # noqa: E731
        return (f"{self.path}: {self.rows} rows in {self.duration_s:.1f} s; DUT {self.dut_samples} samples "
                f"({rate(self.dut_samples):.2f} Hz, overflow {self.dut_overflows}, errors: {err(self.dut_errors)}); "
                f"reference {self.ref_samples} samples ({rate(self.ref_samples):.2f} Hz, errors: "
                f"{err(self.ref_errors)}, skipped replies: {err(self.ref_skipped)})"
                + ("" if self.completed else "; INCOMPLETE (.part file kept)"))


def _epoch_of(clock: Clock, sample: MagSample) -> float:
    """Host epoch time of a sample whose ``t_s`` is the clock's monotonic time."""
    return clock.epoch_s() - (clock.monotonic_s() - sample.t_s)


class ProgressLine:
    """A one-line text progress display on a stream (throttled in wall time)."""

    def __init__(self, total_s: float, stream=None, min_interval_s: float = 0.2) -> None:
        self.total_s = total_s
        self.stream = stream if stream is not None else sys.stderr
        self.min_interval_s = min_interval_s
        self._last = -math.inf

    def __call__(self, elapsed_s: float, res: BenchResult, final: bool = False) -> None:
        now = time.monotonic()
        if not final and now - self._last < self.min_interval_s:
            return
        self._last = now
        frac = min(1.0, max(0.0, elapsed_s / self.total_s)) if self.total_s > 0 else 1.0
        bar = "#" * int(frac * 30)
        errs = sum(res.dut_errors.values()) + sum(res.ref_errors.values())
        skipped = sum(res.ref_skipped.values())
        self.stream.write(f"\r[{bar:<30}] {frac:4.0%} {elapsed_s:7.1f}/{self.total_s:.0f} s  dut {res.dut_samples}"
                          f"  ref {res.ref_samples}  skipped {skipped}  errors {errs}" + ("\n" if final else ""))
        self.stream.flush()


def run_bench(dut: Magnetometer, ref: Magnetometer, clock: Clock, out: str | Path, *, seconds: float,
              ref_rate_hz: float = 4.0, dut_rate_hz: float | None = None, session_id: int = 0,
              metadata: Mapping[str, str] | None = None,
              currents: Callable[[float], Mapping[str, float]] | None = None, current_names: tuple[str, ...] = (),
              progress: Callable[..., None] | None = None, max_consecutive_errors: int = 10,
              threaded: bool | None = None, block_rows: int = 20, ref_clock: Clock | None = None) -> BenchResult:
    """Record ``seconds`` of DUT and reference samples into the session file ``out``.

    ``clock`` times the DUT, ``ref_clock`` (default: the same) the reference; in simulation two
    virtual clocks let each instrument keep its own rate while the other blocks (both start at
    the same epoch; the scheduler always serves the instrument that is behind and writes rows in
    time order). ``ref_rate_hz``: reference query rate; ``dut_rate_hz``: None = every new DUT
    sample, else one read per period. ``currents(t_monotonic_s)`` (optional) gives the named
    currents recorded on every row (a current monitor; the simulated bench uses the coil program).
    """
    if not (seconds > 0 and math.isfinite(seconds)):
        raise ConfigurationError(f"seconds must be > 0, got {seconds}")
    if not (ref_rate_hz > 0 and math.isfinite(ref_rate_hz)):
        raise ConfigurationError(f"ref_rate_hz must be > 0, got {ref_rate_hz}")
    if dut_rate_hz is not None and not (dut_rate_hz > 0 and math.isfinite(dut_rate_hz)):
        raise ConfigurationError(f"dut_rate_hz must be > 0, got {dut_rate_hz}")
    if max_consecutive_errors < 1:
        raise ConfigurationError("max_consecutive_errors must be >= 1")
    rclock = ref_clock if ref_clock is not None else clock
    if threaded is None:
        threaded = not (isinstance(clock, VirtualClock) or isinstance(rclock, VirtualClock))
    if rclock is not clock:
        if abs((clock.epoch_s() - clock.monotonic_s()) - (rclock.epoch_s() - rclock.monotonic_s())) > 1e-6:
            raise ConfigurationError("DUT and reference clocks must share one epoch anchor")
        lag = clock.monotonic_s() - rclock.monotonic_s()  # opening/configuring used different times
        (rclock if lag > 0 else clock).sleep_s(abs(lag))
    scheduler = "threads" if threaded else ("discrete-event, one clock per instrument" if rclock is not clock
                                            else "single-thread interleave")
    meta = {"dut_chip": getattr(dut, "name", "unknown"), "dut_serial": str(getattr(dut, "serial", "unknown")),
            "reference": getattr(ref, "name", "unknown"), "ref_rate_hz": f"{ref_rate_hz:g}",
            "dut_rate_hz": "every new sample" if dut_rate_hz is None else f"{dut_rate_hz:g}",
            "alignment_applied": "none (raw host timestamps; one row per sample of either instrument)",
            "start_utc_epoch_s": f"{clock.epoch_s():.3f}", "requested_s": f"{seconds:g}",
            "scheduler": scheduler, "software_version": _software_version(), **dict(metadata or {})}
    res = BenchResult(Path(out))
    writer = SessionWriter(out, meta, current_names=current_names, block_rows=block_rows)
    t0 = clock.monotonic_s()
    consecutive = {"dut": 0, "ref": 0}
    pending: list[tuple[float, int, tuple]] = []  # rows not yet written: (t_epoch, seq, row)
    seq = [0]

    def record(kind: str, sample: MagSample | None, err: Exception | None) -> None:
        if err is not None:
            bucket = res.dut_errors if kind == "dut" else res.ref_errors
            bucket[type(err).__name__] += 1
            consecutive[kind] += 1
            if consecutive[kind] >= max_consecutive_errors:
                raise MagError(f"{kind} failed {consecutive[kind]} times in a row; last: {err}") from err
            return
        assert sample is not None
        consecutive[kind] = 0
        t_epoch = _epoch_of(clock if kind == "dut" else rclock, sample)
        cur = dict(currents(sample.t_s)) if currents is not None else {}
        if kind == "dut":
            res.dut_samples += 1
            res.dut_overflows += bool(sample.overflow)
            temp = math.nan if sample.temp_c is None else float(sample.temp_c)
            row = (t_epoch, NAN3, sample.b_uT, temp, session_id, cur)
        else:
            res.ref_samples += 1
            row = (t_epoch, sample.b_uT, NAN3, math.nan, session_id, cur)
        heapq.heappush(pending, (t_epoch, seq[0], row))
        seq[0] += 1
        res.rows += 1

    def drain(watermark_epoch: float) -> None:
        """Write buffered rows stamped at or before the watermark, in time order."""
        while pending and pending[0][0] <= watermark_epoch:
            writer.write_row(*heapq.heappop(pending)[2])

    def finish_durations() -> None:
        res.duration_s = max(clock.monotonic_s(), rclock.monotonic_s()) - t0
        res.ref_skipped = Counter({k: v for k, v in getattr(ref, "skipped", {}).items() if k != "timeout"})

    try:
        if threaded:
            _run_threaded(dut, ref, clock, rclock, t0, seconds, ref_rate_hz, dut_rate_hz, record, drain, res,
                          progress)
        else:
            _run_event_loop(dut, ref, clock, rclock, t0, seconds, ref_rate_hz, dut_rate_hz, record, drain, res,
                            progress)
        drain(math.inf)
    except BaseException:
        finish_durations()
        try:
            drain(math.inf)
        finally:
            writer.abort()
        raise
    finish_durations()
    writer.close()
    res.completed = True
    if progress is not None:
        progress(res.duration_s, res, final=True)
    return res


def _read(dev: Magnetometer) -> tuple[MagSample | None, Exception | None]:
    try:
        return dev.read(), None
    except MagError as exc:
        return None, exc


def _run_event_loop(dut, ref, dclock, rclock, t0, seconds, ref_rate_hz, dut_rate_hz, record, drain, res,
                    progress) -> None:
    """Single-thread scheduler: serve whichever instrument's next action comes first.

    With one clock this interleaves (a blocking DUT read delays the reference); with one clock
    per instrument the lagging instrument is served until it catches up, so both keep their rates.
    """
    end = t0 + seconds
    ref_period = 1.0 / ref_rate_hz
    next_ref = t0
    next_dut = t0
    same = rclock is dclock
    while True:
        td, tr = dclock.monotonic_s(), rclock.monotonic_s()
        ref_at = max(tr, next_ref)
        dut_at = max(td, next_dut) if dut_rate_hz is not None else td
        if ref_at >= end and dut_at >= end:
            return
        if ref_at < end and ref_at <= dut_at:
            if tr < ref_at:
                rclock.sleep_s(ref_at - tr)
            record("ref", *_read(ref))
            next_ref = ref_at + ref_period
        elif dut_rate_hz is not None:
            if td < dut_at:
                dclock.sleep_s(dut_at - td)
            record("dut", *_read(dut))
            next_dut = dut_at + 1.0 / dut_rate_hz
        elif dut.data_ready():
            record("dut", *_read(dut))
        else:
            wait = 0.001 if not same or ref_at >= end else min(0.001, ref_at - td)
            dclock.sleep_s(max(wait, 1e-6))
        # nothing earlier than either clock's present can still arrive
        watermark = min(dclock.epoch_s() if dclock.monotonic_s() < end else math.inf,
                        rclock.epoch_s() if max(rclock.monotonic_s(), next_ref) < end else math.inf)
        drain(watermark)
        if progress is not None:
            progress(min(dclock.monotonic_s(), rclock.monotonic_s()) - t0, res)


def _run_threaded(dut, ref, dclock, rclock, t0, seconds, ref_rate_hz, dut_rate_hz, record, drain, res,
                  progress) -> None:
    events: queue.Queue = queue.Queue()
    stop = threading.Event()

    def worker(kind: str, dev, clock, period: float | None) -> None:
        nxt = clock.monotonic_s()
        while not stop.is_set() and clock.monotonic_s() - t0 < seconds:
            if period is not None:
                wait = nxt - clock.monotonic_s()
                if wait > 0:
                    clock.sleep_s(wait)
                nxt = max(nxt + period, clock.monotonic_s())
            sample, err = _read(dev)
            events.put((kind, sample, err))
        events.put((kind, None, None))  # done marker

    threads = [threading.Thread(target=worker, args=("ref", ref, rclock, 1.0 / ref_rate_hz), daemon=True),
               threading.Thread(target=worker, args=("dut", dut, dclock,
                                                     None if dut_rate_hz is None else 1.0 / dut_rate_hz),
                                daemon=True)]
    for th in threads:
        th.start()
    done = 0
    try:
        while done < 2:
            try:
                kind, sample, err = events.get(timeout=0.2)
            except queue.Empty:
                if progress is not None:
                    progress(dclock.monotonic_s() - t0, res)
                continue
            if sample is None and err is None:
                done += 1
                continue
            record(kind, sample, err)
            drain(math.inf)  # rows in arrival order
            if progress is not None:
                progress(dclock.monotonic_s() - t0, res)
    finally:
        stop.set()
        for th in threads:
            th.join(timeout=5.0)


def _software_version() -> str:
    from magstack import __version__

    return f"magstack {__version__}"


# ------------------------------------------------------------------------ simulated bench
#: How each chip's simulated factory receives the bench truth source (chip -> builder of kwargs).
def _sim_dut_kwargs(chip: str, clock, truth, seed: int) -> dict:
    if chip == "hmc1053":
        return {"truth": truth, "seed": seed}
    from magstack.sim.i2c_bench import default_bench

    return {"bench": default_bench(clock, truth, seed=seed)}


@dataclass
class SimBench:
    """The simulated bench: one clock, one coil program, the DUT and a registered FVM400 model."""

    clock: VirtualClock
    ref_clock: VirtualClock
    truth: object
    dut: Magnetometer
    ref: Magnetometer
    ref_model: object
    ref_url: str


def build_sim_bench(chip: str, *, program: str = "steps_x", seconds: float = 60.0, seed: int = 0,
                    ref_faults: Mapping[str, float] | None = None, ref_noise_uT: float = 0.0,
                    ref_probe_from_truth=None, instrument_name: str = "bench") -> SimBench:
    """Coil program -> truth -> DUT (via magstack.drivers.registry) and FVM400 model (``fvm400sim://<name>``)."""
    from magstack.drivers.fvm400 import FVM400
    from magstack.drivers.registry import open_chip
    from magstack.sim.coil_programs import program as build_program
    from magstack.sim.fvm400_model import FVM400Faults, FVM400Model, register_instrument

    clock = VirtualClock()
    ref_clock = VirtualClock()  # same epoch anchor; lets the reference keep 4 Hz while the DUT blocks
    try:
        truth = build_program(program, seconds, sessions=1)
    except ValueError as exc:
        raise ConfigurationError(str(exc)) from None
    model = FVM400Model(truth, ref_clock, probe_from_truth=ref_probe_from_truth, noise_uT=ref_noise_uT, seed=seed,
                        faults=FVM400Faults(**dict(ref_faults or {})))
    register_instrument(instrument_name, model)
    url = f"fvm400sim://{instrument_name}"
    ref = FVM400.open(url, ref_clock)
    dut = open_chip(chip, "sim", clock, **_sim_dut_kwargs(chip, clock, truth, seed))
    return SimBench(clock, ref_clock, truth, dut, ref, model, url)


def truth_currents(truth) -> tuple[tuple[str, ...], Callable[[float], Mapping[str, float]] | None]:
    """Current names and a lookup for a truth source that has named currents (else none)."""
    names = tuple(sorted(truth.currents_A(0.0)))
    if not names:
        return (), None
    return names, lambda t: {k: float(v) for k, v in truth.currents_A(t).items()}


def paired_view(session) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t_dut, dut_uT, t_ref, ref_uT) of a raw bench session (:func:`magstack.data.pairing.split_streams`)."""
    st = split_streams(session)
    return st.t_dut_s, st.dut_uT, st.t_ref_s, st.ref_uT
