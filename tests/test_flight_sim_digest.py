"""`magstack run --sim` writes the same telemetry bytes for the same configuration, seed and duration.

The example board (HMC1053 on the ADS1248 at 1 Hz, LIS3MDL at 10 Hz, `[ccsds]` packets, the default `rotation`
programme, seed 0) with a fixed identity-gain table runs 600 s of virtual time; the SHA-256 of every telemetry
file must equal the digests below. They pin the simulation's output: speeding up the executive, the simulated
buses, the chip models, the writer or the packet stream must not change one byte. A change to them is a change
of what the simulator or the flight code produces and has to be made on purpose (with the reason in the commit).
"""
from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from magstack.cli.main import main

DATA = Path(__file__).parent / "data" / "flight-digest"

#: SHA-256 of each output of `run --config flight.toml --duration 600` (tests/data/flight-digest/).
DIGESTS = {
    "events-0001.jsonl": "1494eedc021fd4f914eea086413f3c008323a5f56bd65769d3b0e31854de6cf0",
    "hmc1053-0001-0001.csv": "942125eb7887aebb2cefff368ad1f35dd0c4b0d7e1ea09a37603651bcb2e7b75",
    "lis3mdl-0001-0001.csv": "00c7739122b686f80540c8a207841299bbdf7d583802aea13e883e7bcc3c5d47",
    "packets-0001.bin": "a124f9a83f693e44e231c5fb5daf2c919bd05f92fffad6627628739b9afcdc2e",
}


def _config(tmp_path: Path) -> Path:
    (tmp_path / "tables").mkdir()
    shutil.copy(DATA / "hmc1053.json", tmp_path / "tables" / "hmc1053.json")
    shutil.copy(DATA / "flight.toml", tmp_path / "flight.toml")
    return tmp_path / "flight.toml"


@pytest.mark.slow
def test_600_simulated_seconds_of_the_example_board_are_byte_identical(tmp_path, capsys, monkeypatch):
    _config(tmp_path)
    monkeypatch.chdir(tmp_path)          # the table's path in the TABLE_ACTIVATED event is the config's, as given
    assert main(["run", "--config", "flight.toml", "--duration", "600", "--out", "tlm", "-q"]) == 0
    capsys.readouterr()
    got = {name: hashlib.sha256((tmp_path / "tlm" / name).read_bytes()).hexdigest() for name in DIGESTS}
    assert got == DIGESTS
