"""Bus transports, chip tables and chip drivers (register semantics only), and the chip factory.

Layering (one-way): ``magstack.drivers.bus`` -> chip drivers -> ``magstack.drivers.registry``.
No driver opens a device node by itself: callers inject a bus. Backends other than the real
Linux buses (the simulator) register themselves through the ``magstack.plugins`` entry point.
"""
