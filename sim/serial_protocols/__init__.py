"""pyserial URL handlers for simulated serial instruments.

``magstack.drivers.bus.serial_port.open_serial`` adds this package to
``serial.protocol_handler_packages``; ``serial.serial_for_url("<scheme>://...")`` then imports
``magstack.sim.serial_protocols.protocol_<scheme>`` and uses its ``Serial`` class.
"""
