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

Stopping early: ``stop`` (anything with ``is_set()``, e.g. a ``threading.Event`` set by a SIGTERM
handler) ends the session at the next sample; the rows so far are written and the file is closed
and renamed as usual (a complete, shorter session; ``BenchResult.stopped_early``).

The simulated bench (:func:`record_sim_session`) is the one recipe for "a session on simulated
hardware": ``magstack bench --bus sim`` and the demo both call it. Progress goes to a callback
(``progress(elapsed_s, result, final=False)``); the CLI draws it with tqdm. Events are logged
on the ``magstack.hil.bench`` logger.
"""
from __future__ import annotations

import heapq
import logging
import math
import queue
import threading
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
log = logging.getLogger(__name__)


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
    #: True when ``stop`` ended the session before ``seconds`` (the file is still complete and closed)
    stopped_early: bool = False

    def summary(self) -> str:
        err = lambda c: ", ".join(f"{k} {v}" for k, v in sorted(c.items())) or "none"  # noqa: E731
        rate = lambda n: n / self.duration_s if self.duration_s > 0 else math.nan  # noqa: E731
        return (f"{self.path}: {self.rows} rows in {self.duration_s:.1f} s; DUT {self.dut_samples} samples "
                f"({rate(self.dut_samples):.2f} Hz, overflow {self.dut_overflows}, errors: {err(self.dut_errors)}); "
                f"reference {self.ref_samples} samples ({rate(self.ref_samples):.2f} Hz, errors: "
                f"{err(self.ref_errors)}, skipped replies: {err(self.ref_skipped)})"
                + ("" if self.completed else "; INCOMPLETE (.part file kept)")
                + ("; stopped early on request" if self.stopped_early else ""))

    def to_dict(self) -> dict:
        """Stable keys for ``magstack bench --json``."""
        return {"path": str(self.path), "rows": self.rows, "dut_samples": self.dut_samples,
                "ref_samples": self.ref_samples, "dut_errors": dict(self.dut_errors),
                "ref_errors": dict(self.ref_errors), "ref_skipped": dict(self.ref_skipped),
                "dut_overflows": self.dut_overflows, "duration_s": self.duration_s, "completed": self.completed,
                "stopped_early": self.stopped_early}


def _epoch_of(clock: Clock, sample: MagSample) -> float:
    """Host epoch time of a sample whose ``t_s`` is the clock's monotonic time."""
    return clock.epoch_s() - (clock.monotonic_s() - sample.t_s)


def run_bench(dut: Magnetometer, ref: Magnetometer | None, clock: Clock, out: str | Path, *, seconds: float,
              ref_rate_hz: float = 4.0, dut_rate_hz: float | None = None, session_id: int = 0,
              metadata: Mapping[str, str] | None = None,
              currents: Callable[[float], Mapping[str, float]] | None = None, current_names: tuple[str, ...] = (),
              progress: Callable[..., None] | None = None, max_consecutive_errors: int = 10,
              threaded: bool | None = None, block_rows: int = 20, ref_clock: Clock | None = None,
              temp_calibration=None, stop=None, on_sample: Callable[[MagSample], None] | None = None) -> BenchResult:
    """Record ``seconds`` of DUT and reference samples into the session file ``out``.

    ``clock`` times the DUT, ``ref_clock`` (default: the same) the reference; in simulation two
    virtual clocks let each instrument keep its own rate while the other blocks (both start at
    the same epoch; the scheduler always serves the instrument that is behind and writes rows in
    time order). ``ref_rate_hz``: reference query rate; ``dut_rate_hz``: None = every new DUT
    sample, else one read per period. ``currents(t_monotonic_s)`` (optional) gives the named
    currents recorded on every row (a current monitor; the simulated bench uses the coil program).
    ``temp_calibration`` (a :class:`magstack.drivers.hmc1053.TempCalibration` fitted from an earlier
    session against a reference thermometer) is folded into the DUT's board table when the DUT has
    ``calibrate_temperature`` (HMC1053 front end), else applied to each DUT row's ``temp_c``; the
    metadata records it.
    ``stop`` (optional, has ``is_set()``): ends the session early, file closed and complete.
    ``ref`` None records the DUT alone (a hand calibration: no reference instrument; ``ref_*`` cells empty).
    ``on_sample(sample)`` (optional) sees every DUT sample as it is recorded (a live view).
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
    temp_fix = None
    if temp_calibration is not None:
        if hasattr(dut, "calibrate_temperature"):
            dut.calibrate_temperature(temp_calibration)
        else:
            temp_fix = temp_calibration.apply
    scheduler = "threads" if threaded else ("discrete-event, one clock per instrument" if rclock is not clock
                                            else "single-thread interleave")
    meta = {"dut_chip": getattr(dut, "name", "unknown"), "dut_serial": str(getattr(dut, "serial", "unknown")),
            "reference": "none" if ref is None else getattr(ref, "name", "unknown"),
            "ref_rate_hz": "none" if ref is None else f"{ref_rate_hz:g}",
            "dut_rate_hz": "every new sample" if dut_rate_hz is None else f"{dut_rate_hz:g}",
            "alignment_applied": "none (raw host timestamps; one row per sample of either instrument)",
            "start_utc_epoch_s": f"{clock.epoch_s():.3f}", "requested_s": f"{seconds:g}",
            "scheduler": scheduler, "software_version": _software_version(),
            **({"temp_calibration": temp_calibration.describe()} if temp_calibration is not None else {}),
            **dict(metadata or {})}
    res = BenchResult(Path(out))
    writer = SessionWriter(out, meta, current_names=current_names, block_rows=block_rows)
    log.info("bench: recording %g s of %s + %s into %s (%s)", seconds, meta["dut_chip"], meta["reference"],
             writer.part_path, scheduler)
    t0 = clock.monotonic_s()
    rec = _Recorder(res, writer, clock, rclock, currents, session_id, max_consecutive_errors, temp_fix, on_sample)

    def finish_durations() -> None:
        res.duration_s = max(clock.monotonic_s(), rclock.monotonic_s()) - t0
        res.ref_skipped = Counter({k: v for k, v in getattr(ref, "skipped", {}).items() if k != "timeout"})

    try:
        if threaded:
            _run_threaded(dut, ref, clock, rclock, t0, seconds, ref_rate_hz, dut_rate_hz, rec.record, rec.drain,
                          res, progress, stop)
        else:
            _run_event_loop(dut, ref, clock, rclock, t0, seconds, ref_rate_hz, dut_rate_hz, rec.record, rec.drain,
                            res, progress, stop)
        rec.drain(math.inf)
    except BaseException:
        finish_durations()
        try:
            rec.drain(math.inf)
        finally:
            writer.abort()
        raise
    finish_durations()
    writer.close()
    res.completed = True
    res.stopped_early = stop is not None and stop.is_set()
    if res.stopped_early:
        log.warning("bench: stopped on request after %.1f of %g s; %s closed with %d rows", res.duration_s,
                    seconds, res.path, res.rows)
    log.info("bench: %s", res.summary())
    if progress is not None:
        progress(res.duration_s, res, final=True)
    return res


class _Recorder:
    """Turns samples and read errors into counted results and time-ordered session rows.

    ``record`` counts an error (aborting after ``max_consecutive`` in a row on one instrument) or
    buffers a sample as a row stamped with its host epoch; ``drain`` writes the buffered rows up
    to a watermark in time order (rows of the two instruments interleave correctly).
    """

    def __init__(self, res: BenchResult, writer: SessionWriter, dut_clock: Clock, ref_clock: Clock,
                 currents: Callable[[float], Mapping[str, float]] | None, session_id: int,
                 max_consecutive: int, temp_fix: Callable[[float], float] | None = None,
                 on_sample: Callable[[MagSample], None] | None = None) -> None:
        self.res = res
        self.writer = writer
        self.clocks = {"dut": dut_clock, "ref": ref_clock}
        self.currents = currents
        self.session_id = session_id
        self.max_consecutive = max_consecutive
        self.temp_fix = temp_fix          # a temperature-channel calibration applied to each DUT row
        self.on_sample = on_sample        # sees each DUT sample (live view)
        self.consecutive = {"dut": 0, "ref": 0}
        self.pending: list[tuple[float, int, tuple]] = []  # rows not yet written: (t_epoch, seq, row)
        self.seq = 0

    def record(self, kind: str, sample: MagSample | None, err: Exception | None) -> None:
        res = self.res
        if err is not None:
            (res.dut_errors if kind == "dut" else res.ref_errors)[type(err).__name__] += 1
            self.consecutive[kind] += 1
            n = self.consecutive[kind]
            log.debug("bench: %s read failed (%s in a row): %s", kind, n, err)
            if n >= self.max_consecutive:
                log.error("bench: %s failed %d times in a row; aborting, %s kept", kind, n, self.writer.part_path)
                raise MagError(f"{kind} failed {n} times in a row; last: {err}") from err
            return
        assert sample is not None
        self.consecutive[kind] = 0
        t_epoch = _epoch_of(self.clocks[kind], sample)
        cur = dict(self.currents(sample.t_s)) if self.currents is not None else {}
        if kind == "dut":
            res.dut_samples += 1
            res.dut_overflows += bool(sample.overflow)
            temp = math.nan if sample.temp_c is None else float(
                sample.temp_c if self.temp_fix is None else self.temp_fix(sample.temp_c))
            row = (t_epoch, NAN3, sample.b_uT, temp, self.session_id, cur)
            if self.on_sample is not None:
                self.on_sample(sample)
        else:
            res.ref_samples += 1
            row = (t_epoch, sample.b_uT, NAN3, math.nan, self.session_id, cur)
        heapq.heappush(self.pending, (t_epoch, self.seq, row))
        self.seq += 1
        res.rows += 1

    def drain(self, watermark_epoch: float) -> None:
        """Write buffered rows stamped at or before the watermark, in time order."""
        while self.pending and self.pending[0][0] <= watermark_epoch:
            self.writer.write_row(*heapq.heappop(self.pending)[2])


def _read(dev: Magnetometer) -> tuple[MagSample | None, Exception | None]:
    try:
        return dev.read(), None
    except MagError as exc:
        return None, exc


def _run_event_loop(dut, ref, dclock, rclock, t0, seconds, ref_rate_hz, dut_rate_hz, record, drain, res,
                    progress, stop=None) -> None:
    """Single-thread scheduler: serve whichever instrument's next action comes first.

    With one clock this interleaves (a blocking DUT read delays the reference); with one clock
    per instrument the lagging instrument is served until it catches up, so both keep their rates.
    """
    end = t0 + seconds
    ref_period = 1.0 / ref_rate_hz
    next_ref = t0
    next_dut = t0
    same = rclock is dclock
    while stop is None or not stop.is_set():
        td, tr = dclock.monotonic_s(), rclock.monotonic_s()
        ref_at = max(tr, next_ref) if ref is not None else math.inf
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
                        rclock.epoch_s() if ref is not None and max(rclock.monotonic_s(), next_ref) < end
                        else math.inf)
        drain(watermark)
        if progress is not None:
            progress(min(dclock.monotonic_s(), rclock.monotonic_s()) - t0, res)


def _run_threaded(dut, ref, dclock, rclock, t0, seconds, ref_rate_hz, dut_rate_hz, record, drain, res,
                  progress, stop_request=None) -> None:
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

    threads = [threading.Thread(target=worker, args=("dut", dut, dclock,
                                                     None if dut_rate_hz is None else 1.0 / dut_rate_hz),
                                daemon=True)]
    if ref is not None:
        threads.append(threading.Thread(target=worker, args=("ref", ref, rclock, 1.0 / ref_rate_hz), daemon=True))
    for th in threads:
        th.start()
    done = 0
    try:
        while done < len(threads):
            if stop_request is not None and stop_request.is_set():
                stop.set()  # workers finish their current read and post their done marker
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


def record_sim_session(chip: str, out: str | Path, *, program: str, seconds: float, seed: int = 0,
                       session_id: int = 0, ref_rate_hz: float = 4.0, dut_rate_hz: float | None = None,
                       ref_faults: Mapping[str, float] | None = None, ref_noise_uT: float = 0.0,
                       instrument_name: str = "bench", metadata: Mapping[str, str] | None = None,
                       progress: Callable[..., None] | None = None, stop=None) -> tuple[BenchResult, SimBench]:
    """A bench session on the simulated bench: :func:`build_sim_bench` + :func:`run_bench` in virtual time.

    The one recipe behind ``magstack bench --bus sim`` and the demo. Metadata records bus, program,
    seed, reference port and noise, injected reference faults, plus ``metadata``. The simulated
    instrument is closed and unregistered afterwards, also on failure. Returns the result and the
    bench (its clocks give the end time).
    """
    faults = {k: float(v) for k, v in (ref_faults or {}).items() if v}
    sb = build_sim_bench(chip, program=program, seconds=seconds, seed=seed, ref_faults=faults or None,
                         ref_noise_uT=ref_noise_uT, instrument_name=instrument_name)
    try:
        names, cur = truth_currents(sb.truth)
        meta = {"bus": "sim", "program": program, "seed": str(seed), "ref_port": sb.ref_url, "clock": "virtual",
                "ref_noise_uT": f"{ref_noise_uT:g}",
                "ref_faults": ",".join(f"{k}={v:g}" for k, v in sorted(faults.items())) or "none",
                **dict(metadata or {})}
        res = run_bench(sb.dut, sb.ref, sb.clock, out, seconds=seconds, ref_rate_hz=ref_rate_hz,
                        dut_rate_hz=dut_rate_hz, ref_clock=sb.ref_clock, session_id=session_id, metadata=meta,
                        currents=cur, current_names=names, progress=progress, stop=stop)
    finally:
        from magstack.sim.fvm400_model import unregister_instrument

        sb.ref.close()
        unregister_instrument(instrument_name)
    return res, sb


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
