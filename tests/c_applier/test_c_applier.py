"""The C applier (firmware_c/) equals the Python fixed-point applier bit for bit, and its loader refuses
what the Python loader refuses.

Built once per session with the system gcc (``-std=c99 -Wall -Wextra -Werror -pedantic -O2``): a shared
library driven through ctypes (hypothesis tables and samples), a harness under
``-fsanitize=undefined,address`` and, where the Debian cross tools are installed, a 32-bit ARM harness
run by ``qemu-arm``. The full count (>= 1e6 samples over >= 200 tables, host and ARM) is
``python benchmarks/bench_c_applier.py --part equality`` (docs/c-applier.md).
"""
from __future__ import annotations

import ctypes
import re
import struct
import subprocess
import zlib
from pathlib import Path

import c_applier_build as cb
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magstack.firmware import cal_image
from magstack.firmware import fixed_point as fp
from magstack.firmware.cal_table import CalTable
from magstack.firmware.float_applier import ApplyFlag

R = cal_image.ImageResult
#: The C loader's code for a bad argument (no Python counterpart).
E_ARGUMENT = int(re.search(r"MAGSTACK_CAL_E_ARGUMENT = (\d+)", cb.C_DIR.joinpath("magstack_cal.h").read_text())[1])


# ---------------------------------------------------------------------- builds (once per session)
@pytest.fixture(scope="session")
def build_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("c_applier")


@pytest.fixture(scope="session")
def clib(build_dir) -> cb.CApplier:
    if cb.tool("gcc") is None:
        pytest.skip("no gcc: the C applier cannot be built here")
    return cb.CApplier(cb.build_shared(build_dir))


@pytest.fixture(scope="session")
def sanitized(build_dir, clib) -> list[str]:
    return [str(cb.build_harness(build_dir, "harness_san", extra=cb.SANITIZE, opt="-O1"))]


@pytest.fixture(scope="session")
def arm(build_dir, clib) -> list[str]:
    for name, pkg in ((cb.ARM_CC, "gcc-arm-linux-gnueabihf"), (cb.QEMU_ARM, "qemu-user")):
        if cb.tool(name) is None:
            pytest.skip(f"{name} not installed (Debian package {pkg}): the 32-bit ARM check is skipped")
    return [cb.QEMU_ARM, str(cb.build_harness(build_dir, "harness_arm", cc=cb.ARM_CC, extra=("-static",)))]


def _same(fx, names, b, t, c, outputs, statuses) -> None:
    q, s = cb.python_reference(fx, b, t, c, per_sample=False)
    bad = np.nonzero((np.asarray(outputs) != q).any(axis=1) | (np.asarray(statuses) != s))[0]
    assert bad.size == 0, (f"C != Python at row {bad[0]}: b {b[bad[0]]}, T {t[bad[0]]}, I {c[bad[0]]}: "
                           f"C {outputs[bad[0]]} {statuses[bad[0]]}, Python {q[bad[0]]} {s[bad[0]]}")


# ---------------------------------------------------------------------- equality, host
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(case=cb.cases())
def test_equal_to_the_python_applier_bit_for_bit(clib, case):
    """apply_sample (every row) = apply_block = C magstack_cal_apply (every row) = C magstack_cal_apply_block."""
    fx, names, b, t, c = case
    rc, table = clib.load(cb.image_of(fx, names))
    assert rc == 0 and table.as_fixed() == fx
    q, s = cb.python_reference(fx, b, t, c, per_sample=True)
    for r in range(b.shape[0]):
        assert clib.apply(table, b[r], int(t[r]), c[r]) == (tuple(int(x) for x in q[r]), s[r]), r
    _same(fx, names, b, t, c, *clib.apply_block(table, b, t, c))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(case=cb.kernel_cases(), seed=st.integers(0, 2 ** 32 - 1))
def test_kernels_and_precomputed_terms_are_the_python_applier_bit_for_bit(clib, case, seed):
    """Blocks of whole chunks inside the kernel bounds (one temperature, runs of 4, noise, a new one every sample; some
    chunks with one input on a bound or one past it; a tail): magstack_cal_apply_block, without and with terms
    precomputed for all or part of the temperatures, and magstack_cal_apply with them, equal the Python applier."""
    fx, names, b, t, c = case
    rng = np.random.default_rng(seed)
    rc, table = clib.load(cb.image_of(fx, names))
    assert rc == 0
    _same(fx, names, b, t, c, *clib.apply_block(table, b, t, c))
    lo, hi = cb.precomputed_range(rng, t)
    rc, storage = clib.precompute(table, lo, hi)
    assert rc == 0 and (table.pre_lo_cdeg, table.pre_count) == (lo, hi - lo + 1)
    _same(fx, names, b, t, c, *clib.apply_block(table, b, t, c))
    q, s_ = cb.python_reference(fx, b, t, c, per_sample=False)
    for r in rng.integers(0, b.shape[0], 20):
        assert clib.apply(table, b[r], int(t[r]), c[r]) == (tuple(int(x) for x in q[r]), s_[r]), r
    del storage


def test_precompute_refuses_bad_arguments_and_load_forgets_it(clib):
    """E_ARGUMENT (and no precomputed terms) for a NULL table, NULL storage with a count, lo > hi, a temperature beyond
    the clip or too small a count; NULL storage with count 0 takes them away; loading an image forgets them. At the
    clip's ends they are accepted and give the same bits."""
    raw = cal_image.image_from_table(_table())
    fx = fp.FixedPointTable.from_table(_table())
    rc, table = clib.load(raw)
    L = clib.lib
    for lo, hi, count in ((5, 4, 10), (-(2 ** 15) - 1, 0, 2 ** 15 + 2), (0, 2 ** 15 + 1, 2 ** 15 + 2), (0, 99, 99)):
        rc, _storage = clib.precompute(table, lo, hi, count=count)
        assert rc == E_ARGUMENT
        assert table.pre_count == 0 and not table.pre
    assert L.magstack_cal_precompute(None, None, 0, 0, 0) == E_ARGUMENT
    assert L.magstack_cal_precompute(ctypes.byref(table), None, 5, 0, 4) == E_ARGUMENT
    rc, storage = clib.precompute(table, 2 ** 15 - 100, 2 ** 15)
    assert rc == 0 and table.pre_count == 101
    b = np.array([[12345, -23456, 34567]] * 3)
    t, c = np.array([2 ** 15, 2 ** 15 + 7, -(2 ** 15) - 7]), np.array([[1500, -250]] * 3)
    _same(fx, ["heater", "torquer"], b, t, c, *clib.apply_block(table, b, t, c))
    assert L.magstack_cal_precompute(ctypes.byref(table), None, 0, 0, 0) == 0 and table.pre_count == 0
    rc, storage = clib.precompute(table, -(2 ** 15), -(2 ** 15) + 10)
    assert rc == 0 and table.pre_count == 11
    _same(fx, ["heater", "torquer"], b, t, c, *clib.apply_block(table, b, t, c))
    assert clib.lib.magstack_cal_load(ctypes.byref(table), raw, len(raw)) == 0 and table.pre_count == 0
    del storage


@pytest.mark.parametrize("gain", [2 ** 31 - 1, -(2 ** 31), 2 ** 30 + 1])
def test_outputs_next_to_int32_with_inputs_inside_the_kernel_bounds(clib, gain):
    """A gain of about +-16 and fields of -2^19..2^19-1 nT (each chunk's largest magnitudes tight on the kernels'
    no-saturation bound, |acc| <= 2^50 - 2^19): with -2^31 the output of -2^19 nT is 2^31 and saturates, which the
    bound must see; with 2^31 - 1 it is on the bound and does not; then one nT more either way, and other terms
    precomputed. The outputs and status bits are the Python applier's."""
    zero3 = ((0, 0, 0),) * 3
    fx = fp.FixedPointTable(S=((gain, 0, 0), (0, gain, 0), (0, 0, gain)), K_S=zero3, O=(0, 0, 0), K_O=(0, 0, 0), D=(),
                            t0_cdeg=0, field_limit_nT=fp.B_LIMIT_nT, temp_range_cdeg=None, current_ranges_mA=())
    rc, table = clib.load(cb.image_of(fx, []))
    assert rc == 0
    rng = np.random.default_rng(abs(gain) % 1000)
    for lo, hi in ((-(2 ** 19), 2 ** 19 - 1), (-(2 ** 19) - 1, 2 ** 19), (-(2 ** 19) + 1, 2 ** 19 - 2)):
        b = rng.integers(lo, hi, (4 * cb.CHUNK, 3), endpoint=True)
        b[::5], b[2::5] = lo, hi
        t = np.zeros(len(b), np.int64)
        t[cb.CHUNK:2 * cb.CHUNK] = rng.integers(-5, 6, cb.CHUNK)   # a chunk of varying temperatures
        c = np.zeros((len(b), 0))
        out, st_ = clib.apply_block(table, b, t, c)
        _same(fx, [], b, t, c, out, st_)
        rc, storage = clib.precompute(table, -5, 5)
        assert rc == 0
        _same(fx, [], b, t, c, *clib.apply_block(table, b, t, c))
        assert clib.lib.magstack_cal_precompute(ctypes.byref(table), None, 0, 0, 0) == 0
        del storage


def test_extremes_every_flag_and_the_limits(clib):
    """Saturation at both output limits, each status combination, the K_S2 and t0 limits, inputs at and past
    every clip, int32 extremes."""
    big, lim = fp.INT32_MAX, fp.K_S2_INT_LIMIT
    tables = [
        fp.FixedPointTable(S=((big, big, big),) * 3, K_S=((big, -big, big),) * 3, O=(big, -big, 0), K_O=(big,) * 3,
                           D=((big, big, -big),) * 4, t0_cdeg=-fp.T_LIMIT_cdeg, field_limit_nT=fp.B_LIMIT_nT,
                           temp_range_cdeg=(-fp.T_LIMIT_cdeg, fp.T_LIMIT_cdeg),
                           current_ranges_mA=((-fp.I_LIMIT_mA, fp.I_LIMIT_mA),) * 4, K_S2=(lim, -lim, lim)),
        fp.FixedPointTable(S=((fp.INT32_MIN,) * 3,) * 3, K_S=((fp.INT32_MIN,) * 3,) * 3, O=(fp.INT32_MIN,) * 3,
                           K_O=(fp.INT32_MIN,) * 3, D=(), t0_cdeg=fp.T_LIMIT_cdeg, field_limit_nT=0,
                           temp_range_cdeg=None, current_ranges_mA=(), K_S2=(-lim, -lim, -lim)),
        fp.FixedPointTable(S=((2 ** 27, 0, 0), (0, 2 ** 27, 0), (0, 0, 2 ** 27)), K_S=((0,) * 3,) * 3, O=(0, 0, 0),
                           K_O=(0, 0, 0), D=((2 ** 20, 0, 0),), t0_cdeg=2500, field_limit_nT=100_000,
                           temp_range_cdeg=(-4000, 8500), current_ranges_mA=((-1000, 1000),), K_S2=(0, 0, 0)),
    ]
    seen = set()
    for fx in tables:
        names = [f"c{j}" for j in range(len(fx.D))]
        rc, table = clib.load(cb.image_of(fx, names))
        assert rc == 0
        vals_b = [fp.INT32_MIN, -fp.B_LIMIT_nT - 1, -fp.B_LIMIT_nT, -100_001, -1, 0, 1, 100_000, fp.B_LIMIT_nT,
                  fp.INT32_MAX]
        vals_t = [fp.INT32_MIN, -fp.T_LIMIT_cdeg - 1, -fp.T_LIMIT_cdeg, -4001, -4000, 2500, 8500, 8501,
                  fp.T_LIMIT_cdeg, fp.INT32_MAX]
        vals_i = [fp.INT32_MIN, -fp.I_LIMIT_mA - 1, -1001, 0, 1000, 1001, fp.I_LIMIT_mA, fp.INT32_MAX]
        rng = np.random.default_rng(len(seen))
        n = 3000
        b = np.array(vals_b)[rng.integers(0, len(vals_b), (n, 3))]
        t = np.array(vals_t)[rng.integers(0, len(vals_t), n)]
        c = np.array(vals_i)[rng.integers(0, len(vals_i), (n, 4))]
        out, st_ = clib.apply_block(table, b, t, c)
        _same(fx, names, b, t, c, out, st_)
        seen |= set(st_.tolist())
        assert {fp.INT32_MAX, fp.INT32_MIN} <= set(out.ravel().tolist()) or fx is not tables[0]
    assert seen == {0, int(ApplyFlag.OUT_OF_VALIDITY), int(ApplyFlag.SATURATED),
                    int(ApplyFlag.OUT_OF_VALIDITY | ApplyFlag.SATURATED)}


def test_roundings_on_a_half_go_away_from_zero(clib):
    """Every rounding of the sample path on an exact half: the output (S = 2^18: B / 2), rdiv(K_S dTc, 12800)
    (K_S = 6400: dTc / 2), the two K_S2 divisions (K_S2 = 50 and 409600 * 100 at dTc = +-1)."""
    zero3 = ((0, 0, 0),) * 3
    half = fp.FixedPointTable(S=((2 ** 18, 0, 0), (0, 2 ** 18, 0), (0, 0, 2 ** 18)), K_S=zero3, O=(0, 0, 0),
                              K_O=(0, 0, 0), D=(), t0_cdeg=0, field_limit_nT=100, temp_range_cdeg=None,
                              current_ranges_mA=())
    rc, table = clib.load(cb.image_of(half, []))
    b = np.array([[1, -1, 3], [-3, 5, -5], [0, 7, -7]])
    out, _ = clib.apply_block(table, b, np.zeros(3), np.zeros((3, 0)))
    assert rc == 0 and out.tolist() == [[1, -1, 2], [-2, 3, -3], [0, 4, -4]]
    for ks, k2 in ((6400, 0), (-6400, 0), (0, 50), (0, -50), (0, 409600 * 100), (0, -409600 * 100)):
        fx = fp.FixedPointTable(S=((2 ** 27, 0, 0), (0, 2 ** 27, 0), (0, 0, 2 ** 27)), K_S=((ks, 0, 0),) * 3,
                                O=(0, 0, 0), K_O=(0, 0, 0), D=(), t0_cdeg=0, field_limit_nT=100,
                                temp_range_cdeg=None, current_ranges_mA=(), K_S2=(k2, k2, k2))
        rc, table = clib.load(cb.image_of(fx, []))
        b = np.array([[2 ** 19, 1, -(2 ** 19)]] * 6)
        t = np.array([1, -1, 2, -2, 3, -3])
        _same(fx, [], b, t, np.zeros((6, 0)), *clib.apply_block(table, b, t, np.zeros((6, 0))))


def _diag(g, O=(0, 0, 0), axes=None, norm=None, field=None) -> fp.FixedPointTable:
    """A gain-only table (diagonal S, offsets O in nT * 2^8) with the given field limits (nT)."""
    zero3 = ((0, 0, 0),) * 3
    field = max(axes) if field is None and axes is not None else field
    return fp.FixedPointTable(S=((g[0], 0, 0), (0, g[1], 0), (0, 0, g[2])), K_S=zero3, O=O, K_O=(0, 0, 0), D=(),
                              t0_cdeg=0, field_limit_nT=field, temp_range_cdeg=None, current_ranges_mA=(),
                              field_limits_nT=axes, field_norm_nT=norm)


ONE, HALF = 2 ** 27, 2 ** 26
OOV, SAT = int(ApplyFlag.OUT_OF_VALIDITY), int(ApplyFlag.SATURATED)
#: (table, input rows, expected status of each row): the validity region is on the calibrated output, in whole nT
#: rounded half away from zero, per axis and in magnitude; written out by hand (not from the Python applier).
VALIDITY_CASES = [
    # gain 2: an input inside the limit whose output is beyond it; gain 1/2: the other way round
    (_diag((2 * ONE, ONE, ONE), axes=(100, 100, 100)), [(50, 0, 0), (51, 0, 0), (-51, 100, -100), (0, 101, 0)],
     [0, OOV, OOV, OOV]),
    (_diag((HALF, HALF, HALF), axes=(100, 100, 100)), [(150, 0, 0), (200, -200, 200), (199, 0, 0), (201, 0, 0),
                                                       (-201, 0, 0), (0, -202, 0), (0, 0, -203)],
     [0, 0, 0, OOV, OOV, OOV, OOV]),                    # 201 -> 100.5 nT -> 101: the half rounds away from zero
    # an offset of +0.5 nT: 100 + 0.5 -> 101 on x; -100 + 0.5 = -99.5 -> -100 on y
    (_diag((ONE, ONE, ONE), O=(128, 128, -128), axes=(100, 100, 100)), [(100, 0, 0), (99, -100, 0), (0, -101, 0),
                                                                         (0, 0, 100), (0, 0, -100)],
     [OOV, 0, OOV, 0, OOV]),
    # per-axis limits of their own
    (_diag((ONE, ONE, ONE), axes=(10, 20, 0)), [(10, -20, 0), (11, 0, 0), (0, 21, 0), (0, 0, 1), (-10, 20, 0)],
     [0, OOV, OOV, OOV, 0]),
    # magnitude: 1 + 4 + 4 = 9 = 3^2 on the limit; 1 + 4 + 9 = 14 beyond it
    (_diag((ONE, ONE, ONE), axes=(100, 100, 100), norm=3), [(1, 2, 2), (-2, 1, -2), (1, 2, 3), (0, 0, 3), (0, 0, 4),
                                                             (3, 0, 0)],
     [0, 0, OOV, 0, OOV, 0]),
    (_diag((ONE, ONE, ONE), axes=(10 ** 6,) * 3, norm=11 * 2 ** 16), [(2 * 2 ** 16, 6 * 2 ** 16, 9 * 2 ** 16),
                                                                       (2 * 2 ** 16, 6 * 2 ** 16, 9 * 2 ** 16 + 1)],
     [0, OOV]),
    # magnitude on whole nT: 1.5 nT -> 2 (gain 1/2 of 3): 2, 2, 2 is beyond 3^2, 2, 2, -1 on it
    (_diag((HALF, HALF, HALF), axes=(100, 100, 100), norm=3), [(3, 3, 3), (2, 2, 2), (3, 3, -2)], [OOV, 0, 0]),
    # saturated outputs: INT32_MAX and INT32_MIN are 2^23 nT in whole nT
    (_diag((fp.INT32_MAX, fp.INT32_MIN, ONE), axes=(2 ** 23, 2 ** 23, 2 ** 23)), [(2 ** 24, 2 ** 24, 0)], [SAT]),
    (_diag((fp.INT32_MAX, fp.INT32_MIN, ONE), axes=(2 ** 23, 2 ** 23 - 1, 2 ** 23)), [(2 ** 24, 2 ** 24, 0)],
     [SAT | OOV]),
    (_diag((fp.INT32_MAX, fp.INT32_MIN, fp.INT32_MIN), axes=(2 ** 23,) * 3, norm=14_529_495, field=2 ** 24),
     [(2 ** 24, 2 ** 24, -(2 ** 24)), (fp.INT32_MAX, fp.INT32_MIN, fp.INT32_MIN)], [SAT | OOV, SAT | OOV]),
    (_diag((fp.INT32_MAX, fp.INT32_MIN, fp.INT32_MIN), axes=(2 ** 23,) * 3, norm=14_529_496, field=2 ** 24),
     [(2 ** 24, 2 ** 24, -(2 ** 24)), (fp.INT32_MAX, fp.INT32_MIN, fp.INT32_MIN)], [SAT, SAT]),
    (_diag((fp.INT32_MAX, fp.INT32_MIN, ONE), axes=(2 ** 23,) * 3, norm=fp.B_NORM_LIMIT_nT, field=2 ** 24),
     [(fp.INT32_MAX, fp.INT32_MAX, 0), (fp.INT32_MIN, fp.INT32_MIN, 5)], [SAT, SAT]),
]


@pytest.mark.parametrize("case", range(len(VALIDITY_CASES)))
def test_validity_is_on_the_calibrated_output(clib, case):
    """Per-axis and magnitude limits on the output (inputs only clip): the status bits written out by hand, from
    both C entry points and both Python ones. 14_529_495^2 < 3 * 2^46 <= 14_529_496^2 (the saturated magnitude)."""
    fx, rows, want = VALIDITY_CASES[case]
    rc, table = clib.load(cb.image_of(fx, []))
    assert rc == 0 and table.as_fixed() == fx
    b = np.array(rows, np.int64)
    n = b.shape[0]
    t, c = np.zeros(n, np.int64), np.zeros((n, 0), np.int64)
    _, s = cb.python_reference(fx, b, t, c, per_sample=True)
    assert s.tolist() == want
    out, st_ = clib.apply_block(table, b, t, c)
    assert st_.tolist() == want
    assert [clib.apply(table, b[r], 0, ())[1] for r in range(n)] == want
    _same(fx, [], b, t, c, out, st_)


def test_a_version_1_image_is_refused_by_both_loaders(clib):
    """A version-1 image (320 bytes, its field limit on the measured field) gets E_VERSION and a reason."""
    old = bytearray(320)
    old[:8] = b"MCAL" + struct.pack("<HH", 1, 320)
    struct.pack_into("<I", old, 316, zlib.crc32(bytes(old[:316])))
    assert clib.load(bytes(old))[0] == R.E_VERSION == cal_image.check_image(bytes(old))
    with pytest.raises(cal_image.ImageInvalid, match="format version 1 .* export the table again"):
        cal_image.decode_image(bytes(old), "old.mcal")


@pytest.mark.parametrize("flags", [("-O2", "-DMAGSTACK_CAL_COMPACT"), ("-Os", "-DMAGSTACK_CAL_TERMS_CACHE=1u"),
                                   ("-O3", "-march=native"), ("-O3", "-march=native", "-DMAGSTACK_CAL_VECTOR"),
                                   ("-O2", "-DMAGSTACK_CAL_VECTOR", "-DMAGSTACK_CAL_TERMS_CACHE=2u")])
def test_other_builds_are_the_same(build_dir, clib, flags):
    """The compact block path, a one-entry terms cache, the vectorised kernels of -O3 -march=native, and the mixed
    kernels of MAGSTACK_CAL_VECTOR; temperatures in long runs, in short runs and on every sample; whole chunks inside
    the kernel bounds; without and with precomputed terms."""
    r = subprocess.run(["gcc", *flags, "-x", "c", "-c", "-o", "/dev/null", "-"], input="int x;\n", capture_output=True,
                       text=True, timeout=60)
    if r.returncode != 0:
        pytest.skip(f"gcc does not take {' '.join(flags)} here")
    sub = build_dir / "".join(f.strip("-=") for f in flags)
    sub.mkdir(exist_ok=True)
    lib = cb.CApplier(cb.compile_c("gcc", [*flags, "-fPIC", "-shared", str(cb.SOURCE)], sub / "lib.so"))
    for seed in range(40):
        rng = np.random.default_rng(seed)
        fx, names = cb.random_fixed(rng)
        b, t, c = cb.random_samples(rng, 600, fx)
        t[:300] = np.repeat(t[:300:50], 50)       # long runs of one temperature (the vector kernel)
        t[300:400] = np.repeat(t[300:400:4], 4)   # short runs (the mixed kernel)
        kb, kt, kc = cb.kernel_samples(rng, 6, fx)   # whole chunks inside the kernel bounds
        b, t, c = np.vstack([b, kb]), np.concatenate([t, kt]), np.vstack([c, kc])
        fx = cb.limits_at_outputs(rng, fx, b, t, c)
        rc, table = lib.load(cb.image_of(fx, names))
        assert rc == 0
        _same(fx, names, b, t, c, *lib.apply_block(table, b, t, c))
        q, st_ = cb.python_reference(fx, b[:1], t[:1], c[:1], per_sample=False)
        assert lib.apply(table, b[0], int(t[0]), c[0]) == (tuple(q[0].tolist()), int(st_[0]))
        rc, storage = lib.precompute(table, *cb.precomputed_range(rng, t))
        assert rc == 0
        _same(fx, names, b, t, c, *lib.apply_block(table, b, t, c))
        del storage


# ---------------------------------------------------------------------- sanitizers and ARM
def _batch_check(cmd, batch) -> None:
    """The harness on ``batch``, without and with precomputed terms (``check pre``: the records' lowest temperature
    and up to 4096 centi-degC above it)."""
    records = [cb.Record(cb.image_of(fx, names), b, t, c) for fx, names, b, t, c in batch]
    for mode in (("check",), ("check", "pre")):
        for (fx, names, b, t, c), (rc, out, status, differ) in zip(batch, cb.run_harness(cmd, records, mode=mode),
                                                                   strict=True):
            assert rc == 0 and differ == 0
            _same(fx, names, b, t, c, out, status)


_BATCH = st.tuples(st.lists(cb.cases(n_random=300), min_size=8, max_size=8),
                   st.lists(cb.kernel_cases(n_chunks=6), min_size=6, max_size=6)).map(lambda p: p[0] + p[1])


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(batch=_BATCH)
def test_equal_under_undefined_behaviour_and_address_sanitizers(sanitized, batch):
    """-fsanitize=undefined,address -fno-sanitize-recover=all: any report ends the harness with an error."""
    _batch_check(sanitized, batch)


def test_the_sanitizers_do_report_here(build_dir, clib):
    """The sanitizer build is not silent by construction: a signed overflow aborts it."""
    src = build_dir / "overflow.c"
    src.write_text("#include <limits.h>\nint main(int argc, char **argv)\n{\n    int x = INT_MAX;\n    (void)argv;\n"
                   "    x += argc;\n    return x == 0;\n}\n")
    exe = cb.compile_c("gcc", ["-O0", *cb.SANITIZE, str(src)], build_dir / "overflow")
    r = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "runtime error" in r.stderr


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(batch=_BATCH)
def test_equal_on_32_bit_arm(arm, batch):
    """arm-linux-gnueabihf-gcc -O2 -static, run by qemu-arm: the same bits on a 32-bit target."""
    _batch_check(arm, batch)


def test_cortex_m4_build_has_no_floating_point(build_dir, clib):
    if cb.tool(cb.M4_CC) is None:
        pytest.skip(f"{cb.M4_CC} not installed (Debian package gcc-arm-none-eabi): no Cortex-M4 build")
    obj = cb.compile_c(cb.M4_CC, ["-Os", "-mcpu=cortex-m4", "-mthumb", "-mgeneral-regs-only", "-c", str(cb.SOURCE)],
                       build_dir / "m4.o")
    assert obj.stat().st_size > 0


# ---------------------------------------------------------------------- what the source may contain
def _code(path: Path) -> str:
    """C source without comments and string/char literals."""
    text = re.sub(r"/\*.*?\*/", " ", path.read_text(), flags=re.S)
    text = re.sub(r"//[^\n]*", " ", text)
    return re.sub(r'"(?:\\.|[^"\\])*"|\'(?:\\.|[^\'\\])*\'', '""', text)


def _last_argument(code: str, start: int) -> str:
    """The last top-level argument of the call whose '(' ends at ``start``."""
    depth, last = 1, start
    for i in range(start, len(code)):
        ch = code[i]
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
            if depth == 0:
                return code[last:i].strip()
        elif ch == "," and depth == 1:
            last = i + 1
    raise AssertionError("unbalanced call")


def test_no_floating_point_no_heap_and_divisions_by_constants_only(build_dir, clib):
    for path in (cb.SOURCE, cb.C_DIR / "magstack_cal.h"):
        code = _code(path)
        for word in ("float", "double", "math.h", "malloc", "calloc", "realloc", "free", "alloca", "setjmp"):
            assert not re.search(rf"\b{re.escape(word)}\b", code), (path.name, word)
    code = _code(cb.SOURCE)
    # every '/' or '%' is in rdiv's body, dividing by its divisor d (or d by 2), and every rdiv call divides by a
    # positive literal
    body = re.search(r"static int64_t rdiv\(int64_t a, uint64_t d\)\s*\{(.*?)\n\}", code, re.S)
    assert body and "%" not in body.group(1)
    assert sorted(re.findall(r"/\s*(\w+)", body.group(1))) == ["2u", "d", "d"]
    rest = code.replace(body.group(0), "")
    assert not re.findall(r"[/%]", rest)
    divisors = [_last_argument(code, m.end()) for m in re.finditer(r"\brdiv\(", code)
                if not code.startswith("int64_t a", m.end())]
    assert len(divisors) == 4 and all(re.fullmatch(r"[1-9][0-9]*u", d) for d in divisors), divisors
    # the compiler agrees: no floating-point register may be used (x86-64 and AArch64 gcc take this flag)
    r = subprocess.run(["gcc", "-mgeneral-regs-only", "-x", "c", "-c", "-o", "/dev/null", "-"], input="int x;\n",
                       capture_output=True, text=True, timeout=60)
    if r.returncode != 0:
        pytest.skip("this gcc has no -mgeneral-regs-only")
    cb.compile_c("gcc", ["-O2", "-mgeneral-regs-only", "-c", str(cb.SOURCE)], build_dir / "general_regs.o")


def test_header_constants_and_offsets_are_the_python_ones(clib):
    h = cb.C_DIR.joinpath("magstack_cal.h").read_text()
    defines = {m[0]: int(m[1]) for m in re.findall(r"#define (MAGSTACK_CAL_\w+) (?:0x)?([0-9A-Fa-f]+)[uL]*\b", h)
               if not m[0].startswith("MAGSTACK_CAL_TERM") and not m[0].startswith("MAGSTACK_CAL_OPT")}
    hexes = {m[0]: int(m[1], 16) for m in re.findall(r"#define (MAGSTACK_CAL_(?:TERM|OPT)_\w+) 0x([0-9A-Fa-f]+)u", h)}
    assert defines["MAGSTACK_CAL_IMAGE_VERSION"] == cal_image.VERSION
    assert defines["MAGSTACK_CAL_IMAGE_SIZE"] == cal_image.SIZE
    assert defines["MAGSTACK_CAL_MAX_CURRENTS"] == fp.MAX_CURRENTS
    assert defines["MAGSTACK_CAL_DEVICE_ID_BYTES"] == cal_image.DEVICE_ID_BYTES
    assert defines["MAGSTACK_CAL_CURRENT_NAME_BYTES"] == cal_image.CURRENT_NAME_BYTES
    assert defines["MAGSTACK_CAL_OUT_OF_VALIDITY"] == ApplyFlag.OUT_OF_VALIDITY
    assert defines["MAGSTACK_CAL_SATURATED"] == ApplyFlag.SATURATED
    assert defines["MAGSTACK_CAL_B_LIMIT_NT"] == fp.B_LIMIT_nT
    assert defines["MAGSTACK_CAL_T_LIMIT_CDEG"] == fp.T_LIMIT_cdeg
    assert defines["MAGSTACK_CAL_I_LIMIT_MA"] == fp.I_LIMIT_mA
    assert defines["MAGSTACK_CAL_K_S2_LIMIT"] == fp.K_S2_INT_LIMIT
    assert defines["MAGSTACK_CAL_B_NORM_LIMIT_NT"] == fp.B_NORM_LIMIT_nT
    assert {k.removeprefix("MAGSTACK_CAL_TERM_").lower(): v for k, v in hexes.items() if "_TERM_" in k} == \
        cal_image.TERM_BITS
    assert (hexes["MAGSTACK_CAL_OPT_TEMP_RANGE"], hexes["MAGSTACK_CAL_OPT_FIELD_AXES"],
            hexes["MAGSTACK_CAL_OPT_FIELD_NORM"]) == (cal_image.OPT_TEMP_RANGE, cal_image.OPT_FIELD_AXES,
                                                      cal_image.OPT_FIELD_NORM)
    enum = dict(re.findall(r"MAGSTACK_CAL_(OK|E_\w+) = (\d+)", h))
    assert {k: int(v) for k, v in enum.items() if k != "E_ARGUMENT"} == {r.name: int(r) for r in R}
    offsets = dict(re.findall(r"#define OFF_(\w+) (\d+)u", cb.SOURCE.read_text()))
    names = {"MAGIC": "magic", "VERSION": "version", "SIZE": "size", "SOURCE_CRC": "source_crc32", "TERMS": "terms",
             "N_CURRENTS": "n_currents", "OPTIONS": "options", "RESERVED": "reserved", "DEVICE_ID": "device_id",
             "T0": "t0_cdeg", "FIELD_LIMIT": "field_limit_nT", "FIELD_AXES": "field_axes_nT",
             "FIELD_NORM": "field_norm_nT", "TEMP_LO": "temp_lo_cdeg", "TEMP_HI": "temp_hi_cdeg",
             "S": "S", "K_S": "K_S", "K_S2": "K_S2", "O": "O", "K_O": "K_O", "D": "D",
             "CURRENT_RANGES": "current_ranges_mA", "CURRENT_NAMES": "current_names", "CRC": "crc32"}
    assert {names[k]: int(v) for k, v in offsets.items()} == {f.name: f.offset for f in cal_image.FIELDS}


# ---------------------------------------------------------------------- the loader
def _table() -> CalTable:
    return CalTable(device_id="hmc1053:sn7", terms=("gain_matrix", "temperature_gain", "temperature_gain2", "offset",
                                                    "temperature_offset", "currents"),
                    S=[[1.1, 0.05, -0.02], [0.01, 1.12, 0.03], [0.0, 0.07, 1.11]], K_S=np.full((3, 3), 1e-3),
                    K_S2=[1e-5, -2e-5, 3e-6], O=[-0.34, -0.09, 0.46], K_O=[0.01, -0.02, 0.16],
                    D=(("heater", [1.0, 2.0, -3.0]), ("torquer", [0.5, 0, 0])), validity_temp_c=(-40.0, 85.0),
                    validity_field_uT=100.0, validity_field_axes_uT=(100.0, 80.0, 90.5), validity_field_norm_uT=120.0,
                    validity_currents_A=(("heater", (0.0, 2.0)), ("torquer", (-1.0, 1.0))), crc32=0x12345678)


def test_every_single_bit_flip_of_an_image_is_refused(clib):
    raw = cal_image.image_from_table(_table())
    assert clib.load(raw)[0] == 0
    for bit in range(8 * len(raw)):
        bad = bytearray(raw)
        bad[bit // 8] ^= 1 << (bit % 8)
        code, _ = clib.load(bytes(bad))
        assert code != 0 and code == cal_image.check_image(bytes(bad)), bit


def _with(raw: bytes, **fields) -> bytes:
    """``raw`` with fields replaced (struct values) and the CRC made right again."""
    b = bytearray(raw)
    for name, value in fields.items():
        f = next(f for f in cal_image.FIELDS if f.name == name)
        values = value if isinstance(value, (list, tuple)) else [value]
        struct.pack_into("<" + f.fmt, b, f.offset, *values)
    struct.pack_into("<I", b, cal_image.SIZE - 4, zlib.crc32(bytes(b[:-4])) & 0xFFFFFFFF)
    return bytes(b)


def _loader_cases():
    base = cal_image.image_from_table(_table())
    names = b"heater".ljust(16, b"\0") + b"torquer".ljust(16, b"\0")
    zero_d = [0] * 12
    return base, [
        (base[:-1], R.E_SIZE), (base + b"\0", R.E_SIZE), (base[:3], R.E_SIZE), (b"MCAL\x01\x00", R.E_SIZE),
        (b"{" + base[1:], R.E_MAGIC), (_with(base, version=3), R.E_VERSION), (_with(base, version=1), R.E_VERSION),
        (_with(base, size=337), R.E_SIZE), (base[:-4] + b"\0\0\0\0", R.E_CRC), (_with(base, reserved=1), R.E_RESERVED),
        (_with(base, options=8 | 7), R.E_RESERVED), (_with(base, options=0x80 | 7), R.E_RESERVED),
        (_with(base, terms=0x7F), R.E_TERMS), (_with(base, terms=0x3E), R.E_TERMS),
        (_with(base, terms=0x3D), R.E_TERMS),                    # K_S without temperature_gain
        (_with(base, terms=0x3B), R.E_TERMS),                    # K_S2 without temperature_gain2
        (_with(base, terms=0x17), R.E_CURRENTS),                 # currents without their term
        (_with(base, device_id=b""), R.E_DEVICE_ID), (_with(base, device_id=b"ab\0c"), R.E_DEVICE_ID),
        (_with(base, device_id=b"caf\xe9"), R.E_DEVICE_ID), (_with(base, device_id=b"a\tb"), R.E_DEVICE_ID),
        (_with(base, n_currents=5), R.E_CURRENTS), (_with(base, n_currents=1), R.E_CURRENTS),
        (_with(base, current_names=b"heater".ljust(16, b"\0") * 2), R.E_CURRENTS),
        (_with(base, current_names=b"\0" * 16 + names[16:]), R.E_CURRENTS),
        (_with(base, t0_cdeg=2 ** 15 + 1), R.E_T0), (_with(base, t0_cdeg=-(2 ** 15) - 1), R.E_T0),
        (_with(base, t0_cdeg=fp.INT32_MIN), R.E_T0),
        (_with(base, K_S2=[0, 2 ** 28, 0]), R.E_K_S2), (_with(base, K_S2=[0, 0, -(2 ** 28)]), R.E_K_S2),
        (_with(base, field_limit_nT=-1), R.E_VALIDITY), (_with(base, field_limit_nT=2 ** 24 + 1), R.E_VALIDITY),
        (_with(base, temp_lo_cdeg=100, temp_hi_cdeg=99), R.E_VALIDITY),
        (_with(base, temp_hi_cdeg=2 ** 15 + 1), R.E_VALIDITY),
        (_with(base, options=0 | 6), R.E_VALIDITY),              # a range without its bit
        (_with(base, field_axes_nT=[100_000, 100_001, 0]), R.E_VALIDITY),   # beyond the field limit
        (_with(base, field_axes_nT=[-1, 0, 0]), R.E_VALIDITY),
        (_with(base, options=5), R.E_VALIDITY),                  # per-axis limits without their bit
        (_with(base, options=3), R.E_VALIDITY),                  # a magnitude limit without its bit
        (_with(base, field_norm_nT=-1), R.E_VALIDITY),
        (_with(base, field_norm_nT=fp.B_NORM_LIMIT_nT + 1), R.E_VALIDITY),
        (_with(base, field_limit_nT=89_999), R.E_VALIDITY),      # below an axis limit
        (_with(base, current_ranges_mA=[1, 0, 0, 0, 0, 0, 0, 0]), R.E_VALIDITY),
        (_with(base, current_ranges_mA=[0, 2 ** 20 + 1, -1, 1, 0, 0, 0, 0]), R.E_VALIDITY),
        (_with(base, current_ranges_mA=[0, 1, -1, 1, 0, 7, 0, 0]), R.E_CURRENTS),
        (_with(base, D=[*zero_d[:6], 0, 0, 1, 0, 0, 0]), R.E_CURRENTS),
        # accepted at the limits
        (_with(base, t0_cdeg=2 ** 15), R.OK), (_with(base, t0_cdeg=-(2 ** 15)), R.OK),
        (_with(base, K_S2=[2 ** 28 - 1, -(2 ** 28 - 1), 0]), R.OK), (_with(base, field_limit_nT=2 ** 24), R.OK),
        (_with(base, field_axes_nT=[0, 100_000, 100_000]), R.OK), (_with(base, field_norm_nT=0), R.OK),
        (_with(base, field_norm_nT=fp.B_NORM_LIMIT_nT), R.OK),
        (_with(base, options=5, field_axes_nT=[100_000] * 3), R.OK),   # one limit for every axis
        (_with(base, options=1, field_axes_nT=[100_000] * 3, field_norm_nT=0), R.OK),   # and no magnitude limit
        (_with(base, temp_lo_cdeg=-(2 ** 15), temp_hi_cdeg=2 ** 15), R.OK), (base, R.OK),
    ]


def test_loader_bounds_are_the_python_loaders(clib):
    _, table = _loader_cases()
    for k, (raw, want) in enumerate(table):
        assert cal_image.check_image(raw) == want, (k, cal_image.check_image(raw))
        code, t = clib.load(raw)
        assert code == want, (k, code, clib.lib.magstack_cal_result_name(code))
        if code == 0:
            img = cal_image.decode_image(raw)
            assert t.as_fixed() == img.fixed and t.device_id.decode() == img.device_id
            assert [t.current_names[j].value.decode() for j in range(t.n_currents)] == list(img.current_names)
            assert (t.source_crc32, t.image_crc32) == (img.source_crc32, img.image_crc32)
        else:
            assert t.t0_cdeg == 0 and t.n_currents == 0 and t.S[0][0] == 0   # nothing half-loaded


@settings(max_examples=300, deadline=None)
@given(edits=st.lists(st.tuples(st.integers(0, cal_image.SIZE - 5), st.integers(0, 255)), min_size=1, max_size=4),
       seed=st.integers(0, 2 ** 32 - 1))
def test_any_re_signed_image_gets_the_same_verdict_from_both_loaders(clib, edits, seed):
    """Bytes changed and the CRC made right again (a writer's mistake, not corruption): C and Python agree on
    the result code, and on every decoded field when they accept."""
    fx, names = cb.random_fixed(np.random.default_rng(seed))
    b = bytearray(cb.image_of(fx, names))
    for pos, value in edits:
        b[pos] = value
    struct.pack_into("<I", b, cal_image.SIZE - 4, zlib.crc32(bytes(b[:-4])) & 0xFFFFFFFF)
    raw = bytes(b)
    code, t = clib.load(raw)
    assert code == cal_image.check_image(raw)
    if code == 0:
        img = cal_image.decode_image(raw)
        assert t.as_fixed() == img.fixed and t.device_id.decode() == img.device_id and t.terms == sum(
            cal_image.TERM_BITS[x] for x in img.terms)


def test_crc_is_zlibs(clib):
    rng = np.random.default_rng(1)
    for n in (0, 1, 7, 316, 4096):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert clib.lib.magstack_cal_crc32(data, n) == zlib.crc32(data)


# ---------------------------------------------------------------------- the exported folder builds
def test_exported_folder_with_its_const_array_builds_and_applies(tmp_path, clib):
    """``table export --c DIR --c-array`` writes a folder that compiles as it is (no file system: the image
    from the generated header) and calibrates a sample as the Python applier does."""
    from magstack.cli.main import main
    from magstack.firmware.cal_table import save_table

    src = save_table(_table(), tmp_path / "cal.json")
    out = tmp_path / "c"
    assert main(["table", "export", str(src), "--c", str(out), "--c-array", "-q"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["magstack_cal.c", "magstack_cal.h", "magstack_cal_image.h",
                                                     "table.mcal"]
    main_c = tmp_path / "main.c"
    main_c.write_text(
        '#include <stdio.h>\n#include "magstack_cal.h"\n#include "magstack_cal_image.h"\n'
        "int main(void)\n{\n    magstack_cal_table t;\n    const int32_t b[3] = {12345, -23456, 34567};\n"
        "    const int32_t cur[2] = {1500, -250};\n    int32_t out[3];\n    unsigned st;\n"
        "    int rc = magstack_cal_load(&t, magstack_cal_image, sizeof magstack_cal_image);\n"
        "    if (rc != MAGSTACK_CAL_OK) {\n        return 10 + rc;\n    }\n"
        "    st = magstack_cal_apply(&t, b, 3712, cur, out);\n"
        '    printf("%ld %ld %ld %u\\n", (long)out[0], (long)out[1], (long)out[2], st);\n    return 0;\n}\n')
    exe = tmp_path / "demo"
    cmd = ["gcc", *cb.STRICT, "-O2", "-I", str(out), "-o", str(exe), str(main_c), str(out / "magstack_cal.c")]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and not r.stderr, r.stderr
    got = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60)
    assert got.returncode == 0, got.returncode
    fx = fp.FixedPointTable.from_table(_table())
    q, s = fx.apply_sample((12345, -23456, 34567), 3712, (1500, -250))
    assert got.stdout.split() == [str(x) for x in (*q, s)]
    from magstack.firmware.cal_table import load_table
    assert (out / "table.mcal").read_bytes() == cal_image.image_from_table(load_table(src))
