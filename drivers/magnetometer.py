"""The common magnetometer interface the firmware uses (never an address or register).

Every chip driver (LIS3MDL, HMC5983, LSM303DLHC, HMC1053 front end) returns
:class:`MagSample` from :meth:`Magnetometer.read`. Field unit is microtesla (``_uT``)
throughout the float code of the stack; temperatures are degC; times are seconds of
the injected clock's monotonic time.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class MagSample:
    """One vector sample in the sensor frame.

    ``t_s`` is the nominal sample time; ``axis_t_s`` the instant each axis was actually
    converted (equal to ``t_s`` for chips that sample the axes simultaneously; different
    for sequential conversion, where the skew is a real error source).
    ``overflow`` lists axes (0=X,1=Y,2=Z) that saturated; their ``b_uT`` entries are NaN.
    """

    t_s: float
    b_uT: tuple[float, float, float]
    temp_c: float | None = None
    axis_t_s: tuple[float, float, float] | None = None
    overflow: tuple[int, ...] = ()
    extra: dict = field(default_factory=dict)

    @property
    def valid(self) -> bool:
        return not self.overflow


@runtime_checkable
class Magnetometer(Protocol):
    """What the firmware needs from any magnetometer driver."""

    name: str

    def read(self) -> MagSample:
        """Wait for the next new sample (through the injected clock) and return it.

        Raises :class:`magstack.drivers.errors.BusError`, :class:`magstack.drivers.errors.BusTimeout`
        or :class:`magstack.drivers.errors.DataOverflow`-flagged samples never silently.
        """

    def data_ready(self) -> bool:
        """True when a sample not yet returned by :meth:`read` is available."""
