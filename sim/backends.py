"""The simulated backend of the chip factory (:mod:`magstack.drivers.registry`).

``register()`` is the ``magstack.plugins`` entry point: it registers the ``sim`` bus spec with
the chip factory and the ``fvm400sim://`` serial URL scheme with pyserial, so that drivers and
on-board code open simulated parts exactly as they open real ones (``open_chip(chip, "sim")``,
``open_serial("fvm400sim://bench")``) without importing this package.

* I2C chips sit on the default simulated bench (:func:`magstack.sim.i2c_bench.default_bench`)
  unless ``bench=`` gives another one.
* The HMC1053 is a simulated board (:func:`magstack.sim.hmc1053_bridge.build_sim_hmc1053`):
  truth source (default :class:`magstack.sim.truth_source.StaticTruth`) -> shared error model ->
  bridge -> ADS1248 model on a simulated SPI bus and GPIO lines, in virtual time. Tools that need
  the board itself (fault injection) call ``build_sim_hmc1053`` and get the typed rig.
"""
from __future__ import annotations

from typing import Any

#: pyserial searches this package for ``<scheme>://`` handlers (``protocol_fvm400sim``).
SERIAL_PROTOCOL_PACKAGE = "magstack.sim.serial_protocols"


def register() -> None:
    """Entry point: register the ``sim`` chip backend and the simulated serial URL schemes."""
    import serial

    from magstack.drivers.clock import VirtualClock
    from magstack.drivers.registry import Backend, register_backend

    register_backend("sim", Backend(open_sim_chip, sim_i2c_buses, VirtualClock))
    if SERIAL_PROTOCOL_PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(SERIAL_PROTOCOL_PACKAGE)


def open_sim_chip(chip: str, bus_spec: str = "sim", clock: Any = None, *, bench: Any = None,
                  table: Any = "hf8.2", truth: Any = None, sensor: Any = None, seed: int = 0, **config: Any):
    """Open ``chip`` on the simulator. I2C chips: ``bench`` and driver ``config``; HMC1053: ``table``,
    ``truth``, ``sensor``, ``seed`` and ``bridge_kwargs``/``adc_kwargs`` for the simulated board."""
    if chip == "hmc1053":
        from magstack.sim.hmc1053_bridge import build_sim_hmc1053

        return build_sim_hmc1053(clock, truth=truth, sensor=sensor, seed=seed, table=table, **config).front_end
    from magstack.drivers.registry import i2c_driver_class
    from magstack.sim.i2c_bench import default_bench

    b = bench if bench is not None else default_bench(clock=clock)
    config.setdefault("address", b.address(chip))
    return i2c_driver_class(chip)(b.bus_for(chip), b.clock, **config)


def sim_i2c_buses(bus_spec: str = "sim") -> list[tuple[str, Any]]:
    """The default simulated bench's I2C buses, ``(name, bus)``."""
    from magstack.sim.i2c_bench import default_bench

    return list(default_bench().buses.items())
