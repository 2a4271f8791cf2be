"""Ground actions at virtual times: ``magstack run --sim --duration S --scenario ground.toml``.

A scenario file lists what the ground does while a simulated flight runs, each a ``magstack`` command line at
a virtual time (seconds after the run's start)::

    [[at]]
    t_s = 400
    run = "magstack tm decode e2e/packets-0001.bin --out dec1/"

    [[at]]
    t_s = 400
    run = "magstack tm command --config flight.toml activate_table channel=hmc1053 --send"
    expect = 0                 # the exit status the action must end with (default 0)

At each time the flight application stands still (virtual time stops; every packet written so far is in the
packet file), the actions due run one after the other, each as its own ``magstack`` process in the scenario
file's directory (the ground is another program: telecommands reach the application through its UDP port or
its ``tc_dir``, as from a ground station), and then the flight goes on. An action whose exit status is not
``expect`` stops the run: ``magstack run`` ends with exit 1 and the action's last output lines. One command
per action: no shell (``|``, ``>``, ``&&``, ``;``). ``magstack run --example-scenario`` prints the end-to-end
scenario of docs/ccsds.md.
"""
from __future__ import annotations

import math
import shlex
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from magstack.firmware.errors import FlightConfigError

EXAMPLE_NAME = "ground.example.toml"
MAX_SCENARIO_BYTES = 1 << 20
_SHELL = {"|", "||", ">", ">>", "<", "&&", ";", "&"}


@dataclass(frozen=True)
class GroundAction:
    t_s: float
    argv: tuple[str, ...]          # the arguments after "magstack"
    expect: int = 0

    @property
    def line(self) -> str:
        return "magstack " + shlex.join(self.argv)


@dataclass
class Scenario:
    path: Path
    actions: list[GroundAction]
    done: list[dict] = field(default_factory=list)
    failed: str = ""


def example_scenario_text() -> str:
    """The shipped example scenario (the end-to-end scenario of docs/ccsds.md)."""
    return resources.files("magstack.cli").joinpath(EXAMPLE_NAME).read_text(encoding="utf-8")


def load_scenario(path: str | Path, duration_s: float) -> Scenario:
    """Read and check a scenario file (FlightConfigError naming the file and entry, exit 3)."""
    p = Path(path)
    try:
        if p.stat().st_size > MAX_SCENARIO_BYTES:
            raise FlightConfigError(f"{p}: larger than {MAX_SCENARIO_BYTES} bytes")
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise FlightConfigError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise FlightConfigError(f"{p}: not TOML: {exc}") from None
    unknown = set(doc) - {"at"}
    if unknown or not isinstance(doc.get("at"), list) or not doc["at"]:
        raise FlightConfigError(f"{p}: needs [[at]] entries and nothing else (unknown: {sorted(unknown)})")
    actions = []
    for i, e in enumerate(doc["at"]):
        where = f"{p}: at[{i}]"
        if not isinstance(e, dict) or set(e) - {"t_s", "run", "expect"} or not {"t_s", "run"} <= set(e):
            raise FlightConfigError(f"{where}: keys t_s, run and optionally expect")
        t = e["t_s"]
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or not 0 <= t <= duration_s:
            raise FlightConfigError(f"{where}.t_s: a time in 0..{duration_s:g} s (--duration), got {t!r}")
        try:
            words = shlex.split(e["run"]) if isinstance(e["run"], str) else []
        except ValueError as exc:
            raise FlightConfigError(f"{where}.run: {exc}") from None
        if len(words) < 2 or words[0] != "magstack":
            raise FlightConfigError(f"{where}.run: a magstack command line, got {e['run']!r}")
        shell = [w for w in words if w in _SHELL]
        if shell:
            raise FlightConfigError(f"{where}.run: one command, no shell ({shell[0]!r})")
        expect = e.get("expect", 0)
        if isinstance(expect, bool) or not isinstance(expect, int) or not 0 <= expect <= 255:
            raise FlightConfigError(f"{where}.expect: an exit status 0..255, got {expect!r}")
        actions.append(GroundAction(float(t), tuple(words[1:]), expect))
    return Scenario(p, sorted(actions, key=lambda a: a.t_s))


def pauses(scenario: Scenario, stop) -> list[tuple[float, object]]:
    """``(t_s, action)`` pairs for :meth:`magstack.firmware.flight.app.FlightApp.run`; ``stop()`` ends the run
    after a failed action."""
    cwd = scenario.path.resolve().parent

    def make(a: GroundAction):
        def act() -> None:
            if scenario.failed:
                return
            res = subprocess.run([sys.executable, "-m", "magstack", *a.argv], cwd=cwd, capture_output=True,
                                 text=True, stdin=subprocess.DEVNULL)
            tail = (res.stdout + res.stderr).strip().splitlines()[-3:]
            scenario.done.append({"t_s": a.t_s, "run": a.line, "exit_code": res.returncode, "expect": a.expect,
                                  "output": tail})
            if res.returncode != a.expect:
                scenario.failed = (f"ground action at {a.t_s:g} s `{a.line}` exited {res.returncode} "
                                   f"(expected {a.expect}): " + " | ".join(tail))
                stop()
        return act
    return [(a.t_s, make(a)) for a in scenario.actions]
