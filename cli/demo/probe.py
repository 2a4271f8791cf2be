"""Demo step 1: probe the simulated I2C buses and the HMC1053 front end, read every chip."""
from __future__ import annotations

from dataclasses import dataclass

from magstack.cli.demo.config import PROBE_TEMP_C, PROBE_FIELD_uT, Say, vec_text
from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import MagError
from magstack.drivers.i2c_probe import driver_for, format_probe_result, probe
from magstack.drivers.registry import open_chip
from magstack.sim.i2c_bench import CHIPS, default_bench
from magstack.sim.truth_source import StaticTruth


@dataclass
class ProbeFigures:
    devices: list[dict]                      # bus, address, chip, identity_hex, notes
    shared_address_chips: dict[str, str]     # bus -> chip identified at 0x1E
    ads1248_id: int                          # IDAC0 ID nibble read over simulated SPI
    front_end_table: str
    samples: dict[str, list[dict]]           # chip -> [{t_s, b_uT, temp_c}]
    truth_uT: tuple[float, float, float]
    truth_temp_c: float


def probe_bench(seed: int, *, samples_per_chip: int = 3, say: Say = print) -> ProbeFigures:
    """Probe the simulated I2C buses and the HMC1053 front end; read each chip."""
    clock = VirtualClock()
    truth = StaticTruth(PROBE_FIELD_uT, PROBE_TEMP_C)
    bench = default_bench(clock, truth, seed=seed)
    devices, shared = [], {}
    for bus_name, bus in bench.buses.items():
        for r in probe(bus):
            devices.append({"bus": bus_name, "address": r.address, "chip": r.chip, "identity_hex": r.identity.hex(),
                            "notes": r.notes})
            if r.address == 0x1E:
                shared[bus_name] = r.chip
            say("  " + format_probe_result(bus_name, r))
    found = {driver_for(d["chip"]) for d in devices}  # an 'H43' part may be reported as hmc5883l_or_hmc5983
    missing = [c for c in CHIPS if c not in found]
    if missing:
        raise MagError(f"probe did not identify {missing} on the simulated bench")
    fe = open_chip("hmc1053", "sim", clock, truth=truth, seed=seed)
    ads_id = fe.adc.read_register("IDAC0") >> 4
    say(f"  {fe.adc.spi.name:<12} CS0   hmc1053     ADS1248 IDAC0 ID nibble {ads_id:#x}; front-end table "
        f"{fe.table.name} (PGA {fe.table.pga}, {fe.table.data_rate_sps} SPS, set/reset strap)")
    samples: dict[str, list[dict]] = {}
    say(f"  truth: B = {vec_text(truth.b_uT, '7.2f')} uT, T = {PROBE_TEMP_C:.1f} degC; raw readings "
        f"(offsets and gains not yet calibrated):")
    for chip in (*CHIPS, "hmc1053"):
        mag = fe if chip == "hmc1053" else open_chip(chip, "sim", clock, bench=bench)
        rows = []
        for _ in range(samples_per_chip):
            s = mag.read()
            rows.append({"t_s": s.t_s, "b_uT": list(s.b_uT), "temp_c": s.temp_c})
            temp = "   n/a" if s.temp_c is None else f"{s.temp_c:6.2f}"
            say(f"    {chip:<11} t {s.t_s:8.4f} s  B = {vec_text(s.b_uT)} uT  T = {temp} degC"
                + (f"  OVERFLOW {s.overflow}" if s.overflow else ""))
        samples[chip] = rows
    return ProbeFigures(devices, shared, int(ads_id), fe.table.name, samples,
                        tuple(float(x) for x in truth.b_uT), PROBE_TEMP_C)
