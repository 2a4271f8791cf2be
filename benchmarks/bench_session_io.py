"""Session file I/O against numpy on the same 1e6-row file.

    python benchmarks/bench_session_io.py [ROWS]

Builds a session of ROWS rows (default 1,000,000; 9 v1 columns plus one current and a flag),
then, best of 3 each, in this process:

* write: ``write_session`` (blocks of 20,000 rows, each fsynced, closing line, rename) vs
  ``numpy.savetxt`` of the same array with the same per-column formats;
* read: ``read_session`` vs ``numpy.loadtxt`` of the file ``write_session`` wrote (``#`` lines
  skipped as comments);
* read of a raw bench-like file (DUT and reference rows interleaved: every row has empty cells,
  which ``numpy.loadtxt`` cannot read) vs ``numpy.loadtxt`` of the gap-free file above;
* read of a file whose last row has a bad cell (the fast path fails, the line parser names the
  line) vs ``numpy.loadtxt``.

Prints the times and the ratios (target: <= 2 for the first two).
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _timing import best_wall_s  # noqa: E402  (sibling module; scripts run from benchmarks/)

from magstack.data.errors import SessionFileError  # noqa: E402
from magstack.data.session import Session, read_session, session_table, write_session  # noqa: E402


def _session(n: int, gaps: bool) -> Session:
    rng = np.random.default_rng(0)
    ref, dut = rng.normal(0, 30, (n, 3)), rng.normal(0, 30, (n, 3))
    if gaps:   # interleaved raw bench rows: even rows DUT only, odd rows reference only
        ref[0::2] = np.nan
        dut[1::2] = np.nan
    return Session(1.7e9 + np.arange(n) * 0.0125, ref, dut, 20 + rng.normal(0, 1, n), np.arange(n) // 100000,
                   {"coil": rng.uniform(-1, 1, n)}, {"dut_chip": "hmc1053", "reference": "fvm400"},
                   np.zeros(n, np.int64))


def main(argv: list[str]) -> int:
    n = int(argv[1]) if len(argv) > 1 else 1_000_000
    s, raw = _session(n, False), _session(n, True)
    table = session_table(s)
    fmt = ["%.6f"] * 7 + ["%.4f", "%d", "%.6f", "%d"]
    with tempfile.TemporaryDirectory(prefix="bench-session-io-") as tmp:
        d = Path(tmp)
        counter = iter(range(10_000))

        def ours_write() -> None:
            write_session(d / f"w{next(counter)}.csv", s)

        t_savetxt = best_wall_s(lambda: np.savetxt(d / "np.csv", table, fmt=fmt, delimiter=","))
        t_write = best_wall_s(ours_write)
        path = write_session(d / "s.csv", s)
        t_loadtxt = best_wall_s(lambda: np.loadtxt(path, delimiter=",", skiprows=4, comments="#"))
        t_read = best_wall_s(lambda: read_session(path))
        raw_path = write_session(d / "raw.csv", raw)
        t_read_gaps = best_wall_s(lambda: read_session(raw_path))
        bad = d / "bad.csv"
        bad.write_bytes(path.read_bytes().replace(b"\n# magstack-end", b"\n1,2,3,x,5,6,7,8,0,0,0\n# magstack-end"))

        def read_bad() -> None:
            try:
                read_session(bad)
            except SessionFileError:
                return
            raise AssertionError("bad file was accepted")

        t_bad = best_wall_s(read_bad, repeat=1)
        mb = path.stat().st_size / 1e6
    print(f"session file: {n:,} rows x {table.shape[1]} columns, {mb:.1f} MB")
    print(f"write: write_session {t_write:.3f} s  numpy.savetxt {t_savetxt:.3f} s  ratio {t_write / t_savetxt:.2f}")
    print(f"read:  read_session {t_read:.3f} s  numpy.loadtxt {t_loadtxt:.3f} s  ratio {t_read / t_loadtxt:.2f}")
    print(f"read, raw bench file with empty cells on every row: {t_read_gaps:.3f} s  "
          f"ratio to loadtxt of the gap-free file {t_read_gaps / t_loadtxt:.2f}")
    print(f"read, bad cell on the last row (fast path fails, line parser names it): {t_bad:.3f} s  "
          f"ratio {t_bad / t_loadtxt:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
