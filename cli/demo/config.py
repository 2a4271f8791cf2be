"""What the demo runs (:class:`DemoConfig`), its constants and small shared helpers."""
from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magstack.drivers.errors import ConfigurationError

#: Device id of the simulated HMC1053 board (tables and sessions carry it).
DEVICE_ID = "hmc1053:sim-bench"
#: Static field and temperature for the probe / read step (uT, degC).
PROBE_FIELD_uT = (20.0, -5.0, 40.0)
PROBE_TEMP_C = 25.0
#: Static field and temperature the flight loop sees (inside the table's validity box).
LOOP_FIELD_uT = (-12.0, 27.0, 35.0)
LOOP_TEMP_C = 40.0
#: Shortest bench session the demo accepts (s): below this the coil program's plateaus are
#: shorter than a few DUT cycles and the temperature cycle too fast to pair reliably.
MIN_SECONDS = 300.0
MAX_SECONDS = 36000.0
#: Files the demo writes (their stale ``.part`` siblings from an interrupted run are removed).
ARTEFACTS = ("probe.json", "session.csv", "session-paired.csv", "fit-report.txt", "cal.json",
             "cal-corrupted.json", "cal-truncated.json", "holdout-session.csv", "holdout-paired.csv",
             "holdout-calibrated.csv", "flight-loop.csv", "flight-events.jsonl", "report.html",
             "summary.json")

#: A step's way to print one line for a person.
Say = Callable[[str], None]


@dataclass(frozen=True)
class DemoConfig:
    """What the demo runs. ``seconds``: calibration session length (virtual s); the held-out
    session lasts ``holdout_seconds`` (default seconds / 2) with seed ``seed + 1``."""

    out_dir: Path = Path("magstack-demo")
    seed: int = 0
    seconds: float = 1200.0
    program: str = "full_in_range"
    holdout_program: str = "full_in_range"
    holdout_seconds: float | None = None
    #: fit and held-out figures leave out rows next to a reference change above this (uT between
    #: consecutive DUT rows, ~0.36 s): coil steps and excursion ramps, where pairing a 4 Hz
    #: reference with a 2.8 Hz DUT by interpolation, not the sensor, dominates the error.
    exclude_steps_uT: float = 2.0
    #: probability of a garbled FVM400 reply (the driver must skip and count them)
    ref_garble: float = 0.005
    loop_cycles: int = 16
    loop_period_s: float = 0.5
    samples_per_chip: int = 3

    def __post_init__(self) -> None:
        object.__setattr__(self, "out_dir", Path(self.out_dir))
        if int(self.seed) != self.seed or self.seed < 0:
            raise ConfigurationError(f"seed must be an integer >= 0, got {self.seed!r}")
        for name in ("seconds", "holdout_seconds"):
            v = getattr(self, name)
            if v is None:
                continue
            if not (math.isfinite(v) and MIN_SECONDS <= v <= MAX_SECONDS):
                raise ConfigurationError(f"{name} must be in [{MIN_SECONDS:g}, {MAX_SECONDS:g}] s, got {v!r}")
        if not (self.exclude_steps_uT > 0 and math.isfinite(self.exclude_steps_uT)):
            raise ConfigurationError(f"exclude_steps_uT must be > 0, got {self.exclude_steps_uT!r}")
        if not 0.0 <= self.ref_garble <= 0.2:
            raise ConfigurationError(f"ref_garble must be in [0, 0.2], got {self.ref_garble!r}")
        if self.loop_cycles < 12:
            raise ConfigurationError(f"loop_cycles must be >= 12 (two faults are injected), got {self.loop_cycles}")
        if not (self.loop_period_s > 0 and math.isfinite(self.loop_period_s)):
            raise ConfigurationError(f"loop_period_s must be > 0, got {self.loop_period_s!r}")
        if self.samples_per_chip < 1:
            raise ConfigurationError("samples_per_chip must be >= 1")

    @property
    def holdout_s(self) -> float:
        return self.holdout_seconds if self.holdout_seconds is not None else max(MIN_SECONDS, self.seconds / 2.0)


def vec_text(v, fmt: str = "8.3f") -> str:
    """``(x, y, z)`` formatted for the demo's text."""
    return "(" + ", ".join(format(float(x), fmt) for x in v) + ")"


def norm_rms_uT(err_uT: np.ndarray) -> float:
    """Vector norm of the per-axis RMS of (N,3) errors (uT); NaN rows must be removed first."""
    if err_uT.shape[0] == 0:
        return math.nan
    return float(np.linalg.norm(np.sqrt(np.mean(err_uT ** 2, axis=0))))


def iso_utc(epoch_s: float) -> str:
    return _dt.datetime.fromtimestamp(round(epoch_s), _dt.UTC).isoformat().replace("+00:00", "Z")
