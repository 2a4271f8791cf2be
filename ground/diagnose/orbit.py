"""Orbit telemetry as a diagnosis session: the refit's reference and its error budget.

On orbit there is no reference magnetometer: the reference is the IGRF field at the GPS position rotated
into the body frame by the attitude, exactly as ``refit`` computes it
(:func:`magstack.firmware.calibration.refit.reference_block`), with housekeeping currents interpolated onto
the magnetometer rows by the same rule (:func:`magstack.firmware.calibration.housekeeping.interpolate_currents`).
That reference has errors of its own that no sensor effect explains; they are stated as a budget and join the
noise floor (:func:`reference_budget`):

* crustal field: IGRF stops at degree 13; the lithospheric field above it is a few nT at 500 km, up to ~20 nT
  over the strongest anomalies ([I] per-axis sd ``CRUSTAL_NT``);
* external fields: magnetospheric and ionospheric currents, ~10-20 nT per axis at low and middle latitudes on
  quiet days, 50-100s of nT in the auroral zones ([I] ``EXTERNAL_NT`` below ``AURORAL_LAT_DEG``,
  ``AURORAL_NT`` above);
* attitude knowledge: a rotation error of sd ``attitude_sd_deg`` per axis moves component i by
  ``sd_rad * sqrt(|B|^2 - B_i^2)`` (``delta B = delta theta x B``); 0.1 deg at 40 uT is 70 nT
  (``--attitude-sd-deg``; a star tracker is ~0.01 deg, sun sensor + magnetometer ~1 deg).

Position error (GPS, ~10 m) moves the field by < 1 nT and is left out. The budget is the RMS over rows of
the per-row norm; the diagnosis reports it beside the measured white floor and judges "after" and the
unexplained remainder against their root sum square.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from magstack.data.errors import SessionFileError
from magstack.data.session import Session
from magstack.data.telemetry import TelemetryBlock, iter_telemetry, read_header
from magstack.ground.errors import DiagnosisError

#: [I] per-axis sd of the lithospheric field IGRF leaves out at LEO altitude, nT.
CRUSTAL_NT = 5.0
#: [I] per-axis sd of external fields on quiet days at low and middle latitudes, nT.
EXTERNAL_NT = 15.0
#: [I] per-axis sd of external fields in the auroral zones (field-aligned currents), nT.
AURORAL_NT = 80.0
#: Geodetic latitude (abs, deg) from which the auroral value applies.
AURORAL_LAT_DEG = 55.0
#: Default attitude knowledge, deg (1 sd per axis).
ATTITUDE_SD_DEG = 0.1
#: Session.extra column with the geodetic latitude of each row, deg.
LAT_COLUMN = "geodetic_lat_deg"


def is_orbit_telemetry(path) -> bool:
    """True when ``path`` carries position and attitude columns (a telemetry file, docs/refit.md)."""
    try:
        read_header(path)
    except SessionFileError:    # not telemetry (missing columns) or unreadable: the session reader reports it
        return False
    return True


def orbit_session(paths: Sequence[str], dut1_s: float = 0.0, reference: str = "igrf") -> Session:
    """One Session of telemetry files in order (see :func:`session_from_blocks`)."""
    from magstack.firmware.calibration.housekeeping import MAX_GAP_S, interpolate_currents

    files = []
    names: tuple[str, ...] | None = None
    meta: dict = {}
    for path in paths:
        hdr = read_header(path)
        if names is None:
            names, meta = hdr.currents, dict(hdr.metadata)
        elif hdr.currents != names:
            raise DiagnosisError(f"{path}: current columns {list(hdr.currents)} differ from the first file's "
                                 f"{list(names)}")
        if reference == "session" and not hdr.has_ref:
            raise DiagnosisError(f"{path}: --reference session needs ref_x_uT, ref_y_uT, ref_z_uT columns")
        files.append(interpolate_currents(iter_telemetry(path), names, MAX_GAP_S))
    return session_from_blocks(files, names or (), meta, dut1_s, reference)


def session_from_blocks(files: Iterable[Iterable[TelemetryBlock]], names: Sequence[str], meta: dict,
                        dut1_s: float = 0.0, reference: str = "igrf") -> Session:
    """One Session of telemetry blocks (per file, currents already interpolated) and its reference field.

    ``reference``: "igrf" = IGRF + attitude (NaN on rows without a plausible position or attitude), the
    geodetic latitude (deg) in the extra column :data:`LAT_COLUMN`; "session" = the blocks' own ``ref_uT``
    (e.g. a simulator's truth; latitude NaN); "auto" = the blocks' own values when every block has the
    columns and some cell holds a value (merged flight telemetry has the columns, every cell empty), else
    IGRF. ``meta["reference"]`` is "igrf" when IGRF was used. Session ids are kept per file and offset
    between files."""
    from magstack.firmware.calibration.refit import reference_block

    blocks = []
    offset = 0
    for per_file in files:
        top = offset
        for blk in per_file:
            sess = blk.session.astype(np.int64) + offset
            top = max(top, int(sess.max()) + 1 if sess.size else top)
            blocks.append((blk, sess))
        offset = top
    if not blocks:
        raise DiagnosisError("the telemetry holds no rows")
    own = reference == "session" or (reference == "auto" and all(b.ref_uT is not None for b, _ in blocks)
                                     and any(np.isfinite(b.ref_uT).any() for b, _ in blocks))
    parts = []
    for blk, sess in blocks:
        if own:
            b_ref, lat = blk.ref_uT, np.full(len(blk), np.nan)
        else:
            b_ref, lat, _ecl = reference_block(blk, dut1_s)
        parts.append((blk.t_s, b_ref, blk.dut_uT, blk.temp_c, sess, blk.currents_A, blk.flag, lat))
    cat = np.concatenate
    flag = None if any(p[6] is None for p in parts) else cat([p[6] for p in parts])
    meta = dict(meta)
    if not own:
        meta["reference"] = "igrf"
    meta["reference_model"] = ("the files' ref columns" if own
                               else "IGRF at the GPS position, rotated by the attitude (the refit's reference)")
    return Session(cat([p[0] for p in parts]), cat([p[1] for p in parts]), cat([p[2] for p in parts]),
                   cat([p[3] for p in parts]), cat([p[4] for p in parts]),
                   {k: cat([p[5][k] for p in parts]) for k in names}, meta, flag,
                   extra={LAT_COLUMN: cat([p[7] for p in parts])})


def without_missing_currents(s: Session) -> tuple[Session, list[str]]:
    """``s`` without rows whose housekeeping current could not be interpolated (refit's rule: such a row
    cannot be used by a model with that current; the interference candidate needs every current), and the
    note that says how many."""
    if not s.currents_A:
        return s, []
    gone = ~np.all(np.isfinite(np.column_stack(list(s.currents_A.values()))), axis=1)
    if not gone.any():
        return s, []
    return s.select(~gone), [f"{int(gone.sum())} rows whose housekeeping currents cannot be interpolated (no "
                             "sample within 60 s in the same session, refit's rule) left out"]


def session_budget(s: Session, attitude_sd_deg: float = ATTITUDE_SD_DEG) -> dict | None:
    """:func:`reference_budget` of a session made by :func:`orbit_session` with the IGRF reference (None else)."""
    if s.metadata.get("reference") != "igrf" or LAT_COLUMN not in s.extra:
        return None
    return reference_budget(s.ref_uT, s.extra[LAT_COLUMN], attitude_sd_deg)


def reference_budget(b_ref_uT: np.ndarray, lat_deg: np.ndarray, attitude_sd_deg: float = ATTITUDE_SD_DEG) -> dict:
    """The reference's error budget (module docs) on these rows: per-axis RMS (nT) of each part and the total
    (RMS over rows of the per-row vector norm, nT)."""
    b = np.asarray(b_ref_uT, dtype=float) * 1e3
    lat = np.abs(np.asarray(lat_deg, dtype=float))
    n = max(b.shape[0], 1)
    sd = np.deg2rad(float(attitude_sd_deg))
    b2 = np.sum(b ** 2, axis=1, keepdims=True)
    att_var = sd ** 2 * np.maximum(b2 - b ** 2, 0.0)                      # (N,3)
    ext = np.where(lat >= AURORAL_LAT_DEG, AURORAL_NT, EXTERNAL_NT)[:, None] * np.ones((1, 3))
    var = att_var + CRUSTAL_NT ** 2 + ext ** 2

    def axes(v: np.ndarray) -> list[float]:
        return [float(x) for x in np.sqrt(np.sum(v, axis=0) / n)]
    return {"total_nT": float(np.sqrt(np.sum(var) / n)), "axes_nT": axes(var),
            "attitude_axes_nT": axes(att_var), "attitude_sd_deg": float(attitude_sd_deg),
            "crustal_nT_per_axis": CRUSTAL_NT, "external_nT_per_axis": EXTERNAL_NT,
            "auroral_nT_per_axis": AURORAL_NT, "auroral_rows": int(np.sum(lat >= AURORAL_LAT_DEG)),
            "sources": "[I] crustal: lithospheric field beyond IGRF degree 13 at LEO; external: quiet-day "
                       "magnetospheric/ionospheric fields, auroral zone above |lat| 55 deg; attitude: the given "
                       "knowledge sd"}
