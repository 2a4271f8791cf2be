"""The default simulated I2C bench: LIS3MDL, HMC5983 and LSM303DLHC on simulated buses.

Real wiring cannot put the HMC5983 and the LSM303DLHC magnetometer on one bus (both are fixed
at 0x1E), so the bench has two buses sharing one :class:`~magstack.drivers.clock.VirtualClock` and one
truth source:

- ``sim-i2c-1``: LIS3MDL at 0x1C (SA1 low) and HMC5983 at 0x1E;
- ``sim-i2c-2``: LSM303DLHC magnetometer at 0x1E.

Each chip senses the truth through its own ``sensor`` (default
``ErrorModel(preset(chip), seed=chip_seed(seed, i))`` without its quantization/saturation, an
independent random stream per chip); ``sensors`` overrides it per chip name.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magstack.drivers.clock import VirtualClock
from magstack.sim.hmc5983_model import HMC5983Model
from magstack.sim.i2c_bus import SimI2CBus
from magstack.sim.i2c_register_model import default_sensor
from magstack.sim.lis3mdl_model import LIS3MDLModel
from magstack.sim.lsm303dlhc_model import LSM303DLHCModel
from magstack.sim.truth_source import StaticTruth

CHIPS = ("lis3mdl", "hmc5983", "lsm303dlhc")


@dataclass
class I2CBench:
    """Buses by name, and for each chip (bus name, address, model)."""

    clock: object
    truth: object
    buses: dict[str, SimI2CBus] = field(default_factory=dict)
    chips: dict[str, tuple[str, int, object]] = field(default_factory=dict)

    def add(self, chip: str, bus_name: str, address: int, model) -> None:
        bus = self.buses.setdefault(bus_name, SimI2CBus(bus_name))
        bus.attach(address, model)
        self.chips[chip] = (bus_name, address, model)

    def _entry(self, chip: str):
        try:
            return self.chips[chip]
        except KeyError:
            from magstack.drivers.errors import DeviceNotFound

            raise DeviceNotFound(f"no {chip!r} on the simulated bench; present: {', '.join(self.chips)}") from None

    def bus_for(self, chip: str) -> SimI2CBus:
        return self.buses[self._entry(chip)[0]]

    def address(self, chip: str) -> int:
        return self._entry(chip)[1]

    def model(self, chip: str):
        return self._entry(chip)[2]


def chip_seed(seed: int, index: int) -> int:
    """Error-model seed of the ``index``-th chip of a bench seeded ``seed`` (independent streams)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        from magstack.drivers.errors import ConfigurationError

        raise ConfigurationError(f"bench seed must be an int >= 0, got {seed!r}")
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0])


def default_bench(clock=None, truth=None, *, seed: int = 0, sensors: dict | None = None) -> I2CBench:
    """The three chips on two buses, one clock (default VirtualClock), one truth (default StaticTruth)."""
    clock = clock if clock is not None else VirtualClock()
    truth = truth if truth is not None else StaticTruth()
    sensors = dict(sensors or {})
    for i, chip in enumerate(CHIPS):
        if chip not in sensors:
            # one independent noise stream per chip: the same seed for all three would give the
            # chips identical standard-normal draws (perfectly correlated noise)
            sensors[chip] = default_sensor(chip, chip_seed(seed, i))
    bench = I2CBench(clock, truth)
    bench.add("lis3mdl", "sim-i2c-1", 0x1C, LIS3MDLModel(clock, truth, sensors["lis3mdl"], address=0x1C))
    bench.add("hmc5983", "sim-i2c-1", 0x1E, HMC5983Model(clock, truth, sensors["hmc5983"], address=0x1E))
    bench.add("lsm303dlhc", "sim-i2c-2", 0x1E, LSM303DLHCModel(clock, truth, sensors["lsm303dlhc"], address=0x1E))
    return bench
