"""`run` telemetry into `refit`: informational flag bits keep a row, bad bits drop it,
a flag that is not a non-negative integer is bad input (exit 3)."""
from __future__ import annotations

import numpy as np
import pytest

from magstack.cli.main import main
from magstack.data.errors import SessionFileError
from magstack.data.session import read_session, write_session
from magstack.data.telemetry import iter_telemetry
from magstack.firmware.calibration.refit import RefitOptions, refit
from magstack.firmware.flight.channel import BAD, INFORMATIONAL, TlmFlag


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    path = tmp_path_factory.mktemp("orbit") / "orbit.csv"
    assert main(["simulate", "--program", "orbit_tumbling", "--seconds", "7200", "--rate-hz", "1", "--sessions",
                 "1", "--seed", "3", "--t0", "1780272000", "--effects", "misalignment,gain,offset,noise",
                 "--out", str(path)]) == 0
    return path


def _with_flags(src, dst, pattern):
    s = read_session(src)
    s.flag = np.resize(np.asarray(pattern, dtype=np.int64), len(s))
    return write_session(dst, s), s.flag


def test_informational_bits_do_not_disqualify_a_row(orbit, tmp_path):
    # what `run` writes: 16 (no table), 128/144 (overrun, informational), 32|16 out of validity, 256 repeat
    good = [0, int(TlmFlag.UNCALIBRATED), int(TlmFlag.OVERRUN), int(TlmFlag.OVERRUN | TlmFlag.UNCALIBRATED),
            int(TlmFlag.OUT_OF_VALIDITY | TlmFlag.UNCALIBRATED), int(TlmFlag.REPEATED)]
    bad = [int(TlmFlag.NO_SAMPLE), int(TlmFlag.IMPLAUSIBLE | TlmFlag.OVERRUN), int(TlmFlag.DEGRADED | 1),
           int(TlmFlag.STALE), 1 << 20]
    pattern = good * 2 + bad
    path, flags = _with_flags(orbit, tmp_path / "flags.csv", pattern)
    r = refit([path], options=RefitOptions(robust=False))
    n_bad = int(np.isin(flags, bad).sum())
    assert n_bad > 1000 and r.counts.get("flag: not a good sample") == n_bad   # only the bad rows are excluded
    assert not INFORMATIONAL & BAD and not INFORMATIONAL & TlmFlag.DEGRADED


@pytest.mark.parametrize("value", ["0.5", "-0.9", "-1", "3.25"])
def test_a_flag_that_is_not_a_bit_set_is_bad_input(orbit, tmp_path, value, capsys):
    path, _ = _with_flags(orbit, tmp_path / "ok.csv", [0])
    lines = path.read_text().splitlines(keepends=True)
    k = next(i for i, line in enumerate(lines) if not line.startswith("#") and line[0].isdigit())
    cells = lines[k + 5].rstrip("\n").split(",")
    cells[-1] = value
    lines[k + 5] = ",".join(cells) + "\n"
    bad = tmp_path / "bad.csv"
    bad.write_text("".join(lines))
    with pytest.raises(SessionFileError, match="'flag' must be a non-negative integer"):
        for _ in iter_telemetry(bad):
            pass
    assert main(["refit", str(bad), "--out", str(tmp_path / "cand.json")]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'flag' must be a non-negative integer" in err[0]
