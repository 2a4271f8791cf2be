"""Build and drive the C applier (``firmware_c/``) for the equality tests and the benchmark.

* :func:`build_shared` compiles ``magstack_cal.c`` into a shared library for :class:`CApplier` (ctypes).
* :func:`build_harness` compiles ``harness.c`` (stdin records -> stdout results) natively, with
  sanitizers, or with a cross compiler; :func:`run_harness` feeds it (through ``qemu-arm`` for ARM).
* :func:`random_case` draws a table image and samples from a seed (extremes included), for the full-count
  script; the test module draws them with hypothesis.
"""
from __future__ import annotations

import ctypes
import dataclasses
import math
import shutil
import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

from magstack.firmware import cal_image
from magstack.firmware import fixed_point as fp

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
C_DIR = ROOT / "firmware_c"
SOURCE = C_DIR / "magstack_cal.c"
HARNESS = HERE / "harness.c"
#: The compile flags every build uses.
STRICT = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic")
SANITIZE = ("-fsanitize=undefined,address", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer")
ARM_CC = "arm-linux-gnueabihf-gcc"
M4_CC = "arm-none-eabi-gcc"
QEMU_ARM = "qemu-arm"
I32 = np.iinfo(np.int32)
#: Coefficients that put a rounding exactly on a half with small inputs (B odd, dTc = +-1 ...): S = 2^18 makes
#: the output B / 2; K_S = 6400 makes rdiv(K_S dTc, 12800) = dTc / 2; K_S2 = 50 makes rdiv(K_S2 dTc, 100) = dTc / 2.
TIES = {"S": (2 ** 18, -(2 ** 18), 3 * 2 ** 18), "K_S": (6400, -6400, 19200), "K_S2": (50, -50, 150, 409600 * 100)}


def tool(name: str) -> str | None:
    return shutil.which(name)


def compile_c(cc: str, args, out: Path, timeout: float = 120) -> Path:
    """Run the compiler; AssertionError with its output on failure (a warning fails: -Werror)."""
    cmd = [cc, *STRICT, *args, "-I", str(C_DIR), "-o", str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{' '.join(cmd)}\n{r.stdout}{r.stderr}"
    assert not r.stderr.strip(), f"compiler said something: {r.stderr}"
    return out


def build_shared(out_dir: Path, opt: str = "-O2") -> Path:
    return compile_c("gcc", [opt, "-fPIC", "-shared", str(SOURCE)], out_dir / "libmagstack_cal.so")


def build_harness(out_dir: Path, name: str, cc: str = "gcc", extra=(), opt: str = "-O2") -> Path:
    return compile_c(cc, [opt, *extra, str(SOURCE), str(HARNESS)], out_dir / name)


# ---------------------------------------------------------------------- ctypes
class CTable(ctypes.Structure):
    """``magstack_cal_table`` (magstack_cal.h)."""

    _fields_ = [("image_crc32", ctypes.c_uint32), ("source_crc32", ctypes.c_uint32), ("terms", ctypes.c_uint8),
                ("n_currents", ctypes.c_uint8), ("has_temp_range", ctypes.c_uint8), ("has_field_axes", ctypes.c_uint8),
                ("has_field_norm", ctypes.c_uint8), ("device_id", ctypes.c_char * 33),
                ("current_names", (ctypes.c_char * 17) * 4), ("t0_cdeg", ctypes.c_int32),
                ("field_limit_nT", ctypes.c_int32), ("field_axes_nT", ctypes.c_int32 * 3),
                ("field_norm_nT", ctypes.c_int32), ("temp_lo_cdeg", ctypes.c_int32),
                ("temp_hi_cdeg", ctypes.c_int32), ("S", (ctypes.c_int32 * 3) * 3), ("K_S", (ctypes.c_int32 * 3) * 3),
                ("K_S2", ctypes.c_int32 * 3), ("O", ctypes.c_int32 * 3), ("K_O", ctypes.c_int32 * 3),
                ("D", (ctypes.c_int32 * 3) * 4), ("current_lo_mA", ctypes.c_int32 * 4),
                ("current_hi_mA", ctypes.c_int32 * 4), ("pre", ctypes.c_void_p), ("pre_lo_cdeg", ctypes.c_int32),
                ("pre_count", ctypes.c_uint32), ("pre_reach", (ctypes.c_uint64 * 3) * 2)]

    def as_fixed(self) -> fp.FixedPointTable:
        """The decoded integers as a FixedPointTable (to compare with the Python decoder)."""
        k = self.n_currents
        return fp.FixedPointTable(
            S=tuple(tuple(r) for r in self.S), K_S=tuple(tuple(r) for r in self.K_S), O=tuple(self.O),
            K_O=tuple(self.K_O), D=tuple(tuple(self.D[j]) for j in range(k)), t0_cdeg=self.t0_cdeg,
            field_limit_nT=self.field_limit_nT,
            temp_range_cdeg=(self.temp_lo_cdeg, self.temp_hi_cdeg) if self.has_temp_range else None,
            current_ranges_mA=tuple((self.current_lo_mA[j], self.current_hi_mA[j]) for j in range(k)),
            K_S2=tuple(self.K_S2), field_limits_nT=tuple(self.field_axes_nT) if self.has_field_axes else None,
            field_norm_nT=self.field_norm_nT if self.has_field_norm else None)


_P32 = ctypes.POINTER(ctypes.c_int32)
#: Bytes of one temperature's precomputed terms (``magstack_cal_terms``: 9 int64 gains, 3 uint64 constants), and their
#: alignment.
TERMS_BYTES, TERMS_ALIGN = 96, 32


class CApplier:
    """The shared library through ctypes."""

    def __init__(self, lib: Path) -> None:
        self.lib = ctypes.CDLL(str(lib))
        L = self.lib
        L.magstack_cal_load.argtypes = [ctypes.POINTER(CTable), ctypes.c_char_p, ctypes.c_size_t]
        L.magstack_cal_load.restype = ctypes.c_int
        L.magstack_cal_crc32.argtypes = [ctypes.c_char_p, ctypes.c_size_t]
        L.magstack_cal_crc32.restype = ctypes.c_uint32
        L.magstack_cal_result_name.argtypes = [ctypes.c_int]
        L.magstack_cal_result_name.restype = ctypes.c_char_p
        L.magstack_cal_apply.argtypes = [ctypes.POINTER(CTable), _P32, ctypes.c_int32, _P32, _P32]
        L.magstack_cal_apply.restype = ctypes.c_uint
        L.magstack_cal_apply_block.argtypes = [ctypes.POINTER(CTable), ctypes.c_size_t, _P32, _P32, _P32, _P32,
                                               ctypes.POINTER(ctypes.c_uint8)]
        L.magstack_cal_apply_block.restype = None
        L.magstack_cal_precompute.argtypes = [ctypes.POINTER(CTable), ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int32,
                                              ctypes.c_int32]
        L.magstack_cal_precompute.restype = ctypes.c_int

    def load(self, raw: bytes) -> tuple[int, CTable]:
        t = CTable()
        return self.lib.magstack_cal_load(ctypes.byref(t), raw, len(raw)), t

    def precompute(self, t: CTable, lo_cdeg: int, hi_cdeg: int, count: int | None = None) -> tuple[int, np.ndarray]:
        """``magstack_cal_precompute`` into a new buffer of ``count`` entries (enough when None), aligned as the C type
        is (32 bytes); the buffer must be kept while ``t`` is used."""
        n = max(hi_cdeg - lo_cdeg + 1, 1) if count is None else count
        raw = np.zeros(n * TERMS_BYTES + TERMS_ALIGN, np.uint8)
        skip = -raw.ctypes.data % TERMS_ALIGN
        storage = raw[skip:skip + n * TERMS_BYTES]
        return self.lib.magstack_cal_precompute(ctypes.byref(t), storage.ctypes.data, n, lo_cdeg, hi_cdeg), storage

    def apply(self, t: CTable, b, temp: int, cur) -> tuple[tuple[int, int, int], int]:
        bb = (ctypes.c_int32 * 3)(*b)
        cc = (ctypes.c_int32 * 4)(*cur)
        out = (ctypes.c_int32 * 3)()
        st = self.lib.magstack_cal_apply(ctypes.byref(t), bb, temp, cc, out)
        return (out[0], out[1], out[2]), st

    def apply_block(self, t: CTable, b: np.ndarray, temp: np.ndarray, cur: np.ndarray):
        n = b.shape[0]
        b = np.ascontiguousarray(b, np.int32)
        temp = np.ascontiguousarray(temp, np.int32)
        cur = np.ascontiguousarray(np.asarray(cur, np.int32).reshape(n, -1)[:, :t.n_currents])
        out = np.empty((n, 3), np.int32)
        status = np.empty(n, np.uint8)
        self.apply_block_into(t, b, temp, cur, out, status)
        return out, status

    def apply_block_into(self, t, b, temp, cur, out, status) -> None:
        """No conversions (the benchmark's timed call): contiguous int32 arrays, uint8 status."""
        self.lib.magstack_cal_apply_block(ctypes.byref(t), b.shape[0], b.ctypes.data_as(_P32),
                                          temp.ctypes.data_as(_P32), cur.ctypes.data_as(_P32),
                                          out.ctypes.data_as(_P32),
                                          status.ctypes.data_as(ctypes.POINTER(ctypes.c_uint8)))


# ---------------------------------------------------------------------- harness protocol
@dataclass
class Record:
    image: bytes
    b: np.ndarray       # (n, 3) int32
    temp: np.ndarray    # (n,) int32
    cur: np.ndarray     # (n, 4) int32 (the table's first k columns are used)


def encode(records) -> bytes:
    parts = []
    for r in records:
        rows = np.zeros((r.b.shape[0], 8), "<i4")
        rows[:, :3], rows[:, 3], rows[:, 4:] = r.b, r.temp, r.cur
        parts += [struct.pack("<I", len(r.image)), r.image, struct.pack("<I", r.b.shape[0]), rows.tobytes()]
    return b"".join(parts)


def run_harness(cmd: list[str], records, mode=("check",), timeout: float = 600) -> list:
    """Per record: (loader result, outputs (n,3) int32 or None, status (n,) or None, block mismatches) in
    "check" mode; (loader result, ns) in "bench" mode."""
    r = subprocess.run([*cmd, *mode], input=encode(records), capture_output=True, timeout=timeout)
    assert r.returncode == 0, f"harness exit {r.returncode}: {r.stderr.decode(errors='replace')[-3000:]}"
    assert not r.stderr, r.stderr.decode(errors="replace")[-3000:]
    buf, pos, res = r.stdout, 0, []
    for rec in records:
        (rc,) = struct.unpack_from("<i", buf, pos)
        pos += 4
        if rc != 0:
            res.append((rc, None, None, 0) if mode[0] == "check" else (rc, None))
            continue
        if mode[0] == "bench":
            (ns,) = struct.unpack_from("<Q", buf, pos)
            pos += 8
            res.append((rc, ns))
            continue
        n = rec.b.shape[0]
        a = np.frombuffer(buf, "<i4", 4 * n, pos).reshape(n, 4)
        pos += 16 * n
        (differ,) = struct.unpack_from("<I", buf, pos)
        pos += 4
        res.append((rc, a[:, :3].astype(np.int64), a[:, 3].view("<u4").astype(np.int64), differ))
    assert pos == len(buf), "harness output longer than expected"
    return res


def qemu_prefix() -> list[str]:
    return [QEMU_ARM]


# ---------------------------------------------------------------------- cases from a seed
def _pick(rng: np.random.Generator, size, lo: int, hi: int, edges=()) -> np.ndarray:
    """Integers in [lo, hi] of mixed scales (full range, small, near the edges), with ``edges`` mixed in."""
    size = tuple(np.atleast_1d(size))
    kind = rng.integers(0, 4, size)
    full = rng.integers(lo, hi, size, endpoint=True)
    mag = np.minimum(2.0 ** rng.uniform(0, np.log2(max(hi, 1)), size), hi)
    small = (np.sign(rng.uniform(-1, 1, size)) * mag).astype(np.int64).clip(lo, hi)
    e = np.array(list(edges) or [lo, hi, 0], np.int64)
    edge = e[rng.integers(0, e.size, size)]
    return np.select([kind == 0, kind == 1, kind == 2], [full, small, edge], rng.integers(-3, 4, size).clip(lo, hi))


def random_fixed(rng: np.random.Generator, realistic: bool | None = None) -> tuple[fp.FixedPointTable, list[str]]:
    """A fixed-point table within the image's bounds: any int32 coefficient and the limits (extreme), or a
    physical AMR calibration (``realistic``: gains near 1, offsets to 500 uT, tempcos, 0-4 currents);
    drawn at random when None."""
    if realistic is None:
        realistic = bool(rng.random() < 0.5)
    lo, hi = int(I32.min), int(I32.max)
    k = int(rng.integers(0, fp.MAX_CURRENTS + 1))
    if realistic:
        S = np.round((np.eye(3).ravel() * rng.uniform(0.5, 3, 9) + rng.uniform(-0.3, 0.3, 9)) * 2 ** fp.S_FRAC)
        KS = np.round(rng.uniform(-0.02, 0.02, 9) * 2 ** fp.K_S_FRAC)
        K2 = np.round(rng.uniform(-2e-4, 2e-4, 3) * 2 ** fp.K_S2_FRAC)
        O = np.round(rng.uniform(-5e5, 5e5, 3) * 2 ** fp.O_FRAC)
        KO = np.round(rng.uniform(-5e3, 5e3, 3) * 2 ** fp.K_O_FRAC)
        D = np.round(rng.uniform(-200, 200, (k, 3)) * 2 ** fp.D_FRAC)
        t0 = int(rng.integers(-2000, 6000))
        field = int(rng.integers(50_000, 200_001))
        a = int(rng.integers(-5500, t0 + 1))
        tr = (a, int(rng.integers(t0, 12_501)))
        ranges = tuple((-int(x), int(y)) for x, y in rng.integers(0, 10_001, (k, 2)))
    else:
        S = _pick(rng, 9, lo, hi, (lo, hi, 0, 2 ** 27, -(2 ** 27), *TIES["S"]))
        KS = _pick(rng, 9, lo, hi, (lo, hi, 0, *TIES["K_S"]))
        K2 = _pick(rng, 3, -fp.K_S2_INT_LIMIT, fp.K_S2_INT_LIMIT, (-fp.K_S2_INT_LIMIT, fp.K_S2_INT_LIMIT, 0,
                                                                   *TIES["K_S2"]))
        O, KO = _pick(rng, 3, lo, hi), _pick(rng, 3, lo, hi)
        D = _pick(rng, (k, 3), lo, hi)
        t0 = int(_pick(rng, 1, -fp.T_LIMIT_cdeg, fp.T_LIMIT_cdeg)[0])
        field = int(_pick(rng, 1, 0, fp.B_LIMIT_nT)[0])
        tr = None
        if rng.random() < 0.8:
            a, b = sorted(int(x) for x in _pick(rng, 2, -fp.T_LIMIT_cdeg, fp.T_LIMIT_cdeg))
            tr = (a, b)
        ranges = tuple(tuple(sorted(int(x) for x in _pick(rng, 2, -fp.I_LIMIT_mA, fp.I_LIMIT_mA))) for _ in range(k))
    axes = norm = None
    if rng.random() < 0.5:
        axes = tuple(int(x) for x in (np.round(field * rng.uniform(0.5, 1.0, 3)) if realistic
                                      else _pick(rng, 3, 0, field)))
    if rng.random() < 0.5:
        norm = (int(field * rng.uniform(0.8, 1.8)) if realistic
                else int(_pick(rng, 1, 0, fp.B_NORM_LIMIT_nT, (0, fp.B_NORM_LIMIT_nT, 2 ** 23))[0]))

    def ints(a) -> tuple[int, ...]:
        return tuple(int(x) for x in np.asarray(a).ravel())

    fx = fp.FixedPointTable(
        S=(ints(S[0:3]), ints(S[3:6]), ints(S[6:9])), K_S=(ints(KS[0:3]), ints(KS[3:6]), ints(KS[6:9])),
        O=ints(O), K_O=ints(KO), D=tuple(ints(r) for r in np.asarray(D).reshape(k, 3)), t0_cdeg=t0,
        field_limit_nT=field, temp_range_cdeg=tr, current_ranges_mA=ranges, K_S2=ints(K2), field_limits_nT=axes,
        field_norm_nT=norm)
    return fx, [f"i{j}" for j in range(k)]


def whole_nT(q) -> np.ndarray:
    """|output| in whole nT, rounded half away from zero (the applier's validity test of its output)."""
    return (np.abs(np.asarray(q, np.int64)) + (1 << (fp.OUT_FRAC - 1))) >> fp.OUT_FRAC


def limits_at_outputs(rng: np.random.Generator, fx: fp.FixedPointTable, b, t, c) -> fp.FixedPointTable:
    """``fx`` with field limits on the calibrated outputs of these samples, so that outputs fall on the limits and
    one past them: each axis' limit the whole-nT output of a row, or one below it (the row mostly one whose output
    is on a half nT, which rounds away from zero); the magnitude limit the square root (rounded down) of a row's
    sum of squares, or one below it (the row mostly one whose sum is a square, so on the limit exactly); the field
    limit the largest axis limit, or above it to 2^24. Saturated outputs are 2^23 whole nT."""
    k = len(fx.D)
    q, _ = fx.apply_block(np.asarray(b, np.int64), np.asarray(t, np.int64), np.asarray(c, np.int64)[:, :k])
    nt = whole_nT(q)
    n = nt.shape[0]

    def row(good: np.ndarray) -> int:
        idx = np.flatnonzero(good)
        return int(rng.choice(idx)) if idx.size and rng.random() < 0.7 else int(rng.integers(0, n))

    half = np.abs(q) % 256 == 128
    axes = tuple(max(0, int(nt[row(half[:, i]), i]) - int(rng.integers(0, 2))) for i in range(3))
    field = max(axes) if rng.random() < 0.7 else int(rng.integers(max(axes), fp.B_LIMIT_nT, endpoint=True))
    sums = [int(x) for x in (nt ** 2).sum(axis=1)]
    root = [math.isqrt(x) for x in sums]
    r = row(np.array([a * a == x for a, x in zip(root, sums, strict=True)]))
    norm = min(fp.B_NORM_LIMIT_nT, max(0, root[r] - int(rng.integers(0, 2))))
    return dataclasses.replace(fx, field_limit_nT=field, field_limits_nT=axes if rng.random() < 0.8 else None,
                               field_norm_nT=norm if rng.random() < 0.8 else None)


#: Integer triples whose squares sum to a square (1 + 4 + 4 = 9, ...): through a gain of one they put the
#: calibrated field's magnitude exactly on an integer.
QUADRUPLES = np.array([(1, 2, 2), (2, 3, 6), (1, 4, 8), (4, 4, 7), (2, 6, 9), (0, 3, 4), (2, 10, 11)], np.int64)


def quadruple_rows(rng: np.random.Generator, n: int, fx: fp.FixedPointTable):
    """(b, temp, cur): ``n`` rows of QUADRUPLES scaled (1..2^20), permuted and signed at random, at t0 with zero
    currents."""
    q = QUADRUPLES[rng.integers(0, len(QUADRUPLES), n)] * rng.integers(1, 2 ** 20, (n, 1))
    q = np.take_along_axis(q, rng.permuted(np.tile(np.arange(3), (n, 1)), axis=1), axis=1)
    b = q * rng.choice([-1, 1], (n, 3))
    return b.astype(np.int32), np.full(n, fx.t0_cdeg, np.int32), np.zeros((n, 4), np.int32)


def image_of(fx: fp.FixedPointTable, names, device_id: str = "dut:1", source_crc32: int = 0) -> bytes:
    """The image of ``fx`` declaring every flight term (any coefficient may be non-zero)."""
    terms = [t for t in cal_image.TERM_BITS if t != "currents" or fx.D]
    return cal_image.pack_fixed(fx, device_id=device_id, terms=terms, current_names=names, source_crc32=source_crc32)


def random_samples(rng: np.random.Generator, n: int, fx: fp.FixedPointTable | None = None):
    """(b (n,3), temp (n,), cur (n,4)) int32. Rows of three kinds: anywhere in int32 (every scale, the clips
    and the int32 limits), inside ``fx``'s input ranges (field limit, temperature and current ranges), and on
    their edges (each limit and one past it). Temperatures change on every sample, in runs of 4, and in runs of
    8..64 (the C block path's mixed and run kernels)."""
    lo, hi = int(I32.min), int(I32.max)
    B, T, I = fp.B_LIMIT_nT, fp.T_LIMIT_cdeg, fp.I_LIMIT_mA
    b = _pick(rng, (n, 3), lo, hi, (lo, hi, B, B + 1, -B, -B - 1, 0))
    run = np.repeat(_pick(rng, n // 4 + 1, lo, hi, (lo, hi, T, T + 1, -T - 1, 0)), 4)[:n]
    temp = np.where(rng.random(n) < 0.5, run, _pick(rng, n, -(2 ** 16), 2 ** 16))
    if fx is not None:   # a few degrees from t0 (the temperature terms' roundings on a half)
        near = fx.t0_cdeg + np.repeat(rng.integers(-3, 4, n // 4 + 1), 4)[:n]
        temp = np.where(rng.random(n) < 0.2, near, temp)
    cur = _pick(rng, (n, 4), lo, hi, (lo, hi, I, I + 1, -I - 1, 0))
    if fx is not None:
        kind = rng.integers(0, 3, n)
        f = fx.field_limit_nT
        t_lo, t_hi = fx.temp_range_cdeg or (fx.t0_cdeg - 5000, fx.t0_cdeg + 5000)
        inside = kind == 1
        b[inside] = rng.integers(-f, f, (int(inside.sum()), 3), endpoint=True)
        tin = np.repeat(rng.integers(t_lo, t_hi, n // 4 + 1, endpoint=True), 4)[:n]
        temp = np.where(inside, tin, temp)
        edge = kind == 2
        b[edge] = np.array([-f - 1, -f, f, f + 1], np.int64)[rng.integers(0, 4, (int(edge.sum()), 3))]
        temp = np.where(edge, np.array([t_lo - 1, t_lo, t_hi, t_hi + 1])[rng.integers(0, 4, n)], temp)
        for j, (a, c) in enumerate(fx.current_ranges_mA):
            cur[inside, j] = rng.integers(a, c, int(inside.sum()), endpoint=True)
            cur[edge, j] = np.array([a - 1, a, c, c + 1])[rng.integers(0, 4, int(edge.sum()))]
    for _ in range(max(1, n // 100)):   # runs of one temperature of 8..64 samples (the block path's run kernel)
        a, m = int(rng.integers(0, n)), int(rng.integers(8, 65))
        temp[a:a + m] = temp[a]
    return b.astype(np.int32), temp.astype(np.int32), cur.astype(np.int32)


def python_reference(fx: fp.FixedPointTable, b, temp, cur, per_sample: bool = True):
    """(out (n,3) int64, status (n,) int64) of the Python applier: apply_block, and apply_sample on every
    row when ``per_sample`` (asserting the two agree)."""
    k = len(fx.D)
    q, s = fx.apply_block(b.astype(np.int64), temp.astype(np.int64), cur[:, :k].astype(np.int64))
    if per_sample:
        for r in range(b.shape[0]):
            o, st = fx.apply_sample(tuple(int(x) for x in b[r]), int(temp[r]), tuple(int(x) for x in cur[r, :k]))
            assert o == tuple(int(x) for x in q[r]) and st == s[r], f"apply_sample != apply_block at row {r}"
    return q, s


_I32 = st.integers(fp.INT32_MIN, fp.INT32_MAX)


# ---------------------------------------------------------------------- hypothesis strategies
def _coeff(edges=()):
    return st.one_of(_I32, st.sampled_from([fp.INT32_MIN, fp.INT32_MAX, 0, 1, -1, *edges]), st.integers(-999, 999))


def _limited(lim: int):
    return st.one_of(st.integers(-lim, lim), st.sampled_from([-lim, lim, 0]))


@st.composite
def fixed_tables(draw):
    """A FixedPointTable within the image's bounds: 3 in 10 physical calibrations, 2 in 10 exact gains (+-1 or
    +-1/2 on the diagonal, offsets of 0, +-1/2 or +-3/2 nT, no other term: outputs on whole and half nT), half any
    int32 coefficients with every limit (K_S2 +-(2^28 - 1), t0 +-2^15, field 0..2^24, per-axis limits
    0..field, magnitude limits 0..B_NORM_LIMIT_nT, ranges to the input clips)."""
    kind = draw(st.integers(0, 9))
    if kind < 3:
        return random_fixed(np.random.default_rng(draw(st.integers(0, 2 ** 32 - 1))), realistic=True)
    k = draw(st.integers(0, fp.MAX_CURRENTS))
    field = draw(st.one_of(st.integers(0, fp.B_LIMIT_nT), st.sampled_from([0, 2 ** 23, fp.B_LIMIT_nT])))
    axes = draw(st.one_of(st.none(), st.tuples(*[st.one_of(st.integers(0, field), st.sampled_from([0, field]))] * 3)))
    norm = draw(st.one_of(st.none(), st.integers(0, fp.B_NORM_LIMIT_nT),
                          st.sampled_from([0, 2 ** 23, fp.B_NORM_LIMIT_nT])))
    cur_iv = st.tuples(_limited(fp.I_LIMIT_mA), _limited(fp.I_LIMIT_mA)).map(lambda p: tuple(sorted(p)))
    if kind in (3, 4):
        zero3 = ((0, 0, 0),) * 3
        g = draw(st.tuples(*[st.sampled_from([2 ** 27, -(2 ** 27), 2 ** 26, -(2 ** 26)])] * 3))
        fx = fp.FixedPointTable(
            S=((g[0], 0, 0), (0, g[1], 0), (0, 0, g[2])), K_S=zero3, O=draw(st.one_of(st.just((0, 0, 0)), st.tuples(
                *[st.sampled_from([0, 128, -128, 384, -384])] * 3))), K_O=(0, 0, 0), D=((0, 0, 0),) * k,
            t0_cdeg=draw(_limited(fp.T_LIMIT_cdeg)), field_limit_nT=field, temp_range_cdeg=None,
            current_ranges_mA=tuple(draw(cur_iv) for _ in range(k)), field_limits_nT=axes, field_norm_nT=norm)
        return fx, [f"c{j}" for j in range(k)]
    s_row = st.tuples(_coeff((2 ** 27, -(2 ** 27), *TIES["S"])), _coeff(TIES["S"]), _coeff(TIES["S"]))
    k_row = st.tuples(*[_coeff(TIES["K_S"])] * 3)
    interval = st.tuples(_limited(fp.T_LIMIT_cdeg), _limited(fp.T_LIMIT_cdeg)).map(lambda p: tuple(sorted(p)))
    fx = fp.FixedPointTable(
        S=draw(st.tuples(s_row, s_row, s_row)), K_S=draw(st.tuples(k_row, k_row, k_row)),
        O=draw(st.tuples(_coeff(), _coeff(), _coeff())),
        K_O=draw(st.tuples(_coeff(), _coeff(), _coeff())),
        D=tuple(draw(st.tuples(_coeff(), _coeff(), _coeff())) for _ in range(k)),
        t0_cdeg=draw(_limited(fp.T_LIMIT_cdeg)), field_limit_nT=field,
        temp_range_cdeg=draw(st.one_of(st.none(), interval)),
        current_ranges_mA=tuple(draw(cur_iv) for _ in range(k)),
        K_S2=draw(st.tuples(*[st.one_of(_limited(fp.K_S2_INT_LIMIT), st.sampled_from(TIES["K_S2"]))] * 3)),
        field_limits_nT=axes, field_norm_nT=norm)
    return fx, [f"c{j}" for j in range(k)]


_EDGE_B = [fp.INT32_MIN, fp.INT32_MAX, fp.B_LIMIT_nT, fp.B_LIMIT_nT + 1, -fp.B_LIMIT_nT, -fp.B_LIMIT_nT - 1, 0]
_EDGE_T = [fp.INT32_MIN, fp.INT32_MAX, fp.T_LIMIT_cdeg, fp.T_LIMIT_cdeg + 1, -fp.T_LIMIT_cdeg - 1, 0]
_EDGE_I = [fp.INT32_MIN, fp.INT32_MAX, fp.I_LIMIT_mA, fp.I_LIMIT_mA + 1, -fp.I_LIMIT_mA - 1, 0]
_ROW = st.tuples(st.one_of(_I32, st.sampled_from(_EDGE_B)), st.one_of(_I32, st.sampled_from(_EDGE_B)),
                 st.one_of(_I32, st.sampled_from(_EDGE_B)), st.one_of(_I32, st.sampled_from(_EDGE_T)),
                 *[st.one_of(_I32, st.sampled_from(_EDGE_I))] * 4)


@st.composite
def cases(draw, n_random: int = 200):
    """(table, names, b, temp, cur): hypothesis rows (edges), 8 rows of :data:`QUADRUPLES`, then ``n_random`` rows
    from :func:`random_samples` (inside, on and beyond the table's input ranges); in 2 cases of 3 the table's field
    limits are then put on these samples' outputs (:func:`limits_at_outputs`)."""
    fx, names = draw(fixed_tables())
    rows = np.array(draw(st.lists(_ROW, min_size=1, max_size=12)), np.int64)
    rng = np.random.default_rng(draw(st.integers(0, 2 ** 32 - 1)))
    qb, qt, qc = quadruple_rows(rng, 8, fx)
    b, t, c = random_samples(rng, n_random, fx)
    b = np.vstack([rows[:, :3], qb, b]).astype(np.int32)
    t = np.concatenate([rows[:, 3], qt, t]).astype(np.int32)
    c = np.vstack([rows[:, 4:], qc, c]).astype(np.int32)
    if draw(st.integers(0, 2)):
        fx = limits_at_outputs(rng, fx, b, t, c)
    return fx, names, b, t, c


# ---------------------------------------------------------------------- chunks for the block path's kernels
#: ``magstack_cal_apply_block`` works in chunks of this many samples; a chunk whose inputs are all inside the kernel
#: bounds goes through a kernel (firmware_c/magstack_cal.c, CHUNK and the bounds below), any other a sample at a time.
CHUNK = 32
#: The kernel bounds: fields -2^23..2^23-1 nT, temperatures -2^15..2^15-1 centi-degC, currents -2^19..2^19-1 mA.
KERNEL_B, KERNEL_T, KERNEL_I = 2 ** 23, 2 ** 15, 2 ** 19


def _kernel_temps(rng: np.random.Generator, fx: fp.FixedPointTable) -> np.ndarray:
    """One chunk's temperatures inside the kernel bound: one value (in or out of the table's range, or near t0), runs
    of 4, noise of +-2 around one value, a new value every sample (in the table's range and beyond), or anywhere."""
    lo, hi = fx.temp_range_cdeg or (fx.t0_cdeg - 5000, fx.t0_cdeg + 5000)
    lo, hi = max(lo - 200, -KERNEL_T), min(hi + 200, KERNEL_T - 1)
    lo, hi = min(lo, hi), max(lo, hi)
    kind = int(rng.integers(0, 6))
    if kind == 0:
        t = np.full(CHUNK, int(rng.integers(lo, hi, endpoint=True)))
    elif kind == 1:
        t = np.full(CHUNK, fx.t0_cdeg + int(rng.integers(-3, 4)))
    elif kind == 2:
        t = np.repeat(rng.integers(lo, hi, CHUNK // 4, endpoint=True), 4)
    elif kind == 3:
        t = int(rng.integers(lo, hi, endpoint=True)) + rng.integers(-2, 3, CHUNK)
    elif kind == 4:
        t = rng.integers(lo, hi, CHUNK, endpoint=True)
    else:
        t = rng.integers(-KERNEL_T, KERNEL_T, CHUNK)
    return np.clip(t, -KERNEL_T, KERNEL_T - 1)


def kernel_samples(rng: np.random.Generator, n_chunks: int, fx: fp.FixedPointTable):
    """(b (n,3), temp (n,), cur (n,4)) int32: ``n_chunks`` chunks of CHUNK samples and a tail of 0..CHUNK-1, most with
    every input inside the kernel bounds (fields and currents of one scale a chunk, from a few units to the bound;
    temperatures by :func:`_kernel_temps`), some with one input on a bound or one past it, at a random place."""
    n = n_chunks * CHUNK + int(rng.integers(0, CHUNK))
    b = np.empty((n, 3), np.int64)
    t = np.empty(n, np.int64)
    c = np.empty((n, 4), np.int64)
    for start in range(0, n, CHUNK):
        m = min(CHUNK, n - start)
        sb = int(rng.choice([2 ** 4, 2 ** 10, 2 ** 17, 2 ** 20, KERNEL_B]))
        sc = int(rng.choice([2 ** 4, 2 ** 12, KERNEL_I]))
        b[start:start + m] = rng.integers(-sb, sb, (m, 3))
        c[start:start + m] = rng.integers(-sc, sc, (m, 4))
        t[start:start + m] = _kernel_temps(rng, fx)[:m]
        if rng.random() < 0.3:   # one input on a kernel bound or one past it
            r, what = start + int(rng.integers(0, m)), int(rng.integers(0, 3))
            if what == 0:
                b[r, int(rng.integers(0, 3))] = rng.choice([KERNEL_B - 1, KERNEL_B, -KERNEL_B, -KERNEL_B - 1])
            elif what == 1:
                t[r] = rng.choice([KERNEL_T - 1, KERNEL_T, -KERNEL_T, -KERNEL_T - 1])
            else:
                c[r, int(rng.integers(0, 4))] = rng.choice([KERNEL_I - 1, KERNEL_I, -KERNEL_I, -KERNEL_I - 1])
    return b.astype(np.int32), t.astype(np.int32), c.astype(np.int32)


@st.composite
def kernel_cases(draw, n_chunks: int = 8):
    """(table, names, b, temp, cur) for the block path's kernels (:func:`kernel_samples`), tables from
    :func:`fixed_tables` (extreme ones saturate on inputs inside the bounds); in 2 cases of 3 the table's field limits
    are then put on these samples' outputs (:func:`limits_at_outputs`)."""
    fx, names = draw(fixed_tables())
    rng = np.random.default_rng(draw(st.integers(0, 2 ** 32 - 1)))
    b, t, c = kernel_samples(rng, n_chunks, fx)
    if draw(st.integers(0, 2)):
        fx = limits_at_outputs(rng, fx, b, t, c)
    return fx, names, b, t, c


def precomputed_range(rng: np.random.Generator, temp: np.ndarray) -> tuple[int, int]:
    """A temperature range (centi-degC) for ``magstack_cal_precompute``: the samples' whole span (clipped), or a part
    of it (some samples then have no precomputed terms)."""
    lo, hi = int(max(temp.min(), -fp.T_LIMIT_cdeg)), int(min(temp.max(), fp.T_LIMIT_cdeg))
    lo, hi = min(lo, hi), max(lo, hi)
    if rng.random() < 0.5 or hi - lo < 2:
        return lo, hi
    a, z = sorted(int(x) for x in rng.integers(lo, hi, 2, endpoint=True))
    return a, z
