"""ST LIS3MDL 3-axis magnetometer on I2C (hardware-facts section 1).

Register semantics only; the bus is injected. Field in uT, temperature in degC.

- identity: WHO_AM_I (0x0F) = 0x3D; address 0x1C (SA1 low) or 0x1E (SA1 high).
- data: X, Y, Z little-endian int16 from 0x28 (burst with the 0x80 auto-increment flag).
- ranges 400 / 800 / 1200 / 1600 uT (+-4/8/12/16 G) at 6842 / 3421 / 2281 / 1711 LSB/G.
- rates 0.625 ... 80 Hz (DO), and 155 / 300 / 560 / 1000 Hz (FAST_ODR), which force the
  performance mode ultra / high / medium / low.
- data-ready: STATUS.ZYXDA (latched until the data is read). Overflow: no saturation code;
  an axis at the int16 rail, or INT_SRC.MROI, flags the sample (NaN on that axis).
- temperature: int16 / 8 + 25 degC (TEMP_EN).
- self-test: ST's reference procedure (hardware-facts 1.4).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magstack.drivers.chip_table import (
    ChipTable,
    Field,
    NamedOption,
    RangeOption,
    RateOption,
    TableMagnetometer,
    TempFormat,
    check_identity,
    lookup,
    write_checked,
    write_field,
)
from magstack.drivers.errors import BusTimeout, ConfigurationError, SelfTestFailed

WHO_AM_I = 0x0F
CTRL_REG1, CTRL_REG2, CTRL_REG3, CTRL_REG4, CTRL_REG5 = 0x20, 0x21, 0x22, 0x23, 0x24
STATUS_REG = 0x27
OUT_X_L = 0x28
TEMP_OUT_L = 0x2E
INT_CFG, INT_SRC = 0x30, 0x31

SOFT_RST = 0x04
REBOOT = 0x08
ST_BIT = 0x01
BDU_BIT = 0x40
ZYXDA = 0x08
ZYXOR = 0x80
MROI = 0x02

#: OM / OMZ performance-mode codes.
PERFORMANCE = (NamedOption("low", 0), NamedOption("medium", 1), NamedOption("high", 2), NamedOption("ultra", 3))

LIS3MDL_TABLE = ChipTable(
    name="lis3mdl",
    addresses=(0x1C, 0x1E),
    id_checks=((WHO_AM_I, b"\x3d"),),
    auto_increment_flag=0x80,
    data_reg=OUT_X_L,
    big_endian=False,
    slot_axes=(0, 1, 2),
    overflow_code=None,
    # no saturation code: the int16 rails are treated as saturated [I]
    valid_code=(-32767, 32766),
    ranges=(
        RangeOption(400.0, 0, (6842.0, 6842.0, 6842.0)),
        RangeOption(800.0, 1, (3421.0, 3421.0, 3421.0)),
        RangeOption(1200.0, 2, (2281.0, 2281.0, 2281.0)),
        RangeOption(1600.0, 3, (1711.0, 1711.0, 1711.0)),
    ),
    # rate code = CTRL_REG1[4:1] = DO << 1 | FAST_ODR (Adafruit's 4-bit code)
    rates=(
        RateOption(0.625, 0b0000), RateOption(1.25, 0b0010), RateOption(2.5, 0b0100), RateOption(5.0, 0b0110),
        RateOption(10.0, 0b1000), RateOption(20.0, 0b1010), RateOption(40.0, 0b1100), RateOption(80.0, 0b1110),
        RateOption(155.0, 0b0001, "ultra"), RateOption(300.0, 0b0011, "high"),
        RateOption(560.0, 0b0101, "medium"), RateOption(1000.0, 0b0111, "low"),
    ),
    modes=(NamedOption("continuous", 0b00), NamedOption("single", 0b01), NamedOption("idle", 0b10)),
    range_field=Field(CTRL_REG2, 0x60),
    rate_field=Field(CTRL_REG1, 0x1E),
    mode_field=Field(CTRL_REG3, 0x03),
    status_reg=STATUS_REG,
    drdy_mask=ZYXDA,
    overrun_mask=ZYXOR,
    drdy_latched=True,
    temperature=TempFormat(regs=(TEMP_OUT_L, TEMP_OUT_L + 1), big_endian=False, shift=0, lsb_per_c=8.0,
                           offset_c=25.0, separate_reads=False, enable=Field(CTRL_REG1, 0x80)),
    default_range_uT=400.0,
    default_odr_hz=80.0,
    reset_values=((CTRL_REG1, 0x10), (CTRL_REG2, 0x00), (CTRL_REG3, 0x03), (CTRL_REG4, 0x00),
                  (CTRL_REG5, 0x00), (INT_CFG, 0xE8)),
    notes="WHO_AM_I 0x3D; burst reads need the 0x80 flag; output block wraps 0x2D -> 0x28",
)

OM_FIELD = Field(CTRL_REG1, 0x60)
OMZ_FIELD = Field(CTRL_REG4, 0x0C)
LP_FIELD = Field(CTRL_REG3, 0x20)
ST_FIELD = Field(CTRL_REG1, ST_BIT)
BDU_FIELD = Field(CTRL_REG5, BDU_BIT)

#: ST reference self-test (hardware-facts 1.4): +-12 G, LP 80 Hz, 5-sample averages,
#: pass windows on |on - off| in uT.
SELF_TEST_RANGE_UT = 1200.0
SELF_TEST_ODR_HZ = 80.0
SELF_TEST_WINDOW_UT = ((100.0, 300.0), (100.0, 300.0), (10.0, 100.0))
SELF_TEST_SAMPLES = 5


@dataclass(frozen=True)
class SelfTestResult:
    """Self-test outcome: ``delta_uT`` = |on - off| per axis, ``window_uT`` = (lo, hi) per axis."""

    passed: bool
    delta_uT: tuple[float, float, float]
    window_uT: tuple[tuple[float, float], ...]
    off_uT: tuple[float, float, float]
    on_uT: tuple[float, float, float]


def _rail_or_mroi(codes, mroi: bool, full_scale_codes) -> tuple[int, ...]:
    if not mroi:
        return ()
    beyond = tuple(i for i in range(3) if abs(codes[i]) > full_scale_codes[i])
    return beyond or (0, 1, 2)


class LIS3MDL(TableMagnetometer):
    """LIS3MDL driver. ``performance`` is the X/Y and Z operating mode (low/medium/high/ultra).

    ``check_mroi`` reads INT_SRC after each sample and flags MROI (one extra bus transfer).
    """

    table = LIS3MDL_TABLE

    def __init__(self, bus, clock, *, address: int | None = None, range_uT: float = 400.0,
                 odr_hz: float = 80.0, performance: str | None = None, mode: str = "continuous",
                 temperature: bool = True, check_mroi: bool = True, reset: bool = True, **kw) -> None:
        super().__init__(bus, clock, address=address, **kw)
        self.check_mroi = check_mroi
        self._perf = "ultra"
        self._temp_on = temperature
        self._config = dict(range_uT=range_uT, odr_hz=odr_hz, performance=performance, mode=mode,
                            temperature=temperature)
        if reset:
            self.soft_reset()
        self.configure(**self._config)

    # -- configuration ---------------------------------------------------------------
    @property
    def performance(self) -> str:
        return self._perf

    def configure(self, *, range_uT: float | None = None, odr_hz: float | None = None,
                  performance: str | None = None, mode: str | None = None, temperature: bool | None = None) -> None:
        """Set range (uT), output rate (Hz), performance mode, operating mode and TEMP_EN.

        Invalid values raise ConfigurationError naming the valid ones; a fast rate (>80 Hz)
        forces its performance mode, and an explicit conflicting one is refused.
        """
        t = self.table
        rng = t.range_option(range_uT) if range_uT is not None else self._range
        rate = t.rate_option(odr_hz) if odr_hz is not None else self._rate
        if performance is not None:
            lookup(PERFORMANCE, "name", performance, "lis3mdl performance")
        if rate.perf is not None:
            if performance is not None and performance != rate.perf:
                raise ConfigurationError(f"lis3mdl odr_hz {rate.odr_hz:g} requires performance {rate.perf!r}, "
                                         f"not {performance!r}")
            perf = rate.perf
        else:
            perf = performance if performance is not None else self._perf
        md = t.mode_option(mode) if mode is not None else t.mode_option(self._mode)
        if md.name == "single" and rate.odr_hz > 80.0:
            raise ConfigurationError("lis3mdl single-conversion mode needs odr_hz <= 80; valid: "
                                     + ", ".join(f"{r.odr_hz:g}" for r in t.rates if r.odr_hz <= 80))
        temp_on = self._temp_on if temperature is None else bool(temperature)
        om = lookup(PERFORMANCE, "name", perf, "lis3mdl performance").code
        reg1 = (0x80 if temp_on else 0) | OM_FIELD.encode(om) | t.rate_field.encode(rate.code)
        # power down while reconfiguring, then write rate/mode fields (ST driver order)
        write_field(self.dev, t.mode_field, t.mode_option("idle").code, verify=self.verify)
        write_checked(self.dev, CTRL_REG1, reg1, verify=self.verify)
        write_field(self.dev, OMZ_FIELD, om, verify=self.verify)
        write_field(self.dev, t.range_field, rng.code, verify=self.verify)
        write_field(self.dev, BDU_FIELD, 1, verify=self.verify)
        write_field(self.dev, LP_FIELD, 0, verify=self.verify)
        self._range, self._rate, self._perf, self._temp_on = rng, rate, perf, temp_on
        self._mode = md.name
        if md.name == "continuous":
            write_field(self.dev, t.mode_field, md.code, verify=self.verify)
        self._config.update(range_uT=rng.range_uT, odr_hz=rate.odr_hz, performance=performance,
                            mode=md.name, temperature=temp_on)
        self._mark_restart()

    def _trigger_single(self) -> None:
        self.dev.write_register(CTRL_REG3, (self.dev.read_register(CTRL_REG3) & ~0x03) | 0b01)

    def _temp_enabled(self) -> bool:
        return self._temp_on

    def _sample_extra(self, codes) -> dict:
        if not self.check_mroi:
            return {}
        src = self.dev.read_register(INT_SRC)
        mroi = bool(src & MROI)
        fs = [self._range.range_uT / 100.0 * s for s in self._range.lsb_per_gauss]
        return {"mroi": mroi, "_overflow": _rail_or_mroi(codes, mroi, fs)}

    # -- reset -----------------------------------------------------------------------
    def soft_reset(self, timeout_s: float = 0.05) -> None:
        """CTRL_REG2.SOFT_RST, then poll until the bit clears (BusTimeout otherwise)."""
        self.dev.write_register(CTRL_REG2, SOFT_RST)
        deadline = self.clock.monotonic_s() + timeout_s
        while self.dev.read_register(CTRL_REG2) & SOFT_RST:
            if self.clock.monotonic_s() >= deadline:
                raise BusTimeout("lis3mdl SOFT_RST did not clear", address=self.address, operation="soft reset")
            self.clock.sleep_s(1e-3)
        self._range = self.table.range_option(self.table.default_range_uT)
        self._mode = "idle"
        self._last_raw = None
        self._same_count = 0

    def reinit(self) -> None:
        """Soft reset, identity check and re-apply the last configuration."""
        self.soft_reset()
        self.identity = check_identity(self.dev, self.table, known_present=True)
        self.configure(**self._config)

    # -- self-test -------------------------------------------------------------------
    def _average(self, n: int) -> np.ndarray:
        acc = []
        for _ in range(n):
            s = self.read()
            if s.overflow:
                raise SelfTestFailed(f"lis3mdl self-test: overflow on axes {s.overflow} during averaging")
            acc.append(s.b_uT)
        return np.mean(np.asarray(acc, dtype=float), axis=0)

    def self_test(self) -> SelfTestResult:
        """ST reference self-test (hardware-facts 1.4); restores the previous configuration.

        Returns the result when every axis is inside its window, else raises SelfTestFailed
        (the result is attached as ``exc.result``).
        """
        saved = dict(self._config, performance=self._perf if self._rate.perf is None else None)
        stuck = self.stuck_limit
        self.stuck_limit = None
        try:
            self.soft_reset()
            self.configure(range_uT=SELF_TEST_RANGE_UT, odr_hz=SELF_TEST_ODR_HZ, performance="low",
                           mode="idle", temperature=self._temp_on)
            self.clock.sleep_s(0.02)
            self.configure(mode="continuous")
            self.clock.sleep_s(0.02)
            self.read()
            off = self._average(SELF_TEST_SAMPLES)
            write_field(self.dev, ST_FIELD, 1, verify=self.verify)
            self.clock.sleep_s(0.06)
            self.read()
            on = self._average(SELF_TEST_SAMPLES)
            write_field(self.dev, ST_FIELD, 0, verify=self.verify)
        finally:
            self.stuck_limit = stuck
            self.soft_reset()
            self.configure(**saved)
        delta = np.abs(on - off)
        passed = all(lo <= d <= hi for d, (lo, hi) in zip(delta, SELF_TEST_WINDOW_UT, strict=True))
        result = SelfTestResult(passed, tuple(float(x) for x in delta), SELF_TEST_WINDOW_UT,
                                tuple(float(x) for x in off), tuple(float(x) for x in on))
        if not passed:
            exc = SelfTestFailed(f"lis3mdl self-test failed: |on-off| = {np.round(delta, 1).tolist()} uT, "
                                 f"windows {SELF_TEST_WINDOW_UT} uT")
            exc.result = result
            raise exc
        return result
