"""The command directory under abuse: hostile files are rejected once, with an
event and a result, without blocking or crashing; commands run at most once; telemetry is never overwritten."""
from __future__ import annotations

import json
import os
import stat
import threading
from pathlib import Path

import numpy as np
import pytest

from magstack.firmware import cal_table as ct
from magstack.firmware.errors import FlightConfigError
from magstack.firmware.flight.app import FlightApp
from magstack.firmware.flight.config import parse_config
from magstack.firmware.flight.events import EventId
from magstack.sim.coil_programs import program
from magstack.sim.i2c_bench import default_bench

TRUTH = program("rotation", 200.0, sessions=1)


def _config(root, **flight):
    doc = {"flight": {"name": "cmds", "telemetry_dir": "tlm", "command_dir": "cmd", **flight},
           "rate_group": [{"name": "fast", "rate_hz": 10.0}],
           "sensor": [{"name": "lis3mdl", "chip": "lis3mdl", "bus": "sim", "rate_group": "fast",
                       "device_id": "lis3mdl:sn1", "options": {"odr_hz": 40.0}}]}
    return parse_config(doc, root / "flight.toml")


def _app(root, **kw):
    return FlightApp(_config(root, **kw.pop("flight", {})), virtual=True, simulate=True,
                     chip_options=lambda s, clock: {"bench": default_bench(clock, TRUTH, seed=1)}, **kw)


def _table(path, device="lis3mdl:sn1"):
    path.parent.mkdir(parents=True, exist_ok=True)
    ct.save_table(ct.CalTable(device_id=device, terms=("gain_matrix", "offset"), S=np.eye(3), O=np.zeros(3),
                              validity_field_uT=100.0), path)
    return path


def _cmd(root, name, doc):
    p = root / "cmd" / name
    p.write_text(json.dumps(doc))
    return p


def _results(root):
    return {p.name[: -len(".result.json")]: json.loads(p.read_text())
            for p in (root / "cmd" / "done").glob("*.result.json")}


def _huge_int_table(path):
    """A table whose CRC is right but one offset is a 400-digit integer (float() of it overflows)."""
    good = _table(path.with_name("good-for-huge.json"))
    doc = json.loads(good.read_text())
    doc["parameters"]["O"]["value"][0] = 10 ** 400
    doc.pop("crc32")
    doc["crc32"] = f"0x{ct._crc(doc):08x}"
    path.write_text(json.dumps(doc))
    return path


def test_hostile_command_files_are_rejected_once_without_blocking(tmp_path):
    root = tmp_path
    (root / "cmd").mkdir(mode=0o700)
    good = _table(root / "tables" / "good.json")
    outside = _table(tmp_path.parent / f"{tmp_path.name}-elsewhere" / "t.json")
    fifo_table = root / "tables" / "fifo.json"
    os.mkfifo(fifo_table)
    huge = _huge_int_table(root / "tables" / "huge.json")
    _cmd(root, "01-devzero.json", {"cmd": "load_table", "channel": "lis3mdl", "path": "/dev/zero"})
    _cmd(root, "02-huge-int.json", {"cmd": "load_table", "channel": "lis3mdl", "path": str(huge)})
    _cmd(root, "03-fifo-table.json", {"cmd": "validate_table", "channel": "lis3mdl", "path": "tables/fifo.json"})
    _cmd(root, "04-outside.json", {"cmd": "load_table", "channel": "lis3mdl", "path": str(outside)})
    _cmd(root, "05-etc.json", {"cmd": "start_refit", "channel": "lis3mdl", "files": "/etc/*"})
    with open(root / "cmd" / "06-sparse.json", "wb") as fh:      # 100 MiB, sparse: refused before a byte is read
        fh.truncate(100 << 20)
    os.symlink(good, root / "cmd" / "07-symlink.json")
    os.mkfifo(root / "cmd" / "08-fifo.json")
    _cmd(root, "09-world-writable.json", {"cmd": "dump_counters"}).chmod(0o666)
    foreign = _cmd(root, "10-foreign.json", {"cmd": "dump_counters"})
    os.chown(foreign, 12345, 12345) if os.geteuid() == 0 else None
    _cmd(root, "11-load-good.json", {"cmd": "load_table", "channel": "lis3mdl", "path": "tables/good.json"})
    _cmd(root, "12-linked-table.json", {"cmd": "load_table", "channel": "lis3mdl", "path": "tables/link.json"})
    os.symlink("/etc/passwd", root / "tables" / "link.json")
    unblock = threading.Timer(60.0, lambda: open(fifo_table, "wb").close())   # a reader opening the FIFO waits
    unblock.start()
    app = _app(root, run_id=1)
    try:
        app.run(10.0)
    finally:
        unblock.cancel()
        app.close()
    res = _results(root)
    expect = {"01-devzero.json": "outside the allowed directories",
              "02-huge-int.json": "integer of 401 digits",
              "03-fifo-table.json": "not a regular file",
              "04-outside.json": "outside the allowed directories",
              "05-etc.json": "outside the allowed directories",
              "06-sparse.json": "more than the limit of 65536",
              "07-symlink.json": "is a symbolic link",
              "08-fifo.json": "not a regular file",
              "09-world-writable.json": "writable by group or others",
              "12-linked-table.json": "symbolic link"}
    if os.geteuid() == 0:
        expect["10-foreign.json"] = "owned by uid 12345"
    for name, why in expect.items():
        assert res[name]["ok"] is False and why in res[name]["message"], (name, res[name]["message"])
        assert app.events.count(EventId.CMD_REJECTED, name) == 1, name
    assert res["11-load-good.json"]["ok"] is True
    assert app.events.count(EventId.TABLE_LOADED, "lis3mdl") == 1
    # nothing left to take, nothing running twice, the sensor group never skipped a slot
    assert sorted(os.listdir(root / "cmd" / "processing")) == []
    assert app.executive.group("fast").stats.missed_slots == 0
    assert app.slots["lis3mdl"].channel.cycles == 100


def test_command_directory_is_private(tmp_path):
    old = os.umask(0)
    try:
        app = _app(tmp_path, run_id=1)
        app.close()
        assert stat.S_IMODE(os.stat(tmp_path / "cmd").st_mode) == 0o700
        open_dir = tmp_path / "open"
        open_dir.mkdir(mode=0o777)
        with pytest.raises(FlightConfigError, match="writable by group or others"):
            _app(tmp_path, run_id=2, flight={"command_dir": "open"})
    finally:
        os.umask(old)


def test_each_command_runs_at_most_once(tmp_path, monkeypatch):
    root = tmp_path
    (root / "cmd" / "done" / "01.json").mkdir(parents=True)       # done/ cannot take 01.json
    (root / "cmd" / "done" / "01.json" / "x").write_text("")
    _cmd(root, "01.json", {"cmd": "dump_counters"})
    _cmd(root, "02.json", {"cmd": "dump_counters"})                # cannot be claimed (rename refused)
    (root / "cmd" / "processing").mkdir(mode=0o700)
    (root / "cmd" / "processing" / "03.json").write_text(json.dumps({"cmd": "dump_counters"}))   # crash leftover
    rename = os.rename

    def refuse(src, dst, *a, **k):
        if str(src).endswith("02.json"):
            raise PermissionError(13, "Permission denied", str(src))
        return rename(src, dst, *a, **k)
    monkeypatch.setattr(os, "rename", refuse)
    app = _app(root, run_id=1)
    try:
        app.run(5.0)                     # ten polls of the command spool
    finally:
        app.close()
    assert app.events.count(EventId.CMD_ACCEPTED, "01.json") == 1
    assert app.events.count(EventId.CMD_COMPLETED, "01.json") == 1
    assert app.events.count(EventId.CMD_ACCEPTED, "02.json") == 0
    assert app.events.count(EventId.CMD_REJECTED, "02.json") == 1              # reported once, never run
    assert app.events.count(EventId.CMD_ACCEPTED, "03.json") == 0
    assert app.events.count(EventId.CMD_REJECTED, "03.json") == 1
    assert "interrupted" in _results(root)["03.json"]["message"]


def test_a_fresh_run_id_never_overwrites_telemetry(tmp_path):
    app = _app(tmp_path)
    app.run(2.0)
    app.close()
    assert app.run_id == 1
    first = {p.name: p.read_bytes() for p in (tmp_path / "tlm").glob("lis3mdl-*.csv")}
    assert first
    (tmp_path / "tlm" / "events-0001.jsonl").unlink()              # the event log is gone, the data is not
    (tmp_path / "tlm" / "lis3mdl-0002-0001.csv.part").write_text("# killed run\n")
    app = _app(tmp_path)
    app.run(2.0)
    app.close()
    assert app.run_id == 3
    assert {p.name: p.read_bytes() for p in (tmp_path / "tlm").glob("lis3mdl-0001-*.csv")} == first


def test_allowed_directories_with_relative_paths(tmp_path, monkeypatch):
    """A config given by a relative path (`magstack run --config flight.toml`) names relative roots."""
    from magstack.firmware.flight.intake import UnsafeInput, inside_roots

    _table(tmp_path / "tables" / "t.json")
    os.symlink(tmp_path / "tables", tmp_path / "linked")
    monkeypatch.chdir(tmp_path)
    base, roots = Path("."), (Path("."),)
    assert inside_roots("tables/t.json", roots, base) == tmp_path.resolve() / "tables" / "t.json"
    for bad, why in (("../x.json", "outside"), ("tables/../../x.json", "outside"), ("/etc/passwd", "outside"),
                     ("linked/t.json", "symbolic link")):
        with pytest.raises(UnsafeInput, match=why):
            inside_roots(bad, roots, base)
