"""Telemetry files: one rotating series of session files per channel.

Every record a channel publishes becomes one row of a session file (docs/session-file.md), so
``magstack fit``, ``diagnose`` and ``refit`` read telemetry without conversion:

* ``dut_x_uT..dut_z_uT`` the **raw** sensor output (what a calibration is fitted to), ``temp_c``,
  ``session`` the boot/run id, ``flag`` the record's :class:`~magstack.firmware.flight.channel.TlmFlag`
  bits (0 = good and calibrated), ``ref_*`` empty (no reference on board);
* extra columns ``cal_x_uT, cal_y_uT, cal_z_uT`` (the published calibrated field, empty when not
  calibrated), ``table_crc32`` (the table that produced it) and ``error_count``.

Files are crash-safe like every session file (``.part``, fsync per block, atomic rename on close)
and rotate when they reach ``rotate_bytes``: ``<dir>/<channel>-<run>-<index>.csv``.
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

from magstack.data.session import SessionWriter
from magstack.firmware.flight.channel import TelemetryRecord, TlmFlag
from magstack.firmware.flight.events import EventId, EventLog

EXTRA_COLUMNS = ("cal_x_uT", "cal_y_uT", "cal_z_uT", "table_crc32", "error_count")
_NAN3 = (math.nan, math.nan, math.nan)
#: Bytes of one row, for rotation bookkeeping (the writer does not report file sizes per row).
_ROW_BYTES_ESTIMATE = 160


def flag_legend() -> str:
    return " ".join(f"{int(f)}={f.name.lower()}" for f in TlmFlag)


class ChannelTelemetry:
    """Writes one channel's records; call it with each record (it is the channel's ``sink``)."""

    def __init__(self, directory: str | os.PathLike, channel: str, *, run_id: int, metadata: Mapping[str, str],
                 rotate_bytes: int = 16 << 20, block_rows: int = 50, events: EventLog | None = None) -> None:
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
        self._writer: SessionWriter | None = None
        self._bytes = 0

    def _open(self) -> SessionWriter:
        self.index += 1
        path = self.directory / f"{self.channel}-{self.run_id:04d}-{self.index:04d}.csv"
        meta = {**self.metadata, "telemetry_channel": self.channel, "telemetry_file_index": str(self.index),
                "flag_bits": flag_legend(), "dut_field": "raw"}
        w = SessionWriter(path, meta, with_flag=True, block_rows=self.block_rows, extra_names=EXTRA_COLUMNS,
                          integer_extras=("table_crc32", "error_count"))
        self.files.append(path)
        self._bytes = 0
        return w

    def __call__(self, rec: TelemetryRecord) -> None:
        if self._writer is None:
            self._writer = self._open()
        elif self._bytes >= self.rotate_bytes:
            self._writer.close()
            if self.events is not None:
                self.events.emit(rec.t_s, EventId.TLM_FILE_ROTATED, self.channel, str(self.files[-1]))
            self._writer = self._open()
        cal = rec.cal_uT or _NAN3
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

    def close(self) -> None:
        """Flush and rename the current file to its final name."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
