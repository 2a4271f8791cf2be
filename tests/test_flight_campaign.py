"""Seeded fault-injection campaign over the whole flight application, in virtual time.

Three channels (HMC1053 on the simulated ADS1248 at 1 Hz, LIS3MDL and LSM303DLHC on simulated I2C at
10 Hz) run for 700 simulated seconds (> 10,000 cycles). One I2C channel is the victim: a seeded schedule
injects bus errors, timeouts (stuck data-ready), frozen registers, garbage bytes, overflows and foreign
exceptions into its reads; a table corrupted on disk is commanded in; a command arrives mid-cycle. The
executive must never crash, every injected fault must appear once in its counter and once in the event
log, no published sample may be stale or corrupt while marked good, the healthy channels must keep their
rate, and everything must recover when the faults stop.
"""
from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import replace

import numpy as np
import pytest

from magstack.drivers.errors import BusError, BusTimeout
from magstack.firmware import cal_table as ct
from magstack.firmware.flight.app import FlightApp
from magstack.firmware.flight.channel import TlmFlag
from magstack.firmware.flight.config import parse_config
from magstack.firmware.flight.events import EventId
from magstack.sim.coil_programs import program
from magstack.sim.i2c_bench import default_bench

DURATION_S = 700.0
FAULT_END_S = 600.0
KINDS = ("bus", "timeout", "frozen", "garbage", "overflow", "exception")
#: counter and event each injected fault kind must land in
EXPECT = {"bus": ("bus_errors", EventId.CHAN_BUS_ERROR), "timeout": ("timeouts", EventId.CHAN_TIMEOUT),
          "frozen": ("stale", EventId.CHAN_STALE), "garbage": ("implausible", EventId.CHAN_IMPLAUSIBLE),
          "overflow": ("overflows", EventId.CHAN_OVERFLOW), "exception": ("exceptions", EventId.CHAN_EXCEPTION)}


class Injector:
    """Wraps a driver; on a seeded schedule a read fails or returns a damaged sample instead."""

    def __init__(self, mag, clock, seed: int, rate: float = 0.06):
        self.mag, self.clock, self.name = mag, clock, mag.name
        self.range_uT = getattr(mag, "range_uT", None)
        self.rng = np.random.default_rng(seed)
        self.rate = rate
        self.injected: Counter = Counter()
        self.damaged_t: dict[float, str] = {}     # sample time -> kind, for samples returned damaged
        self.last = None
        self.true_last = None

    def data_ready(self):
        return True

    def reinit(self):
        self.mag.reinit()

    def read(self):
        t = self.clock.monotonic_s()
        kind = None
        if t < FAULT_END_S and self.rng.random() < self.rate:
            kind = KINDS[self.rng.integers(len(KINDS))]
            if kind == "frozen" and (self.last is None or self.last.t_s in self.damaged_t):
                kind = "bus"      # registers freeze holding the last real conversion
        if kind is not None:
            self.injected[kind] += 1
        if kind == "bus":
            raise BusError("injected NACK", address=0x1C, operation="read")
        if kind == "timeout":
            self.clock.sleep_s(0.05)
            raise BusTimeout("injected: data-ready stuck low")
        if kind == "exception":
            raise ValueError("injected: invalid literal for int() with base 10")
        if kind == "frozen":
            self.clock.sleep_s(0.025)
            s = replace(self.last, t_s=self.clock.monotonic_s())   # new read, unchanged registers
            self.damaged_t[s.t_s] = kind
            return s
        s = self.mag.read()
        if kind == "garbage":                         # a corrupted high byte: hundreds of uT off
            b = list(s.b_uT)
            ax = int(self.rng.integers(3))
            b[ax] += float(self.rng.choice([-1, 1]) * self.rng.uniform(250.0, 700.0))
            b[ax] = float(np.clip(b[ax], -399.0, 399.0)) if abs(b[ax]) > 399 else b[ax]
            s = replace(s, b_uT=tuple(b), extra={**s.extra, "repeats": 0})
            self.damaged_t[s.t_s] = kind
        elif kind == "overflow":
            b = list(s.b_uT)
            b[0] = math.nan
            s = replace(s, b_uT=tuple(b), overflow=(0,))
            self.damaged_t[s.t_s] = kind
        self.last = s
        return s


CONFIG = {
    "flight": {"name": "campaign", "telemetry_dir": "tlm", "command_dir": "cmd", "block_rows": 200},
    "rate_group": [{"name": "slow", "rate_hz": 1.0}, {"name": "fast", "rate_hz": 10.0},
                   {"name": "fast2", "rate_hz": 10.0}],
    "sensor": [
        {"name": "hmc1053", "chip": "hmc1053", "bus": "sim", "rate_group": "slow", "device_id": "hmc1053:sn1",
         "table": "hmc1053.json"},
        {"name": "lis3mdl", "chip": "lis3mdl", "bus": "sim", "rate_group": "fast", "device_id": "lis3mdl:sn1",
         "options": {"odr_hz": 40.0}, "max_rate_uT_per_s": 1000.0},
        {"name": "lsm303dlhc", "chip": "lsm303dlhc", "bus": "sim", "rate_group": "fast2",
         "device_id": "lsm303dlhc:sn1", "options": {"odr_hz": 30.0}},
    ],
}


def _table(device: str, path) -> ct.CalTable:
    t = ct.CalTable(device_id=device, terms=("gain_matrix", "offset"), S=np.eye(3), O=np.zeros(3),
                    validity_field_uT=100.0, created_utc="2026-01-01T00:00:00Z")
    ct.save_table(t, path)
    return t


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    root = tmp_path_factory.mktemp("campaign")
    (root / "cmd").mkdir()
    cfg = parse_config(json.loads(json.dumps(CONFIG)), root / "flight.toml")
    _table("hmc1053:sn1", root / "hmc1053.json")
    _table("lis3mdl:sn1", root / "lis3mdl.json")
    good = root / "lis3mdl-new.json"
    _table("lis3mdl:sn1", good)
    bad = root / "lis3mdl-corrupt.json"
    raw = bytearray(good.read_bytes())
    i = raw.index(b'"value"', raw.index(b'"O"'))
    i = next(k for k in range(i, len(raw)) if chr(raw[k]).isdigit())
    raw[i] ^= 0x04                                # one flipped bit on disk: 0 -> 4 in an offset
    bad.write_bytes(bytes(raw))
    truth = program("rotation", DURATION_S + 10, sessions=1)
    injectors: dict[str, Injector] = {}

    def options(sensor, clock):
        if sensor.chip == "hmc1053":
            return {"truth": truth, "seed": 3}
        return {"bench": default_bench(clock, truth, seed=4)}

    app = FlightApp(cfg, virtual=True, simulate=True, chip_options=options, run_id=1)
    lis = app.slots["lis3mdl"].channel
    inj = Injector(lis.mag, app.clocks["fast"], seed=2024)
    lis.mag = inj
    injectors["lis3mdl"] = inj
    # commands: the corrupted table, then a good one and its activation, one arriving mid-cycle
    cmd = root / "cmd"
    (cmd / "01-load-corrupt.json").write_text(json.dumps({"cmd": "load_table", "channel": "lis3mdl",
                                                            "path": str(bad)}))
    mid_cycle = {"written_at": None}

    class MidCycleWriter:
        name = "writer"

        def __init__(self, clock):
            self.clock = clock

        def run(self, now_s):
            if mid_cycle["written_at"] is None and now_s >= 100.0:
                # written while the fast group is inside its cycle (between two channel reads)
                (cmd / "02-load-good.json").write_text(json.dumps({"cmd": "load_table", "channel": "lis3mdl",
                                                                     "path": str(good)}))
                (cmd / "03-activate.json").write_text(json.dumps({"cmd": "activate_table", "channel": "lis3mdl"}))
                (cmd / "04-dump.json").write_text(json.dumps({"cmd": "dump_counters"}))
                mid_cycle["written_at"] = now_s

    fast = app.executive.group("fast")
    fast.components.insert(0, MidCycleWriter(app.clocks["fast"]))
    records: dict[str, list] = {n: [] for n in app.slots}
    for name, slot in app.slots.items():
        sink = slot.channel.sink

        def tee(rec, _sink=sink, _name=name):
            records[_name].append(rec)
            _sink(rec)
        slot.channel.sink = tee
    app.run(DURATION_S)
    app.close()
    return app, injectors, records, root, mid_cycle


def test_campaign_size_and_no_crash(campaign):
    app, _, records, _, _ = campaign
    assert sum(len(r) for r in records.values()) >= 10_000
    assert app.events.count(EventId.EXEC_STOPPED) == 1


def test_every_injected_fault_is_counted_once_in_its_class(campaign):
    app, inj, _, _, _ = campaign
    lis = app.slots["lis3mdl"].channel
    injected = inj["lis3mdl"].injected
    assert sum(injected.values()) > 200 and all(injected[k] > 10 for k in KINDS)
    for kind, (counter, eid) in EXPECT.items():
        assert getattr(lis.health, counter) == injected[kind], kind
        assert app.events.count(eid, "lis3mdl") == injected[kind], kind
    assert lis.health.other_errors == 0


def test_no_bad_sample_is_published_as_good(campaign):
    _, inj, records, _, _ = campaign
    damaged = inj["lis3mdl"].damaged_t
    published_bad_as_good = [r for r in records["lis3mdl"] if r.good and r.t_s - 1767225600.0 in damaged]
    assert not published_bad_as_good
    for recs in records.values():
        for r in recs:
            if r.calibrated:
                assert r.good and not r.flags & (TlmFlag.OUT_OF_VALIDITY | TlmFlag.STALE)


def test_healthy_channels_keep_their_rate(campaign):
    app, _, records, _, _ = campaign
    for group, n_expected in (("fast2", 10 * DURATION_S), ("slow", DURATION_S)):
        st = app.executive.group(group).stats
        assert st.runs == pytest.approx(n_expected, abs=1) and st.missed_slots == 0, group
    assert all(r.good for r in records["lsm303dlhc"]) and all(r.good for r in records["hmc1053"])
    assert app.executive.group("fast").stats.min_interval_s >= 0.1 - 1e-9


def test_tables_commands_and_recovery(campaign):
    app, _, records, root, mid = campaign
    slot = app.slots["lis3mdl"]
    assert app.events.count(EventId.TABLE_REJECTED, "lis3mdl") == 1          # the corrupted file
    assert app.events.count(EventId.TABLE_LOADED, "lis3mdl") == 1
    assert app.events.count(EventId.TABLE_ACTIVATED, "lis3mdl") == 1          # the good one, at a boundary
    assert slot.store.active is not None and slot.store.reject_count == 1
    done = root / "cmd" / "done"
    results = {p.name: json.loads(p.read_text()) for p in done.glob("*.result.json")}
    assert results["01-load-corrupt.json.result.json"]["ok"] is False
    assert "CRC-32 mismatch" in results["01-load-corrupt.json.result.json"]["message"]
    assert all(results[f"{n}.result.json"]["ok"] for n in ("02-load-good.json", "03-activate.json", "04-dump.json"))
    assert "lis3mdl" in results["04-dump.json.result.json"]["result"]["channels"]
    # calibrated only after the activation, which came after the mid-cycle write
    first_cal = min(r.t_s for r in records["lis3mdl"] if r.calibrated) - 1767225600.0
    assert first_cal > mid["written_at"]
    # after the faults stop: every sample good and calibrated, channel not degraded
    tail = [r for r in records["lis3mdl"] if r.t_s - 1767225600.0 > FAULT_END_S + 1.0]
    assert len(tail) > 900 and all(r.good and r.calibrated for r in tail)
    assert not slot.channel.degraded


def test_telemetry_files_read_back_as_sessions(campaign):
    from magstack.data.session import read_session

    app, _, records, _, _ = campaign
    for name, slot in app.slots.items():
        rows = sum(len(read_session(p)) for p in slot.telemetry.files)
        assert rows == len(records[name])
        assert all(not str(p).endswith(".part") for p in slot.telemetry.files)


# ---------------------------------------------------------------------------------------------------------
# Register corruptions right after an outage (0.2-0.6 s after the last good sample), when a
# rate limit that grows with the gap would let them through.
class OutageThenCorruption:
    """Wraps a driver: on a seeded schedule 1-5 reads fail (NACK), then one sample comes back with a
    corrupted register (one axis 150-700 uT off, clipped to the range like a saturated high byte)."""

    def __init__(self, mag, seed: int, rate: float):
        self.mag, self.name, self.range_uT = mag, mag.name, getattr(mag, "range_uT", None)
        self.rng = np.random.default_rng(seed)
        self.rate = rate
        self.failing = 0
        self.corrupt_next = False
        self.corrupted_t: set[float] = set()
        self.episodes = 0

    def data_ready(self):
        return True

    def reinit(self):
        self.mag.reinit()

    def read(self):
        if self.failing == 0 and not self.corrupt_next and self.rng.random() < self.rate:
            self.failing = int(self.rng.integers(1, 6))
            self.episodes += 1
        if self.failing:
            self.failing -= 1
            self.corrupt_next = self.failing == 0
            raise BusError("injected NACK", address=0x1C, operation="read")
        s = self.mag.read()
        if self.corrupt_next:
            self.corrupt_next = False
            b = list(s.b_uT)
            ax = int(self.rng.integers(3))
            b[ax] = float(np.clip(b[ax] + self.rng.choice([-1, 1]) * self.rng.uniform(150.0, 700.0), -399.0, 399.0))
            s = replace(s, b_uT=tuple(b), extra={**s.extra, "repeats": 0})
            self.corrupted_t.add(round(s.t_s, 6))
        return s


@pytest.mark.slow
def test_corruptions_after_an_outage_are_never_published_as_good(tmp_path):
    cfg_doc = {"flight": {"name": "outage", "telemetry_dir": "tlm", "block_rows": 500},
               "rate_group": [{"name": "fast", "rate_hz": 10.0}],
               "sensor": [{"name": "lis3mdl", "chip": "lis3mdl", "bus": "sim", "rate_group": "fast",
                           "device_id": "lis3mdl:sn1", "options": {"odr_hz": 40.0}, "max_rate_uT_per_s": 1000.0,
                           "reinit_after": 10}]}
    cfg = parse_config(cfg_doc, tmp_path / "flight.toml")
    truth = program("rotation", 1210.0, sessions=1)
    app = FlightApp(cfg, virtual=True, simulate=True, run_id=1,
                    chip_options=lambda s, clock: {"bench": default_bench(clock, truth, seed=5)})
    ch = app.slots["lis3mdl"].channel
    inj = OutageThenCorruption(ch.mag, seed=77, rate=0.1)
    ch.mag = inj
    records = []
    sink = ch.sink

    def tee(rec):
        records.append(rec)
        sink(rec)
    ch.sink = tee
    app.run(1200.0)
    app.close()
    t0 = 1767225600.0
    corrupt = [r for r in records if r.raw_uT is not None and round(r.t_s - t0, 6) in inj.corrupted_t]
    published = [r for r in corrupt if r.good]
    good_rejected = [r for r in records
                     if r.flags & TlmFlag.IMPLAUSIBLE and round(r.t_s - t0, 6) not in inj.corrupted_t]
    print(f"outage campaign: {inj.episodes} episodes, {len(corrupt)} corrupt samples, {len(published)} published "
          f"as good, {len(good_rejected)} real samples held back")
    assert inj.episodes > 500 and len(corrupt) == len(inj.corrupted_t) >= inj.episodes - 1
    assert published == []
    # a real sample is held back only when the field moved beyond one period's change during an outage
    assert len(good_rejected) <= 0.02 * len(records)


# ---------------------------------------------------------------------------------------------------------
# A full disk. Telemetry loss is counted, the loop keeps every slot, the event log keeps no
# partial line, writing resumes by itself when space returns, the summary is written.
ONE_CHANNEL = {"flight": {"name": "disk", "telemetry_dir": "tlm", "block_rows": 10},
               "rate_group": [{"name": "fast", "rate_hz": 10.0}],
               "sensor": [{"name": "lis3mdl", "chip": "lis3mdl", "bus": "sim", "rate_group": "fast",
                           "device_id": "lis3mdl:sn1", "options": {"odr_hz": 40.0}}]}


class At:
    """A component running ``action`` once when its group's time passes ``t_s``."""

    name = "at"

    def __init__(self, t_s, action):
        self.t_s, self.action, self.done = t_s, action, False

    def run(self, now_s):
        if not self.done and now_s >= self.t_s:
            self.done = True
            self.action()


def _disk_app(root, tlm_dir, duration_s, actions, **flight):
    cfg = parse_config({**ONE_CHANNEL, "flight": {**ONE_CHANNEL["flight"], **flight}}, root / "flight.toml")
    truth = program("rotation", duration_s + 10, sessions=1)
    app = FlightApp(cfg, virtual=True, simulate=True, run_id=1, telemetry_dir=tlm_dir,
                    chip_options=lambda s, clock: {"bench": default_bench(clock, truth, seed=6)})
    fast = app.executive.group("fast")
    for t_s, action in actions:
        fast.components.insert(0, At(t_s, action))
    return app


def _check_recovered(app, tlm_dir, duration_s):
    from magstack.data.session import read_session

    tlm = app.slots["lis3mdl"].telemetry
    st = app.executive.group("fast").stats
    assert st.runs == pytest.approx(10 * duration_s, abs=1) and st.missed_slots == 0    # the loop kept running
    assert tlm.rows_lost > 0 and tlm.write_errors >= 1
    assert app.events.count(EventId.TLM_WRITE_ERROR, "lis3mdl") == tlm.write_errors
    assert app.events.count(EventId.TLM_RECOVERED, "lis3mdl") == tlm.write_errors
    assert tlm.rows + tlm.rows_lost == app.slots["lis3mdl"].channel.cycles            # every row written or counted
    assert tlm.files and all(len(read_session(p)) for p in tlm.files)                 # closed files read back
    assert sum(len(read_session(p)) for p in tlm.files) <= tlm.rows
    for line in (tlm_dir / "events-0001.jsonl").read_text().splitlines():
        json.loads(line)                                                                # no partial event line
    assert any("telemetry rows could not be written" in r for r in app.degraded_reasons())
    print(f"full disk: {app.slots['lis3mdl'].channel.cycles} cycles, {tlm.rows} rows written, {tlm.rows_lost} "
          f"counted lost in {tlm.write_errors} outage(s), {app.events.count(EventId.TLM_RECOVERED)} recovered, "
          f"{app._event_sink.lost} events lost, {len(tlm.files)} complete files")
    summary = app.write_summary(tlm_dir / "summary-0001.json")
    assert json.loads(summary.read_text())["channels"]["lis3mdl"]["telemetry"]["rows_lost"] == tlm.rows_lost
    return tlm


def test_full_disk_with_a_patched_writer(tmp_path, monkeypatch):
    import errno
    import os

    from magstack.data.io import write_error
    from magstack.data.session import SessionWriter

    disk = {"full": False}
    orig_write, orig_os_write = SessionWriter._write, os.write

    def write(self, data):
        if disk["full"]:
            raise write_error(self.part_path, OSError(errno.ENOSPC, "No space left on device"))
        return orig_write(self, data)

    app_box = {}

    def os_write(fd, data):
        sink = app_box.get("sink")
        if disk["full"] and sink is not None and fd == sink._fd:
            raise OSError(errno.ENOSPC, "No space left on device")
        return orig_os_write(fd, data)
    monkeypatch.setattr(SessionWriter, "_write", write)
    monkeypatch.setattr(os, "write", os_write)
    app = _disk_app(tmp_path, tmp_path / "tlm", 120.0, [(30.0, lambda: disk.update(full=True)),
                                                        (60.0, lambda: disk.update(full=False))])
    app_box["sink"] = app._event_sink
    app.run(120.0)
    app.close()
    tlm = _check_recovered(app, tmp_path / "tlm", 120.0)
    assert tlm.write_errors == 1 and 290 <= tlm.rows_lost <= 360     # 30 s at 10 Hz (+ the failed block)
    assert app._event_sink.lost >= 1


def test_full_disk_on_a_small_tmpfs(tmp_path):
    import os
    import subprocess

    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)],
                                           capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        filler = disk / "filler"
        st = os.statvfs(disk)
        filler.write_bytes(b"\0" * (st.f_bavail * st.f_frsize - 48 * 1024))   # leave 48 KiB: ~30 s of rows
        app = _disk_app(tmp_path, disk / "tlm", 150.0, [(100.0, filler.unlink)])
        try:
            app.run(150.0)
        finally:
            app.close()
        _check_recovered(app, disk / "tlm", 150.0)
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


# ---------------------------------------------------------------------------------------------------------
# A burst of 1,000 commands, each costing the group that handles it 5 ms (virtual time),
# must not make the sensor group skip a slot.
def test_a_burst_of_commands_does_not_starve_the_fast_group(tmp_path):
    root = tmp_path
    (root / "cmd").mkdir(mode=0o700)
    _table("lis3mdl:sn1", root / "lis3mdl.json")
    cfg = parse_config({**ONE_CHANNEL, "flight": {**ONE_CHANNEL["flight"], "command_dir": "cmd"}},
                       root / "flight.toml")
    truth = program("rotation", 200.0, sessions=1)
    app = FlightApp(cfg, virtual=True, simulate=True, run_id=1,
                    chip_options=lambda s, clock: {"bench": default_bench(clock, truth, seed=6)})
    for k in range(1000):
        (root / "cmd" / f"{k:04d}.json").write_text(json.dumps({"cmd": "validate_table", "channel": "lis3mdl",
                                                                "path": "lis3mdl.json"}))
    cost_s = 0.005
    # whichever group polls the spool or executes a command pays 5 ms of its own time per command
    for g in app.executive.groups:
        for i, hook in enumerate(g.boundary):
            if getattr(hook, "__self__", None) is app.spool:
                def polled(now_s, _hook=hook, _clock=g.clock):
                    n = _hook(now_s)
                    _clock.sleep_s(cost_s * n)
                    return n
                g.boundary[i] = polled
    execute = app._execute

    def costly(slot, cmd):
        app.clocks[slot.group if slot is not None else "fast"].sleep_s(cost_s)
        execute(slot, cmd)
    app._execute = costly
    app.run(160.0)
    app.close()
    fast = app.executive.group("fast").stats
    print(f"command burst: {app.spool.accepted} accepted, fast group {fast.runs} runs, "
          f"{fast.missed_slots} skipped slots")
    assert app.events.count(EventId.CMD_COMPLETED) == 1000           # every command executed, once
    assert fast.missed_slots == 0 and fast.runs == 1600
