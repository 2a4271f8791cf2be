"""Import the AV-MagEval bench files (MIT-STARLab/AV-MagEval-Data) as a magstack Session.

``dataN.csv`` (DUT logger: HMC1053 ``x_test..z_test`` in uT, temperatures in kelvin) and
``refN.csv`` (FVM400 fluxgate: ``time, bx, by, bz`` in uT, clock ~4 h behind) are paired:

1. the reference axes are mapped onto the DUT axes (authors' map by default:
   ``dut_x = ref_y, dut_y = ref_x, dut_z = -ref_z``);
2. the clock offset (added to reference time) is estimated from the data with
   :func:`magstack.ground.alignment.estimate_clock_offset` (with the chosen temperature: its Eq. 3
   temperature terms are used when the temperature span is material; ``clock_offset_model``
   records the model); when the data do not determine it (static
   field) the authors' ``4 h - 0.5 s`` prior is used and the fact is recorded (or, with
   ``on_undetermined="raise"``, AlignmentError is raised);
3. one stream is linearly interpolated onto the other's timestamps (or both onto a uniform
   grid, the authors' method), never extrapolated; targets outside the source's span or inside
   a source gap longer than ``max_gap_s`` are marked NaN with ``flag`` bits or dropped, and
   counted;
4. temperature: the chosen kelvin column (``temp_pi`` by default, as the authors' calibration)
   minus 273.15.

Everything done is written into ``Session.metadata``. ``t_s`` is the DUT logger's epoch (UTC).
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from magstack.data.dictionary import FLAG
from magstack.data.errors import SessionFileError
from magstack.data.pairing import sort_unique
from magstack.data.session import Session, data_row_line, parse_table, read_file_bytes
from magstack.drivers.errors import ConfigurationError
from magstack.ground.alignment import estimate_clock_offset, interp_no_extrapolation
from magstack.ground.errors import AlignmentError

#: DUT logger header (dataN.csv).
DATA_COLUMNS = ("time", "x_test", "y_test", "z_test", "x_U7", "y_U7", "z_U7", "x_U9", "y_U9", "z_U9",
                "temp_mag", "temp_pi")
#: Authors' axis map: DUT axis i = sign[i] * reference component perm[i] (0=bx, 1=by, 2=bz).
AUTHORS_AXIS_MAP: tuple[tuple[int, int], ...] = ((1, 1), (0, 1), (2, -1))
#: Authors' hand-picked clock correction, seconds added to the reference clock.
AUTHORS_OFFSET_S = 4 * 3600 - 0.5
KELVIN_OFFSET = 273.15
#: flag bits in the returned Session (the one flag definition, :data:`magstack.data.dictionary.FLAG_BITS`)
FLAG_NO_REF = FLAG["NO_REF"].value
FLAG_NO_DUT = FLAG["NO_DUT"].value


#: Physical range of each kind of column; a value outside it is refused with its line.
#: Field: above every sensor's range on this bench (HMC1053 +-600 uT, FVM400 +-100 uT). Time: Unix
#: epoch seconds 1970..2100. Temperature: kelvin, -123..177 degC (beyond any electronics on the bench).
FIELD_LIMIT_UT = 1000.0
EPOCH_RANGE_S = (0.0, 4.1e9)
KELVIN_RANGE = (150.0, 450.0)
REF_COLUMNS = ("time", "bx", "by", "bz")


def _limits(column: str) -> tuple[float, float, str]:
    if column == "time":
        return (*EPOCH_RANGE_S, "s")
    if column.startswith("temp_"):
        return (*KELVIN_RANGE, "K")
    return (-FIELD_LIMIT_UT, FIELD_LIMIT_UT, "uT")


def _bad_cells(arr: np.ndarray, columns: Sequence[str]) -> np.ndarray:
    """(n, ncols) mask of cells that are not finite or outside their column's physical range."""
    lo = np.array([_limits(c)[0] for c in columns])
    hi = np.array([_limits(c)[1] for c in columns])
    with np.errstate(invalid="ignore"):
        return ~(np.isfinite(arr) & (arr >= lo) & (arr <= hi))


def _cell_error(path: Path, lineno: int, column: str, value: float) -> SessionFileError:
    if not math.isfinite(value):
        return SessionFileError(f"{path}: line {lineno}: column {column!r}: non-finite value (empty or nan)")
    lo, hi, unit = _limits(column)
    return SessionFileError(f"{path}: line {lineno}: column {column!r}: {value:g} {unit} is outside the physical "
                            f"range [{lo:g}, {hi:g}] {unit}")


def _parse_rows(path: Path, columns: Sequence[str], has_header: bool, bad_lines: str) -> tuple[np.ndarray, int]:
    """Rows of an AV-MagEval file: plain decimal cells within each column's physical range.

    Vectorised (:func:`magstack.data.session.parse_table`); with ``bad_lines="skip"`` a file with bad
    lines is read line by line and each bad line is skipped and counted.
    """
    raw = read_file_bytes(path, "file")
    first = 1
    if has_header:
        end = raw.find(b"\n")
        head = raw if end < 0 else raw[:end]
        if not head.strip():
            raise SessionFileError(f"{path}: empty file (expected header {','.join(columns)})")
        try:
            got = [c.strip() for c in head.decode("utf-8").split(",")]
        except UnicodeDecodeError as exc:
            raise SessionFileError(f"{path}: not a text file ({exc})") from None
        if got[:len(columns)] != list(columns):
            raise SessionFileError(f"{path}: header {got} is not the AV-MagEval data header {list(columns)}")
        raw, first = (b"" if end < 0 else raw[end + 1:]), 2
    if raw and not raw.endswith(b"\n"):
        raw += b"\n"
    skipped = 0
    try:
        arr = parse_table(raw, first, columns, str(path))
        bad = _bad_cells(arr, columns)
        if bad.any():
            k, j = (int(x[0]) for x in np.nonzero(bad))
            raise _cell_error(path, data_row_line(raw, first, k), columns[j], float(arr[k, j]))
    except SessionFileError:
        if bad_lines != "skip":
            raise
        rows = []
        for k, line in enumerate(raw.decode("utf-8", "replace").split("\n")[:-1], start=first):
            if not line.strip():
                continue
            try:
                row = parse_table((line + "\n").encode("utf-8", "replace"), k, columns, str(path))
                if row.shape[0] != 1 or _bad_cells(row, columns).any():
                    raise SessionFileError("bad line")
            except SessionFileError:
                skipped += 1
                continue
            rows.append(row[0])
        arr = np.array(rows, dtype=float).reshape(len(rows), len(columns))
    if arr.shape[0] < 2:
        raise SessionFileError(f"{path}: only {arr.shape[0]} usable rows")
    return arr, skipped


def read_mageval_data(data_csv: str | os.PathLike, *, bad_lines: str = "raise") -> tuple[dict[str, np.ndarray], int]:
    """Columns of a ``dataN.csv`` file by name, plus the number of skipped bad lines."""
    arr, skipped = _parse_rows(Path(data_csv), DATA_COLUMNS, True, bad_lines)
    return {c: arr[:, i] for i, c in enumerate(DATA_COLUMNS)}, skipped


def read_mageval_ref(ref_csv: str | os.PathLike, *, bad_lines: str = "raise") -> tuple[np.ndarray, np.ndarray, int]:
    """``(t_s (N,), b_uT (N,3) in raw reference axes, skipped)`` from a ``refN.csv`` file."""
    arr, skipped = _parse_rows(Path(ref_csv), REF_COLUMNS, False, bad_lines)
    return arr[:, 0], arr[:, 1:4], skipped


def apply_axis_map(ref_uT: np.ndarray, axis_map: Sequence[tuple[int, int]]) -> np.ndarray:
    """Reference vectors in DUT axes: ``out[:, i] = sign_i * ref[:, perm_i]``."""
    amap = [(int(p), int(s)) for p, s in axis_map]
    if len(amap) != 3 or sorted(p for p, _ in amap) != [0, 1, 2] or any(s not in (1, -1) for _, s in amap):
        raise ConfigurationError(f"axis_map must be a signed permutation ((perm, +-1) x3), got {axis_map!r}")
    return np.column_stack([s * ref_uT[:, p] for p, s in amap])


def import_mageval(data_csv: str | os.PathLike, ref_csv: str | os.PathLike, *,
                   axis_map: Sequence[tuple[int, int]] = AUTHORS_AXIS_MAP,
                   temp_column: str = "temp_pi",
                   clock_offset_s: float | None = None,
                   offset_prior_s: float = AUTHORS_OFFSET_S,
                   offset_search_halfwidth_s: float | None = None,
                   on_undetermined: str = "prior",
                   onto: str | float = "dut",
                   max_gap_s: float = 1.0,
                   gaps: str = "nan",
                   bad_lines: str = "raise",
                   session_id: int = 0,
                   metadata: Mapping[str, str] | None = None,
                   progress: Callable[[str, float], None] | None = None) -> Session:
    """Pair an AV-MagEval ``dataN.csv`` with its ``refN.csv`` into an aligned :class:`Session`.

    Parameters
    ----------
    axis_map: signed permutation, DUT axis i = sign * reference column perm (0=bx,1=by,2=bz).
    temp_column: ``"temp_pi"`` (authors' choice) or ``"temp_mag"``; kelvin -> degC.
    clock_offset_s: seconds added to the reference clock; ``None`` = estimate from the data.
    offset_prior_s: used as fallback when the data do not determine the offset (and reported).
    offset_search_halfwidth_s: search ``prior +- this``; ``None`` = every offset with >= 50 % overlap.
    on_undetermined: ``"prior"`` (fall back, recorded in metadata) or ``"raise"`` (AlignmentError).
    onto: ``"dut"`` (reference interpolated onto DUT times), ``"ref"`` (DUT and temperature onto
        reference times, shifted to the DUT clock) or a grid step in s (both onto a uniform grid
        over the overlap, the authors' method with 0.25).
    max_gap_s: a target inside a source gap longer than this is a gap (NaN), never bridged.
    gaps: ``"nan"`` keeps gap rows with NaN and ``flag`` bits (``FLAG_NO_REF``, ``FLAG_NO_DUT``);
        ``"drop"`` removes them. Either way the count is in the metadata.
    bad_lines: ``"raise"`` (SessionFileError naming the line) or ``"skip"`` (counted in metadata).
    progress: ``progress(stage, fraction)`` callback of the clock-offset search (see alignment).
    """
    if temp_column not in ("temp_pi", "temp_mag"):
        raise ConfigurationError(f"temp_column must be 'temp_pi' or 'temp_mag', got {temp_column!r}")
    if on_undetermined not in ("prior", "raise"):
        raise ConfigurationError(f"on_undetermined must be 'prior' or 'raise', got {on_undetermined!r}")
    if gaps not in ("nan", "drop"):
        raise ConfigurationError(f"gaps must be 'nan' or 'drop', got {gaps!r}")
    if bad_lines not in ("raise", "skip"):
        raise ConfigurationError(f"bad_lines must be 'raise' or 'skip', got {bad_lines!r}")
    if not (isinstance(onto, str) and onto in ("dut", "ref")):
        try:
            step = float(onto)
        except (TypeError, ValueError):
            raise ConfigurationError(f"onto must be 'dut', 'ref' or a grid step in s, got {onto!r}") from None
        if not (math.isfinite(step) and step > 0):
            raise ConfigurationError(f"grid step must be > 0 s, got {onto!r}")
    if not (max_gap_s > 0):
        raise ConfigurationError(f"max_gap_s must be > 0, got {max_gap_s}")
    if clock_offset_s is not None and not math.isfinite(clock_offset_s):
        raise ConfigurationError(f"clock_offset_s must be finite, got {clock_offset_s}")

    cols, skipped_dut = read_mageval_data(data_csv, bad_lines=bad_lines)
    t_ref_raw, ref_raw, skipped_ref = read_mageval_ref(ref_csv, bad_lines=bad_lines)
    dut_raw = np.column_stack([cols["x_test"], cols["y_test"], cols["z_test"]])
    temp_c_raw = cols[temp_column] - KELVIN_OFFSET
    t_dut, (dut, temp_c), dup_dut = sort_unique(cols["time"], dut_raw, temp_c_raw)
    t_ref, (ref_native,), dup_ref = sort_unique(t_ref_raw, ref_raw)
    ref = apply_axis_map(ref_native, axis_map)

    meta: dict[str, str] = {
        "source": "MIT-STARLab/AV-MagEval-Data release 1.0 (Belsten et al. 2023)",
        "dut_file": Path(data_csv).name, "ref_file": Path(ref_csv).name,
        "dut_chip": "hmc1053", "reference": "fvm400",
        "axis_map": "; ".join(f"dut_{'xyz'[i]} = {'-' if s < 0 else '+'}ref_col{p + 2}"
                              for i, (p, s) in enumerate(axis_map)),
        "temp_source": f"{temp_column} (K) - {KELVIN_OFFSET}",
    }
    if clock_offset_s is not None:
        offset = float(clock_offset_s)
        meta["clock_offset_method"] = "given"
        meta["clock_offset_sigma_s"] = "nan"
    else:
        try:
            est = estimate_clock_offset(t_dut, dut, t_ref, ref, prior_s=offset_prior_s,
                                        search_halfwidth_s=offset_search_halfwidth_s, max_gap_s=max_gap_s,
                                        temp_c=temp_c, progress=progress)
            offset = est.offset_s
            meta["clock_offset_method"] = "estimated (min residual of ref ~ A dut + b)"
            meta["clock_offset_model"] = est.model
            meta["clock_offset_sigma_s"] = f"{est.sigma_s:.4f}"
            meta["clock_offset_r2"] = f"{est.r2:.6f}"
        except AlignmentError as exc:
            if on_undetermined == "raise":
                raise
            offset = float(offset_prior_s)
            meta["clock_offset_method"] = f"prior ({exc})"
            meta["clock_offset_sigma_s"] = "nan"
    meta["clock_offset_s"] = f"{offset:.6f}"
    meta["clock_offset_vs_authors_s"] = f"{offset - AUTHORS_OFFSET_S:+.4f}"
    t_ref_dut = t_ref + offset  # reference timestamps on the DUT clock

    flag: np.ndarray
    if isinstance(onto, str) and onto == "dut":
        t_out = t_dut
        ref_out, ok_ref = interp_no_extrapolation(t_ref_dut, ref, t_out, max_gap_s)
        dut_out, ok_dut = dut, np.ones(t_out.size, bool)
        temp_out = temp_c
        meta["resampling"] = f"reference linearly interpolated onto DUT timestamps (max gap {max_gap_s} s)"
    else:
        if isinstance(onto, str):  # "ref"
            t_out = t_ref_dut
            meta["resampling"] = f"DUT linearly interpolated onto reference timestamps (max gap {max_gap_s} s)"
        else:
            lo, hi = max(t_dut[0], t_ref_dut[0]), min(t_dut[-1], t_ref_dut[-1])
            if hi <= lo:
                raise AlignmentError("DUT and reference do not overlap at the chosen clock offset")
            n_grid = (hi - lo) / float(onto) + 1
            limit = 10 * (t_dut.size + t_ref.size)
            if n_grid > limit:
                raise ConfigurationError(f"grid step {float(onto):g} s gives {n_grid:.3g} rows over {hi - lo:.1f} s, "
                                         f"more than 10x the {t_dut.size + t_ref.size} input samples")
            t_out = lo + np.arange(0, (hi - lo) + 1e-9, float(onto))
            meta["resampling"] = (f"both linearly interpolated onto a uniform {float(onto)} s grid over the "
                                  f"overlap (max gap {max_gap_s} s)")
        ref_out, ok_ref = interp_no_extrapolation(t_ref_dut, ref, t_out, max_gap_s)
        dt_both, ok_dut = interp_no_extrapolation(t_dut, np.column_stack([dut, temp_c]), t_out, max_gap_s)
        dut_out, temp_out = dt_both[:, :3], dt_both[:, 3]
    flag = np.where(ok_ref, 0, FLAG_NO_REF) | np.where(ok_dut, 0, FLAG_NO_DUT)
    n_gap = int(np.count_nonzero(flag))
    meta["gap_rows"] = str(n_gap)
    meta["gap_policy"] = gaps
    meta["skipped_bad_lines"] = f"dut={skipped_dut} ref={skipped_ref}"
    meta["duplicate_timestamps_removed"] = f"dut={dup_dut} ref={dup_ref}"
    meta.update({str(k): str(v) for k, v in (metadata or {}).items()})
    sess = Session(t_out, ref_out, dut_out, temp_out, np.full(t_out.size, int(session_id)), {}, meta,
                   flag.astype(np.int64))
    if gaps == "drop":
        sess = sess.select(flag == 0)
    if len(sess) == 0 or n_gap == flag.size:
        raise AlignmentError("no paired rows: DUT and reference do not overlap at the chosen clock offset")
    return sess
