"""Calibration table: versioned JSON file with CRC-32, validation, and an active-slot store.

Lifecycle (cFE tables): ``load_table(path)`` parses and checks schema + CRC ->
``validate(table)`` (pure: finite, physical bounds, conditioning, fixed-point headroom
over the validity range) -> ``CalTableStore`` stages it in the inactive slot; activation
is a request honoured at the next cycle boundary. Any failure raises
:class:`CalTableInvalid` and the active table stays in force. Readers get an immutable
snapshot; "never loaded" is an explicit state (``active is None``).

File layout (``schema_version`` 1), a JSON object with keys: ``schema``
("magstack-cal-table"), ``schema_version``, ``table_name``, ``device_id``, ``description``,
``created_utc`` (ISO 8601), ``model`` {name, terms, currents, t0_c}, ``parameters``
{S, K_S, K_S2, O, K_O, D, c3, P: {unit, value}; ground_only {...}}, ``validity`` {temp_c: [lo, hi]
or null, field_uT, currents_A {name: [lo, hi]}}, ``fit`` (statistics, informational), and
``crc32``: "0x%08x" of zlib.crc32 over the canonical JSON (sorted keys, no spaces, ASCII)
of the object without ``crc32``.
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import os
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from magstack.data.io import atomic_write_text, json_safe, read_bytes_bounded
from magstack.errors import InputDataError
from magstack.firmware import fixed_point
from magstack.firmware.cal_terms import CAL_TERMS, GROUND_ONLY_TERMS, TEMPERATURE_TERMS
from magstack.firmware.errors import CalTableInvalid
from magstack.firmware.table_schema import MAX_BYTES as MAX_TABLE_BYTES
from magstack.firmware.table_schema import check_document, parse_table_json

SCHEMA = "magstack-cal-table"
SCHEMA_VERSION = 1
TABLE_NAME = "mag_cal"

#: Physical bounds checked at validation (value ranges a real AMR calibration stays in).
BOUNDS = {
    "S_diag": (0.1, 10.0),          # unitless
    "S_offdiag": 5.0,               # |.|, unitless
    "K_S": 0.1,                     # |.| 1/degC
    "K_S2": 2e-4,                   # |.| 1/degC^2 (a bridge's a^2 is ~1e-5; the fixed-point limit is 2.4e-4)
    "O_uT": 1000.0,                 # |.| uT
    "K_O_uT_per_degC": 10.0,        # |.| uT/degC
    "D_uT_per_A": 1000.0,           # |.| uT/A
    "c3_per_uT2": 1e-3,             # |.| 1/uT^2
    "P_per_uT": 0.1,                # |.| 1/uT
    "temp_c": (-55.0, 125.0),       # validity range must lie inside
    "field_uT": 2000.0,             # validity field must be in (0, this]
    "current_A": 1000.0,            # |.| validity range of each current
}
#: Maximum condition number of S + K_S dT anywhere in the validity temperature range.
MAX_COND = 1e3

_UNITS = {"S": "1", "K_S": "1/degC", "K_S2": "1/degC^2", "O": "uT", "K_O": "uT/degC", "D": "uT/A", "c3": "1/uT^2",
          "P": "1/uT"}
_TERM_PARAMS = {"gain_matrix": "S", "temperature_gain": "K_S", "temperature_gain2": "K_S2", "offset": "O",
                "temperature_offset": "K_O",
                "currents": "D", "cubic": "c3", "cross_products": "P"}


def _ro(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class CalTable:
    """An immutable calibration table (float parameters in the units of ``_UNITS``)."""

    device_id: str
    terms: tuple[str, ...]
    S: np.ndarray
    K_S: np.ndarray = field(default_factory=lambda: _ro(np.zeros((3, 3))))
    K_S2: np.ndarray = field(default_factory=lambda: _ro(np.zeros(3)))    # on-axis, 1/degC^2
    O: np.ndarray = field(default_factory=lambda: _ro(np.zeros(3)))
    K_O: np.ndarray = field(default_factory=lambda: _ro(np.zeros(3)))
    D: tuple[tuple[str, np.ndarray], ...] = ()
    c3: np.ndarray = field(default_factory=lambda: _ro(np.zeros(3)))
    P: np.ndarray = field(default_factory=lambda: _ro(np.zeros((3, 3))))
    t0_c: float = 25.0
    validity_temp_c: tuple[float, float] | None = None
    validity_field_uT: float = 100.0
    validity_field_axes_uT: tuple[float, float, float] | None = None   # per calibrated axis (None: field_uT on each)
    validity_field_norm_uT: float | None = None                         # calibrated |B| limit (None: none)
    validity_currents_A: tuple[tuple[str, tuple[float, float]], ...] = ()
    model_name: str = "eq3"
    table_name: str = TABLE_NAME
    description: str = ""
    created_utc: str = ""
    fit_stats: Mapping[str, Any] = field(default_factory=dict)
    ground_only: Mapping[str, Any] = field(default_factory=dict)
    schema_version: int = SCHEMA_VERSION
    crc32: int | None = None
    posterior: Mapping[str, Any] | None = None    # optional: {"x": {"names", "cov"}, ..., "bound_uT", ...}

    def __post_init__(self) -> None:
        for name in ("S", "K_S", "P"):
            object.__setattr__(self, name, _ro(np.asarray(getattr(self, name), dtype=float).reshape(3, 3)))
        for name in ("K_S2", "O", "K_O", "c3"):
            object.__setattr__(self, name, _ro(np.asarray(getattr(self, name), dtype=float).reshape(3)))
        object.__setattr__(self, "D", tuple((str(k), _ro(np.asarray(v, dtype=float).reshape(3)))
                                            for k, v in self.D))
        object.__setattr__(self, "terms", tuple(self.terms))
        object.__setattr__(self, "validity_currents_A", tuple((str(k), (float(a), float(b)))
                                                              for k, (a, b) in self.validity_currents_A))
        if self.validity_temp_c is not None:
            object.__setattr__(self, "validity_temp_c", tuple(float(x) for x in self.validity_temp_c))
        if self.validity_field_axes_uT is not None:
            object.__setattr__(self, "validity_field_axes_uT", tuple(float(x) for x in self.validity_field_axes_uT))

    @property
    def field_limits_uT(self) -> tuple[float, float, float]:
        """The validity field limit of each input axis, ``|B_j| <= F_j`` (uT)."""
        if self.validity_field_axes_uT is not None:
            return self.validity_field_axes_uT
        return (self.validity_field_uT,) * 3

    @property
    def currents(self) -> tuple[str, ...]:
        return tuple(k for k, _ in self.D)

    def gain_at(self, temp_c: float) -> np.ndarray:
        """S + K_S dT + diag(K_S2) dT^2, dT = T - t0."""
        dT = temp_c - self.t0_c
        return self.S + self.K_S * dT + np.diag(self.K_S2) * dT * dT

    # ------------------------------------------------------------------ JSON
    def to_document(self) -> dict:
        """The JSON object (with ``crc32`` computed)."""
        params: dict[str, Any] = {}
        for term in self.terms:
            p = _TERM_PARAMS.get(term)
            if p == "D":
                params["D"] = {"unit": _UNITS["D"], "value": {k: v.tolist() for k, v in self.D}}
            elif p:
                params[p] = {"unit": _UNITS[p], "value": getattr(self, p).tolist()}
        if self.ground_only:
            params["ground_only"] = json_safe(self.ground_only)
        doc = {
            "schema": SCHEMA, "schema_version": self.schema_version, "table_name": self.table_name,
            "device_id": self.device_id, "description": self.description,
            "created_utc": self.created_utc or _now_utc(),
            "model": {"name": self.model_name, "terms": list(self.terms), "currents": list(self.currents),
                      "t0_c": self.t0_c},
            "parameters": params,
            "validity": {"temp_c": None if self.validity_temp_c is None else list(self.validity_temp_c),
                         "field_uT": self.validity_field_uT,
                         **({} if self.validity_field_axes_uT is None else
                            {"field_axes_uT": list(self.validity_field_axes_uT)}),
                         **({} if self.validity_field_norm_uT is None else
                            {"field_norm_uT": self.validity_field_norm_uT}),
                         "currents_A": {k: list(v) for k, v in self.validity_currents_A}},
            "fit": json_safe(dict(self.fit_stats)),
        }
        if self.posterior is not None:
            doc["posterior"] = json_safe(dict(self.posterior))
        doc["crc32"] = f"0x{_crc(doc):08x}"
        return doc

    def to_json(self) -> str:
        return json.dumps(self.to_document(), indent=1, sort_keys=True, allow_nan=False) + "\n"


def _now_utc() -> str:
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def _canonical(doc: Mapping) -> bytes:
    body = {k: v for k, v in doc.items() if k != "crc32"}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode()


def _crc(doc: Mapping) -> int:
    return zlib.crc32(_canonical(doc)) & 0xFFFFFFFF


# ---------------------------------------------------------------------- parse
def table_from_document(doc: Any, source: str = "<table>") -> CalTable:
    """Parse a JSON object into a CalTable, checking schema, CRC and structure."""
    def bad(msg: str) -> CalTableInvalid:
        return CalTableInvalid(f"{source}: {msg}")
    if not isinstance(doc, dict):
        raise bad("not a JSON object")
    if doc.get("schema") != SCHEMA:
        raise bad(f"foreign file: schema {doc.get('schema')!r}, expected {SCHEMA!r}")
    # strict structure first: no unknown/missing keys, no wrong types, no undeclared coefficients
    check_document(doc, source, term_params=_TERM_PARAMS, units=_UNITS, known_terms=CAL_TERMS,
                   schema=SCHEMA, schema_version=SCHEMA_VERSION)
    crc = doc.get("crc32")
    if not isinstance(crc, str):
        raise bad("missing crc32")
    try:
        want = int(crc, 16)
        got = _crc(doc)
    except (ValueError, TypeError) as exc:
        raise bad(f"cannot check crc32: {exc}") from None
    if want != got:
        raise bad(f"CRC-32 mismatch: file says {crc}, content gives 0x{got:08x} (corrupt or edited)")
    try:
        for key in ("model", "parameters", "validity"):
            if not isinstance(doc.get(key), dict):
                raise bad(f"{key!r} must be a JSON object")
        if not isinstance(doc.get("fit", {}), (dict, type(None))):
            raise bad("'fit' must be a JSON object")
        if not isinstance(doc["parameters"].get("ground_only", {}), (dict, type(None))):
            raise bad("parameters.ground_only must be a JSON object")
        if not isinstance(doc.get("device_id"), str) or not doc["device_id"]:
            raise bad(f"device_id must be a non-empty string, got {doc.get('device_id')!r}")
        model = doc["model"]
        if not isinstance(model.get("terms"), list) or not all(isinstance(t, str) for t in model["terms"]):
            raise bad("model.terms must be a list of term names")
        terms = tuple(model["terms"])
        unknown = [t for t in terms if t not in CAL_TERMS]
        if unknown:
            raise bad(f"unknown terms {unknown}")
        params = doc["parameters"]
        kw: dict[str, Any] = {}
        for term in terms:
            p = _TERM_PARAMS.get(term)
            if p is None:
                continue
            if p not in params:
                raise bad(f"term {term!r} present but parameter {p!r} missing")
            if not isinstance(params[p], dict):
                raise bad(f"parameter {p} must be an object {{unit, value}}")
            if params[p].get("unit") != _UNITS[p]:
                raise bad(f"parameter {p}: unit {params[p].get('unit')!r}, expected {_UNITS[p]!r}")
            val = params[p]["value"]
            if p == "D":
                if not isinstance(val, dict) or list(val) != list(model["currents"]):
                    raise bad(f"D currents {list(val)} differ from model currents {model['currents']}")
                kw["D"] = tuple((k, np.asarray(v, dtype=float)) for k, v in val.items())
            else:
                kw[p] = np.asarray(val, dtype=float)
        if "gain_matrix" not in terms:
            raise bad("table has no gain_matrix")
        v = doc["validity"]
        vt = v["temp_c"]
        if not isinstance(v.get("currents_A", {}), dict):
            raise bad("validity.currents_A must be an object {name: [lo, hi]}")
        table = CalTable(
            device_id=str(doc["device_id"]), terms=terms, t0_c=float(model["t0_c"]),
            validity_temp_c=None if vt is None else (float(vt[0]), float(vt[1])),
            validity_field_uT=float(v["field_uT"]),
            validity_field_axes_uT=None if v.get("field_axes_uT") is None else tuple(v["field_axes_uT"]),
            validity_field_norm_uT=None if v.get("field_norm_uT") is None else float(v["field_norm_uT"]),
            validity_currents_A=tuple((k, (float(a), float(b))) for k, (a, b) in v.get("currents_A", {}).items()),
            model_name=str(model.get("name", "")), table_name=str(doc.get("table_name", "")),
            description=str(doc.get("description", "")), created_utc=str(doc.get("created_utc", "")),
            fit_stats=doc.get("fit", {}) or {}, ground_only=params.get("ground_only", {}) or {},
            crc32=got, posterior=doc.get("posterior"), **kw)
    except CalTableInvalid:
        raise
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise bad(f"malformed table ({type(exc).__name__}: {exc})") from None
    if set(table.currents) != {k for k, _ in table.validity_currents_A}:
        raise bad("validity.currents_A must name exactly the model currents")
    return table


def load_table(path: str | os.PathLike) -> CalTable:
    """Read and parse (schema, CRC, structure). Validation is separate: :func:`validate`."""
    p = Path(path)
    try:   # regular file, non-blocking open, at most MAX_BYTES read: a FIFO or /dev/zero cannot hang or fill memory
        raw = read_bytes_bounded(p, MAX_TABLE_BYTES, "calibration table")
    except InputDataError as exc:
        raise CalTableInvalid(str(exc)) from None
    return table_from_document(parse_table_json(raw, str(p)), str(p))


def save_table(table: CalTable, path: str | os.PathLike) -> Path:
    """Atomic write (:func:`magstack.data.io.atomic_write_text`): temp file, fsync, rename, fsync the directory."""
    p = Path(path)
    try:
        text = table.to_json()
    except ValueError as exc:   # json refuses NaN/inf (allow_nan=False)
        raise CalTableInvalid(f"{p}: table not written: {exc} (non-finite parameter or validity value)") from None
    atomic_write_text(p, text)
    return p


# ---------------------------------------------------------------------- validate
@dataclass(frozen=True)
class ValidationResult:
    ok: bool
    problems: tuple[str, ...] = ()
    worst_output_uT: float = math.nan   # fixed-point headroom figure over the validity range
    max_cond: float = math.nan

    def raise_if_bad(self, source: str = "table") -> None:
        if not self.ok:
            raise CalTableInvalid(f"{source}: validation failed: " + "; ".join(self.problems))


def validate(table: CalTable) -> ValidationResult:
    """Pure check of a parsed table; returns every problem found."""
    pr: list[str] = []
    arrays = {"S": table.S, "K_S": table.K_S, "K_S2": table.K_S2, "O": table.O, "K_O": table.K_O, "c3": table.c3,
              "P": table.P, **{f"D_{k}": v for k, v in table.D}}
    for k, a in arrays.items():
        if not np.all(np.isfinite(a)):
            pr.append(f"{k} has non-finite values")
    scalars = {"t0_c": table.t0_c, "validity.field_uT": table.validity_field_uT}
    if table.validity_temp_c is not None:
        scalars["validity.temp_c"] = sum(table.validity_temp_c)
    for k, x in scalars.items():
        if not math.isfinite(x):
            pr.append(f"{k} is not finite")
    tlo, thi = BOUNDS["temp_c"]
    if not tlo <= table.t0_c <= thi:
        pr.append(f"t0_c {table.t0_c} degC outside [{tlo}, {thi}]")
    if pr:
        return ValidationResult(False, tuple(pr))
    if not table.device_id:
        pr.append("device_id is empty")
    d = np.diag(table.S)
    lo, hi = BOUNDS["S_diag"]
    if np.any((d < lo) | (d > hi)):
        pr.append(f"S diagonal {d.tolist()} outside [{lo}, {hi}]")
    off = table.S[~np.eye(3, dtype=bool)]
    if np.any(np.abs(off) > BOUNDS["S_offdiag"]):
        pr.append(f"S off-diagonal beyond +-{BOUNDS['S_offdiag']}")
    for name, a, key, unit in (("K_S", table.K_S, "K_S", "1/degC"), ("K_S2", table.K_S2, "K_S2", "1/degC^2"),
                               ("O", table.O, "O_uT", "uT"),
                               ("K_O", table.K_O, "K_O_uT_per_degC", "uT/degC"),
                               ("c3", table.c3, "c3_per_uT2", "1/uT^2"), ("P", table.P, "P_per_uT", "1/uT")):
        if np.any(np.abs(a) > BOUNDS[key]):
            pr.append(f"{name} max |{np.abs(a).max():g}| {unit} beyond physical bound {BOUNDS[key]:g}")
    for k, v in table.D:
        if np.any(np.abs(v) > BOUNDS["D_uT_per_A"]):
            pr.append(f"D_{k} beyond physical bound {BOUNDS['D_uT_per_A']:g} uT/A")
    if abs(round(table.t0_c * 100) - table.t0_c * 100) > 1e-6:
        pr.append(f"t0_c {table.t0_c} is not a multiple of 0.01 degC")
    temps = [table.t0_c]
    if table.validity_temp_c is not None:
        a, b = table.validity_temp_c
        if not (tlo <= a <= b <= thi):
            pr.append(f"validity temp_c [{a}, {b}] not an interval inside [{tlo}, {thi}] degC")
        temps = [a, b]
    elif set(TEMPERATURE_TERMS) & set(table.terms):
        pr.append("table has temperature terms but no validity temperature range")
    if not 0 < table.validity_field_uT <= BOUNDS["field_uT"]:
        pr.append(f"validity field_uT {table.validity_field_uT} not in (0, {BOUNDS['field_uT']}]")
    if table.validity_field_axes_uT is not None:
        fa = table.validity_field_axes_uT
        if not all(math.isfinite(f) and 0 <= f <= table.validity_field_uT for f in fa):
            pr.append(f"validity field_axes_uT {list(fa)} not each in [0, field_uT = {table.validity_field_uT}]")
    fn = table.validity_field_norm_uT
    if fn is not None and not (math.isfinite(fn) and 0 < fn <= BOUNDS["field_uT"] * math.sqrt(3)):
        pr.append(f"validity field_norm_uT {fn} not in (0, {BOUNDS['field_uT'] * math.sqrt(3):.6g}]")
    for k, (a, b) in table.validity_currents_A:
        if not (-BOUNDS["current_A"] <= a <= b <= BOUNDS["current_A"]):
            pr.append(f"validity current {k} [{a}, {b}] A not an interval within +-{BOUNDS['current_A']}")
    # conditioning over the validity temperature range (the gain is linear in T, or quadratic with K_S2:
    # both ends and a grid between them)
    conds = []
    for t in _temperature_grid(temps, table):
        sv = np.linalg.svd(table.gain_at(t), compute_uv=False)
        conds.append(sv[0] / sv[-1] if sv[-1] > 0 else math.inf)
    max_cond = float(max(conds))
    if max_cond > MAX_COND:
        pr.append(f"gain matrix condition number {max_cond:.3g} > {MAX_COND:g} in the validity range")
    # fixed-point representation and headroom over the validity box
    worst = math.nan
    ground = [t for t in table.terms if t in GROUND_ONLY_TERMS]
    flight_terms = [t for t in table.terms if t not in ground]
    fixed_ok = all(t in fixed_point.FIXED_POINT_TERMS for t in flight_terms)
    if fixed_ok:
        try:
            fixed_point.FixedPointTable.from_table(table)
        except CalTableInvalid as exc:
            pr.append(f"fixed point: {exc}")
        except (OverflowError, ValueError) as exc:   # a validity bound too large for any integer form
            pr.append(f"fixed point: cannot quantise the validity range ({exc})")
        worst = worst_case_output_uT(table)
        if worst > fixed_point.OUT_LIMIT_uT:
            pr.append(f"fixed point: output up to {worst:.1f} uT over the validity range exceeds the "
                      f"{fixed_point.OUT_LIMIT_uT:.1f} uT output range (would saturate)")
        if table.validity_field_uT * 1e3 > fixed_point.B_LIMIT_nT:
            pr.append("validity field beyond the fixed-point input range")
    return ValidationResult(not pr, tuple(pr), worst, max_cond)


def _temperature_grid(temps: list[float], table: CalTable) -> list[float]:
    """The ends of the validity temperature range, and 31 points between them when K_S2 is non-zero."""
    if len(temps) == 2 and np.any(table.K_S2):
        return [float(t) for t in np.linspace(temps[0], temps[1], 33)]
    return temps


def worst_case_output_uT(table: CalTable) -> float:
    """Max over axes of an upper bound on |B_cal| for any input in the validity box (uT)."""
    temps = [table.t0_c] if table.validity_temp_c is None else list(table.validity_temp_c)
    dT2 = max((t - table.t0_c) ** 2 for t in temps)
    worst = 0.0
    for i in range(3):
        m = 0.0
        for t in temps:  # the linear terms' max |.| is at an end of the range; K_S2 dT^2 bounded apart
            dT = t - table.t0_c
            g = (np.abs(table.S[i] + table.K_S[i] * dT).sum() + abs(table.K_S2[i]) * dT2) * table.validity_field_uT
            o = abs(table.O[i] + table.K_O[i] * dT)
            m = max(m, g + o)
        for (_name, d), (_, (a, b)) in zip(table.D, table.validity_currents_A, strict=True):
            m += abs(d[i]) * max(abs(a), abs(b))
        worst = max(worst, m)
    return float(worst)


# ---------------------------------------------------------------------- from a fit
#: A validity box narrower than this (degC) or with a lower field limit (uT, per axis) draws a warning.
NARROW_TEMP_C = 10.0
NARROW_FIELD_uT = 50.0
#: The field limit is also capped at this multiple of the largest field the fit saw on each axis.
FIELD_EXTRAPOLATION = 2.0
#: The data's own field region: this quantile of the rows' |B_j| per axis, and ``DATA_NORM_QUANTILE`` of their
#: |B| (the magnitude most rows share: excursions along one axis, such as a hysteresis screen, would otherwise
#: admit every axis at that field at once, a combination no row had); the region grows beyond it where the bound
#: allows.
DATA_FIELD_QUANTILE = 0.95
DATA_NORM_QUANTILE = 0.75
#: Default validity: the region is where the predictive vector sd stays within this multiple of its RMS over
#: the fit data, or within ``VALIDITY_SD_HEADROOM`` x its largest value over the data's own region (temperature
#: range x per-axis field extents x largest |B|) when that is higher, but never above ``VALIDITY_SD_CAP`` x the
#: RMS: where the data cannot pin the table to that, the region is narrower than the data. The bound, ``2 x``
#: that sd, is the vector error the table promises inside its region.
VALIDITY_SD_FACTOR = 1.5
VALIDITY_SD_HEADROOM = 1.2
VALIDITY_SD_CAP = 5.0


def posterior_block(result) -> dict | None:
    """The table's ``posterior`` block from a FitResult: per axis the flight parameters and the parameters of the
    catalogue terms the model leaves out (``left_out``, value 0 in the table), their covariance (per-parameter
    inflation applied, the left-out terms' data-capped prior beyond what the fitted terms absorb; ground-only
    terms marginalised: their rows and columns dropped), the noise and the discrepancy
    (:mod:`magstack.firmware.cal_uncertainty`). None when the fit has no posterior or a flight parameter is
    undetermined (no prior, ``--no-priors``)."""
    post = getattr(result, "posterior", None)
    if post is None:
        return None
    unc = getattr(result, "uncertainty", None)
    m = result.model
    mask = m.axis_mask()
    block: dict[str, Any] = {}
    left: list[str] = []
    for i, a in enumerate(("x", "y", "z")):
        cols = [c for c, col in enumerate(m.columns) if mask[i, c] and col.term in _TERM_PARAMS]
        if not np.all(np.isfinite(post.cov[i][np.ix_(cols, cols)])):
            return None
        names = [m.param_name(i, c) for c in cols]
        if unc is None:
            C = post.cov[i][np.ix_(cols, cols)]
        else:
            lo, C = unc.axis_block(i, cols)
            names += lo
            left += lo
        block[a] = {"names": names, "cov": (0.5 * (C + C.T)).tolist()}
    block["sigma_uT"] = [float(x) for x in post.sigma_uT]
    if unc is not None:
        block["left_out"] = left
        block["noise_uT"] = [float(x) for x in unc.noise_uT]
        if unc.discrepancy is not None:
            block["discrepancy"] = dict(unc.discrepancy)
    return block


def typical_sd_uT(result, pred) -> float:
    """RMS over the fit rows of the predictive vector sd (uT): from the held-out bins' design moments when the
    fit has them, else at the data's centre temperature over fields of the data's RMS magnitude."""
    unc = getattr(result, "uncertainty", None)
    cov = result.coverage
    if unc is not None and unc.typical_sd_uT is not None and math.isfinite(unc.typical_sd_uT):
        return float(unc.typical_sd_uT)
    centre = 0.5 * (cov.temp_min_c + cov.temp_max_c) if math.isfinite(cov.temp_min_c) else result.model.t0_c
    F = np.where(np.isfinite(cov.field_max_uT), cov.field_max_uT, 0.0)
    return pred.worst_vector_sd_uT(centre, F, cov.norm_max_uT / math.sqrt(3.0))


def _one_blas_thread():
    """:func:`magstack.firmware.blas.single_thread` where its libraries are installed (the ground tools), else a
    no-op."""
    import contextlib

    try:
        from magstack.firmware.blas import single_thread

        return single_thread()
    except ImportError:
        return contextlib.nullcontext()


def _validity_from_posterior(result, block: dict, validity_sd_uT: float | None, part_temp_c, part_field_uT: float,
                             currents: dict):
    """(temperature interval, per-axis field limits, field-magnitude limit, bound, sd limit, notes) where twice the
    predictive vector sd stays within the bound (:func:`magstack.firmware.cal_uncertainty.validity_region`)."""
    from magstack.firmware.cal_uncertainty import Predictive, validity_region

    m, cov = result.model, result.coverage
    par = m.unpack(result.theta)
    pred = Predictive(block, m.t0_c, (par["S"], par["K_S"], par["K_S2"], par["O"], par["K_O"]))
    tlo, thi = BOUNDS["temp_c"]
    lim = (max(tlo, part_temp_c[0]), min(thi, part_temp_c[1]))
    ref = cov.has_reference          # the region is in the calibrated field: the reference's extents
    max_F, max_R = cov.field_quantile_uT(1.0, ref)
    data_F, _ = cov.field_quantile_uT(DATA_FIELD_QUANTILE, ref)
    _, data_R = cov.field_quantile_uT(DATA_NORM_QUANTILE, ref)
    f_cap = min(part_field_uT, BOUNDS["field_uT"])
    caps = np.minimum(f_cap, np.maximum(1.0, np.ceil(FIELD_EXTRAPOLATION * max_F)))
    norm_cap = min(f_cap, max(1.0, math.ceil(FIELD_EXTRAPOLATION * max_R)))
    has_t = math.isfinite(cov.temp_min_c)
    data_t = ((math.floor(cov.temp_min_c * 100) / 100, math.ceil(cov.temp_max_c * 100) / 100) if has_t else None)
    centre = m.t0_c
    data_region = (np.minimum(data_F, caps), min(data_R, norm_cap))
    max_region = (np.minimum(np.maximum(max_F, data_F), caps), min(max(max_R, data_R), norm_cap))
    if data_t is not None:      # the data's best-pinned temperature (over its own fields): where the region starts
        grid = np.linspace(data_t[0], data_t[1], 41)
        per_t = pred.worst_per_temperature_uT(grid, *data_region, currents)
        centre = float(grid[int(np.argmin([per_t[float(t)] for t in grid]))])
    if validity_sd_uT is not None:
        sd = validity_sd_uT
    else:
        typical = typical_sd_uT(result, pred)
        temps = np.linspace(data_t[0], data_t[1], 21) if data_t is not None else [centre]
        in_data = pred.worst_over_region_uT(temps, *max_region, currents)
        sd = min(max(VALIDITY_SD_FACTOR * typical, VALIDITY_SD_HEADROOM * in_data), VALIDITY_SD_CAP * typical)
    bound = 2.0 * sd
    with _one_blas_thread():        # many small products: BLAS threads only wait (firmware/blas.py)
        t_box, F, R, notes = validity_region(pred, bound, centre_c=centre, data_temp_c=data_t, data_field_uT=data_F,
                                             data_norm_uT=data_R, temp_limits_c=lim, field_caps_uT=caps,
                                             norm_cap_uT=norm_cap, currents_A=currents,
                                             has_temperature=bool(set(TEMPERATURE_TERMS) & set(m.terms)),
                                             data_field_max_uT=max_F, data_norm_max_uT=max_R)
    if not pred.complete:
        notes.append("the fit gave no noise or discrepancy estimate (no held-out folds): the predictive sd is the "
                     "parameter part only")
    return t_box, F, R, bound, sd, notes


def table_from_fit(result, device_id: str, *, description: str = "", created_utc: str = "",
                   validity_temp_c: tuple[float, float] | None = None, validity_field_uT: float | None = None,
                   validity_currents_A: Mapping[str, tuple[float, float]] | None = None,
                   validity_sd_uT: float | None = None) -> CalTable:
    """A table from a :class:`magstack.firmware.calibration.FitResult`.

    With a posterior (the MAP fit) the table carries its predictive parts (block ``posterior``) and the validity
    box is where twice the predictive vector sd stays within the bound ``2 x validity_sd_uT`` (default: 1.5x the
    sd's RMS over the fit data, see ``VALIDITY_SD_FACTOR``): a temperature interval, a limit per calibrated axis
    and on the calibrated magnitude, clipped to the part's operating range (the chip's priors) and to
    ``FIELD_EXTRAPOLATION`` x each axis's largest field in the data
    (:mod:`magstack.firmware.cal_uncertainty`). :class:`~magstack.firmware.errors.NoValidityRegion` when even the
    data's centre exceeds the bound. Without a posterior, validity is what the fit data covered (temperature
    range, max |B| component). Given values override; currents: the data's ranges. The decisions are in
    ``fit_stats["validity"]``."""
    from magstack.drivers.cal_priors import priors_for
    from magstack.firmware.errors import NoValidityRegion

    m = result.model
    p = m.unpack(result.theta)
    cov = result.coverage
    vc = dict(validity_currents_A or {})
    for k in m.currents:
        vc.setdefault(k, tuple(cov.currents_A.get(k, (0.0, 0.0))))
    block = posterior_block(result)
    stats = result.stats()
    vinfo: dict[str, Any] = {"rule": "data range"}
    field_axes = field_norm = None
    if block is not None:
        part = priors_for(getattr(result, "chip", None))
        t_box, F, R, bound, sd, notes = _validity_from_posterior(result, block, validity_sd_uT,
                                                                 part.operating_temp_c, part.field_range_uT, vc)
        block["bound_uT"] = bound
        block["prior"] = getattr(result, "prior_name", "") or ""
        nf = np.asarray(result.noise_floor_uT, dtype=float)
        if np.all(np.isfinite(nf)):
            block["noise_floor_uT"] = [float(x) for x in nf]
        vinfo = {"rule": "2 x predictive vector sd <= bound", "bound_uT": bound, "sd_limit_uT": sd,
                 "part": part.chip, "part_temp_c": list(part.operating_temp_c), "part_field_uT": part.field_range_uT,
                 "notes": notes}
        if F is None and validity_temp_c is None and validity_field_uT is None:
            raise NoValidityRegion("no validity region: " + "; ".join(notes) + " (a larger --validity-sd, more "
                                   "data, or a model with the missing terms)")
        if validity_temp_c is None:
            validity_temp_c = t_box
        if validity_field_uT is None and F is not None:
            field_axes = tuple(float(x) for x in F)
            validity_field_uT = float(max(F))
            field_norm = R
    if validity_temp_c is None and math.isfinite(cov.temp_min_c):
        validity_temp_c = (math.floor(cov.temp_min_c * 100) / 100, math.ceil(cov.temp_max_c * 100) / 100)
    if validity_field_uT is None:
        validity_field_uT = float(np.ceil((cov.field_quantile_uT(1.0, True)[0] if cov.has_reference
                                           else cov.field_max_uT).max()))
    warn = []
    if validity_temp_c is not None and validity_temp_c[1] - validity_temp_c[0] < NARROW_TEMP_C:
        warn.append(f"validity temperature {validity_temp_c[0]:g}..{validity_temp_c[1]:g} degC is narrower than "
                    f"{NARROW_TEMP_C:g} degC: samples outside it will not be calibrated")
    if field_norm is not None and field_norm < NARROW_FIELD_uT:
        warn.append(f"validity |B| <= {field_norm:g} uT is below {NARROW_FIELD_uT:g} uT")
    narrow = [a for a, f in zip("xyz", field_axes or (validity_field_uT,) * 3, strict=True) if f < NARROW_FIELD_uT]
    if narrow:
        warn.append(f"validity field per axis {list(field_axes or (validity_field_uT,) * 3)} uT is below "
                    f"{NARROW_FIELD_uT:g} uT on {', '.join(narrow)}: samples beyond it will not be calibrated")
    vinfo["warnings"] = warn
    stats["validity"] = vinfo
    ground = {}
    if "time_skew" in m.terms:
        ground["tau_s"] = p["tau"]
    if "session_offset" in m.terms:
        ground["session_offset_uT"] = {str(k): v for k, v in p["dO"].items()}
    if "drift" in m.terms:
        ground["drift_uT_per_s"] = p["r"]
        ground["drift_t_ref_s"] = m.t_ref_s
    # terms without table parameters (the bench mount: fitted as a nuisance, reported in fit_stats)
    terms = tuple(t for t in m.terms if t != "mount_rotation")
    return CalTable(device_id=device_id, terms=terms, S=p["S"], K_S=p["K_S"], K_S2=p["K_S2"], O=p["O"],
                    K_O=p["K_O"], D=tuple((k, p["D"][k]) for k in m.currents), c3=p["c3"], P=p["P"], t0_c=m.t0_c,
                    validity_temp_c=validity_temp_c,
                    validity_field_uT=validity_field_uT, validity_field_axes_uT=field_axes,
                    validity_field_norm_uT=field_norm,
                    validity_currents_A=tuple((k, vc[k]) for k in m.currents), model_name=m.name,
                    description=description, created_utc=created_utc or _now_utc(),
                    fit_stats=stats, ground_only=ground, posterior=block)


# ---------------------------------------------------------------------- store
class CalTableStore:
    """Active/inactive slots keyed to one device id (a swapped sensor cannot reuse another
    sensor's table). ``active`` is None until a table has been activated."""

    def __init__(self, device_id: str) -> None:
        self.device_id = device_id
        self._active: CalTable | None = None
        self._active_fixed: fixed_point.FixedPointTable | None = None
        self._staged: tuple[CalTable, fixed_point.FixedPointTable | None] | None = None
        self._activation_requested = False
        self.last_validation: ValidationResult | None = None
        self.last_error: str = ""
        self.load_count = 0
        self.reject_count = 0

    @property
    def active(self) -> CalTable | None:
        return self._active

    @property
    def active_fixed(self) -> fixed_point.FixedPointTable | None:
        return self._active_fixed

    def read(self, path: str | os.PathLike) -> CalTable:
        """Parse the table at ``path`` and check its device id (nothing staged); subclasses change how the
        file is reached (the flight application: inside configured roots only)."""
        table = load_table(path)
        if table.device_id != self.device_id:
            raise CalTableInvalid(f"{path}: foreign table for device {table.device_id!r}, "
                                  f"this store serves {self.device_id!r}")
        return table

    def load(self, path: str | os.PathLike) -> ValidationResult:
        """:meth:`read` + validate into the inactive slot. CalTableInvalid on any failure (a hostile table's
        unexpected exception included); the active table is untouched either way."""
        try:
            table = self.read(path)
            res = validate(table)
            self.last_validation = res
            res.raise_if_bad(str(path))
            fixed = fixed_point.FixedPointTable.from_table(table) if all(
                t in fixed_point.FIXED_POINT_TERMS or t in GROUND_ONLY_TERMS for t in table.terms) else None
        except CalTableInvalid as exc:
            self.reject_count += 1
            self.last_error = str(exc)
            raise
        except Exception as exc:  # noqa: BLE001 - validation of a hostile table must not escape either
            self.reject_count += 1
            self.last_error = f"{path}: invalid table ({type(exc).__name__}: {str(exc)[:120]})"
            raise CalTableInvalid(self.last_error) from None
        self._staged = (table, fixed)
        self._activation_requested = False
        self.load_count += 1
        return res

    def request_activation(self) -> None:
        if self._staged is None:
            raise CalTableInvalid("no validated table staged for activation")
        self._activation_requested = True

    def cycle_boundary(self) -> bool:
        """Called by the scheduler between cycles: swaps in a requested table. True if swapped."""
        if not self._activation_requested or self._staged is None:
            return False
        self._active, self._active_fixed = self._staged
        self._staged = None
        self._activation_requested = False
        return True

    def load_and_activate(self, path: str | os.PathLike) -> CalTable:
        self.load(path)
        self.request_activation()
        self.cycle_boundary()
        return self._active

    def telemetry(self) -> dict:
        a = self._active
        return {"device_id": self.device_id, "active": a is not None,
                "active_crc32": None if a is None else f"0x{a.crc32:08x}" if a.crc32 is not None else None,
                "active_created_utc": None if a is None else a.created_utc,
                "active_schema_version": None if a is None else a.schema_version,
                "last_validation_ok": None if self.last_validation is None else self.last_validation.ok,
                "last_error": self.last_error, "load_count": self.load_count, "reject_count": self.reject_count}
