"""Simulated ADS1248: loud failures, register file, DRDY timing in virtual time, premature reads."""
from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.drivers.ads1248 import (
    ADS1248,
    CODE_POS_FS,
    DATA_RATES,
    PGA_CODES,
    REGISTERS,
    ChannelConfig,
    Command,
    signed24,
)
from magstack.drivers.clock import VirtualClock
from magstack.drivers.errors import BusError
from magstack.sim.ads1248_model import ADS1248Model
from magstack.sim.spi_bus import SimSpiBus
from tests.test_ads1248_driver import Inputs

NOP3 = bytes([Command.NOP] * 3)


def ready_model(volts=None, **kw):
    """A model after a pin reset, in SDATAC mode, START high (the driver's bring-up)."""
    clock = VirtualClock()
    model = ADS1248Model(clock, Inputs(volts), **kw)
    spi = SimSpiBus(model, mode=1, max_speed_hz=1_000_000)
    adc = ADS1248(spi, clock, start=model.start_line, drdy=model.drdy_line, reset=model.reset_line)
    adc.reset()
    return clock, model, spi, adc


def test_power_on_register_values_and_rreg_wrap():
    clock, model, spi, adc = ready_model()
    regs = spi.transfer(bytes((Command.RREG | 0x00, 14)) + bytes([0xFF] * 15))[2:]
    assert regs[0] == 0x01 and regs[3] == 0x00 and regs[0x0B] == 0xFF and regs[0x0A] >> 4 == 0x9
    assert regs[7:10] == bytes((0x00, 0x00, 0x40))  # FSC = 0x400000 (untrimmed default of the model)
    wrapped = spi.transfer(bytes((Command.RREG | 0x0E, 1)) + bytes([0xFF] * 2))[2:]
    assert wrapped == bytes((regs[0x0E], regs[0x00]))


@pytest.mark.parametrize("tx, msg", [
    (b"\xf1", "illegal command"),
    (b"\x08", "illegal command"),
    (bytes((Command.WREG | 0x03, 0x00, 0x80)), "bit 7"),
    (bytes((Command.WREG | 0x03, 0x00, 0x0A)), "above 1001"),
    (bytes((Command.WREG | 0x0B, 0x00, 0xA0)), "undefined"),
    (bytes((Command.WREG | 0x0E, 0x01, 0x00, 0x00)), "past 0x0E"),
    (bytes((Command.RREG | 0x0F, 0x00, 0xFF)), "0x0f"),
    (bytes((Command.RREG | 0x00, 0x10, 0xFF)), "upper bits"),
    (bytes((Command.RREG | 0x00, 0x01, 0xFF)), "needs 2 data bytes"),
    (bytes((Command.RDATA, 0xFF)), "needs 3 NOP"),
    (bytes((Command.RDATA, 0xFF, 0x12, 0xFF)), "non-NOP"),
    (bytes((Command.SYNC,)), "twice"),
])
def test_illegal_traffic_fails_loudly(tx, msg):
    clock, model, spi, adc = ready_model()
    with pytest.raises(BusError, match=msg):
        spi.transfer(tx)


def test_register_access_in_rdatac_mode_fails():
    clock = VirtualClock()
    model = ADS1248Model(clock, Inputs())
    spi = SimSpiBus(model, mode=1, max_speed_hz=1_000_000)
    with pytest.raises(BusError, match="RDATAC"):
        spi.transfer(bytes((Command.RREG, 0x00, 0xFF)))
    spi.transfer(bytes((Command.SDATAC,)))
    with pytest.raises(BusError, match="SDATAC took effect"):
        spi.transfer(bytes((Command.WREG, 0x00, 0x01)))


def test_commands_during_reset_fail():
    clock = VirtualClock()
    model = ADS1248Model(clock, Inputs())
    spi = SimSpiBus(model, mode=1, max_speed_hz=1_000_000)
    model.reset_line.set(False)
    with pytest.raises(BusError, match="RESET is held low"):
        spi.transfer(bytes((Command.SDATAC,)))
    model.reset_line.set(True)
    clock.sleep_s(0.3e-3)
    with pytest.raises(BusError, match="too early after reset"):
        spi.transfer(bytes((Command.SDATAC,)))
    clock.sleep_s(0.3e-3)
    spi.transfer(bytes((Command.SDATAC,)))


def test_wrong_spi_mode_and_clock_rejected_by_bus():
    clock = VirtualClock()
    model = ADS1248Model(clock, Inputs())
    with pytest.raises(BusError, match="mode"):
        SimSpiBus(model, mode=3, max_speed_hz=1_000_000).transfer(b"\xff")
    with pytest.raises(BusError, match="clock"):
        SimSpiBus(model, mode=1, max_speed_hz=10_000_000).transfer(b"\xff")


def test_read_only_bits_ignore_writes():
    clock, model, spi, adc = ready_model()
    spi.transfer(bytes((Command.WREG | 0x02, 0x00, 0xB0)))  # CLKSTAT (bit 7) is read-only
    assert adc.read_register("MUX1") == 0x30
    spi.transfer(bytes((Command.WREG | 0x0A, 0x00, 0x05)))  # ID nibble is read-only
    assert adc.read_register("IDAC0") == 0x95


@pytest.mark.parametrize("sps", sorted(DATA_RATES))
def test_drdy_timing_after_mux_write_and_continuous(sps):
    clock, model, spi, adc = ready_model()
    rate = DATA_RATES[sps]
    t0 = adc.configure(ChannelConfig(0, 1, data_rate_sps=sps))
    clock.sleep_s(rate.first_after_write_s - 1e-7)
    assert model.drdy_line.get() is True  # not yet
    clock.sleep_s(1e-7)
    assert model.drdy_line.get() is False
    assert clock.monotonic_s() - t0 == pytest.approx(rate.first_after_write_s)
    adc.read_data()
    assert model.drdy_line.get() is True
    # later results every period_s while START stays high
    clock.sleep_s(rate.period_s - 1e-7)
    assert model.drdy_line.get() is True
    clock.sleep_s(2e-7)
    assert model.drdy_line.get() is False


def test_sync_restarts_with_first_after_reset_time():
    clock, model, spi, adc = ready_model()
    adc.convert(ChannelConfig(0, 1, data_rate_sps=20))
    adc.command(Command.SYNC)
    t0 = clock.monotonic_s()
    t = adc.wait_drdy(t0, DATA_RATES[20].first_after_reset_s)
    assert t - t0 == pytest.approx(DATA_RATES[20].first_after_reset_s)


def test_start_low_stops_after_current_conversion_and_sync_needs_start():
    clock, model, spi, adc = ready_model()
    adc.configure(ChannelConfig(0, 1, data_rate_sps=1000))
    model.start_line.set(False)
    clock.sleep_s(2e-3)
    assert model.drdy_line.get() is False  # the conversion in progress completed
    adc.read_data()
    clock.sleep_s(10e-3)
    assert model.drdy_line.get() is True  # and no further ones
    with pytest.raises(BusError, match="START is low"):
        adc.command(Command.SYNC)


def test_premature_read_returns_blend_of_old_and_new_channel():
    clock, model, spi, adc = ready_model({(0, 1): 1e-3, (2, 3): 3e-3})
    ch0 = ChannelConfig(0, 1, pga=1, data_rate_sps=20)
    ch1 = ChannelConfig(2, 3, pga=1, data_rate_sps=20)
    old = adc.convert(ch0).code
    adc.configure(ch1)
    clock.sleep_s(DATA_RATES[20].first_after_write_s / 2)
    blended = adc.read_data()  # a buggy driver: no DRDY wait
    new = round(3e-3 / 2.048 * (2**23 - 1))
    assert model.reads_before_drdy == 1 and model.blended_reads == 1
    assert blended == pytest.approx((old + new) / 2, abs=2)
    assert old < blended < new


def test_rdatac_readout_and_mode_switch_at_drdy():
    clock, model, spi, adc = ready_model({(0, 1): 1e-3})
    adc.convert(ChannelConfig(0, 1, pga=1, data_rate_sps=1000))
    spi.transfer(bytes((Command.RDATAC,)))
    assert not model.rdatac  # effective at next DRDY only
    clock.sleep_s(1e-3)
    assert model.drdy_line.get() is False and model.rdatac
    code = signed24(spi.transfer(NOP3))
    assert code == round(1e-3 / 2.048 * (2**23 - 1))
    with pytest.raises(BusError, match="RDATAC"):
        adc.read_register("MUX0")


def test_saturation_codes_and_unwired_inputs():
    clock, model, spi, adc = ready_model({(0, 1): 5.0})
    assert adc.convert(ChannelConfig(0, 1, pga=1)).code == CODE_POS_FS
    with pytest.raises(BusError, match="not wired"):
        adc.convert(ChannelConfig(4, 5))


def test_unmodelled_monitor_fails_loudly():
    clock, model, spi, adc = ready_model()
    with pytest.raises(BusError, match="not modelled"):
        adc.convert(ChannelConfig(0, 1, muxcal="avdd_monitor"))


def test_lazy_evaluation_samples_once_per_read_conversion():
    clock, model, spi, adc = ready_model()
    adc.configure(ChannelConfig(0, 1, data_rate_sps=2000))
    clock.sleep_s(1.0)  # ~2000 conversions complete unread
    assert model.drdy_line.get() is False
    adc.read_data()
    assert model.sample_calls == 1


def test_internal_temperature_diode():
    clock, model, spi, adc = ready_model()
    model.inputs.temp = 60.0
    conv = adc.convert(ChannelConfig(muxcal="temperature", pga=1))
    assert conv.volts == pytest.approx(0.118 + 35 * 405e-6, abs=1e-6)


def test_register_map_covers_all_addresses_once():
    assert sorted(r.address for r in REGISTERS.values()) == list(range(15))


@settings(max_examples=100, deadline=None)
@given(volts=st.floats(-3.0, 3.0), pga=st.sampled_from(sorted(PGA_CODES)))
def test_conversion_tracks_input_and_clips_at_full_scale(volts, pga):
    clock, model, spi, adc = ready_model({(0, 1): volts})
    conv = adc.convert(ChannelConfig(0, 1, pga=pga, data_rate_sps=2000))
    fs = 2.048 / pga
    lsb = fs / (2**23 - 1)
    assert conv.volts == pytest.approx(min(max(volts, -fs - lsb), fs), abs=lsb)
    assert conv.clipped == (abs(volts) >= fs - lsb / 2)


@pytest.mark.parametrize("kw, word", [
    ({"noise_V_rms": float("nan")}, "noise_V_rms"),
    ({"noise_V_rms": -1e-6}, "noise_V_rms"),
    ({"adc_offset_V": float("inf")}, "adc_offset_V"),
    ({"ref0_V": float("nan")}, "ref0_V"),
    ({"ref1_V": 0.0}, "ref1_V"),
    ({"calibration_conversions": 0.0}, "calibration_conversions"),
    ({"power_up_s": float("nan")}, "power_up_s"),
    ({"device_id": 0x1F}, "device_id"),          # would have been silently truncated to 0xF
    ({"fsc": 1 << 24}, "fsc"),                    # does not fit the 24-bit FSC registers
    ({"fsc": 1.5}, "fsc"),
    ({"max_clock_hz": 0}, "max_clock_hz"),
])
def test_model_refuses_bad_parameters_with_a_typed_error(kw, word):
    from magstack.drivers.errors import ConfigurationError

    with pytest.raises(ConfigurationError, match=word):
        ADS1248Model(VirtualClock(), Inputs(), **kw)
    assert ADS1248Model(VirtualClock(), Inputs(), device_id=0xF, fsc=0xFFFFFF).regs[0x0A] >> 4 == 0xF
