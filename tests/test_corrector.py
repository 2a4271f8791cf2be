"""On-board TableCorrector (firmware_py/corrector.py): the flight channel's calibration step."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magstack.firmware.cal_table import CalTable, CalTableStore, save_table
from magstack.firmware.corrector import STATUSES, TableCorrector
from magstack.firmware.fixed_point import to_fixed_inputs
from magstack.firmware.float_applier import apply_float

EQ3 = ("gain_matrix", "temperature_gain", "offset", "temperature_offset")
S = np.array([[1.02, 0.01, -0.003], [0.004, 0.98, 0.02], [-0.01, 0.005, 1.01]])
K_S = np.full((3, 3), 2e-5)
O = np.array([1.5, -2.25, 0.75])
K_O = np.array([0.01, -0.02, 0.005])


def _store(tmp_path, *, name="cal.json", device="dev", temps=(-20.0, 60.0), field=200.0, S=S, O=O) -> CalTableStore:
    table = CalTable(device_id=device, terms=EQ3, S=S, K_S=K_S, O=O, K_O=K_O, t0_c=25.0, validity_temp_c=temps,
                     validity_field_uT=field)
    store = CalTableStore(device)
    store.load_and_activate(save_table(table, tmp_path / name))
    return store


def test_no_active_table_is_counted_not_applied():
    corr = TableCorrector(CalTableStore("dev"))
    c = corr.correct((10.0, -20.0, 30.0), 30.0)
    assert c.b_uT is None and c.status == "no_table" and c.table_crc32 is None
    assert corr.status["no_table"] == 1 and set(corr.status) <= set(STATUSES)


def test_matches_float_applier_on_the_same_rounded_inputs(tmp_path):
    store = _store(tmp_path)
    corr = TableCorrector(store)
    rng = np.random.default_rng(5)
    b = rng.uniform(-150, 150, (200, 3))
    t = rng.uniform(-20, 60, 200)
    bi, ti, _, _ = to_fixed_inputs(b, t)
    ref, _ = apply_float(store.active, bi / 1e3, ti / 1e2)
    got = np.array([corr.correct(tuple(bb), tt).b_uT for bb, tt in zip(b, t, strict=True)])
    assert np.max(np.abs(got - ref)) * 1e3 < 0.5   # integer arithmetic within half a nT of float64
    assert corr.status["ok"] == 200


def test_refuses_samples_it_cannot_calibrate(tmp_path):
    corr = TableCorrector(_store(tmp_path))
    cases = {
        "no_temperature": ((1.0, 2.0, 3.0), None),
        "out_of_validity": ((1.0, 2.0, 300.0), 25.0),   # |B_z| > 200 uT validity
        "bad_input": ((1e30, 2.0, 3.0), 25.0),          # beyond the applier's input range
    }
    for key, (b, t) in cases.items():
        c = corr.correct(b, t)
        assert c.b_uT is None and c.status == key, key
        assert corr.status[key] == 1, key
    assert corr.status["ok"] == 0
    assert corr.correct((1.0, 2.0, 3.0), 80.0).b_uT is None and corr.status["out_of_validity"] == 2


@pytest.mark.parametrize("b,temp,key", [
    ((1e308, 0.0, 0.0), 25.0, "bad_input"), ((math.nan, 0.0, 0.0), 25.0, "bad_input"),
    ((math.inf, 0.0, 0.0), 25.0, "bad_input"), ((1.0, 2.0, 3.0), 1e308, "no_temperature"),
    ((1.0, 2.0, 3.0), math.inf, "no_temperature")])
def test_never_raises_on_non_finite_or_overflowing_readings(tmp_path, b, temp, key):
    """A 1e308 or non-finite reading is refused by status, never an OverflowError inside the corrector."""
    corr = TableCorrector(_store(tmp_path))
    assert corr.correct(b, temp).b_uT is None
    assert corr.status[key] == 1 and sum(corr.status.values()) == 1


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=3, max_size=3),
       st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)))
def test_property_any_reading_gives_a_field_or_none(b, temp):
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        corr = TableCorrector(_store(Path(d)))
    out = corr.correct(tuple(b), temp).b_uT
    assert out is None or (len(out) == 3 and all(math.isfinite(v) for v in out))
    assert sum(corr.status.values()) == 1


def test_follows_the_table_swapped_in_at_the_cycle_boundary(tmp_path):
    store = _store(tmp_path)
    corr = TableCorrector(store)
    before = corr.correct((10.0, 20.0, 30.0), 25.0)
    table2 = CalTable(device_id="dev", terms=EQ3, S=np.eye(3), K_S=np.zeros((3, 3)), O=np.zeros(3),
                      K_O=np.zeros(3), t0_c=25.0, validity_temp_c=(-20.0, 60.0), validity_field_uT=200.0)
    store.load(save_table(table2, tmp_path / "identity.json"))
    store.request_activation()
    assert corr.correct((10.0, 20.0, 30.0), 25.0) == before           # staged, not yet active
    store.cycle_boundary()
    after = corr.correct((10.0, 20.0, 30.0), 25.0)
    assert after.b_uT == pytest.approx((10.0, 20.0, 30.0), abs=1e-9) and after.table_crc32 != before.table_crc32


def test_flight_channel_publishes_calibrated_field(tmp_path):
    from magstack.drivers.clock import VirtualClock
    from magstack.drivers.magnetometer import MagSample
    from magstack.firmware.flight.channel import MagChannel
    from magstack.firmware.flight.events import EventLog

    class Fixed:
        name = "fixed"

        def __init__(self, clock):
            self.clock, self.n = clock, 0

        def read(self):
            self.n += 1
            return MagSample(self.clock.monotonic_s(), (10.0, 20.0, 30.0 + 1e-3 * self.n), 25.0)

        def data_ready(self):
            return True

    clock = VirtualClock()
    store = _store(tmp_path)
    ch = MagChannel("c", Fixed(clock), TableCorrector(store), EventLog())
    rec = ch.run(clock.monotonic_s())
    expect, _ = apply_float(store.active, np.array([[10.0, 20.0, 30.001]]), np.array([25.0]))
    assert rec.calibrated and np.allclose(rec.cal_uT, expect[0], atol=5e-4)
    assert rec.table_crc32 == store.active.crc32
