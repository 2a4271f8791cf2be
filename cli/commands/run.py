"""``magstack run --config flight.toml [--sim] [--duration S] [--out DIR]``: the flight application.

On the Raspberry Pi it opens the configured buses and runs until Ctrl-C / SIGTERM (or ``--duration``).
With ``--sim`` (or a config whose buses are all ``sim``) the sensors are simulated: with
``--duration`` in virtual time (a simulated day takes minutes at most), without it in real time.
``--example-config`` prints the shipped example configuration.
"""
from __future__ import annotations

import argparse
import json
import math
import signal
import sys
from pathlib import Path

from magstack.drivers.errors import ConfigurationError
from magstack.firmware.flight.app import FlightApp
from magstack.firmware.flight.config import example_config_text, load_config


def register(subparsers) -> None:
    p = subparsers.add_parser("run", help="run the flight application (rate groups, telemetry, events, commands)",
                              description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("--config", metavar="flight.toml", help="flight configuration (see --example-config)")
    p.add_argument("--example-config", action="store_true", help="print the shipped example flight.toml and exit")
    p.add_argument("--sim", action="store_true", help="simulated sensors instead of the configured buses")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds (virtual time with --sim)")
    p.add_argument("--out", default=None, metavar="DIR", help="telemetry directory (overrides the config)")
    p.add_argument("--sim-program", default="rotation", metavar="NAME",
                   help="with --sim: coil program giving the simulated field (default rotation; see magstack "
                        "simulate --help)")
    p.add_argument("--seed", type=int, default=0, help="with --sim: simulation seed (default 0)")
    p.add_argument("--json", action="store_true", help="print the end-of-run counters as JSON")
    p.set_defaults(func=run)


def _sim_options(program_name: str, duration_s: float, seed: int):
    """Per-sensor simulator options: one truth source for the run, a simulated bench per timeline."""
    from magstack.sim.coil_programs import PROGRAMS, program
    from magstack.sim.i2c_bench import default_bench

    if program_name not in PROGRAMS:
        raise ConfigurationError(f"--sim-program: unknown program {program_name!r}; valid: {', '.join(PROGRAMS)}")
    truth = program(program_name, max(duration_s, PROGRAMS[program_name].default_duration_s), sessions=1)
    benches: dict[int, object] = {}

    def options(sensor, clock) -> dict:
        if sensor.chip == "hmc1053":
            return {"truth": truth, "seed": seed}
        bench = benches.get(id(clock))
        if bench is None:
            bench = benches[id(clock)] = default_bench(clock, truth, seed=seed)
        return {"bench": bench}
    return options


def run(args: argparse.Namespace) -> int:
    if args.example_config:
        sys.stdout.write(example_config_text())
        return 0
    if not args.config:
        raise ConfigurationError("--config is required (or --example-config)")
    if args.duration is not None and not (math.isfinite(args.duration) and 0 < args.duration <= 366 * 86400):
        raise ConfigurationError(f"--duration must be a number of seconds in (0, 366 days], got {args.duration}")
    if args.seed < 0:
        raise ConfigurationError(f"--seed must be >= 0, got {args.seed}")
    cfg = load_config(args.config)
    simulate = args.sim or cfg.simulated
    virtual = simulate and args.duration is not None
    options = _sim_options(args.sim_program, args.duration or 3600.0, args.seed) if simulate else None
    app = FlightApp(cfg, virtual=virtual, simulate=simulate, telemetry_dir=args.out, chip_options=options)
    previous = {}

    def _stop(signum, _frame):
        print(f"magstack run: signal {signum}: stopping after the cycles under way", file=sys.stderr)
        app.stop()

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[sig] = signal.signal(sig, _stop)
        except ValueError:   # not the main thread (tests calling main() from a thread)
            pass
    try:
        app.run(args.duration)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        app.close()
        summary = app.write_summary(Path(app.telemetry_dir) / f"summary-{app.run_id:04d}.json")
    counters = app.counters()
    if args.json:
        print(json.dumps(counters, indent=1, sort_keys=True, default=str))
        return 0
    mode = "virtual time" if virtual else "real time"
    print(f"flight run {app.run_id} ({'simulated sensors, ' if simulate else ''}{mode}); telemetry in "
          f"{app.telemetry_dir}; summary {summary}")
    for g in app.executive.groups:
        st = g.stats
        print(f"  rate group {g.name:<8} {g.rate_hz:7.3f} Hz: {st.runs} runs, {st.overruns} overruns, "
              f"{st.missed_slots} skipped slots, max execution {st.exec_max_s * 1e3:.1f} ms")
    for name, slot in app.slots.items():
        c = slot.channel.counters()
        cal = slot.channel.corrector.status.get("ok", 0)
        table = f"0x{slot.store.active.crc32:08x}" if slot.store.active else "none"
        print(f"  {name:<12} {c['cycles']} cycles: {c['samples_ok']} good, {cal} calibrated, "
              f"{c['error_count']} faults{' (DEGRADED)' if c['degraded'] else ''}; table {table}")
    return 0
