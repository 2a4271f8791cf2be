"""Ground tools under faults and hostile input: `tm decode` attribution and output rule, the table posterior
check, the bounded readers (every hang-prone case runs in a child process with a memory limit and a timeout),
and `merge` on impossible ADCS data."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.firmware import cal_table as ct
from magstack.firmware.errors import CalTableInvalid
from tests.test_ccsds_packets import sim_config


def _one_line(capsys, argv, code):
    got = main(argv)
    err = capsys.readouterr().err
    assert got == code, (argv, got, err)
    assert "Traceback" not in err
    return err


# ------------------------------------------------------------------------------------- tm decode: attribution
def _run(root: Path, *, swap: bool = False, seconds: int = 25) -> Path:
    """A simulated run (run id 1 in its own telemetry directory); ``swap``: the sensors in the other order."""
    cfg = sim_config(root)
    if swap:
        text = cfg.read_text()
        head, rest = text.split("[[sensor]]", 1)
        first, second = rest.split("[[sensor]]", 1)
        second, tail = second.split("# CCSDS", 1)
        cfg.write_text(head + "[[sensor]]" + second + "[[sensor]]" + first + "# CCSDS" + tail)
    assert main(["run", "--config", str(cfg), "--duration", str(seconds), "--out", str(root / "tlm"), "-q"]) == 0
    return root / "tlm"


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    a = _run(tmp_path_factory.mktemp("run_a"))
    b = _run(tmp_path_factory.mktemp("run_b"), swap=True)
    return a, b


def _decoded(out: Path) -> dict[str, list]:
    got: dict[str, list] = {}
    for p in sorted(out.glob("*.csv")):
        s = read_session(p)
        got.setdefault(s.metadata["telemetry_channel"], []).append(s)
    return got


def test_concatenated_runs_with_sensors_in_another_order_never_mix(two_runs, tmp_path, capsys):
    a, b = two_runs
    both = tmp_path / "both.bin"
    both.write_bytes((a / "packets-0001.bin").read_bytes() + (b / "packets-0001.bin").read_bytes())
    assert main(["tm", "decode", str(both), "--out", str(tmp_path / "dec"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["unattributed"] == 0 and rep["identity_conflicts"] == 2      # APIDs 0x100, 0x101 renamed by run b
    got = _decoded(tmp_path / "dec")
    for ch in ("hmc1053", "lis3mdl"):
        want = [read_session(d / f"{ch}-0001-0001.csv") for d in (a, b)]
        dec = got[ch]
        assert len(dec) == 2, ch                                 # split, one file per run instance
        assert {s.metadata["device_id"] for s in dec} == {f"{ch}:sn1"}
        for w, d in zip(want, dec, strict=True):
            assert len(w) == len(d) and np.allclose(w.dut_uT, d.dut_uT, atol=1e-4, equal_nan=True), ch


def test_rows_a_lost_identification_cannot_vouch_for_are_refused_and_counted(two_runs, tmp_path, capsys):
    from magstack.ground.tm_decode import DecodeReport, iter_packets

    a, b = two_runs
    pb = bytearray((b / "packets-0001.bin").read_bytes())
    rep = DecodeReport()
    offsets, at = [], 0
    for p in iter_packets(bytes(pb), rep):                  # the run's first identification packets
        n = 7 + int.from_bytes(pb[at + 4:at + 6], "big")
        if p.packet.name == "apid_map" and len(offsets) < 8:
            offsets.append(at)
        at += n
    for o in offsets[:8]:                  # every identification of run b before its first channel packet: lost
        pb[o + 20] ^= 0xFF
    both = tmp_path / "both.bin"
    both.write_bytes((a / "packets-0001.bin").read_bytes() + bytes(pb))
    assert main(["tm", "decode", str(both), "--out", str(tmp_path / "dec"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["bad_packets"] >= 2 and out["unattributed"] > 0
    got = _decoded(tmp_path / "dec")
    total = sum(len(read_session(d / f"{ch}-0001-0001.csv")) for d in (a, b) for ch in ("hmc1053", "lis3mdl"))
    assert sum(len(s) for v in got.values() for s in v) + out["unattributed"] == total    # every row counted
    for ch in ("hmc1053", "lis3mdl"):                            # and no row in another sensor's file
        ref = np.vstack([read_session(d / f"{ch}-0001-0001.csv").dut_uT for d in (a, b)])
        for s in got[ch]:
            for row in s.dut_uT[np.all(np.isfinite(s.dut_uT), axis=1)]:
                assert np.min(np.max(np.abs(ref - row), axis=1)) <= 1e-4, ch


def test_two_runs_of_one_directory_are_two_outputs(tmp_path, capsys):
    cfg = sim_config(tmp_path)
    for _ in range(2):
        assert main(["run", "--config", str(cfg), "--duration", "5", "--out", str(tmp_path / "tlm"), "-q"]) == 0
    both = tmp_path / "both.bin"
    both.write_bytes(b"".join((tmp_path / f"tlm/packets-000{k}.bin").read_bytes() for k in (1, 2)))
    capsys.readouterr()
    assert main(["tm", "decode", str(both), "--out", str(tmp_path / "dec"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["runs"] == [1, 2] and rep["unattributed"] == 0
    for run in (1, 2):
        s = read_session(tmp_path / "dec" / f"lis3mdl-{run:04d}-0001.csv")
        assert len(s) == 50 and np.all(s.session == run)


# ------------------------------------------------------------------------------------- tm decode: output rule
def test_decode_never_replaces_the_flight_files_nor_follows_a_planted_symlink(two_runs, tmp_path, capsys):
    a, _ = two_runs
    import shutil

    tlm = tmp_path / "tlm"
    shutil.copytree(a, tlm)
    before = {p.name: p.read_bytes() for p in tlm.iterdir()}
    err = _one_line(capsys, ["tm", "decode", str(tlm / "packets-0001.bin"), "--out", str(tlm)], 2)
    assert "decode into another directory" in err
    assert {p.name: p.read_bytes() for p in tlm.iterdir()} == before          # nothing replaced
    # a directory holding the flight's files (not the input's own) is refused too
    other = tmp_path / "copy.bin"
    other.write_bytes((tlm / "packets-0001.bin").read_bytes())
    err = _one_line(capsys, ["tm", "decode", str(other), "--out", str(tlm)], 2)
    assert "holds the flight application's files" in err
    # planted temporary-file symlinks point at a victim: never followed
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me\n")
    dec = tmp_path / "dec"
    dec.mkdir()
    for name in (".events.jsonl.tmp", ".housekeeping.jsonl.tmp", ".decode-report.json.tmp",
                 ".hmc1053-0001-0001.csv.part", "hmc1053-0001-0001.csv.part"):
        os.symlink(victim, dec / name)
    assert main(["tm", "decode", str(other), "--out", str(dec), "-q"]) == 2    # a .part file is the flight's
    for p in dec.iterdir():
        if p.name.endswith(".part"):
            p.unlink()
    assert main(["tm", "decode", str(other), "--out", str(dec), "-q"]) == 0
    assert victim.read_text() == "keep me\n"
    assert len(read_session(dec / "hmc1053-0001-0001.csv")) == 25
    # an output name already taken by a file no decode wrote: refused; a second decode into its own output: fine
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "events.jsonl").write_text("precious\n")
    assert main(["tm", "decode", str(other), "--out", str(tmp_path / "mine"), "-q"]) == 2
    assert (tmp_path / "mine" / "events.jsonl").read_text() == "precious\n"
    assert main(["tm", "decode", str(other), "--out", str(dec), "-q"]) == 0


def test_decode_says_the_bad_packet_count_and_strict_refuses(two_runs, tmp_path, capsys):
    a, _ = two_runs
    data = bytearray((a / "packets-0001.bin").read_bytes())
    data[200] ^= 0x55
    bad = tmp_path / "bad.bin"
    bad.write_bytes(bytes(data))
    assert main(["tm", "decode", str(bad), "--out", str(tmp_path / "d1")]) == 0
    err = capsys.readouterr().err
    assert "1 bad packets" in err
    err = _one_line(capsys, ["tm", "decode", str(bad), "--out", str(tmp_path / "d2"), "--strict"], 3)
    assert "--strict" in err and not (tmp_path / "d2").exists()


# ------------------------------------------------------------------------------------- table posterior
def _posterior_table(path: Path, cov_x, **extra) -> Path:
    names = {a: [f"S[{a},{j}]" for j in "xyz"] + [f"O[{a}]"] for a in "xyz"}
    post = {a: {"names": names[a], "cov": (np.eye(4) * 1e-6).tolist()} for a in "xyz"}
    post["x"]["cov"] = cov_x
    post.update(extra)
    ct.save_table(ct.CalTable(device_id="lis3mdl:sn1", terms=("gain_matrix", "offset"), S=np.eye(3), O=np.zeros(3),
                              validity_field_uT=100.0, posterior=post), path)
    return path


def _cov(entries: dict | None = None) -> list:
    c = np.eye(4) * 1e-6
    for (i, j), v in (entries or {}).items():
        c[i, j] = v
    return c.tolist()


@pytest.mark.parametrize("case, cov, extra, why", [
    ("negative variance beside a large one", _cov({(0, 0): 1e10, (1, 1): -1.0}), {}, "negative variance"),
    ("asymmetry beside a large one", _cov({(0, 0): 1e10, (2, 3): 5e-7}), {}, "not symmetric"),
    ("not positive semi-definite", _cov({(1, 2): 3e-6, (2, 1): 3e-6}), {}, "not positive semi-definite"),
    ("huge entries", (np.full((4, 4), 1e308)).tolist(), {}, "beyond any posterior covariance"),
    ("negative sigma", None, {"sigma_uT": [0.1, -0.2, 0.1]}, "sigma_uT[1]"),
    ("negative bound", None, {"bound_uT": -1.0}, "bound_uT"),
    ("negative noise floor", None, {"noise_floor_uT": [-1e-3, 0.0, 0.0]}, "noise_floor_uT[0]"),
])
def test_posterior_check_refuses_in_one_line(tmp_path, capsys, case, cov, extra, why):
    p = _posterior_table(tmp_path / "t.json", cov if cov is not None else _cov(), **extra)
    for argv, code in ((["table", "validate", str(p)], 1), (["table", "show", str(p)], 3),
                       (["apply", str(p), str(p), "--out", str(tmp_path / "o.csv")], 3)):
        err = _one_line(capsys, argv, code)
        assert why in err and len(err.strip().splitlines()) == 1, (case, err)
    # the flight table store refuses it too: nothing staged
    from magstack.firmware.flight.tables import FlightTableStore

    store = FlightTableStore("lis3mdl:sn1", "lis3mdl", (tmp_path,), tmp_path)
    with pytest.raises(CalTableInvalid, match=why.split("[")[0]):
        store.load(p)
    assert store._staged is None and store.reject_count == 1


def test_a_valid_posterior_with_disparate_scales_is_accepted(tmp_path, capsys):
    p = _posterior_table(tmp_path / "t.json", _cov({(0, 0): 1e10, (3, 3): 1e-20}), sigma_uT=[0.1, 0.1, 0.1],
                         bound_uT=0.5, noise_floor_uT=[0.0, 0.01, 0.02])
    assert main(["table", "validate", str(p)]) == 0


# ------------------------------------------------------------------------------------- bounded readers
CHILD = textwrap.dedent("""
    import resource, sys
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))      # a reader that reads without bound fails here
    from magstack.cli.main import main
    sys.exit(main(sys.argv[1:]))
""")


def _child(argv, timeout=60):
    """``magstack argv`` in a child process (memory limit 3 GiB, ``timeout`` s): (exit code, stderr)."""
    try:
        r = subprocess.run([sys.executable, "-c", CHILD, *argv], capture_output=True, text=True, timeout=timeout,
                           cwd=Path(__file__).resolve().parents[1])
    except subprocess.TimeoutExpired:
        pytest.fail(f"hang: magstack {' '.join(argv)} still running after {timeout} s")
    return r.returncode, r.stderr


@pytest.fixture(scope="module")
def merge_inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("readers")
    assert main(["simulate", "--program", "orbit_tumbling", "--seconds", "120", "--rate-hz", "1", "--t0",
                 "1780272000", "--out", str(d / "orbit.csv"), "-q"]) == 0
    s = read_session(d / "orbit.csv")
    from magstack.data.session import Session, write_session
    from magstack.data.telemetry import POS_COLUMNS, QUAT_COLUMNS

    mag = Session(s.t_s, s.ref_uT, s.dut_uT, s.temp_c, s.session, extra={})
    write_session(d / "mag.csv", mag)
    rows = ["t_s," + ",".join(POS_COLUMNS + QUAT_COLUMNS)]
    for k in range(len(s)):
        rows.append(",".join(f"{v:.9f}" for v in (s.t_s[k], *(s.extra[c][k] for c in POS_COLUMNS + QUAT_COLUMNS))))
    (d / "adcs.csv").write_text("\n".join(rows) + "\n")
    return d


@pytest.mark.slow
def test_readers_refuse_devices_fifos_and_huge_files_in_one_line(merge_inputs, tmp_path):
    d = merge_inputs
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    sparse = tmp_path / "huge.bin"
    with open(sparse, "wb") as fh:
        fh.truncate(6 << 30)                                          # 6 GiB, sparse
    cases = [
        (["merge", str(d / "mag.csv"), "--adcs", "/dev/zero", "--out", str(tmp_path / "m1.csv")], 3, "regular file"),
        (["merge", str(d / "mag.csv"), "--adcs", str(fifo), "--out", str(tmp_path / "m2.csv")], 3, "regular file"),
        (["merge", "/dev/zero", "--adcs", str(d / "adcs.csv"), "--out", str(tmp_path / "m3.csv")], 3, "regular file"),
        (["fit", "/dev/zero", "--out", str(tmp_path / "t.json")], 3, "regular file"),
        (["fit", str(fifo), "--out", str(tmp_path / "t2.json")], 3, "regular file"),
        (["align", str(sparse)], 3, "more than the"),
        (["tm", "decode", "/dev/zero", "--out", str(tmp_path / "dz")], 3, "regular file"),
        (["tm", "decode", str(sparse), "--out", str(tmp_path / "dh")], 3, "more than the"),
        (["refit", str(fifo), "--out", str(tmp_path / "c.json")], 3, "regular file"),
    ]
    for argv, code, why in cases:
        got, err = _child(argv)
        assert got == code and "Traceback" not in err and why in err, (argv, got, err[-500:])
        assert len(err.strip().splitlines()) == 1, (argv, err)


def test_tm_decode_streams_a_long_file_in_blocks(two_runs, tmp_path):
    from magstack.ground.tm_decode import DecodeReport, iter_packets, iter_stream

    a, _ = two_runs
    data = (a / "packets-0001.bin").read_bytes()
    junk = bytes((k * 37) % 256 for k in range(5000))
    stream = data[:3001] + junk + data[3001:] + b"\0" * 70_000 + data[:500]
    (tmp_path / "s.bin").write_bytes(stream)
    whole, blocks = DecodeReport(), DecodeReport()
    want = [(p.apid, p.seq_count) for p in iter_packets(stream, whole)]
    got = [(p.apid, p.seq_count) for p in iter_stream(tmp_path / "s.bin", blocks, block_bytes=4099)]
    assert got == want and blocks.to_dict() == whole.to_dict() and whole.bad_packets >= 2


# ------------------------------------------------------------------------------------- merge: impossible ADCS
def _adcs_with(d: Path, tmp_path: Path, row: int, col: str, value: str) -> Path:
    lines = (d / "adcs.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row].split(",")
    cells[header.index(col)] = value
    lines[row] = ",".join(cells)
    p = tmp_path / f"adcs-{col}-{value}.csv"
    p.write_text("\n".join(lines) + "\n")
    return p


@pytest.mark.parametrize("pos, why", [(("1e308", "0", "0"), "beyond any Earth orbit"),
                                      (("0", "0", "0"), "inside the Earth"),
                                      (("3000", "2000", "1000"), "inside the Earth"),
                                      (("2e6", "0", "0"), "beyond any Earth orbit")])
def test_merge_refuses_impossible_positions(merge_inputs, tmp_path, capsys, pos, why):
    d = merge_inputs
    lines = (d / "adcs.csv").read_text().splitlines()
    cells = lines[5].split(",")
    cells[1:4] = pos
    lines[5] = ",".join(cells)
    p = tmp_path / "adcs.csv"
    p.write_text("\n".join(lines) + "\n")
    err = _one_line(capsys, ["merge", str(d / "mag.csv"), "--adcs", str(p), "--out", str(tmp_path / "m.csv")], 3)
    assert why in err and "line 6" in err


def test_merge_reports_skipped_samples_and_normalises_quaternions(merge_inputs, tmp_path, capsys):
    d = merge_inputs
    p = _adcs_with(d, tmp_path, 7, "pos_ecef_y_km", "nan")
    lines = p.read_text().splitlines()
    header = lines[0].split(",")
    k = header.index("q_body_eci_w")
    for r in range(1, len(lines)):                       # every quaternion 1.0009 long
        cells = lines[r].split(",")
        cells[k:k + 4] = [f"{float(c) * 1.0009:.12f}" for c in cells[k:k + 4]]
        lines[r] = ",".join(cells)
    p.write_text("\n".join(lines) + "\n")
    out = tmp_path / "m.csv"
    assert main(["merge", str(d / "mag.csv"), "--adcs", str(p), "--out", str(out), "--method", "nearest",
                 "--json"]) == 0
    io = capsys.readouterr()
    rep = json.loads(io.out)
    assert rep["adcs_rows_skipped"] == 1 and rep["adcs_skipped_lines"] == [8] and "1 ADCS samples" in io.err
    m = read_session(out)
    q = np.column_stack([m.extra[c] for c in ("q_body_eci_w", "q_body_eci_x", "q_body_eci_y", "q_body_eci_z")])
    ok = np.all(np.isfinite(q), axis=1)
    assert ok.sum() > 100 and np.allclose(np.linalg.norm(q[ok], axis=1), 1.0, atol=1e-9)
    assert m.metadata["adcs_samples_skipped"] == "1"
    # beyond the stated tolerance a quaternion is refused, not normalised
    lines[3] = ",".join(c if i < k else f"{float(c) * 1.01:.12f}" for i, c in enumerate(lines[3].split(",")))
    p.write_text("\n".join(lines) + "\n")
    err = _one_line(capsys, ["merge", str(d / "mag.csv"), "--adcs", str(p), "--out", str(tmp_path / "m2.csv")], 3)
    assert "quaternion norm" in err and "line 4" in err
