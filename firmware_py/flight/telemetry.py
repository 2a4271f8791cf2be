"""Telemetry files: one rotating series of session files per channel.

Every record a channel publishes becomes one row of a session file (docs/session-file.md), so
``magstack fit``, ``diagnose`` and ``refit`` read telemetry without conversion:

* ``dut_x_uT..dut_z_uT`` the **raw** sensor output (what a calibration is fitted to), ``temp_c``,
  ``session`` the boot/run id, ``flag`` the record's :class:`~magstack.firmware.flight.channel.TlmFlag`
  bits (0 = good and calibrated), ``ref_*`` empty (no reference on board);
* extra columns ``cal_x_uT, cal_y_uT, cal_z_uT`` (the published calibrated field, empty when not
  calibrated), ``table_crc32`` (the table that produced it) and ``error_count``.

Files are crash-safe like every session file (``.part``, fsync per block, atomic rename on close)
and rotate when they reach ``rotate_bytes``: ``<dir>/<channel>-<run>-<index>.csv``. An existing file
is never overwritten (its index is skipped).

A write that fails (disk full, I/O error) never reaches the channel: the rows of the failed block and
every row offered while writing is impossible are counted (``rows_lost``, event ``TLM_WRITE_ERROR`` once
per outage); the broken file is left as its ``.part`` (every block fsynced before the failure stays
readable) and a fresh file is tried again ``retry_s`` later (record time), so writing resumes by itself
when space returns (event ``TLM_RECOVERED`` with the number of rows lost).
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

from magstack.data.errors import FileWriteError
from magstack.data.session import SessionWriter
from magstack.firmware.flight.channel import TelemetryRecord, TlmFlag
from magstack.firmware.flight.events import EventId, EventLog

EXTRA_COLUMNS = ("cal_x_uT", "cal_y_uT", "cal_z_uT", "table_crc32", "error_count")
_NAN3 = (math.nan, math.nan, math.nan)
#: Bytes of one row, for rotation bookkeeping (the writer does not report file sizes per row).
_ROW_BYTES_ESTIMATE = 160
#: Seconds (record time) between attempts to resume writing after a write error.
RETRY_S = 5.0


def flag_legend() -> str:
    return " ".join(f"{int(f)}={f.name.lower()}" for f in TlmFlag)


class ChannelTelemetry:
    """Writes one channel's records; call it with each record (it is the channel's ``sink``)."""

    def __init__(self, directory: str | os.PathLike, channel: str, *, run_id: int, metadata: Mapping[str, str],
                 rotate_bytes: int = 16 << 20, block_rows: int = 50, events: EventLog | None = None,
                 retry_s: float = RETRY_S) -> None:
        if rotate_bytes < 4096:
            raise ValueError(f"rotate_bytes must be >= 4096, got {rotate_bytes}")
        self.directory = Path(directory)
        self.channel = channel
        self.run_id = int(run_id)
        self.metadata = dict(metadata)
        self.rotate_bytes = int(rotate_bytes)
        self.block_rows = int(block_rows)
        self.events = events
        self.index = 0
        self.files: list[Path] = []
        self.rows = 0
        self.retry_s = float(retry_s)
        self.rows_lost = 0              # rows that could not be written
        self.write_errors = 0           # outages (a failed write after a good one)
        self._writer: SessionWriter | None = None
        self._bytes = 0
        self.broken: list[Path] = []    # .part files left by a write error (every fsynced block readable)
        self._failed_at: float | None = None    # record time of the last failure while broken
        self._lost_in_outage = 0
        self._handed = 0                # rows given to the current writer
        self._last_t = 0.0
        self._in_writer = False         # the current record was given to the writer

    def _open(self) -> SessionWriter:
        """The next file of the series; an existing file or ``.part`` is never reused (its index is skipped)."""
        while True:
            self.index += 1
            path = self.directory / f"{self.channel}-{self.run_id:04d}-{self.index:04d}.csv"
            if not (path.exists() or path.with_name(path.name + ".part").exists()):
                break
        meta = {**self.metadata, "telemetry_channel": self.channel, "telemetry_file_index": str(self.index),
                "flag_bits": flag_legend(), "dut_field": "raw"}
        try:
            w = SessionWriter(path, meta, with_flag=True, block_rows=self.block_rows, extra_names=EXTRA_COLUMNS,
                             integer_extras=("table_crc32", "error_count"))
        except FileWriteError:              # the header could not be written: remove the empty .part we made
            self.index -= 1
            _remove(path.with_name(path.name + ".part"))
            raise
        self.files.append(path)
        self._bytes = 0
        self._handed = 0
        return w

    def __call__(self, rec: TelemetryRecord) -> None:
        """Write one record; a failure is counted and evented, never raised (the loop must go on)."""
        self._last_t = rec.t_s
        if self._failed_at is not None and rec.t_s - self._failed_at < self.retry_s:
            self.rows_lost += 1
            self._lost_in_outage += 1
            return
        try:
            self._write(rec)
        except (OSError, ValueError) as exc:     # FileWriteError (disk full ...) and SessionFileError
            self._fail(rec.t_s, exc)
            return
        if self._failed_at is not None:
            self._failed_at = None
            if self.events is not None:
                self.events.emit(rec.t_s, EventId.TLM_RECOVERED, self.channel,
                                 f"writing {self.files[-1].name}; {self._lost_in_outage} rows lost")
            self._lost_in_outage = 0

    def _fail(self, t_s: float, exc: Exception, *, current: bool = True) -> None:
        """Count what is lost: the current record (``current``) and the rows the failed writer did not write."""
        w, self._writer = self._writer, None
        lost = 1 if current and not self._in_writer else 0    # the record never reached a writer
        if w is not None:
            block = self._handed - w.rows_written             # handed to the writer, never written
            lost += block
            self.rows -= block - (1 if current and self._in_writer else 0)
            self.broken.append(w.part_path)
            if self.files and self.files[-1] == w.path:
                self.files.pop()
            try:
                w.abort()                              # close the .part as it is (no rename)
            except (OSError, ValueError):
                pass
        self.rows_lost += lost
        self._lost_in_outage += lost
        if self._failed_at is None:
            self.write_errors += 1
            if self.events is not None:
                self.events.emit(t_s, EventId.TLM_WRITE_ERROR, self.channel,
                                 f"{type(exc).__name__}: {exc}; rows are counted as lost until writing resumes"[:200])
        self._failed_at = t_s

    def _write(self, rec: TelemetryRecord) -> None:
        self._in_writer = False
        if self._writer is None:
            self._writer = self._open()
        elif self._bytes >= self.rotate_bytes:
            self._writer.close()
            if self.events is not None:
                self.events.emit(rec.t_s, EventId.TLM_FILE_ROTATED, self.channel, str(self.files[-1]))
            self._writer = self._open()
        cal = rec.cal_uT or _NAN3
        self._handed += 1
        self._in_writer = True
        self._writer.write_row(rec.t_s, _NAN3, rec.raw_uT or _NAN3,
                               math.nan if rec.temp_c is None else rec.temp_c, self.run_id, flag=rec.flags,
                               extra={"cal_x_uT": cal[0], "cal_y_uT": cal[1], "cal_z_uT": cal[2],
                                      "table_crc32": math.nan if rec.table_crc32 is None else rec.table_crc32,
                                      "error_count": rec.error_count})
        self.rows += 1
        self._bytes += _ROW_BYTES_ESTIMATE

    def flush(self) -> None:
        if self._writer is not None:
            self._writer.flush()

    def stats(self) -> dict:
        return {"rows": self.rows, "rows_lost": self.rows_lost, "write_errors": self.write_errors,
                "files": len(self.files), "broken_files": [str(p) for p in self.broken]}

    def close(self) -> None:
        """Flush and rename the current file to its final name (a failure is counted, not raised)."""
        if self._writer is not None:
            try:
                self._writer.close()
            except (OSError, ValueError) as exc:
                self._fail(self._last_t, exc, current=False)
            self._writer = None


def _remove(path: Path) -> None:
    try:
        path.unlink()
    except OSError:
        pass
