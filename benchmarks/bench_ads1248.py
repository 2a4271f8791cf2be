"""CPU cost of the ADS1248 driver per conversion on the simulated bus (virtual time).

Run: ``python benchmarks/bench_ads1248.py``. Everything is measured in this process and
printed as a ratio to the baseline: one bare RDATA transfer through SimSpiBus + the ADC model
(the cheapest complete bus operation). Wall-clock conversion time is virtual and costs nothing.
"""
from __future__ import annotations

import time

from magstack.drivers.ads1248 import ADS1248, ChannelConfig, Command
from magstack.drivers.clock import VirtualClock
from magstack.sim.ads1248_model import ADS1248Model
from magstack.sim.hmc1053_bridge import IdealSensor, build_sim_hmc1053
from magstack.sim.spi_bus import SimSpiBus


class _Inputs:
    def differential_V(self, pos, neg, t_s):
        return 1e-3 * (pos - neg)

    def temp_c(self, t_s):
        return 25.0


class _Line:
    def set(self, level):
        pass

    def get(self):
        return False


class _CannedSpi:
    """Minimal stand-in: remembers WREG data, answers RREG with it, RDATA with a fixed code."""

    mode = 1
    max_speed_hz = 1_000_000

    def __init__(self):
        self.regs = bytearray(15)

    def transfer(self, tx):
        op = tx[0] & 0xF0
        if op == Command.WREG:
            a = tx[0] & 0x0F
            self.regs[a:a + len(tx) - 2] = tx[2:]
            return bytes(len(tx))
        if op == Command.RREG:
            a = tx[0] & 0x0F
            return b"\xff\xff" + bytes(self.regs[a:a + len(tx) - 2])
        return b"\xff\x12\x34\x56"[:len(tx)]


def _cpu_per_op(fn, n: int) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(3):
        t0 = time.process_time()
        for _ in range(n):
            fn()
        best = min(best, (time.process_time() - t0) / n)
    return best


def main() -> None:
    clock = VirtualClock()
    model = ADS1248Model(clock, _Inputs())
    spi = SimSpiBus(model, mode=1, max_speed_hz=1_000_000)
    adc = ADS1248(spi, clock, start=model.start_line, drdy=model.drdy_line, reset=model.reset_line)
    adc.reset()
    ch = [ChannelConfig(0, 1, pga=128), ChannelConfig(2, 3, pga=128)]
    adc.convert(ch[0])
    rdata = bytes((Command.RDATA, 0xFF, 0xFF, 0xFF))
    base = _cpu_per_op(lambda: spi.transfer(rdata), 20000)

    k = {"i": 0}

    def one_conversion():
        k["i"] ^= 1
        adc.convert(ch[k["i"]])

    n0 = spi.transfer_count
    conv = _cpu_per_op(one_conversion, 3000)
    per_conv_transfers = (spi.transfer_count - n0) / (3 * 3000 + 1)

    # the driver alone: a canned SPI device that echoes written registers, DRDY always low
    canned = _CannedSpi()
    drv = ADS1248(canned, clock, start=_Line(), drdy=_Line(), reset=_Line())
    drv_only = _cpu_per_op(lambda: drv.convert(ch[0]), 3000)

    ideal = build_sim_hmc1053(sensor=IdealSensor()).front_end
    fe_ideal = _cpu_per_op(ideal.read, 300) / 7
    full = build_sim_hmc1053(seed=0).front_end
    fe_full = _cpu_per_op(full.read, 300) / 7

    rows = [
        ("baseline: one RDATA transfer (SimSpiBus + model)", base),
        ("ADS1248.convert, driver alone (canned SPI, no model)", drv_only),
        (f"ADS1248.convert on the sim ({per_conv_transfers:.1f} transfers: WREG, RREG verify, RDATA)", conv),
        ("HMC1053 cycle per conversion, ideal bridge", fe_ideal),
        ("HMC1053 cycle per conversion, shared error model", fe_full),
    ]
    for label, cpu in rows:
        print(f"{label:<78} {cpu * 1e6:8.2f} us CPU  ratio {cpu / base:6.2f}")
    print(f"{'one 7-conversion vector at 20 SPS (0.356 s virtual), error model':<78} {fe_full * 7e3:8.3f} ms CPU")

if __name__ == "__main__":
    main()
