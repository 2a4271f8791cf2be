"""``magstack run --config flight.toml [--sim] [--duration S] [--out DIR]``: the flight application.

On the Raspberry Pi it opens the configured buses and runs until Ctrl-C / SIGTERM (or ``--duration``).
With ``--sim`` (or a config whose buses are all ``sim``) the sensors are simulated: with
``--duration`` in virtual time (a simulated day of the example board: 186 s CPU, docs/benchmarks.md
run-sim-day), without it in real time. ``--init DIR`` writes the example configuration and the table it names;
``--example-config`` prints the configuration; ``--scenario`` runs ground actions at virtual times.

Events of severity WARNING_HI and worse (a table rejected, a channel degraded, telemetry that cannot be
written, ...) are shown on stderr while the application runs (rate-limited). Exit status: 0 the run
ended healthy; 1 it ran but ended degraded (a channel degraded at the end, a configured table rejected
and no table active since, telemetry rows or events that could not be written: the reasons are printed);
3 bad configuration; 129 / 130 / 143 stopped by SIGHUP / SIGINT / SIGTERM (files complete).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from magstack.cli.interrupt import EXIT_FOR_SIGNAL, graceful_stop
from magstack.cli.options import finite_float, int_range, nonempty_dir
from magstack.cli.output import CommandResult
from magstack.drivers.errors import ConfigurationError
from magstack.firmware.flight.config import example_config_text, load_config

#: Exit status of a run that ended degraded (the reasons are printed and in ``degraded``).
EXIT_DEGRADED = 1


def register(subparsers) -> None:
    p = subparsers.add_parser("run", help="run the flight application (rate groups, telemetry, events, commands)",
                              description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("--config", metavar="flight.toml", help="flight configuration (see --example-config)")
    p.add_argument("--example-config", action="store_true", help="print the shipped example flight.toml and exit")
    p.add_argument("--init", metavar="DIR", type=Path, default=None,
                   help="write DIR/flight.toml (the example) and the table it names, DIR/tables/hmc1053.json (a "
                        "simulated bench fit of the part), then exit: a configuration that runs as it stands")
    p.add_argument("--sim", action="store_true", help="simulated sensors instead of the configured buses")
    p.add_argument("--duration", type=finite_float(0.0, 366 * 86400.0, lo_open=True, unit="s"), default=None,
                   metavar="S", help="stop after S seconds (virtual time with --sim)")
    p.add_argument("--out", type=nonempty_dir, default=None, metavar="DIR",
                   help="telemetry directory (overrides the config)")
    p.add_argument("--sim-program", default="rotation", metavar="NAME",
                   help="with --sim: coil program giving the simulated field (default rotation; see magstack "
                        "simulate --help); an orbit_* programme starts at the run's clock epoch (it needs "
                        "magstack[ground])")
    p.add_argument("--seed", type=int_range(0, 2**32 - 1), default=0, help="with --sim: simulation seed (default 0)")
    p.add_argument("--scenario", metavar="ground.toml", type=Path, default=None,
                   help="with --sim --duration: ground actions (magstack command lines) at virtual times, run with "
                        "the flight standing still (docs/flight.md)")
    p.add_argument("--example-scenario", action="store_true",
                   help="print the example scenario (the end-to-end scenario of docs/ccsds.md) and exit")
    p.set_defaults(func=run)


def _sim_options(program_name: str, duration_s: float, seed: int):
    """Per-sensor simulator options: one truth source for the run, a simulated bench per timeline."""
    from magstack.sim.coil_programs import PROGRAMS, program
    from magstack.sim.i2c_bench import default_bench
    from magstack.sim.truth_memo import TruthMemo

    if program_name not in PROGRAMS:
        raise ConfigurationError(f"--sim-program: unknown program {program_name!r}; valid: {', '.join(PROGRAMS)}")
    base = program(program_name, max(duration_s, PROGRAMS[program_name].default_duration_s), sessions=1)
    benches: dict[int, object] = {}
    anchored: dict[float, object] = {}

    memo = None if hasattr(base, "at_epoch") else TruthMemo(base)     # a coil programme: evaluated ahead

    def truth_for(clock):
        """The truth on the clock's time line: an orbit programme (``at_epoch``) starts at the clock's epoch of
        monotonic 0, so the field the sensors see belongs to the position and attitude at the telemetry's ``t_s``."""
        if memo is not None:
            return memo
        from magstack.sim.gridded_orbit import GriddedOrbitTruth  # an orbit programme: the ground extra

        epoch0 = round(clock.epoch_s() - clock.monotonic_s(), 3)     # a system clock: calls microseconds apart
        if epoch0 not in anchored:
            anchored[epoch0] = GriddedOrbitTruth(base.at_epoch(epoch0))    # interpolated: one sample at a time
        return anchored[epoch0]

    def options(sensor, clock) -> dict:
        truth = truth_for(clock)
        if sensor.chip == "hmc1053":
            return {"truth": truth, "seed": seed}
        bench = benches.get(id(clock))
        if bench is None:
            bench = benches[id(clock)] = default_bench(clock, truth, seed=seed)
        return {"bench": bench}
    return options


def run(args: argparse.Namespace) -> CommandResult:
    if args.init is not None:
        from magstack.cli.flight_init import init_board

        made = init_board(args.init)
        return CommandResult("run", {"init": made}, [f"wrote {made['config']} and {made['table']} (crc32 "
                                                     f"{made['table_crc32']}, fitted to {made['bench_session']})",
                                                     f"next: magstack run --config {made['config']} --sim "
                                                     "--duration 600"])
    if args.example_scenario:
        from magstack.cli.scenario import example_scenario_text

        return CommandResult("run", {"example_scenario": example_scenario_text()}, [example_scenario_text().rstrip()])
    if args.example_config:
        return CommandResult("run", {"example_config": example_config_text()}, [example_config_text().rstrip()])
    if not args.config:
        raise ConfigurationError("--config is required (or --example-config)")
    cfg = load_config(args.config)
    simulate = args.sim or cfg.simulated
    virtual = simulate and args.duration is not None
    options = _sim_options(args.sim_program, args.duration or 3600.0, args.seed) if simulate else None
    scenario = None
    if args.scenario is not None:
        if not virtual:
            raise ConfigurationError("--scenario needs virtual time: --sim and --duration")
        from magstack.cli.scenario import load_scenario

        scenario = load_scenario(args.scenario, args.duration)
    from magstack.firmware.flight.app import FlightApp  # imported here: --example-config needs none of it

    with graceful_stop() as stop:
        app = FlightApp(cfg, virtual=virtual, simulate=simulate, telemetry_dir=args.out, chip_options=options,
                        stop=stop)
        close_error = ""
        try:
            if scenario is None:
                app.run(args.duration)
            else:
                from magstack.cli.scenario import pauses

                app.run(args.duration, pauses=pauses(scenario, app.stop))
        finally:
            try:
                app.close()
            except Exception as exc:  # noqa: BLE001 - the summary and counters must still be written and shown
                close_error = f"closing the run's files failed: {type(exc).__name__}: {exc}"
            try:
                summary = app.write_summary(Path(app.telemetry_dir) / f"summary-{app.run_id:04d}.json")
            except OSError as exc:          # the disk is still full: the counters are printed below anyway
                summary, summary_error = None, f"{exc.strerror or exc}"
            else:
                summary_error = ""
    counters = app.counters()
    mode = "virtual time" if virtual else "real time"
    lines = [f"flight run {app.run_id} ({'simulated sensors, ' if simulate else ''}{mode}); telemetry in "
             f"{app.telemetry_dir}; summary {summary or 'NOT WRITTEN: ' + summary_error}"]
    if stop.signal_name:
        lines.insert(0, f"{stop.signal_name}: stopped after the cycles under way; every telemetry file closed")
    for g in app.executive.groups:
        st = g.stats
        lines.append(f"  rate group {g.name:<8} {g.rate_hz:7.3f} Hz: {st.runs} runs, {st.overruns} overruns, "
                     f"{st.missed_slots} skipped slots, max execution {st.exec_max_s * 1e3:.1f} ms")
    for name, slot in app.slots.items():
        c = slot.channel.counters()
        cal = slot.channel.corrector.status.get("ok", 0)
        table = f"0x{slot.store.active.crc32:08x}" if slot.store.active else \
            "none (configured table rejected)" if slot.table_rejected else "none"
        lost = slot.telemetry.rows_lost
        lines.append(f"  {name:<12} {c['cycles']} cycles: {c['samples_ok']} good, {cal} calibrated, "
                     f"{c['error_count']} faults{' (DEGRADED)' if c['degraded'] else ''}; table {table}"
                     + (f"; {lost} telemetry rows lost" if lost else ""))
    pk = counters.get("packets")
    if pk is not None:
        lines.append(f"  packets      {pk['written']} written ({pk['bytes']} bytes), {pk['send_errors']} could not be "
                     f"written or sent" + (f", {pk['sync_errors']} fsyncs failed" if pk["sync_errors"] else ""))
    wq = counters["write_queue"]
    if wq is not None:
        lines.append(f"  write queue  {wq['written']} items written behind the rate groups, at most {wq['max_depth']} "
                     f"waiting, {sum(wq['dropped'].values())} dropped for a full queue")
    degraded = counters["degraded"] + ([close_error] if close_error else [])
    if scenario is not None:
        lines += [f"  ground at {d['t_s']:g} s: {d['run']}: exit {d['exit_code']}" for d in scenario.done]
        if scenario.failed:
            degraded = [*degraded, scenario.failed]
    counters["degraded"] = degraded
    lines += [f"  DEGRADED: {why}" for why in degraded]
    if any("cannot read" in s.table_rejected for s in app.slots.values()):
        lines.append("  (magstack run --init DIR writes the example configuration with its table: a simulated "
                     "bench fit)")
    data = {"run_id": app.run_id, "telemetry_dir": str(app.telemetry_dir),
            "summary": None if summary is None else str(summary), "virtual_time": virtual, "simulated": simulate,
            "stopped_by": stop.signal_name, **counters, "degraded": degraded}
    if scenario is not None:
        data["scenario"] = {"file": str(scenario.path), "actions": scenario.done, "failed": scenario.failed or None}
    code = EXIT_FOR_SIGNAL.get(stop.signal_name, 130) if stop.signal_name else EXIT_DEGRADED if degraded else 0
    return CommandResult("run", data, lines, code)
