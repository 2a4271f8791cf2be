"""The ground-to-flight scenario, end to end: a simulated bench session -> `fit` -> table -> the flight application on
simulated buses along an orbit (the truth of `run --sim --sim-program orbit_tumbling`) with that table (samples
calibrated inside its validity box) -> packets -> `tm decode` -> `merge` with a simulated ADCS log of the same
orbit -> `refit` -> candidate -> `load_table` + `activate_table` as telecommands while the application keeps
running -> the CRC change at a cycle boundary in the decoded telemetry -> `diagnose` on the decoded telemetry
merged with the ADCS log (IGRF reference).

The flight application runs in this process in virtual time (as `magstack run --sim --duration` does) so that it
can go on after the ground steps; every ground step is the command line a user runs (`main([...])`). Only the
HMC1053 channel of the example board is kept: the orbit truth costs one IGRF evaluation per simulated sample."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.firmware import cal_table as ct
from tests.test_ccsds_packets import sim_config

#: Virtual seconds of flight before the ground steps, and after the telecommands.
FIRST_S, SECOND_S = 400.0, 30.0
#: The flight simulation's HMC1053 (sim/hmc1053_bridge.default_sensor): the preset without the ADC-side
#: effects the front-end model does itself. The bench session simulates the same part.
BENCH_EFFECTS = ["--without", "time_skew,quantization,saturation"]


def _decode(tmp_path, name, capsys) -> dict:
    capsys.readouterr()
    assert main(["tm", "decode", str(tmp_path / "tlm/packets-0001.bin"), "--out", str(tmp_path / name), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.slow
def test_bench_fit_orbit_flight_packets_merge_refit_activate_by_telecommand_diagnose(tmp_path, capsys):
    from magstack.cli.commands.run import _sim_options
    from magstack.firmware.flight.app import FlightApp
    from magstack.firmware.flight.config import load_config

    # bench: a temperature-cycled session of the part -> table (validity -20..60 degC)
    tables = tmp_path / "tables"
    tables.mkdir()
    bench = tmp_path / "bench.csv"
    assert main(["simulate", "--chip", "hmc1053", "--program", "temp_cycling", "--seconds", "1200", *BENCH_EFFECTS,
                 "--sessions", "1", "--seed", "0", "--out", str(bench), "-q"]) == 0
    assert main(["fit", str(bench), "--device-id", "hmc1053:sn1", "--model", "eq3", "--no-holdout",
                 "--out", str(tables / "hmc1053.json"), "-q"]) == 0
    bench_table = ct.load_table(tables / "hmc1053.json")
    first = bench_table.crc32

    cfg = sim_config(tmp_path, table=False)
    text, n = re.subn(r'(device_id = "hmc1053:sn1"[^\n]*\n)', r'\1table = "tables/hmc1053.json"\n', cfg.read_text())
    text, m = re.subn(r'\[\[sensor\]\]\nname = "lis3mdl".*?\n\n', "", text, flags=re.S)
    assert n == 1 and m == 1
    cfg.write_text(text)
    app = FlightApp(load_config(cfg), virtual=True, simulate=True, telemetry_dir=tmp_path / "tlm", run_id=1,
                    chip_options=_sim_options("orbit_tumbling", FIRST_S + SECOND_S, seed=0))
    t0 = app.epoch_of(0.0)
    try:
        app.run(FIRST_S)
        # ground, while the spacecraft flies on: decode what was downlinked so far
        rep = _decode(tmp_path, "dec1", capsys)
        assert rep["bad_packets"] == 0 and rep["seq_missing"] == 0
        s1 = read_session(tmp_path / "dec1/hmc1053-0001-0001.csv")
        assert len(s1) == rep["by_packet"]["channel"] >= 0.9 * FIRST_S
        assert np.all(s1.extra["table_crc32"] == first) and np.all(s1.flag == 0)
        lo, hi = bench_table.validity_temp_c
        assert np.all((s1.temp_c >= lo) & (s1.temp_c <= hi))               # inside the table's validity box ...
        assert np.all(np.isfinite(s1.extra["cal_x_uT"]))                    # ... so every sample is calibrated
        # a simulated ADCS log of the same orbit on its own clock (0.5 Hz): position and attitude columns
        adcs = tmp_path / "adcs.csv"
        assert main(["simulate", "--program", "orbit_tumbling", "--t0", f"{t0:.6f}", "--seconds",
                     str(FIRST_S + SECOND_S + 30), "--rate-hz", "0.5", "--sessions", "1", "--effects", "noise",
                     "--out", str(adcs), "-q"]) == 0
        capsys.readouterr()
        assert main(["merge", str(tmp_path / "dec1/hmc1053-0001-0001.csv"), "--adcs", str(adcs),
                     "--out", str(tmp_path / "merged1.csv"), "--json"]) == 0
        f = json.loads(capsys.readouterr().out)["files"][0]
        assert f["rows"] == f["merged"] == len(s1) and f["without_adcs"] == 0
        # refit from the bench table: 20 s blocks, every third held out (a few minutes of orbit)
        rc = main(["refit", str(tmp_path / "merged1.csv"), "--active", str(tables / "hmc1053.json"),
                   "--holdout-block-s", "20", "--holdout-every", "3", "--out", str(tables / "candidate.json"),
                   "--json", "-q"])
        r = json.loads(capsys.readouterr().out)
        assert rc == 0 and r["proposed"] is True, r["reasons"]
        assert r["rows"] == len(s1) and r["rows_holdout"] >= 100
        # the orbit's IGRF reference agrees with what the DUT saw: the candidate beats the bench table
        assert r["holdout_rms_candidate_norm_uT"] < 0.5 * r["holdout_rms_active_norm_uT"]
        assert main(["table", "validate", str(tables / "candidate.json"), "-q"]) == 0
        second = ct.load_table(tables / "candidate.json").crc32
        assert second != first
        # uplink: stage and activate the candidate by telecommand; the application keeps running
        for args in (["load_table", "channel=hmc1053", "path=tables/candidate.json"],
                     ["activate_table", "channel=hmc1053"]):
            assert main(["tm", "command", *args, "--config", str(cfg), "-q"]) == 0
        app.run(SECOND_S)
    finally:
        app.close()

    rep = _decode(tmp_path, "dec", capsys)
    assert rep["bad_packets"] == 0 and rep["seq_missing"] == 0
    assert rep["by_packet"]["accept_ok"] == rep["by_packet"]["complete_ok"] == 2
    s = read_session(tmp_path / "dec/hmc1053-0001-0001.csv")
    crc = s.extra["table_crc32"]
    k = int(np.argmax(crc == second))
    assert len(s) > k >= len(s1) and len(s) - k >= SECOND_S - 5
    assert np.all(crc[:k] == first) and np.all(crc[k:] == second)        # one swap, between two cycles
    assert np.all(np.isfinite(s.extra["cal_x_uT"])) and np.all(s.flag == 0)
    activated = [json.loads(line) for line in (tmp_path / "dec/events.jsonl").read_text().splitlines()]
    activated = [e for e in activated if e["name"] == "TABLE_ACTIVATED"]
    assert activated[-1]["message"] == f"crc32 0x{second:08x}" and s1.t_s[-1] < activated[-1]["t_s"] < s.t_s[k]

    # diagnose the decoded telemetry, merged with the ADCS log: reference = IGRF along the orbit (auto)
    assert main(["merge", str(tmp_path / "dec/hmc1053-0001-0001.csv"), "--adcs", str(adcs),
                 "--out", str(tmp_path / "merged.csv"), "-q"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(tmp_path / "merged.csv"), "--table", str(tables / "candidate.json"),
                 "--json", "-q"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert "verdict" in d and d["reference"]["reference"] == "igrf" and d["n_rows"] >= 0.9 * len(s)
    assert d["reference_budget"] is not None and d["reference_budget"]["total_nT"] > 0
