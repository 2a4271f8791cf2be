"""Merge ADCS position and attitude into magnetometer telemetry, making refit input (``magstack merge``).

Flight telemetry (``magstack run``'s session files) carries the sensor, temperature and flags but no
position or attitude; the ADCS logs those on its own clock and rate. For every telemetry row the
ADCS track (all ADCS files, in time order) gives, with ``method``:

* ``interpolate`` (default): position linear in time and attitude by spherical linear
  interpolation (scipy ``Slerp``) between the ADCS samples just before and after the row, if they
  are at most ``tolerance_s`` apart (a row at an ADCS instant takes that sample). Linear position
  between samples dt apart is off the orbit by at most v^2 dt^2 / (8 r): 26 m at dt = 5 s in LEO;
* ``nearest``: the ADCS sample nearest in time, if it is at most ``tolerance_s`` away.

Rows without ADCS within the tolerance are kept, with empty position/attitude cells and the
:data:`~magstack.data.telemetry.NO_ADCS_FLAG` bit set in ``flag`` (refit excludes flagged rows and
counts them); the report lists every run of such rows (a gap). Units: s, km, unit quaternions
(scalar first, GCRS -> body).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from magstack.data.errors import SessionFileError
from magstack.data.session import Session, read_session, refuse_overwriting_inputs, write_session
from magstack.data.telemetry import NO_ADCS_FLAG, POS_COLUMNS, QUAT_COLUMNS, AdcsTrack, read_adcs

METHODS = ("interpolate", "nearest")
#: Default tolerance (s): ADCS samples bracketing a row at most this far apart (interpolate), or the
#: nearest sample at most this far from the row (nearest).
TOLERANCE_S = 5.0


@dataclass(frozen=True)
class Gap:
    """A run of consecutive telemetry rows without ADCS: first and last row times (s) and the row count."""

    t_first_s: float
    t_last_s: float
    rows: int


@dataclass
class MergeReport:
    telemetry: str
    out: str
    rows: int
    merged: int
    gaps: list[Gap] = field(default_factory=list)

    @property
    def flagged(self) -> int:
        return self.rows - self.merged


def combine(tracks: Sequence[AdcsTrack]) -> AdcsTrack:
    """One time-ordered track from several ADCS files; a time present in two files is refused."""
    if len(tracks) == 1:
        return tracks[0]
    t = np.concatenate([a.t_s for a in tracks])
    order = np.argsort(t, kind="stable")
    t = t[order]
    rep = np.flatnonzero(np.diff(t) <= 0)
    if rep.size:
        raise SessionFileError(f"ADCS files {[a.path for a in tracks]} overlap: time {t[rep[0]]!r} s is in two of them")
    return AdcsTrack(";".join(a.path for a in tracks), t, np.vstack([a.pos_ecef_km for a in tracks])[order],
                     np.vstack([a.q_body_eci for a in tracks])[order], sum(a.dropped for a in tracks),
                     tuple(x for a in tracks for x in a.dropped_lines)[:5])


def adcs_at(track: AdcsTrack, t_s: np.ndarray, method: str = "interpolate", tolerance_s: float = TOLERANCE_S
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position (N, 3) km, quaternion (N, 4) scalar first, ok (N,)) of the track at times ``t_s``;
    rows without ADCS within the tolerance are NaN and not ok."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    t = np.asarray(t_s, float)
    n, ta = t.size, track.t_s
    pos = np.full((n, 3), np.nan)
    quat = np.full((n, 4), np.nan)
    if ta.size == 0:
        return pos, quat, np.zeros(n, bool)
    right = np.searchsorted(ta, t, side="right")          # first sample after the row
    before = np.clip(right - 1, 0, ta.size - 1)
    after = np.clip(right, 0, ta.size - 1)
    fin = np.isfinite(t)
    exact = fin & (right > 0) & (ta[before] == t)
    if method == "nearest":
        use = np.where(np.abs(ta[after] - t) < np.abs(t - ta[before]), after, before)
        ok = fin & (np.abs(ta[use] - t) <= tolerance_s)
        pos[ok], quat[ok] = track.pos_ecef_km[use[ok]], track.q_body_eci[use[ok]]
        return pos, quat, ok
    ok = exact | (fin & (right > 0) & (right < ta.size) & (ta[after] - ta[before] <= tolerance_s))
    if ta.size == 1:
        pos[ok], quat[ok] = track.pos_ecef_km[0], track.q_body_eci[0]
        return pos, quat, ok
    for k in range(3):
        pos[ok, k] = np.interp(t[ok], ta, track.pos_ecef_km[:, k])
    rot = Slerp(ta, Rotation.from_quat(track.q_body_eci[:, [1, 2, 3, 0]]))(t[ok])
    quat[ok] = rot.as_quat()[:, [3, 0, 1, 2]]
    return pos, quat, ok


def gaps(t_s: np.ndarray, missing: np.ndarray) -> list[Gap]:
    """Runs of consecutive ``missing`` rows, in row order."""
    m = np.r_[False, np.asarray(missing, bool), False].astype(np.int8)
    starts = np.flatnonzero(np.diff(m) == 1)
    ends = np.flatnonzero(np.diff(m) == -1) - 1
    return [Gap(float(t_s[a]), float(t_s[b]), int(b - a + 1)) for a, b in zip(starts, ends, strict=True)]


def merge_session(s: Session, track: AdcsTrack, method: str = "interpolate",
                  tolerance_s: float = TOLERANCE_S) -> tuple[Session, np.ndarray]:
    """(telemetry session with position/attitude columns, ok (N,)): rows without ADCS keep NaN cells
    and get :data:`NO_ADCS_FLAG` in ``flag``."""
    have = [c for c in (*POS_COLUMNS, *QUAT_COLUMNS) if c in s.extra]
    if have:
        raise SessionFileError(f"{s.source or 'telemetry'}: already has position/attitude columns {have}")
    pos, quat, ok = adcs_at(track, s.t_s, method, tolerance_s)
    extra = dict(s.extra)
    extra.update({c: pos[:, k] for k, c in enumerate(POS_COLUMNS)})
    extra.update({c: quat[:, k] for k, c in enumerate(QUAT_COLUMNS)})
    flag = (s.flag if s.flag is not None else np.zeros(len(s), np.int64)) | np.where(ok, 0, NO_ADCS_FLAG)
    meta = dict(s.metadata)
    legend = meta.get("flag_bits", "")
    meta.update({"adcs_files": track.path, "adcs_method": method, "adcs_tolerance_s": f"{tolerance_s:g}",
                 "adcs_rows_without": str(int((~ok).sum())), "adcs_samples_skipped": str(track.dropped),
                 "flag_bits": (legend + " " if legend else "") + f"{NO_ADCS_FLAG}=no_adcs"})
    return Session(s.t_s, s.ref_uT, s.dut_uT, s.temp_c, s.session, dict(s.currents_A), meta, flag,
                   list(s.warnings), extra, s.source), ok


def output_paths(telemetry: Sequence[str | os.PathLike], out: str | os.PathLike) -> list[Path]:
    """One output per input: ``out`` itself for a single input, else ``out/<input file name>`` (``out`` a directory)."""
    out = Path(out)
    if out.is_dir():
        paths = [out / Path(p).name for p in telemetry]
        if len({p.name for p in paths}) != len(paths):
            raise SessionFileError(f"telemetry files share a file name; cannot write them all into {out}")
        return paths
    if len(telemetry) != 1:
        raise SessionFileError(f"{out}: several telemetry files need an existing output directory")
    return [out]


def merge_files(telemetry: Sequence[str | os.PathLike], adcs: Sequence[str | os.PathLike], out: str | os.PathLike,
                method: str = "interpolate", tolerance_s: float = TOLERANCE_S) -> tuple[list[MergeReport], AdcsTrack]:
    """Merge every telemetry file with the ADCS track of all ``adcs`` files; write one output per input."""
    outs = output_paths(telemetry, out)
    for o in outs:
        refuse_overwriting_inputs(o, [*telemetry, *adcs])
    track = combine([read_adcs(a) for a in adcs])
    sessions = [read_session(p) for p in telemetry]
    merged = [merge_session(s, track, method, tolerance_s) for s in sessions]
    if not any(ok.any() for _, ok in merged):
        span = lambda t: f"{t.min():.3f}..{t.max():.3f} s" if t.size else "no rows"  # noqa: E731
        t_all = np.concatenate([s.t_s for s in sessions])
        raise SessionFileError(f"no telemetry row has ADCS within {tolerance_s:g} s ({method}): telemetry spans "
                               f"{span(t_all)}, ADCS {span(track.t_s)}")
    reports = []
    for p, o, (m, ok) in zip(telemetry, outs, merged, strict=True):
        write_session(o, m)
        reports.append(MergeReport(str(p), str(o), len(m), int(ok.sum()), gaps(m.t_s, ~ok)))
    return reports, track
