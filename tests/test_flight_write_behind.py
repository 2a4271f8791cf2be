"""Write-behind (fsync off the rate group's critical path): the rate groups only queue
telemetry rows, packets and event lines; a writer thread (hardware) or the idle slot (virtual time) writes
and fsyncs them; a full queue drops and counts, never blocks; shutdown drains and closes every file whole;
a simulated run writes the same bytes as the synchronous path."""
from __future__ import annotations

import json
import os
import threading

import pytest

from magstack.cli.commands.run import _sim_options
from magstack.data.dictionary import APP_APID
from magstack.data.session import read_session
from magstack.firmware.errors import FlightConfigError
from magstack.firmware.flight import executive
from magstack.firmware.flight.app import FlightApp
from magstack.firmware.flight.config import load_config
from magstack.firmware.flight.events import EventId, EventLog
from magstack.firmware.flight.writer import DEFAULT_CAPACITY, WriteBehind
from magstack.ground.tm_decode import DecodeReport, iter_packets
from tests.test_ccsds_packets import sim_config


def _packets(data):
    return [(p.apid, p.seq_count, p.raw) for p in iter_packets(data, DecodeReport())]


def _files(directory):
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir()) if p.is_file()}


def _run_sim(cfg, out, *, write_behind, seconds=30.0):
    app = FlightApp(load_config(cfg), virtual=True, simulate=True, telemetry_dir=out, run_id=1,
                    write_behind=write_behind, chip_options=_sim_options("rotation", seconds, 0))   # as run --sim
    try:
        app.run(seconds)
    finally:
        app.close()
    return app


@pytest.mark.parametrize("rotate_mb", [None, 0.01])
def test_simulated_run_writes_the_bytes_of_the_synchronous_path(tmp_path, rotate_mb):
    cfg = sim_config(tmp_path)                               # one config and table for both runs
    if rotate_mb is not None:
        cfg.write_text(cfg.read_text().replace("rotate_mb = 16 ", f"rotate_mb = {rotate_mb}"))
    sync = _run_sim(cfg, tmp_path / "sync", write_behind=False)
    behind = _run_sim(cfg, tmp_path / "behind", write_behind=True)
    assert sync.writer is None and behind.writer.offered > 0 and behind.writer.depth == 0
    a, b = _files(tmp_path / "sync"), _files(tmp_path / "behind")
    csvs = [n for n in a if n.endswith(".csv")]
    assert set(a) == set(b) and "packets-0001.bin" in a and "events-0001.jsonl" in a
    assert len(csvs) >= (6 if rotate_mb else 2) and not any(n.endswith(".part") for n in a)
    for name in csvs:
        assert a[name] == b[name], name                     # telemetry: byte for byte
    if rotate_mb is None:
        assert a["packets-0001.bin"] == b["packets-0001.bin"]
        assert a["events-0001.jsonl"] == b["events-0001.jsonl"]
    else:
        # TLM_FILE_ROTATED is emitted by the writer, i.e. after the other events of its slot: the channel and
        # group packets are the same, byte for byte in order; events are the same lines, a few in another order
        pa, pb = (_packets(x["packets-0001.bin"]) for x in (a, b))
        assert [p for p in pa if p[0] != APP_APID] == [p for p in pb if p[0] != APP_APID]
        same = str(tmp_path / "sync"), str(tmp_path / "behind")                  # the rotated file's path
        assert (sorted(str(p[2]).replace(*same) for p in pa if p[0] == APP_APID)
                == sorted(str(p[2]) for p in pb if p[0] == APP_APID))
        assert (sorted(a["events-0001.jsonl"].decode().replace(*same).splitlines())
                == sorted(b["events-0001.jsonl"].decode().splitlines()))
        assert behind.events.count(EventId.TLM_FILE_ROTATED) >= 4
    assert len(read_session(tmp_path / "behind" / csvs[0])) > 0


def test_no_rate_group_cycle_calls_fsync_in_virtual_time(tmp_path, monkeypatch):
    """Counted, not timed: an fsync made while a rate group's run_once is on the stack is a failure."""
    in_cycle = threading.local()
    calls = {"in_cycle": 0, "idle": 0}
    real_fsync, real_run_once = os.fsync, executive.RateGroup.run_once

    def fsync(fd):
        calls["in_cycle" if getattr(in_cycle, "on", False) else "idle"] += 1
        return real_fsync(fd)

    def run_once(self, *a, **kw):
        in_cycle.on = True
        try:
            return real_run_once(self, *a, **kw)
        finally:
            in_cycle.on = False

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(executive.RateGroup, "run_once", run_once)
    cfg = sim_config(tmp_path)
    _run_sim(cfg, tmp_path / "behind", write_behind=True)
    assert calls["in_cycle"] == 0 and calls["idle"] > 10
    calls.update(in_cycle=0, idle=0)
    _run_sim(cfg, tmp_path / "sync", write_behind=False)          # the synchronous path: fsync inside the cycles
    assert calls["in_cycle"] > 0


def test_a_slow_fsync_runs_on_the_writer_thread_only(tmp_path, monkeypatch):
    """Real time, threads: every fsync of the run is made by the writer thread, none by a rate-group thread,
    though each takes 30 ms longer (an SD card's); counted by thread name, not timed."""
    threads = []
    real_fsync = os.fsync
    stall = threading.Event()

    def slow_fsync(fd):
        threads.append(threading.current_thread().name)
        stall.wait(0.03)
        return real_fsync(fd)

    cfg = sim_config(tmp_path)
    app = FlightApp(load_config(cfg), virtual=False, simulate=True, telemetry_dir=tmp_path / "tlm", run_id=1)
    monkeypatch.setattr(os, "fsync", slow_fsync)
    try:
        app.run(3.0)
    finally:
        app.close()
    during = [t for t in threads if t != threading.current_thread().name]     # close() drains on this thread
    assert during and set(during) == {"flight-writer"}
    assert not any(t.startswith("rg-") for t in threads)
    assert app.writer.stats()["dropped"] == {} and app.writer.depth == 0
    assert sorted(p.name for p in (tmp_path / "tlm").glob("*.part")) == []
    assert all(len(read_session(p)) > 0 for p in (tmp_path / "tlm").glob("*.csv"))


def test_a_full_queue_drops_counts_and_reports_one_event_per_outage():
    w = WriteBehind(capacity=2)
    done = []
    assert w.offer(done.append, 1, "telemetry/a") and w.offer(done.append, 2, "telemetry/a")
    assert not w.offer(done.append, 3, "telemetry/a") and not w.offer(done.append, 4, "packets")
    events = EventLog()
    w.report_overflow(events, 10.0)
    w.report_overflow(events, 11.0)                          # the same outage: reported once
    assert events.count(EventId.TLM_QUEUE_FULL, "writer") == 1
    assert "telemetry/a 1" in events.recent[-1].message and "packets 1" in events.recent[-1].message
    assert w.drain() == 2 and done == [1, 2]
    assert w.offer(done.append, 5, "telemetry/a") and w.offer(done.append, 6, "telemetry/a")
    assert not w.offer(done.append, 7, "events")              # a second outage
    w.report_overflow(events, 12.0)
    assert events.count(EventId.TLM_QUEUE_FULL) == 2 and w.stats()["outages"] == 2
    assert w.stats()["dropped"] == {"events": 1, "packets": 1, "telemetry/a": 1}
    assert w.drain() == 2 and done == [1, 2, 5, 6]


def test_write_queue_is_checked_at_load(tmp_path):
    cfg = sim_config(tmp_path)
    text = cfg.read_text()
    cfg.write_text(text.replace("[flight]\n", "[flight]\nwrite_queue = 8\n", 1))
    with pytest.raises(FlightConfigError, match="flight.write_queue"):
        load_config(cfg)
    cfg.write_text(text.replace("[flight]\n", "[flight]\nwrite_queue = 64\n", 1))
    assert load_config(cfg).write_queue == 64
    cfg.write_text(text)
    assert load_config(cfg).write_queue == DEFAULT_CAPACITY


def test_a_stalled_writer_never_blocks_the_loop_and_shutdown_drains(tmp_path):
    """The writer thread is held (a hung card): the rate groups go on; the queue fills, drops are counted
    and evented, the run ends degraded; once released, close writes everything queued and renames the files."""
    cfg = sim_config(tmp_path)
    cfg.write_text(cfg.read_text().replace("[flight]\n", "[flight]\nwrite_queue = 16\n", 1))
    app = FlightApp(load_config(cfg), virtual=True, simulate=True, telemetry_dir=tmp_path / "tlm", run_id=1)
    held = threading.Event()
    release = threading.Event()

    def hang(_item):
        held.set()
        release.wait(60)

    app.writer.offer(hang, None, "test")
    app.writer.start()                                        # the thread takes the hang job first
    assert held.wait(30)
    app.run(20.0)
    st = app.writer.stats()
    assert app.executive.group("fast").stats.runs >= 190      # 10 Hz for 20 s: the loop did not wait
    assert st["waiting"] == 16 and sum(st["dropped"].values()) > 0 and st["outages"] == 1
    assert app.events.count(EventId.TLM_QUEUE_FULL, "writer") == 1
    assert any("write queue full" in r for r in app.degraded_reasons())
    release.set()
    app.close()
    assert app.writer.depth == 0 and app.writer.stats()["written"] == st["offered"]
    names = sorted(p.name for p in (tmp_path / "tlm").iterdir())
    assert not any(n.endswith(".part") for n in names) and "hmc1053-0001-0001.csv" in names
    for p in (tmp_path / "tlm").glob("*.csv"):
        read_session(p)                                      # whole: closing line and CRC check


def test_run_reports_the_write_queue(tmp_path, capsys):
    from magstack.cli.main import main

    cfg = sim_config(tmp_path)
    assert main(["run", "--config", str(cfg), "--sim", "--duration", "5", "--out", str(tmp_path / "tlm")]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if "write queue" in x)
    assert "items written behind the rate groups" in line and line.endswith("0 dropped for a full queue")
    assert main(["run", "--config", str(cfg), "--sim", "--duration", "5", "--out", str(tmp_path / "tlm"),
                 "--json"]) == 0
    wq = json.loads(capsys.readouterr().out)["write_queue"]
    assert wq["written"] == wq["offered"] > 0 and wq["dropped"] == {} and wq["waiting"] == 0
