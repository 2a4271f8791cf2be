"""The flight application's calibration-table store: every table is read through the flight intake.

:class:`FlightTableStore` is a :class:`~magstack.firmware.cal_table.CalTableStore` whose ``load`` reads
the file with :func:`~magstack.firmware.flight.intake.read_bounded` (regular file, at most
``MAX_TABLE_BYTES``, no symlink, a FIFO never blocks) at a path checked by
:func:`~magstack.firmware.flight.intake.inside_roots`, and turns *every* failure of parsing or
validation (huge integers, deep nesting, a foreign device, ...) into
:class:`~magstack.firmware.errors.CalTableInvalid`: the active table stays in force. A file may hold a
JSON table or its binary image (:mod:`magstack.firmware.cal_image`, told apart by the image's magic);
both are validated and activated the same way.

Device ids (docs/flight.md): a table is accepted only by a channel whose ``device_id`` is exactly the
table's (``magstack fit --device-id hmc1053:sn1`` for ``device_id = "hmc1053:sn1"``); a mismatch names
both ids and the fix.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from magstack.firmware.cal_image import is_image, table_from_image
from magstack.firmware.cal_table import CalTable, CalTableStore, table_from_document
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.flight.intake import UnsafeInput, inside_roots, read_bounded
from magstack.firmware.table_schema import parse_table_json

#: Largest table file read (a table is a few KiB; `magstack table validate` has the same 1 MiB limit).
MAX_TABLE_BYTES = 1 << 20


def device_mismatch(table_id: str, channel: str, channel_id: str, source: str) -> str:
    """The one message for a table fitted for another device than the channel's."""
    return (f"table is for device {table_id!r}, channel {channel} serves {channel_id!r}: device ids must match "
            f"exactly (fit --device-id {channel_id}, or device_id = {table_id!r} in flight.toml); {source}")


def read_table(path: str | os.PathLike, roots: Sequence[Path], base: Path) -> CalTable:
    """Parse a table file (JSON or binary image) inside ``roots``; any failure is :class:`CalTableInvalid`
    naming the file."""
    src = str(path)
    try:
        real = inside_roots(path, roots, base)
        raw = read_bounded(real, MAX_TABLE_BYTES)
        if is_image(raw):
            return table_from_image(raw, src)
        return table_from_document(parse_table_json(raw, src), src)
    except CalTableInvalid:
        raise
    except UnsafeInput as exc:
        raise CalTableInvalid(str(exc)) from None
    except Exception as exc:  # noqa: BLE001 - OverflowError (a 400-digit integer), RecursionError, MemoryError ...
        raise CalTableInvalid(f"{src}: malformed table ({type(exc).__name__}: {str(exc)[:120]})") from None


class FlightTableStore(CalTableStore):
    """A CalTableStore for one channel whose reads go through :func:`read_table` (bounded, inside roots);
    validation and staging are the store's own (:meth:`CalTableStore.load`)."""

    def __init__(self, device_id: str, channel: str, roots: Sequence[Path], base: Path) -> None:
        super().__init__(device_id)
        self.channel, self.roots, self.base = channel, tuple(roots), base

    def read(self, path: str | os.PathLike) -> CalTable:
        """Parse and check the device id (nothing staged)."""
        table = read_table(path, self.roots, self.base)
        if table.device_id != self.device_id:
            raise CalTableInvalid(device_mismatch(table.device_id, self.channel, self.device_id, str(path)))
        return table
