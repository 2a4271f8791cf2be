"""Strict reader for calibration-table JSON: what the CRC covers is exactly what is applied.

A table file is refused (``CalTableInvalid`` naming the file and the JSON path) when it has

* a duplicate key anywhere (a reader keeping the first copy would apply other numbers than the
  CRC was computed over - ``json`` keeps the last),
* a key the schema does not know, or a required key missing,
* a value of the wrong JSON type: a string or boolean where a number belongs (``true`` is not
  ``1``), a flat list where a 3x3 matrix belongs, a non-integer schema version,
* coefficients for a term the table does not declare in ``model.terms`` (or a declared term
  without its coefficients),
* nesting deeper than the schema (a hostile file cannot exhaust the parser's recursion).

Informational objects (``fit`` statistics, ``parameters.ground_only``) are free-form JSON but
still duplicate-free and depth-bounded. The schema is data (:data:`TOP`, :data:`PARAMETER_SHAPES`):
adding a field is one entry here plus its use in :mod:`magstack.firmware.cal_table`.
"""
from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from magstack.firmware.cal_uncertainty import parse_name
from magstack.firmware.errors import CalTableInvalid

#: Deepest nesting any valid table needs (free-form ``fit`` / ``ground_only`` included).
MAX_DEPTH = 8
#: Largest table file accepted (bytes); real tables are a few kB.
MAX_BYTES = 1 << 20

#: Parameter name -> shape of its ``value`` (``"3x3"``, ``"3"``, ``"currents"`` = {name: [3]}).
PARAMETER_SHAPES = {"S": "3x3", "K_S": "3x3", "P": "3x3", "K_S2": "3", "O": "3", "K_O": "3", "c3": "3",
                    "D": "currents"}


class _Path:
    """A JSON path for messages: ``parameters.S.value[1][2]``."""

    def __init__(self, source: str) -> None:
        self.source = source

    def error(self, path: str, msg: str) -> CalTableInvalid:
        return CalTableInvalid(f"{self.source}: {path or 'document'}: {msg}")


def _reject_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _Duplicate(key)
        out[key] = value
    return out


class _Duplicate(ValueError):
    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key


def _no_constant(name: str):
    raise ValueError(f"non-finite constant {name}")


#: Longest integer literal accepted: a table's numbers are floats; a 400-digit integer would overflow.
MAX_INT_DIGITS = 30


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise ValueError(f"integer of {len(text.lstrip('-'))} digits (at most {MAX_INT_DIGITS})")
    return int(text)


def _depth_ok(text: str, limit: int) -> tuple[bool, int]:
    """Maximum bracket depth outside strings, without recursion (so a deep file cannot crash us)."""
    depth = deepest = 0
    in_str = esc = False
    for ch in text:
        if in_str:
            if esc:
                esc = False
            elif ch == "\\":
                esc = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > limit:
                    return False, deepest
        elif ch in "]}":
            depth -= 1
    return True, deepest


def parse_table_json(raw: bytes, source: str) -> dict:
    """Bytes -> JSON object, refusing non-UTF-8, oversize, over-deep, duplicate keys and NaN/Infinity."""
    where = _Path(source)
    if len(raw) > MAX_BYTES:
        raise where.error("", f"file of {len(raw)} bytes is larger than any table ({MAX_BYTES} bytes max)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise where.error("", f"not UTF-8 text (corrupt or truncated: {exc})") from None
    ok, depth = _depth_ok(text, MAX_DEPTH)
    if not ok:
        raise where.error("", f"nested deeper than {MAX_DEPTH} levels (a table needs at most {MAX_DEPTH})")
    try:
        doc = json.loads(text, object_pairs_hook=_reject_duplicates, parse_constant=_no_constant,
                         parse_int=_bounded_int)
    except _Duplicate as exc:
        raise where.error("", f"duplicate key {exc.key!r} (the CRC would not cover what a reader applies)") from None
    except ValueError as exc:
        raise where.error("", f"not a valid JSON table (corrupt or truncated: {exc})") from None
    if not isinstance(doc, dict):
        raise where.error("", "not a JSON object")
    return doc


# ------------------------------------------------------------------------ type checks
def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _number(where: _Path, path: str, x: Any) -> float:
    if not _is_number(x):
        raise where.error(path, f"must be a finite number, got {type(x).__name__} {x!r:.40}")
    return float(x)


def _string(where: _Path, path: str, x: Any, *, nonempty: bool = False) -> str:
    if not isinstance(x, str) or (nonempty and not x):
        raise where.error(path, f"must be a {'non-empty ' if nonempty else ''}string, got {x!r:.40}")
    return x


def _vector(where: _Path, path: str, x: Any, n: int = 3) -> list[float]:
    if not isinstance(x, list) or len(x) != n:
        raise where.error(path, f"must be a list of {n} numbers, got {x!r:.60}")
    return [_number(where, f"{path}[{i}]", v) for i, v in enumerate(x)]


def _matrix(where: _Path, path: str, x: Any) -> list[list[float]]:
    if not isinstance(x, list) or len(x) != 3 or not all(isinstance(r, list) for r in x):
        raise where.error(path, f"must be a 3x3 matrix (list of three lists of 3 numbers), got {x!r:.60}")
    return [_vector(where, f"{path}[{i}]", r) for i, r in enumerate(x)]


def _object(where: _Path, path: str, x: Any, required: set[str], optional: set[str] = frozenset()) -> dict:
    if not isinstance(x, dict):
        raise where.error(path, f"must be a JSON object, got {type(x).__name__}")
    missing = sorted(required - x.keys())
    if missing:
        raise where.error(path, f"missing required key(s) {missing}")
    unknown = sorted(x.keys() - required - optional)
    if unknown:
        raise where.error(path, f"unknown key(s) {unknown} (not part of schema version 1)")
    return x


def _interval(where: _Path, path: str, x: Any) -> list[float]:
    lo, hi = _vector(where, path, x, 2)
    return [lo, hi]


# ------------------------------------------------------------------------ the schema
TOP_REQUIRED = {"schema", "schema_version", "device_id", "model", "parameters", "validity", "crc32"}
TOP_OPTIONAL = {"table_name", "description", "created_utc", "fit", "posterior"}
POSTERIOR_REQUIRED = {"x", "y", "z"}
POSTERIOR_OPTIONAL = {"sigma_uT", "bound_uT", "noise_floor_uT", "prior", "left_out", "noise_uT", "discrepancy"}
DISCREPANCY_VECTORS = ("d0_uT2", "dB_uT2", "dT_uT2")
DISCREPANCY_SCALARS = ("field_ref_uT", "temp_ref_c", "temp_centre_c", "field_max_uT")
MODEL_REQUIRED = {"terms", "currents", "t0_c"}
MODEL_OPTIONAL = {"name"}
VALIDITY_REQUIRED = {"temp_c", "field_uT", "currents_A"}
VALIDITY_OPTIONAL = {"field_axes_uT", "field_norm_uT"}


def check_document(doc: dict, source: str, *, term_params: dict[str, str], units: dict[str, str],
                   known_terms: tuple[str, ...], schema: str, schema_version: int) -> None:
    """Check ``doc`` against schema version 1; raises CalTableInvalid naming the first problem."""
    w = _Path(source)
    _object(w, "", doc, TOP_REQUIRED, TOP_OPTIONAL)
    if doc["schema"] != schema:
        raise w.error("schema", f"foreign file: {doc['schema']!r}, expected {schema!r}")
    ver = doc["schema_version"]
    if not isinstance(ver, int) or isinstance(ver, bool) or ver != schema_version:
        raise w.error("schema_version", f"unsupported schema_version {ver!r} (supported: integer {schema_version})")
    _string(w, "device_id", doc["device_id"], nonempty=True)
    for key in ("table_name", "description", "created_utc"):
        if key in doc:
            _string(w, key, doc[key])
    if "fit" in doc and not isinstance(doc["fit"], dict):
        raise w.error("fit", "must be a JSON object (fit statistics)")

    model = _object(w, "model", doc["model"], MODEL_REQUIRED, MODEL_OPTIONAL)
    if "name" in model:
        _string(w, "model.name", model["name"])
    terms = model["terms"]
    if not isinstance(terms, list) or not all(isinstance(t, str) for t in terms):
        raise w.error("model.terms", "must be a list of term names")
    if len(set(terms)) != len(terms):
        raise w.error("model.terms", f"repeats a term: {terms}")
    unknown = [t for t in terms if t not in known_terms]
    if unknown:
        raise w.error("model.terms", f"unknown term(s) {unknown}; known: {', '.join(known_terms)}")
    if "gain_matrix" not in terms:
        raise w.error("model.terms", "table has no gain_matrix")
    currents = model["currents"]
    if not isinstance(currents, list) or not all(isinstance(c, str) and c for c in currents):
        raise w.error("model.currents", "must be a list of current names")
    if len(set(currents)) != len(currents):
        raise w.error("model.currents", f"repeats a name: {currents}")
    if bool(currents) != ("currents" in terms):
        raise w.error("model.currents", "must be non-empty exactly when the 'currents' term is declared")
    _number(w, "model.t0_c", model["t0_c"])

    declared = {term_params[t] for t in terms if t in term_params}
    params = _object(w, "parameters", doc["parameters"], declared, {"ground_only"})
    if "ground_only" in params and not isinstance(params["ground_only"], dict):
        raise w.error("parameters.ground_only", "must be a JSON object")
    for name in sorted(declared):
        p = _object(w, f"parameters.{name}", params[name], {"unit", "value"})
        if p["unit"] != units[name]:
            raise w.error(f"parameters.{name}.unit", f"{p['unit']!r}, expected {units[name]!r}")
        _check_value(w, f"parameters.{name}.value", PARAMETER_SHAPES[name], p["value"], currents)

    v = _object(w, "validity", doc["validity"], VALIDITY_REQUIRED, VALIDITY_OPTIONAL)
    if v["temp_c"] is not None:
        _interval(w, "validity.temp_c", v["temp_c"])
    _number(w, "validity.field_uT", v["field_uT"])
    if "field_axes_uT" in v:
        _vector(w, "validity.field_axes_uT", v["field_axes_uT"])
    if "field_norm_uT" in v:
        _number(w, "validity.field_norm_uT", v["field_norm_uT"])
    ca = _object(w, "validity.currents_A", v["currents_A"], set(currents))
    for name in currents:
        _interval(w, f"validity.currents_A.{name}", ca[name])
    _string(w, "crc32", doc["crc32"], nonempty=True)
    if "posterior" in doc:
        check_posterior(w, doc["posterior"], declared_params=declared, currents=currents)


#: Largest posterior block per axis (parameters): Eq. 3 + currents + cubic + cross products.
MAX_POSTERIOR_PARAMS = 64
#: Largest |covariance entry| accepted, in the parameters' own units squared (a posterior sd of 1e6 of any
#: parameter's unit is no calibration); beyond it products overflow and the block says nothing.
MAX_POSTERIOR_ABS = 1e12
#: Largest ``sigma_uT`` / ``bound_uT`` / ``noise_floor_uT`` (uT): beyond any field a magnetometer measures.
MAX_POSTERIOR_UT = 1e5
#: Symmetry and positive semi-definiteness are judged entry by entry against the entries' own scale,
#: sqrt(C_ii C_jj), never against the largest entry of the matrix: with this relative tolerance.
POSTERIOR_TOL = 1e-9


def check_posterior(w: _Path, post: Any, *, declared_params: set[str], currents: list[str]) -> None:
    """The optional posterior block: per axis the flight parameter names and their covariance; names must belong
    to declared parameters or be listed in ``left_out`` (parameters of terms the model leaves out, value 0);
    ``sigma_uT``, ``noise_floor_uT``, ``noise_uT`` and the ``discrepancy`` model
    (:mod:`magstack.firmware.cal_uncertainty`) non-negative, ``bound_uT`` positive.

    The covariance must be a covariance whatever its scale: every entry finite and at most
    ``MAX_POSTERIOR_ABS``; every variance (diagonal) >= 0; symmetric, |C_ij - C_ji| <= tol sqrt(C_ii C_jj);
    and positive semi-definite, judged on the correlation matrix C_ij / sqrt(C_ii C_jj) (scale-free: one huge
    entry cannot hide a negative variance or an asymmetry elsewhere); a zero variance needs a zero row. Each
    failure is one CalTableInvalid naming the entry, never a numerical exception."""
    obj = _object(w, "posterior", post, POSTERIOR_REQUIRED, POSTERIOR_OPTIONAL)
    for key in ("sigma_uT", "noise_floor_uT", "noise_uT"):
        if key in obj:
            for i, v in enumerate(_vector(w, f"posterior.{key}", obj[key])):
                if not 0.0 <= v <= MAX_POSTERIOR_UT:
                    raise w.error(f"posterior.{key}[{i}]", f"{v!r} uT is not in [0, {MAX_POSTERIOR_UT:g}]")
    left = obj.get("left_out", [])
    if not isinstance(left, list) or not all(isinstance(x, str) for x in left) or len(set(left)) != len(left):
        raise w.error("posterior.left_out", "must be a list of distinct parameter names")
    for k, nm in enumerate(left):
        try:
            parse_name(nm)
        except ValueError as exc:
            raise w.error(f"posterior.left_out[{k}]", str(exc)) from None
    if "discrepancy" in obj:
        d = _object(w, "posterior.discrepancy", obj["discrepancy"],
                    set(DISCREPANCY_VECTORS) | set(DISCREPANCY_SCALARS) | {"temp_range_c"}, {"held_out_rows"})
        for key in DISCREPANCY_VECTORS:
            for i, v in enumerate(_vector(w, f"posterior.discrepancy.{key}", d[key])):
                if not 0.0 <= v <= MAX_POSTERIOR_UT ** 2:
                    raise w.error(f"posterior.discrepancy.{key}[{i}]", f"{v!r} uT^2 is not in [0, "
                                                                       f"{MAX_POSTERIOR_UT ** 2:g}]")
        for key in DISCREPANCY_SCALARS:
            x = _number(w, f"posterior.discrepancy.{key}", d[key])
            if key != "temp_centre_c" and not 0.0 <= x <= 1e6:
                raise w.error(f"posterior.discrepancy.{key}", f"{x!r} is not in [0, 1e6]")
        if d["field_ref_uT"] <= 0 or d["temp_ref_c"] <= 0:
            raise w.error("posterior.discrepancy", "field_ref_uT and temp_ref_c must be > 0")
        lo, hi = _interval(w, "posterior.discrepancy.temp_range_c", d["temp_range_c"])
        if lo > hi:
            raise w.error("posterior.discrepancy.temp_range_c", "must be an interval lo <= hi")
    if "bound_uT" in obj:
        b = _number(w, "posterior.bound_uT", obj["bound_uT"])
        if not 0.0 < b <= MAX_POSTERIOR_UT:
            raise w.error("posterior.bound_uT", f"{b!r} uT is not in (0, {MAX_POSTERIOR_UT:g}]")
    if "prior" in obj:
        _string(w, "posterior.prior", obj["prior"])
    for axis in ("x", "y", "z"):
        path = f"posterior.{axis}"
        blk = _object(w, path, obj[axis], {"names", "cov"})
        names = blk["names"]
        if not isinstance(names, list) or not all(isinstance(x, str) for x in names) or not names \
                or len(names) > MAX_POSTERIOR_PARAMS or len(set(names)) != len(names):
            raise w.error(f"{path}.names", f"must be a list of 1..{MAX_POSTERIOR_PARAMS} distinct parameter names")
        for k, nm in enumerate(names):
            try:
                par, i, _ = parse_name(nm)
            except ValueError as exc:
                raise w.error(f"{path}.names[{k}]", str(exc)) from None
            base = "D" if par.startswith("D_") else par
            if "xyz"[i] != axis:
                raise w.error(f"{path}.names[{k}]", f"{nm} is not a parameter of output axis {axis}")
            if nm in left:
                continue
            if base not in declared_params or (base == "D" and par[2:] not in currents):
                raise w.error(f"{path}.names[{k}]", f"{nm} is not a parameter of output axis {axis} of this table")
        cov = blk["cov"]
        k = len(names)
        if not isinstance(cov, list) or len(cov) != k:
            raise w.error(f"{path}.cov", f"must be a {k}x{k} matrix")
        rows = [_vector(w, f"{path}.cov[{r}]", row, k) for r, row in enumerate(cov)]
        _check_covariance(w, f"{path}.cov", np.array(rows, dtype=float))


def _check_covariance(w: _Path, path: str, C: np.ndarray) -> None:
    big = np.argwhere(np.abs(C) > MAX_POSTERIOR_ABS)
    if big.size:
        i, j = big[0]
        raise w.error(f"{path}[{i}][{j}]", f"{C[i, j]:g} is beyond any posterior covariance "
                                           f"(|entry| <= {MAX_POSTERIOR_ABS:g})")
    d = np.diag(C)
    neg = np.flatnonzero(d < 0)
    if neg.size:
        i = neg[0]
        raise w.error(f"{path}[{i}][{i}]", f"negative variance {d[i]:g}")
    s = np.sqrt(d)
    scale = np.outer(s, s)                     # each entry's own scale (no overflow: entries are bounded)
    asym = np.argwhere(np.abs(C - C.T) > POSTERIOR_TOL * scale)
    if asym.size:
        i, j = asym[0]
        raise w.error(path, f"is not symmetric: [{i}][{j}] = {C[i, j]:g}, [{j}][{i}] = {C[j, i]:g}")
    with np.errstate(divide="ignore", invalid="ignore"):
        R = np.where(scale > 0, 0.5 * (C + C.T) / scale, 0.0)
    beyond = np.argwhere((np.abs(R) > 1.0 + POSTERIOR_TOL) | ((scale == 0) & (C != 0)))
    if beyond.size:
        i, j = beyond[0]
        raise w.error(path, f"is not positive semi-definite: [{i}][{j}] = {C[i, j]:g} exceeds sqrt(C_ii C_jj) = "
                            f"{scale[i, j]:g}")
    live = s > 0
    if live.sum() > 1:
        try:
            low = float(np.linalg.eigvalsh(R[np.ix_(live, live)]).min())
        except np.linalg.LinAlgError:
            raise w.error(path, "eigenvalues cannot be computed (not a covariance)") from None
        if low < -POSTERIOR_TOL * live.sum():
            raise w.error(path, f"is not positive semi-definite (smallest eigenvalue of the correlation matrix "
                                f"{low:.3g})")


_SHAPES: dict[str, Callable[..., Any]] = {"3x3": _matrix, "3": _vector}


def _check_value(w: _Path, path: str, shape: str, value: Any, currents: list[str]) -> None:
    if shape == "currents":
        obj = _object(w, path, value, set(currents))
        if list(obj) != list(currents):
            raise w.error(path, f"names {list(obj)} must follow model.currents {currents}")
        for name in currents:
            _vector(w, f"{path}.{name}", obj[name])
        return
    _SHAPES[shape](w, path, value)
