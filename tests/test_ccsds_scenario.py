"""Issue 23's scenario, the part that exists on this branch: simulated bench session -> `fit` -> table ->
`run --sim` with it (samples calibrated) -> packets -> `tm decode` -> a new table activated by telecommand at a
cycle boundary -> the CRC change in the decoded telemetry.

Not here: `merge` with simulated ADCS (built in parallel on another branch), hence no `refit` over decoded
telemetry (the second table is fitted on a second bench session instead) and no `diagnose` (decoded flight
telemetry has no reference field until it is merged)."""
from __future__ import annotations

import re

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.session import read_session
from magstack.firmware import cal_table as ct
from tests.test_ccsds_packets import sim_config


@pytest.mark.slow
def test_bench_fit_flight_packets_decode_and_table_swap_by_telecommand(tmp_path, capsys):
    from magstack.firmware.flight.app import FlightApp
    from magstack.firmware.flight.config import load_config

    tables = tmp_path / "tables"
    tables.mkdir()
    for seed, name in ((0, "hmc1053.json"), (1, "second.json")):
        bench = tmp_path / f"bench{seed}.csv"
        assert main(["simulate", "--chip", "hmc1053", "--seconds", "600", "--effects", "gain,offset,noise",
                     "--sessions", "1", "--seed", str(seed), "--out", str(bench), "-q"]) == 0
        assert main(["fit", str(bench), "--device-id", "hmc1053:sn1", "--model", "gain_offset", "--no-holdout",
                     "--out", str(tables / name), "-q"]) == 0
    first, second = (ct.load_table(tables / n).crc32 for n in ("hmc1053.json", "second.json"))
    assert first != second
    cfg = sim_config(tmp_path, table=False)
    text, n = re.subn(r'(device_id = "hmc1053:sn1"[^\n]*\n)', r'\1table = "tables/hmc1053.json"\n', cfg.read_text())
    assert n == 1
    cfg.write_text(text)
    app = FlightApp(load_config(cfg), virtual=True, simulate=True, telemetry_dir=tmp_path / "tlm", run_id=1)
    try:
        app.run(20.0)
        for args in (["load_table", "channel=hmc1053", "path=tables/second.json"],
                     ["activate_table", "channel=hmc1053"]):
            assert main(["tm", "command", *args, "--config", str(cfg), "-q"]) == 0
        app.run(20.0)
    finally:
        app.close()
    capsys.readouterr()
    assert main(["tm", "decode", str(tmp_path / "tlm/packets-0001.bin"), "--out", str(tmp_path / "dec"), "-q"]) == 0
    s = read_session(tmp_path / "dec" / "hmc1053-0001-0001.csv")
    crc = s.extra["table_crc32"]
    k = int(np.argmax(crc == second))
    assert len(s) == 40 and 15 <= k <= 25
    assert np.all(crc[:k] == first) and np.all(crc[k:] == second)        # one swap, at a cycle boundary
    assert np.all(np.isfinite(s.extra["cal_x_uT"]))                       # calibrated inside the validity box
    assert np.all(s.flag & 0b1111 == 0)                                   # every sample good
