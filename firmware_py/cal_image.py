"""Binary image of a calibration table: the fixed-point table, packed for the C applier and for uplink.

One fixed-size record (``SIZE`` = 336 bytes, little-endian, packed; format ``VERSION`` 2) holding the integers
of :class:`~magstack.firmware.fixed_point.FixedPointTable` (the Q formats of that module), the table's flight
terms, device id, current names and validity region (per-axis and magnitude limits of the calibrated field,
temperature and current ranges), the CRC-32 of the JSON table it was made from, and a CRC-32 (``zlib.crc32``)
of everything before it. ``FIELDS`` is the layout (docs/cal-table.md prints it).

A version-1 image is refused (``E_VERSION``): its field limit was on the measured field and it had no per-axis
or magnitude limits, so it cannot say the validity region of this applier; export the JSON table again.

The checks of :func:`check_image` are those of the C loader ``magstack_cal_load`` (``firmware_c/``), in
the same order and with the same result codes (:class:`ImageResult`): size, magic, version, CRC, then
the bounds of every field. :func:`table_from_image` turns an accepted image into a
:class:`~magstack.firmware.cal_table.CalTable` whose fixed-point form is exactly the image's integers, so
that the flight application validates and activates an image as it does a JSON table.

An image does not carry what the on-board applier does not use: the description, creation time, fit
statistics, posterior, ground-only terms (time skew, session offsets, drift) and float-only terms (cubic,
cross products: such a table has no image).
"""
from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass
from enum import IntEnum
from importlib import resources

from magstack.firmware import fixed_point as fp
from magstack.firmware.cal_table import CalTable, validate
from magstack.firmware.cal_terms import FLIGHT_TERMS, GROUND_ONLY_TERMS
from magstack.firmware.errors import CalTableInvalid

MAGIC = b"MCAL"
VERSION = 2
SIZE = 336
DEVICE_ID_BYTES = 32
CURRENT_NAME_BYTES = 16
#: Term bits of the ``terms`` byte, in :data:`~magstack.firmware.cal_terms.FLIGHT_TERMS` order.
TERM_BITS = {name: 1 << i for i, name in enumerate(FLIGHT_TERMS)}
OPT_TEMP_RANGE = 0x01
#: The table gives per-axis field limits (``field_axes_nT``); without it each equals ``field_limit_nT``.
OPT_FIELD_AXES = 0x02
#: The validity region has a magnitude limit (``field_norm_nT``; 0 without it).
OPT_FIELD_NORM = 0x04
OPTIONS = OPT_TEMP_RANGE | OPT_FIELD_AXES | OPT_FIELD_NORM
#: The C sources shipped with the package (``magstack.firmware.c_applier``).
C_SOURCES = ("magstack_cal.c", "magstack_cal.h")
C_PACKAGE = "magstack.firmware.c_applier"


@dataclass(frozen=True)
class ImageField:
    name: str
    offset: int
    fmt: str        # struct code, little-endian
    c_type: str
    meaning: str


def _layout() -> tuple[ImageField, ...]:
    spec = (
        ("magic", "4s", "char[4]", '"MCAL"'),
        ("version", "H", "uint16", "image format version (2)"),
        ("size", "H", "uint16", "image size in bytes (336)"),
        ("source_crc32", "I", "uint32", "crc32 of the JSON table the image was made from"),
        ("terms", "B", "uint8", "flight terms: 1 gain_matrix, 2 temperature_gain, 4 temperature_gain2, 8 offset, "
                                "16 temperature_offset, 32 currents"),
        ("n_currents", "B", "uint8", "number of currents k, 0..4"),
        ("options", "B", "uint8", "1: a temperature range; 2: per-axis field limits; 4: a magnitude limit"),
        ("reserved", "B", "uint8", "0"),
        ("device_id", "32s", "char[32]", "device id, printable ASCII, NUL-padded, not empty"),
        ("t0_cdeg", "i", "int32", "t0, centi-degC, |t0| <= 2^15"),
        ("field_limit_nT", "i", "int32", "the table's field limit (JSON field_uT), nT, 0..2^24"),
        ("field_axes_nT", "3i", "int32[3]", "validity: calibrated field of axis i within +-this[i], whole nT, "
                                            "0..field_limit_nT; each field_limit_nT without option 2"),
        ("field_norm_nT", "i", "int32", "validity: calibrated field's magnitude <= this, whole nT, "
                                        "0..29058990 with option 4, else 0"),
        ("temp_lo_cdeg", "i", "int32", "validity temperature low, centi-degC (0 without a range)"),
        ("temp_hi_cdeg", "i", "int32", "validity temperature high, centi-degC, >= low (0 without a range)"),
        ("S", "9i", "int32[3][3]", "S, row-major, value * 2^27"),
        ("K_S", "9i", "int32[3][3]", "K_S, row-major, 1/degC * 2^34"),
        ("K_S2", "3i", "int32[3]", "K_S2, 1/degC^2 * 2^40, within +-(2^28 - 1)"),
        ("O", "3i", "int32[3]", "O, nT * 2^8"),
        ("K_O", "3i", "int32[3]", "K_O, nT/degC * 2^16"),
        ("D", "12i", "int32[4][3]", "D_k (row k = current k), nT/mA * 2^20; rows >= k zero"),
        ("current_ranges_mA", "8i", "int32[4][2]", "validity [lo, hi] of current k, mA, within +-2^20; rows >= k "
                                                   "zero"),
        ("current_names", "64s", "char[4][16]", "name of current k, printable ASCII, NUL-padded; rows >= k zero"),
        ("crc32", "I", "uint32", "zlib CRC-32 of bytes 0..331"),
    )
    out, off = [], 0
    for name, fmt, c_type, meaning in spec:
        out.append(ImageField(name, off, fmt, c_type, meaning))
        off += struct.calcsize("<" + fmt)
    assert off == SIZE
    return tuple(out)


FIELDS = _layout()
_STRUCT = struct.Struct("<" + "".join(f.fmt for f in FIELDS))
_OFF = {f.name: f.offset for f in FIELDS}


class ImageResult(IntEnum):
    """Result codes of the loader (the C enum ``magstack_cal_result``, same numbers)."""

    OK = 0
    E_SIZE = 1
    E_MAGIC = 2
    E_VERSION = 3
    E_CRC = 4
    E_RESERVED = 5
    E_TERMS = 6
    E_DEVICE_ID = 7
    E_CURRENTS = 8
    E_T0 = 9
    E_K_S2 = 10
    E_VALIDITY = 11


class ImageInvalid(CalTableInvalid):
    """An image the loader refuses; ``code`` is its :class:`ImageResult`."""

    def __init__(self, message: str, code: ImageResult) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class TableImage:
    """A decoded, checked image."""

    fixed: fp.FixedPointTable
    device_id: str
    terms: tuple[str, ...]
    current_names: tuple[str, ...]
    source_crc32: int
    image_crc32: int


def is_image(raw: bytes) -> bool:
    """True when ``raw`` starts with the image magic (a JSON table starts with ``{`` or white space)."""
    return bytes(raw[:4]) == MAGIC


def _text(raw: bytes, what: str, code: ImageResult) -> str:
    s = raw.split(b"\0", 1)[0]
    if not s or any(c < 0x20 or c > 0x7E for c in s) or any(raw[len(s):]):
        raise ImageInvalid(f"{what} is not printable ASCII, non-empty and NUL-padded", code)
    return s.decode("ascii")


def decode_image(raw: bytes, source: str = "<image>") -> TableImage:
    """Check ``raw`` as the C loader does and decode it; :class:`ImageInvalid` (code and reason) otherwise."""
    try:
        return _decode(bytes(raw))
    except ImageInvalid as exc:
        raise ImageInvalid(f"{source}: table image refused: {exc}", exc.code) from None


def check_image(raw: bytes) -> ImageResult:
    """The loader's result code for ``raw`` (:data:`ImageResult.OK` when accepted)."""
    try:
        _decode(bytes(raw))
    except ImageInvalid as exc:
        return exc.code
    return ImageResult.OK


def _decode(raw: bytes) -> TableImage:
    R = ImageResult
    if len(raw) < 4:
        raise ImageInvalid(f"{len(raw)} bytes, an image has {SIZE}", R.E_SIZE)
    if raw[:4] != MAGIC:
        raise ImageInvalid(f"magic {raw[:4]!r}, expected {MAGIC!r} (not a table image)", R.E_MAGIC)
    if len(raw) < 8:
        raise ImageInvalid(f"{len(raw)} bytes, an image has {SIZE}", R.E_SIZE)
    version, size = struct.unpack_from("<HH", raw, 4)
    if version == 1:
        raise ImageInvalid("format version 1 (its field limit is on the measured field, without per-axis or "
                           f"magnitude limits): this loader reads version {VERSION}; export the table again",
                           R.E_VERSION)
    if version != VERSION:
        raise ImageInvalid(f"format version {version}, this loader reads version {VERSION}", R.E_VERSION)
    if size != SIZE or len(raw) != SIZE:
        raise ImageInvalid(f"{len(raw)} bytes (size field {size}), a version-{VERSION} image has {SIZE}", R.E_SIZE)
    v = dict(zip([f.name for f in FIELDS], _unpack(raw), strict=True))
    crc = zlib.crc32(raw[:_OFF["crc32"]]) & 0xFFFFFFFF
    if crc != v["crc32"]:
        raise ImageInvalid(f"CRC-32 mismatch: image says 0x{v['crc32']:08x}, content gives 0x{crc:08x} (corrupt)",
                           R.E_CRC)
    if v["reserved"] or v["options"] & ~OPTIONS:
        raise ImageInvalid("reserved byte or option bits set", R.E_RESERVED)
    bits = v["terms"]
    if bits & ~sum(TERM_BITS.values()) or not bits & TERM_BITS["gain_matrix"]:
        raise ImageInvalid(f"term bits 0x{bits:02x}: unknown bits or no gain_matrix", R.E_TERMS)
    terms = tuple(t for t in FLIGHT_TERMS if bits & TERM_BITS[t])
    device_id = _text(v["device_id"], "device id", R.E_DEVICE_ID)
    k = v["n_currents"]
    if k > fp.MAX_CURRENTS or (k and "currents" not in terms):
        raise ImageInvalid(f"{k} currents (at most {fp.MAX_CURRENTS}, and only with the currents term)",
                           R.E_CURRENTS)
    if abs(v["t0_cdeg"]) > fp.T_LIMIT_cdeg:
        raise ImageInvalid(f"t0 {v['t0_cdeg']} centi-degC beyond +-{fp.T_LIMIT_cdeg}", R.E_T0)
    S, KS, K2, O, KO = (tuple(v[n]) for n in ("S", "K_S", "K_S2", "O", "K_O"))
    if any(abs(x) > fp.K_S2_INT_LIMIT for x in K2):
        raise ImageInvalid(f"K_S2 {list(K2)} beyond +-{fp.K_S2_INT_LIMIT}", R.E_K_S2)
    for term, coeffs in (("temperature_gain", KS), ("temperature_gain2", K2), ("offset", O),
                         ("temperature_offset", KO)):
        if any(coeffs) and term not in terms:
            raise ImageInvalid(f"non-zero coefficients of the undeclared term {term}", R.E_TERMS)
    field, axes, norm = v["field_limit_nT"], v["field_axes_nT"], v["field_norm_nT"]
    lo, hi = v["temp_lo_cdeg"], v["temp_hi_cdeg"]
    has_t = bool(v["options"] & OPT_TEMP_RANGE)
    has_axes, has_norm = bool(v["options"] & OPT_FIELD_AXES), bool(v["options"] & OPT_FIELD_NORM)
    if not 0 <= field <= fp.B_LIMIT_nT:
        raise ImageInvalid(f"field limit {field} nT outside 0..{fp.B_LIMIT_nT}", R.E_VALIDITY)
    for a in axes:
        if not 0 <= a <= field or (not has_axes and a != field):
            raise ImageInvalid(f"per-axis field limits {list(axes)} nT not within 0..{field} (the field limit)"
                               + ("" if has_axes else ", or not each equal to it without their option bit"),
                               R.E_VALIDITY)
    if not 0 <= norm <= fp.B_NORM_LIMIT_nT or (not has_norm and norm):
        raise ImageInvalid(f"magnitude limit {norm} nT outside 0..{fp.B_NORM_LIMIT_nT}"
                           + ("" if has_norm else ", or set without its option bit"), R.E_VALIDITY)
    if has_t and not (abs(lo) <= fp.T_LIMIT_cdeg and abs(hi) <= fp.T_LIMIT_cdeg and lo <= hi):
        raise ImageInvalid(f"temperature range [{lo}, {hi}] centi-degC not an interval within "
                           f"+-{fp.T_LIMIT_cdeg}", R.E_VALIDITY)
    if not has_t and (lo or hi):
        raise ImageInvalid("temperature range set without its option bit", R.E_VALIDITY)
    D, ranges, names = v["D"], v["current_ranges_mA"], v["current_names"]
    d_rows, r_rows, name_list = [], [], []
    for j in range(fp.MAX_CURRENTS):
        row, (a, b) = tuple(D[3 * j:3 * j + 3]), ranges[2 * j:2 * j + 2]
        nm = names[CURRENT_NAME_BYTES * j:CURRENT_NAME_BYTES * (j + 1)]
        if j < k:
            name_list.append(_text(nm, f"current name {j}", R.E_CURRENTS))
            if not (abs(a) <= fp.I_LIMIT_mA and abs(b) <= fp.I_LIMIT_mA and a <= b):
                raise ImageInvalid(f"current {j} range [{a}, {b}] mA not an interval within +-{fp.I_LIMIT_mA}",
                                   R.E_VALIDITY)
            d_rows.append(row)
            r_rows.append((a, b))
        elif any(nm) or any(row) or a or b:
            raise ImageInvalid(f"unused current slot {j} is not zero", R.E_CURRENTS)
    if len(set(name_list)) != len(name_list):
        raise ImageInvalid(f"current names {name_list} repeat", R.E_CURRENTS)
    fixed = fp.FixedPointTable(
        S=(S[0:3], S[3:6], S[6:9]), K_S=(KS[0:3], KS[3:6], KS[6:9]), O=O, K_O=KO, D=tuple(d_rows),
        t0_cdeg=v["t0_cdeg"], field_limit_nT=field, temp_range_cdeg=(lo, hi) if has_t else None,
        current_ranges_mA=tuple(r_rows), K_S2=K2, field_limits_nT=axes if has_axes else None,
        field_norm_nT=norm if has_norm else None)
    return TableImage(fixed, device_id, terms, tuple(name_list), v["source_crc32"], v["crc32"])


def _unpack(raw: bytes) -> list:
    flat = list(_STRUCT.unpack(raw))
    out = []
    for f in FIELDS:
        n = int(f.fmt[:-1]) if f.fmt[:-1] and f.fmt[-1] != "s" else 1
        out.append(tuple(flat[:n]) if n > 1 else flat[0])
        del flat[:n]
    return out


# ---------------------------------------------------------------------- write
def pack_fixed(fixed: fp.FixedPointTable, *, device_id: str, terms, current_names=(), source_crc32: int = 0) -> bytes:
    """The image of a fixed-point table. :class:`ImageInvalid` when the loader would refuse it (the image is
    checked by :func:`decode_image` before it is returned) or a value does not fit its field."""
    k = len(fixed.D)
    names = tuple(current_names)
    if len(names) != k or len(fixed.current_ranges_mA) != k:
        raise ImageInvalid(f"{k} current rows, {len(names)} names, {len(fixed.current_ranges_mA)} ranges",
                           ImageResult.E_CURRENTS)
    if k > fp.MAX_CURRENTS:
        raise ImageInvalid(f"{k} currents, an image holds at most {fp.MAX_CURRENTS}", ImageResult.E_CURRENTS)
    unknown = [t for t in terms if t not in TERM_BITS]
    if unknown:
        raise ImageInvalid(f"terms {unknown} cannot be carried by an image (flight terms: "
                           f"{', '.join(FLIGHT_TERMS)})", ImageResult.E_TERMS)
    dev = _encode_text(device_id, DEVICE_ID_BYTES, "device id", ImageResult.E_DEVICE_ID)
    name_bytes = b"".join(_encode_text(n, CURRENT_NAME_BYTES, f"current name {n!r}", ImageResult.E_CURRENTS)
                          for n in names)
    rows = [x for r in fixed.D for x in r] + [0] * 3 * (fp.MAX_CURRENTS - k)
    ranges = [x for r in fixed.current_ranges_mA for x in r] + [0] * 2 * (fp.MAX_CURRENTS - k)
    tr = fixed.temp_range_cdeg
    options = ((OPT_TEMP_RANGE if tr is not None else 0) | (OPT_FIELD_AXES if fixed.field_limits_nT is not None else 0)
               | (OPT_FIELD_NORM if fixed.field_norm_nT is not None else 0))
    values = [MAGIC, VERSION, SIZE, int(source_crc32) & 0xFFFFFFFF, sum(TERM_BITS[t] for t in set(terms)), k,
              options, 0, dev, fixed.t0_cdeg, fixed.field_limit_nT, *fixed.axis_limits_nT, fixed.field_norm_nT or 0,
              *(tr if tr is not None else (0, 0)), *(x for r in fixed.S for x in r),
              *(x for r in fixed.K_S for x in r), *fixed.K_S2, *fixed.O, *fixed.K_O, *rows, *ranges,
              name_bytes.ljust(CURRENT_NAME_BYTES * fp.MAX_CURRENTS, b"\0"), 0]
    try:
        body = _STRUCT.pack(*values)
    except struct.error as exc:
        raise ImageInvalid(f"a value does not fit its image field ({exc})", ImageResult.E_VALIDITY) from None
    raw = body[:_OFF["crc32"]] + struct.pack("<I", zlib.crc32(body[:_OFF["crc32"]]) & 0xFFFFFFFF)
    decode_image(raw, "image")
    return raw


def _encode_text(text: str, n: int, what: str, code: ImageResult) -> bytes:
    b = text.encode("ascii", errors="replace")
    if not text or not text.isascii() or not text.isprintable() or len(b) > n:
        raise ImageInvalid(f"{what} {text!r} must be 1..{n} printable ASCII characters in an image", code)
    return b.ljust(n, b"\0")


def image_from_table(table: CalTable) -> bytes:
    """The image of a calibration table: the table must validate, carry only flight terms (ground-only
    terms are left out), and its image must load back through :func:`table_from_image` with the same
    integers into a table that validates too (what the flight loader will check)."""
    validate(table).raise_if_bad(table.table_name or "table")
    other = [t for t in table.terms if t not in FLIGHT_TERMS and t not in GROUND_ONLY_TERMS]
    if other:
        raise ImageInvalid(f"terms {other} are float-only: a table image carries only the fixed-point "
                           f"applier's terms ({', '.join(FLIGHT_TERMS)})", ImageResult.E_TERMS)
    fixed = fp.FixedPointTable.from_table(table)
    raw = pack_fixed(fixed, device_id=table.device_id, terms=[t for t in table.terms if t in FLIGHT_TERMS],
                     current_names=table.currents, source_crc32=table.crc32 or 0)
    # a coefficient at a physical bound may pass it by less than one LSB once quantised
    validate(table_from_image(raw, "image")).raise_if_bad(f"{table.table_name or 'table'} (its quantised image)")
    return raw


# ---------------------------------------------------------------------- read as a table
def _just(n: int, scale: float, fn) -> float:
    """The float x nearest n / scale with ``fn(x * scale) == n`` (fn: math.floor or math.ceil)."""
    x = n / scale
    for _ in range(8):
        got = fn(x * scale)
        if got == n:
            return x
        x = math.nextafter(x, math.inf if got < n else -math.inf)
    raise CalTableInvalid(f"cannot represent {n} / {scale:g} as a float bound")


def table_from_image(raw: bytes, source: str = "<image>") -> CalTable:
    """A :class:`CalTable` whose fixed-point form is exactly the image's integers (checked), for the store's
    validation and activation. Its ``crc32`` is the JSON table's (``source_crc32``), so a table has one
    identity in telemetry whichever form was loaded; the image's own CRC is in ``description``."""
    img = decode_image(raw, source)
    fx = img.fixed
    temp = None if fx.temp_range_cdeg is None else (_just(fx.temp_range_cdeg[0], 100.0, math.floor),
                                                      _just(fx.temp_range_cdeg[1], 100.0, math.ceil))
    table = CalTable(
        device_id=img.device_id, terms=img.terms,
        S=[[x / 2 ** fp.S_FRAC for x in r] for r in fx.S], K_S=[[x / 2 ** fp.K_S_FRAC for x in r] for r in fx.K_S],
        K_S2=[x / 2 ** fp.K_S2_FRAC for x in fx.K_S2], O=[x / 2 ** fp.O_FRAC / 1e3 for x in fx.O],
        K_O=[x / 2 ** fp.K_O_FRAC / 1e3 for x in fx.K_O],
        D=tuple((n, [x / 2 ** fp.D_FRAC for x in r]) for n, r in zip(img.current_names, fx.D, strict=True)),
        t0_c=fx.t0_cdeg / 100, validity_temp_c=temp, validity_field_uT=_just(fx.field_limit_nT, 1e3, math.floor),
        validity_field_axes_uT=None if fx.field_limits_nT is None else tuple(
            _just(a, 1e3, math.floor) for a in fx.field_limits_nT),
        validity_field_norm_uT=None if fx.field_norm_nT is None else _just(fx.field_norm_nT, 1e3, math.floor),
        validity_currents_A=tuple((n, (_just(a, 1e3, math.floor), _just(b, 1e3, math.ceil)))
                                  for n, (a, b) in zip(img.current_names, fx.current_ranges_mA, strict=True)),
        description=f"table image v{VERSION}, image CRC-32 0x{img.image_crc32:08x}", crc32=img.source_crc32)
    if fp.FixedPointTable.from_table(table) != fx:
        raise ImageInvalid(f"{source}: table image refused: its integers do not survive the table form",
                           ImageResult.E_VALIDITY)
    return table


# ---------------------------------------------------------------------- C export
def c_sources() -> dict[str, bytes]:
    """``{file name: bytes}`` of the C applier's sources shipped with the package."""
    base = resources.files(C_PACKAGE)
    return {name: base.joinpath(name).read_bytes() for name in C_SOURCES}


def c_array_header(raw: bytes, symbol: str = "magstack_cal_image") -> str:
    """A C header holding one image as a ``static const uint8_t`` array (builds without a file system)."""
    img = decode_image(raw)
    guard = symbol.upper() + "_H"
    rows = [", ".join(f"0x{b:02x}" for b in raw[i:i + 12]) for i in range(0, len(raw), 12)]
    body = ",\n    ".join(rows)
    return (f"/* Calibration table image for magstack_cal_load(): device {img.device_id}, table crc32 "
            f"0x{img.source_crc32:08x}, image crc32 0x{img.image_crc32:08x}. Generated by magstack table export. */\n"
            f"#ifndef {guard}\n#define {guard}\n\n#include <stdint.h>\n\n"
            f"static const uint8_t {symbol}[{len(raw)}] = {{\n    {body}\n}};\n\n#endif /* {guard} */\n")
