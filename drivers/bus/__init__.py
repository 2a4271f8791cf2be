"""Bus transports: I2C (message-list transfer), SPI (transfer), GPIO lines, serial by URL.

Real adapters wrap smbus2 / spidev / lgpio / pyserial; the simulator in ``sim`` implements
the same protocols, so chip drivers never know which one they talk to.
"""
from magstack.drivers.bus.gpio import InputLine, OutputLine
from magstack.drivers.bus.i2c import I2CBus, I2CDevice, I2CRead, I2CWrite, SMBus2I2CBus
from magstack.drivers.bus.serial_port import open_serial
from magstack.drivers.bus.spi import SpiBus, SpidevSpiBus

__all__ = [
    "I2CBus", "I2CDevice", "I2CRead", "I2CWrite", "SMBus2I2CBus",
    "SpiBus", "SpidevSpiBus", "InputLine", "OutputLine", "open_serial",
]
