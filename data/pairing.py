"""DUT and reference streams of a session: the one row split, and the one time-series cleaning.

A raw bench session interleaves DUT rows (``dut_*`` filled, ``ref_*`` empty) and reference rows
(the other way round); a paired session has both on every row. :func:`split_streams` takes the
rows where all three DUT axes are finite as the DUT stream (with their temperature) and the rows
where all three reference axes are finite as the reference stream - a paired row belongs to both.
:func:`sort_unique` sorts a stream by time and drops repeated timestamps (the first row is
kept); :func:`finite_rows` is the usual row filter before it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magstack.data.errors import SessionFileError
from magstack.data.session import Session, row_line


def finite_rows(t_s: np.ndarray, *arrays: np.ndarray) -> np.ndarray:
    """Mask of rows where ``t_s`` and every column of each array are finite."""
    ok = np.isfinite(np.asarray(t_s, float)).reshape(-1)
    if not ok.size:   # no rows (a header-only file): reshape(0, -1) is undefined
        return ok
    for a in arrays:
        a = np.asarray(a, float)
        ok &= np.all(np.isfinite(a.reshape(ok.size, -1)), axis=1)
    return ok


def sort_unique(t_s: np.ndarray, *arrays: np.ndarray, keep: np.ndarray | None = None
                ) -> tuple[np.ndarray, list[np.ndarray], int]:
    """Rows (``keep`` mask, default all) sorted by time, repeated timestamps dropped (first kept).

    Returns ``(t_s, [arrays...], n_duplicates_dropped)``; the sort is stable.
    """
    t = np.asarray(t_s, float).reshape(-1)
    if keep is not None:
        t, arrays = t[keep], tuple(np.asarray(a)[keep] for a in arrays)
    order = np.argsort(t, kind="stable")
    t = t[order]
    first = np.concatenate([[True], np.diff(t) > 0]) if t.size else np.zeros(0, bool)
    return t[first], [np.asarray(a)[order][first] for a in arrays], int((~first).sum())


@dataclass(frozen=True)
class Streams:
    """The DUT and reference streams of one session (rows in file order)."""

    session: Session
    dut_rows: np.ndarray      #: (N,) bool: rows with all three DUT axes finite
    ref_rows: np.ndarray      #: (N,) bool: rows with all three reference axes finite

    @property
    def t_dut_s(self) -> np.ndarray:
        return self.session.t_s[self.dut_rows]

    @property
    def dut_uT(self) -> np.ndarray:
        return self.session.dut_uT[self.dut_rows]

    @property
    def temp_dut_c(self) -> np.ndarray:
        """Temperature (degC) on the DUT rows (may hold NaN)."""
        return self.session.temp_c[self.dut_rows]

    @property
    def t_ref_s(self) -> np.ndarray:
        return self.session.t_s[self.ref_rows]

    @property
    def ref_uT(self) -> np.ndarray:
        return self.session.ref_uT[self.ref_rows]

    def require_increasing(self) -> None:
        """SessionFileError naming file and line when a stream's timestamps do not strictly increase."""
        for what, rows in (("DUT", self.dut_rows), ("reference", self.ref_rows)):
            idx = np.flatnonzero(rows)
            t = self.session.t_s[idx]
            bad = np.flatnonzero(~(np.diff(t) > 0))
            if bad.size:
                k = int(idx[bad[0] + 1])
                line = row_line(self.session, k)
                where = f"{self.session.source or '<session>'}: " + (f"line {line}: " if line else f"row {k + 1}: ")
                raise SessionFileError(f"{where}t_s {float(t[bad[0] + 1])!r} is not after the previous {what} row's "
                                       f"{float(t[bad[0]])!r}: {what} timestamps must strictly increase (sort the file "
                                       "and drop repeated rows first)")


def split_streams(session: Session) -> Streams:
    """Split a session into its DUT stream and its reference stream (see module doc)."""
    return Streams(session, np.all(np.isfinite(session.dut_uT), axis=1), np.all(np.isfinite(session.ref_uT), axis=1))
