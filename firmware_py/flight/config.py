"""``flight.toml``: the flight application's configuration, read with tomllib into validated dataclasses.

Everything is checked before anything starts: an unknown key, a missing required key, a wrong
type, an unknown chip or rate group, a rate the sensor cannot deliver, two rate groups sharing one
bus, or a non-positive size raises :class:`FlightConfigError` naming the file and the key path
(``sensor[1].rate_group``). The shipped example is ``flight.example.toml`` beside this module
(``magstack run --example-config`` prints it).
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from magstack.firmware.errors import FlightConfigError
from magstack.firmware.flight.intake import UnsafeInput, read_bounded
from magstack.firmware.flight.writer import DEFAULT_CAPACITY

EXAMPLE_NAME = "flight.example.toml"
#: Largest configuration file read.
MAX_CONFIG_BYTES = 1 << 20
I2C_CHIPS = ("lis3mdl", "hmc5983", "lsm303dlhc")
CHIPS = (*I2C_CHIPS, "hmc1053")


@dataclass(frozen=True)
class RateGroupConfig:
    name: str
    rate_hz: float

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class SensorConfig:
    name: str
    chip: str
    bus: str
    rate_group: str
    device_id: str
    table: str | None = None                       # calibration table path (relative to the config file)
    options: dict[str, Any] = field(default_factory=dict)   # driver options (range_uT, odr_hz, table, ...)
    max_field_uT: float = 1000.0
    max_rate_uT_per_s: float = 2000.0
    reinit_after: int = 3
    degrade_after: int = 3


@dataclass(frozen=True)
class FlightConfig:
    path: Path
    name: str
    telemetry_dir: Path
    command_dir: Path | None
    rotate_bytes: int
    block_rows: int
    rate_groups: tuple[RateGroupConfig, ...]
    sensors: tuple[SensorConfig, ...]
    ccsds: Any = None          # CcsdsConfig of the [ccsds] table (firmware/flight/ccsds.py), None without one
    table_roots: tuple[Path, ...] = ()              # tables may only be read inside these (default: config dir)
    refit_roots: tuple[Path, ...] = ()              # start_refit inputs only inside these (default: config dir)
    command_rate_hz: float = 2.0                    # the command spool's own rate group
    commands_per_cycle: int = 8                     # command files taken per spool cycle
    write_queue: int = DEFAULT_CAPACITY             # records, packets and event lines waiting to be written

    def group(self, name: str) -> RateGroupConfig:
        return next(g for g in self.rate_groups if g.name == name)

    @property
    def simulated(self) -> bool:
        return all(s.bus.strip().lower().startswith("sim") for s in self.sensors)


# ------------------------------------------------------------------------ checks
class _Ctx:
    def __init__(self, path: Path) -> None:
        self.path = path

    def err(self, key: str, msg: str) -> FlightConfigError:
        return FlightConfigError(f"{self.path}: {key}: {msg}")


def _table(c: _Ctx, key: str, obj: Any, required: set[str], optional: set[str]) -> dict:
    if not isinstance(obj, dict):
        raise c.err(key, f"must be a table, got {type(obj).__name__}")
    missing = sorted(required - obj.keys())
    if missing:
        raise c.err(key, f"missing required key(s) {missing}")
    unknown = sorted(obj.keys() - required - optional)
    if unknown:
        valid = ", ".join(sorted(required | optional))
        raise c.err(key, f"unknown key(s) {unknown}; valid: {valid}")
    return obj


def _str(c: _Ctx, key: str, v: Any) -> str:
    if not isinstance(v, str) or not v.strip():
        raise c.err(key, f"must be a non-empty string, got {v!r}")
    return v.strip()


def _num(c: _Ctx, key: str, v: Any, lo: float, hi: float, *, integer: bool = False) -> float:
    ok = isinstance(v, int) if integer else isinstance(v, (int, float))
    if isinstance(v, bool) or not ok or not math.isfinite(v) or not lo <= v <= hi:
        kind = "an integer" if integer else "a number"
        raise c.err(key, f"must be {kind} in [{lo:g}, {hi:g}], got {v!r}")
    return v


def _max_rate_hz(chip: str, options: dict) -> float:
    """Fastest rate the sensor can deliver new samples at, from the driver tables."""
    if chip == "hmc1053":
        from magstack.drivers.hmc1053 import DEFAULT_FRONT_END, FRONT_ENDS

        if set(options) - {"table"}:
            raise ValueError(f"unknown option(s) {sorted(set(options) - {'table'})} for hmc1053; valid: table")
        name = options.get("table", DEFAULT_FRONT_END)
        if name not in FRONT_ENDS:
            raise ValueError(f"unknown front-end table {name!r}; valid: {', '.join(FRONT_ENDS)}")
        return 1.0 / FRONT_ENDS[name].nominal_cycle_s()
    from magstack.drivers.registry import i2c_driver_class

    cls = i2c_driver_class(chip)
    allowed = _driver_options(cls)
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise ValueError(f"unknown option(s) {unknown} for {chip}; valid: {', '.join(sorted(allowed))}")
    table = cls.table
    if "range_uT" in options:
        table.range_option(options["range_uT"])
    odr = options.get("odr_hz", table.default_odr_hz)
    return float(table.rate_option(odr).odr_hz)


def _driver_options(cls) -> set[str]:
    """Keyword options a driver class accepts (its and its bases' keyword-only parameters)."""
    import inspect

    names: set[str] = set()
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        for prm in inspect.signature(init).parameters.values():
            if prm.kind is prm.KEYWORD_ONLY:
                names.add(prm.name)
    return names


def _bus_key(bus: str) -> str:
    """Which physical bus a spec uses: "sim" specs never clash; "/dev/i2c-1" == "1"; "spi0.0,..." -> spi0.0."""
    b = bus.strip().lower()
    if b.startswith("sim"):
        return ""
    if b.startswith("spi"):
        return b.split(",")[0]
    return "i2c-" + b.rsplit("-", 1)[-1]


def parse_config(doc: dict, path: Path) -> FlightConfig:
    c = _Ctx(path)
    top = _table(c, "document", doc, {"flight", "rate_group", "sensor"}, {"ccsds"})
    fl = _table(c, "flight", top["flight"], {"name", "telemetry_dir"},
                {"command_dir", "rotate_mb", "block_rows", "table_roots", "refit_roots", "command_rate_hz",
                 "commands_per_cycle", "write_queue"})
    base = path.parent
    groups_raw = top["rate_group"]
    if not isinstance(groups_raw, list) or not groups_raw:
        raise c.err("rate_group", "must be a non-empty array of tables ([[rate_group]])")
    groups = []
    for i, g in enumerate(groups_raw):
        k = f"rate_group[{i}]"
        g = _table(c, k, g, {"name", "rate_hz"}, set())
        groups.append(RateGroupConfig(_str(c, f"{k}.name", g["name"]), float(_num(c, f"{k}.rate_hz", g["rate_hz"],
                                                                                  1e-3, 1000.0))))
    names = [g.name for g in groups]
    if len(set(names)) != len(names):
        raise c.err("rate_group", f"names must be unique: {names}")
    sensors_raw = top["sensor"]
    if not isinstance(sensors_raw, list) or not sensors_raw:
        raise c.err("sensor", "must be a non-empty array of tables ([[sensor]])")
    sensors = []
    bus_group: dict[str, tuple[str, str]] = {}
    for i, s in enumerate(sensors_raw):
        k = f"sensor[{i}]"
        s = _table(c, k, s, {"name", "chip", "bus", "rate_group", "device_id"},
                   {"table", "options", "max_field_uT", "max_rate_uT_per_s", "reinit_after", "degrade_after"})
        chip = _str(c, f"{k}.chip", s["chip"]).lower()
        if chip not in CHIPS:
            raise c.err(f"{k}.chip", f"unknown chip {chip!r}; valid: {', '.join(CHIPS)}")
        group = _str(c, f"{k}.rate_group", s["rate_group"])
        if group not in names:
            raise c.err(f"{k}.rate_group", f"no rate group {group!r}; defined: {', '.join(names)}")
        options = s.get("options", {})
        if not isinstance(options, dict):
            raise c.err(f"{k}.options", "must be a table of driver options")
        bus = _str(c, f"{k}.bus", s["bus"])
        rate = next(g.rate_hz for g in groups if g.name == group)
        try:
            fastest = _max_rate_hz(chip, options)
        except Exception as exc:  # noqa: BLE001 - a bad option value is a config error here
            raise c.err(f"{k}.options", f"invalid driver options: {exc}") from None
        if rate > fastest * 1.001:
            raise c.err(f"{k}.rate_group", f"{chip} delivers new samples at most at {fastest:.3g} Hz with these "
                                           f"options; rate group {group!r} runs at {rate:g} Hz")
        bk = _bus_key(bus)
        if bk:
            if bk in bus_group and bus_group[bk][0] != group:
                raise c.err(f"{k}.rate_group", f"bus {bus!r} is also used by sensor {bus_group[bk][1]!r} in rate group "
                                               f"{bus_group[bk][0]!r}: sensors on one bus must share a rate group")
            bus_group.setdefault(bk, (group, s["name"]))
        table = s.get("table")
        if table is not None:
            table = str(base / _str(c, f"{k}.table", table))
        sensors.append(SensorConfig(
            name=_str(c, f"{k}.name", s["name"]), chip=chip, bus=bus, rate_group=group,
            device_id=_str(c, f"{k}.device_id", s["device_id"]), table=table, options=dict(options),
            max_field_uT=float(_num(c, f"{k}.max_field_uT", s.get("max_field_uT", 1000.0), 1.0, 1e5)),
            max_rate_uT_per_s=float(_num(c, f"{k}.max_rate_uT_per_s", s.get("max_rate_uT_per_s", 2000.0), 1e-3,
                                         1e7)),
            reinit_after=int(_num(c, f"{k}.reinit_after", s.get("reinit_after", 3), 1, 1000, integer=True)),
            degrade_after=int(_num(c, f"{k}.degrade_after", s.get("degrade_after", 3), 1, 1000, integer=True))))
    snames = [s.name for s in sensors]
    if len(set(snames)) != len(snames):
        raise c.err("sensor", f"names must be unique: {snames}")
    for s in sensors:
        if not all(ch.isalnum() or ch in "_-" for ch in s.name):
            raise c.err("sensor.name", f"{s.name!r}: use letters, digits, '_' or '-' (it names telemetry files)")
    cmd = fl.get("command_dir")
    from magstack.firmware.flight.ccsds import parse_ccsds  # it uses this module's checks

    def roots(key: str) -> tuple[Path, ...]:
        v = fl.get(key, ["."])
        if not isinstance(v, list) or not v:
            raise c.err(f"flight.{key}", "must be a non-empty array of directories (relative to this file)")
        return tuple(base / _str(c, f"flight.{key}[{i}]", d) for i, d in enumerate(v))
    return FlightConfig(
        path=path, name=_str(c, "flight.name", fl["name"]),
        telemetry_dir=base / _str(c, "flight.telemetry_dir", fl["telemetry_dir"]),
        command_dir=None if cmd is None else base / _str(c, "flight.command_dir", cmd),
        rotate_bytes=int(_num(c, "flight.rotate_mb", fl.get("rotate_mb", 16), 0.01, 4096) * (1 << 20)),
        block_rows=int(_num(c, "flight.block_rows", fl.get("block_rows", 50), 1, 100_000, integer=True)),
        rate_groups=tuple(groups), sensors=tuple(sensors), ccsds=parse_ccsds(c, top.get("ccsds"), base,
                                                                   cmd is not None),
        table_roots=roots("table_roots"), refit_roots=roots("refit_roots"),
        command_rate_hz=float(_num(c, "flight.command_rate_hz", fl.get("command_rate_hz", 2.0), 0.01, 100.0)),
        commands_per_cycle=int(_num(c, "flight.commands_per_cycle", fl.get("commands_per_cycle", 8), 1, 1000,
                                    integer=True)),
        write_queue=int(_num(c, "flight.write_queue", fl.get("write_queue", DEFAULT_CAPACITY), 16, 1_000_000,
                             integer=True)))


def check_directories(cfg: FlightConfig, telemetry_dir: Path | None = None) -> None:
    """The telemetry, command and telecommand directories must be three different directories (the command
    spool would take the telemetry directory's files as orders, results and packets would mix);
    FlightConfigError otherwise. ``telemetry_dir``: the one the run uses (``--out``), default the config's."""
    import os

    dirs = {"flight.telemetry_dir": telemetry_dir if telemetry_dir is not None else cfg.telemetry_dir,
            "flight.command_dir": cfg.command_dir, "ccsds.tc_dir": getattr(cfg.ccsds, "tc_dir", None)}
    seen: dict[str, str] = {}
    for key, d in dirs.items():
        if d is None:
            continue
        real = os.path.realpath(d)
        if real in seen:
            raise FlightConfigError(f"{cfg.path}: {key}: {d} is also {seen[real]}: use different directories")
        seen[real] = key


def load_config(path: str | Path) -> FlightConfig:
    """Read and validate ``path``; FlightConfigError names the file and key on any problem."""
    p = Path(path)
    try:
        raw = read_bounded(p, MAX_CONFIG_BYTES)      # a FIFO or /dev/zero named as the config never blocks
    except UnsafeInput as exc:
        raise FlightConfigError(str(exc)) from None
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise FlightConfigError(f"{p}: not UTF-8 text ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise FlightConfigError(f"{p}: not valid TOML: {exc}") from None
    except (ValueError, RecursionError, MemoryError) as exc:   # a 5,000-digit integer, deep nesting
        raise FlightConfigError(f"{p}: not a usable TOML document ({type(exc).__name__}: {str(exc)[:120]})") from None
    try:
        cfg = parse_config(doc, p)
        check_directories(cfg)
        return cfg
    except FlightConfigError:
        raise
    except (ArithmeticError, ValueError, TypeError, RecursionError) as exc:   # e.g. int too large for a float
        raise FlightConfigError(f"{p}: invalid value ({type(exc).__name__}: {str(exc)[:120]})") from None


def example_config_text() -> str:
    """The shipped example ``flight.toml`` (belsten-style board: HMC1053 on ADS1248 + one I2C chip)."""
    return resources.files("magstack.firmware.flight").joinpath(EXAMPLE_NAME).read_text(encoding="utf-8")
