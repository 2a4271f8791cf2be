"""Demo step 5: the calibration table's life cycle - save, validate, load + activate; two
corrupted copies must be refused while the active table stays in force."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from magstack.cli.demo.config import DEVICE_ID, Say, iso_utc
from magstack.drivers.errors import MagError
from magstack.firmware.cal_table import CalTableStore, save_table, table_from_fit, validate
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.fixed_point import OUT_LIMIT_uT


@dataclass
class TableFigures:
    path: Path
    crc32: str
    valid: bool
    worst_output_uT: float
    max_cond: float
    validity_temp_c: tuple[float, float] | None
    validity_field_uT: float
    refused: list[dict]            # {kind, path, error}
    active_crc32_after: str
    reject_count: int
    store: Any = field(repr=False, default=None)
    table: Any = field(repr=False, default=None)


def corrupt_one_digit(text: str) -> str:
    """The table text with one digit of the first gain value changed (still valid JSON)."""
    start = text.index('"S"')
    start = text.index('"value"', start)
    for i in range(start, len(text)):
        if text[i].isdigit() and text[i] != "0":
            return text[:i] + ("1" if text[i] != "1" else "2") + text[i + 1:]
    raise MagError("no digit to corrupt in the table text")  # pragma: no cover - a table always has S


def table_lifecycle(fit_result, out_dir: Path, *, created_epoch_s: float, description: str,
                    say: Say = print) -> TableFigures:
    """cal.json: save, validate, load + activate; two corrupted copies must be refused."""
    table = table_from_fit(fit_result, DEVICE_ID, description=description, created_utc=iso_utc(created_epoch_s))
    v = validate(table)
    if not v.ok:
        raise CalTableInvalid("fitted table does not validate: " + "; ".join(v.problems))
    path = save_table(table, out_dir / "cal.json")
    store = CalTableStore(DEVICE_ID)
    active = store.load_and_activate(path)
    crc = f"0x{active.crc32:08x}"
    if store.active_fixed is None:
        raise CalTableInvalid("activated table has no fixed-point form")
    say(f"  {path.name}: {active.model_name}, crc32 {crc}, validity {active.validity_temp_c} degC, "
        f"|B_i| <= {active.validity_field_uT:g} uT")
    say(f"  validates: worst-case output {v.worst_output_uT:.1f} uT (fixed-point range "
        f"{OUT_LIMIT_uT:.0f} uT), max condition number {v.max_cond:.3g}; loaded and activated in "
        f"CalTableStore({DEVICE_ID!r})")
    text = Path(path).read_text(encoding="utf-8")
    copies = (("one digit changed", out_dir / "cal-corrupted.json", corrupt_one_digit(text)),
              ("truncated", out_dir / "cal-truncated.json", text[: len(text) // 2]))
    refused = []
    fixed_before = store.active_fixed
    for kind, p, body in copies:
        p.write_text(body, encoding="utf-8")
        try:
            store.load_and_activate(p)
        except CalTableInvalid as exc:
            refused.append({"kind": kind, "path": p, "error": str(exc)})
            say(f"  {p.name} ({kind}): refused, CalTableInvalid: {exc}")
            continue
        raise MagError(f"{p.name} ({kind}) was accepted by the table store")
    after = store.active
    if after is not active or store.active_fixed is not fixed_before:
        raise MagError("a refused table replaced the active one")
    after_crc = f"0x{after.crc32:08x}"
    say(f"  active table still crc32 {after_crc}; store telemetry: rejects {store.reject_count}, "
        f"loads {store.load_count}")
    return TableFigures(Path(path), crc, v.ok, v.worst_output_uT, v.max_cond, active.validity_temp_c,
                        active.validity_field_uT, refused, after_crc, store.reject_count, store, active)
