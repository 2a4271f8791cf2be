"""``magstack run --init DIR``: a flight configuration that runs as it stands, with the table it names.

Writes ``DIR/flight.toml`` (the shipped example, :func:`~magstack.firmware.flight.config.example_config_text`)
and the calibration table it names, ``DIR/tables/hmc1053.json``, fitted to a simulated bench session of the part
the simulation flies (``DIR/bench/hmc1053-bench.csv``: ``magstack simulate --chip hmc1053 --program
temp_cycling`` with the flight simulation's error model, i.e. the preset without the ADC-side effects the
front-end model does itself), exactly as the commands

    magstack simulate --chip hmc1053 --program temp_cycling --seconds 1200 \\
        --without time_skew,quantization,saturation --sessions 1 --seed 0 --out bench/hmc1053-bench.csv
    magstack fit bench/hmc1053-bench.csv --device-id hmc1053:sn1 --model eq3 --no-holdout \\
        --out tables/hmc1053.json

would. Nothing is overwritten: a directory that already holds one of these files is refused (exit 2), and the
configuration is written last, so a failed fit leaves no configuration naming a missing table.
"""
from __future__ import annotations

from pathlib import Path

from magstack.data.io import atomic_write_text
from magstack.drivers.errors import ConfigurationError

#: The files ``--init`` writes, relative to DIR.
CONFIG, TABLE, BENCH = "flight.toml", "tables/hmc1053.json", "bench/hmc1053-bench.csv"
#: The bench session: the part's flight-simulation error model over a temperature cycle.
SIMULATE = ["simulate", "--chip", "hmc1053", "--program", "temp_cycling", "--seconds", "1200",
            "--without", "time_skew,quantization,saturation", "--sessions", "1", "--seed", "0"]
FIT = ["fit", "--device-id", "hmc1053:sn1", "--model", "eq3", "--no-holdout"]


def _command(argv: list[str]):
    """Run one magstack command (its own parser and checks, no output) and return its CommandResult."""
    from magstack.cli import output
    from magstack.cli.main import build_parser

    args = build_parser(load=argv[0]).parse_args([*argv, "-q"])
    before = dict(output._state)
    output.set_json_mode(True, True)    # the command's own text stays quiet: --init reports what it wrote
    try:
        return args.func(args)
    finally:
        output.set_json_mode(before["json"], before["quiet"])


def init_board(directory: str | Path) -> dict:
    """Write the example configuration and its table into ``directory``; the paths written."""
    from magstack.firmware.flight.config import example_config_text

    d = Path(directory)
    taken = [str(d / p) for p in (CONFIG, TABLE, BENCH) if (d / p).exists()]
    if taken:
        raise ConfigurationError(f"--init {directory}: {', '.join(taken)} exist(s): give an empty or new directory")
    (d / "tables").mkdir(parents=True, exist_ok=True)
    (d / "bench").mkdir(parents=True, exist_ok=True)
    bench, table, config = d / BENCH, d / TABLE, d / CONFIG
    try:
        _command([*SIMULATE, "--out", str(bench)])
        fit = _command([FIT[0], str(bench), *FIT[1:], "--out", str(table)])
    except BaseException:
        for p in (bench, table):
            p.unlink(missing_ok=True)
        raise
    atomic_write_text(config, example_config_text())
    return {"config": str(config), "table": str(table), "bench_session": str(bench),
            "table_crc32": fit.data.get("crc32") if hasattr(fit, "data") else None}
