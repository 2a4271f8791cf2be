"""Bus transports and chip drivers (register semantics only).

Layering (one-way): ``drivers.bus`` -> ``drivers.<chip>`` -> ``firmware_py``.
No module here opens a device node by itself: callers inject a bus.
"""
