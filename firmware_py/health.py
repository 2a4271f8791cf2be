"""Health counters published with every sample (PX4/F' style: counters, never exceptions).

Separate counters per fault class so ground can tell a flaky bus from a saturated
sensor from a stuck data-ready line.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass
class HealthCounters:
    """Monotonic fault and activity counters of one magnetometer channel."""

    samples_ok: int = 0
    bus_errors: int = 0          # BusError other than timeouts
    timeouts: int = 0            # BusTimeout: data-ready never came
    overflows: int = 0           # samples with at least one saturated axis
    stale: int = 0               # StaleData: no new sample when one was due
    other_errors: int = 0        # any other MagError
    implausible: int = 0         # beyond the sensor range or an impossible rate of change (corrupt data)
    exceptions: int = 0          # non-magstack exceptions caught at the component boundary
    uncalibrated: int = 0        # samples published without an active calibration table
    out_of_validity: int = 0     # samples outside the active table's validity (published uncalibrated)
    reinits: int = 0             # driver re-initialisations after persistent faults
    reinit_failures: int = 0     # re-initialisations that failed (the error is also counted in its class)
    telemetry_errors: int = 0    # records the telemetry sink could not write
    missed_slots: int = 0        # schedule slots skipped because a read blocked past them
    consecutive_faults: int = 0  # resets on every good sample

    @property
    def error_count(self) -> int:
        """Total faults (the PX4 ``error_count`` published in each sample)."""
        return (self.bus_errors + self.timeouts + self.overflows + self.stale + self.other_errors
                + self.implausible + self.exceptions)

    def snapshot(self) -> dict[str, int]:
        d = asdict(self)
        d["error_count"] = self.error_count
        return d
