"""The demo orchestrator: seven steps in order, each timed, each failure naming its step."""
from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from magstack.cli.demo.bench import AlignFigures, BenchFigures, align_session, record_session
from magstack.cli.demo.config import ARTEFACTS, DemoConfig, Say
from magstack.cli.demo.fit import FitFigures, fit_calibration
from magstack.cli.demo.holdout import HoldoutFigures, holdout_check
from magstack.cli.demo.loop import LoopFigures, flight_loop
from magstack.cli.demo.probe import ProbeFigures, probe_bench
from magstack.cli.demo.report import write_demo_report
from magstack.cli.demo.summary import figures, summary_lines, summary_rows
from magstack.cli.demo.table import TableFigures, table_lifecycle
from magstack.cli.output import dumps
from magstack.drivers.errors import ConfigurationError, MagError
from magstack.firmware.errors import FitError

#: (key, title) of each step, in order.
STEPS = (("probe", "probe the simulated bench and read every chip (magstack.drivers.registry)"),
         ("bench", "record a bench session: hmc1053 DUT + FVM400 reference, program '{program}'"),
         ("align", "align DUT and reference streams (magstack.ground.alignment)"),
         ("fit", "fit the calibration (belsten Eq. 3 + optional terms) on the paired session"),
         ("table", "calibration table: save, validate, activate; corrupted copies refused"),
         ("holdout", "held-out session: apply the table with the fixed-point applier"),
         ("loop", "flight executive with the active table, faults injected"),
         ("report", "HTML report with plots (report.html)"))


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
    #: Wall time of steps 1-7 (s): the figure the report and the console's summary both show.
    wall_s: float = 0.0
    #: Wall time of the whole run, the report included (s): summary.json.
    total_wall_s: float = 0.0
    files: list[Path] = field(default_factory=list)

    def figures(self) -> dict:
        """The headline figures (JSON-friendly)."""
        return figures(self)


@contextmanager
def _step(n: int, result: DemoResult, say: Say, on_step: Callable[[str], None] | None) -> Iterator[None]:
    key, title = STEPS[n - 1]
    if on_step is not None:
        on_step(key)
    say(f"\n[{n}/{len(STEPS)}] {title.format(program=result.config.program)}")
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


def run_demo(config: DemoConfig | None = None, *, say: Say = print,
             on_step: Callable[[str], None] | None = None) -> DemoResult:
    """Run the seven steps; returns every figure. Raises MagError naming the step that failed.

    ``say`` prints a line for a person; ``on_step(key)`` is called as each step starts (a progress bar).
    """
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

    with _step(1, res, say, on_step):
        res.probe = probe_bench(cfg.seed, samples_per_chip=cfg.samples_per_chip, say=say)
        (out / "probe.json").write_text(dumps(res.probe, indent=1) + "\n", encoding="utf-8")
        sh = ", ".join(f"{c} on {b}" for b, c in res.probe.shared_address_chips.items())
        say(f"  -> {len(res.probe.devices)} I2C magnetometers identified (0x1E: {sh}) + HMC1053/ADS1248 on SPI")

    with _step(2, res, say, on_step):
        res.bench = record_session(out / "session.csv", program=cfg.program, seconds=cfg.seconds, seed=cfg.seed,
                                   session_id=1, ref_garble=cfg.ref_garble, instrument_name="demo-bench", say=say)
        say(f"  -> {res.bench.path.name}: {res.bench.rows} rows")

    with _step(3, res, say, on_step):
        res.align = align_session(res.bench.path, out / "session-paired.csv", say=say)
        say(f"  -> {res.align.paired_path.name}")

    with _step(4, res, say, on_step):
        res.fit = f = fit_calibration(res.align.paired_path, out / "fit-report.txt",
                                      exclude_steps_uT=cfg.exclude_steps_uT, say=say)
        if not f.rmse_norm_uT < f.raw_rmse_norm_uT:
            raise FitError(f"calibrated RMSE {f.rmse_norm_uT:.4f} uT is not below raw {f.raw_rmse_norm_uT:.4f} uT")
        held_out = f"{f.holdout_blocks_norm_uT * 1e3:.1f} nT" if f.holdout_blocks_norm_uT is not None else "n/a"
        say(f"  -> raw {f.raw_rmse_norm_uT:.3f} uT -> calibrated {f.rmse_norm_uT * 1e3:.1f} nT in-sample, "
            f"{held_out} held out (time blocks); noise floor {f.noise_floor_norm_uT * 1e3:.1f} nT  "
            f"(vector norm of per-axis RMSE) -> {f.report_path.name}")

    with _step(5, res, say, on_step):
        res.table = table_lifecycle(res.fit.result, out, created_epoch_s=res.bench.end_epoch_s,
                                    description=f"magstack demo fit of {res.bench.path.name} (seed {cfg.seed})",
                                    say=say)

    with _step(6, res, say, on_step):
        res.holdout = holdout_check(res.table.table, out, program=cfg.holdout_program, seconds=cfg.holdout_s,
                                    seed=cfg.seed + 1, ref_garble=cfg.ref_garble,
                                    exclude_steps_uT=cfg.exclude_steps_uT, say=say)

    with _step(7, res, say, on_step):
        res.loop = flight_loop(res.table.store, out / "flight-loop.csv", seed=cfg.seed + 2, cycles=cfg.loop_cycles,
                               period_s=cfg.loop_period_s, say=say)

    res.wall_s = time.perf_counter() - t_start
    with _step(8, res, say, on_step):
        path = write_demo_report(res, out / "report.html", summary_rows(res))
        say(f"  -> {path.name}: open it in a browser (self-contained: plots embedded)")

    res.total_wall_s = time.perf_counter() - t_start
    res.files = [out / n for n in ARTEFACTS if n != "summary.json"] + [out / "summary.json"]
    (out / "summary.json").write_text(dumps(res.figures(), indent=1) + "\n", encoding="utf-8")
    for line in summary_lines(res):
        say(line)
    return res
