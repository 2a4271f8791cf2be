"""A clipped reference is not truth: rows where the bench reference sits at its own full scale are left out.

A fluxgate reference has a measuring range (its datasheet full scale: the FVM400 class +-100 uT,
``magstack.drivers.fvm400.NOMINAL_RANGE_NT``; real files hold readings up to 107.24 uT, so the real clip
sits a little beyond the nominal range). Where the field exceeds it the reference reads a flat plateau at
an extreme while the DUT goes on reading the real, larger field; paired as truth, those rows look like a
gross nonlinearity (kept, a +-107.1 uT plateau against a 119 uT DUT reading leaves "UNEXPLAINED 869 nT, 5.9x
the floor" on a real high-field run).

Per axis and sign (:func:`reference_guard`):

1. Rows whose reference component reaches ``(1 - margin)`` of the range are candidates (the calibration
   fit's rule, ``firmware.calibration.reference.saturated_rows``).
2. Their extreme ``L`` (the largest value of that sign). ``L`` beyond ``(1 + PINNED_LEVEL)`` x the range:
   the reference reads far past its nominal full scale, so the range in the table is not this instrument's
   (a simulator's ideal reference, coils held at 150 uT): nothing is left out, a note says so.
3. A **plateau**: at least PLATEAU_MIN_ROWS rows within PLATEAU_TOL of ``L`` (a clipped loop outputs one
   value; interpolated between two clipped samples the paired rows keep it).
4. The DUT confirms the clip: the DUT reading mapped into reference units (:func:`dut_implied_reference`, an
   affine fit on rows well inside the range) lies beyond ``L`` on the plateau rows by more than
   EXCESS_FRACTION of the range and 5 robust sd of the mapping's scatter. A reference that plateaus where
   the DUT agrees with it (coils held at 105 uT) is a real plateau, not a clip.
5. Then every row that the clip can have corrupted is left out: rows at the range (step 1, also the
   interpolated edges between a clipped sample and an unclipped one, which made an earlier spread test call
   the reference "not pinned"), rows where the DUT reads the field at or beyond the range although the
   (lagging, filtered) reference has not reached it yet, and the rows next to those in the same contiguous
   run (their reference is interpolated across a clipped sample).

Fewer than MIN_CANDIDATE_ROWS candidates (too few to see a plateau): the calibration fit's rule stands (left
out). The summary says how many rows went for which reason, on which axes, at which level.
"""
from __future__ import annotations

import numpy as np

from magstack.data.session import Session
from magstack.firmware.calibration.reference import SATURATION_MARGIN, reference_range

#: A candidate extreme beyond this fraction above the nominal range: the reference reads past its full scale
#: (the range is not this instrument's), not pinned.
PINNED_LEVEL = 0.1
#: Rows within this fraction of the range from the extreme count as the plateau.
PLATEAU_TOL = 0.002
#: Plateau rows needed to call the extreme a plateau.
PLATEAU_MIN_ROWS = 3
#: Fewer candidate rows than this: too few to tell; the fit's rule (left out) stands.
MIN_CANDIDATE_ROWS = 5
#: The DUT's reading beyond the plateau must exceed this fraction of the range (and 5 robust sd of the
#: DUT-to-reference mapping's scatter).
EXCESS_FRACTION = 0.005
#: Rows well inside the range (fraction of it on every axis) fit the DUT-to-reference mapping.
MAPPING_INSIDE = 0.9
#: Largest condition number of the mapping's 3 x 3 matrix; beyond it (one field level) each DUT axis is
#: read as the field in uT.
MAPPING_MAX_COND = 1e4


def dut_implied_reference(s: Session, usable: np.ndarray, range_uT: float) -> tuple[np.ndarray, np.ndarray]:
    """((N,3) the DUT reading mapped into reference units, (3,) robust sd of the mapping's scatter, uT): the
    affine map ``ref ~ (dut - b) M^-1`` fitted on usable rows well inside the range; where it is ill-conditioned
    (one field level) the DUT reading itself (a magnetometer in uT) with the scatter of ``dut - ref``."""
    ref, dut = np.asarray(s.ref_uT, dtype=float), np.asarray(s.dut_uT, dtype=float)
    inside = usable & np.all(np.abs(ref) < MAPPING_INSIDE * range_uT, axis=1)
    implied = dut.copy()
    if inside.sum() >= 20:
        X = np.column_stack([ref[inside], np.ones(int(inside.sum()))])
        coef, *_ = np.linalg.lstsq(X, dut[inside], rcond=None)
        M, b = coef[:3], coef[3]
        if np.all(np.isfinite(M)) and np.linalg.cond(M) < MAPPING_MAX_COND:
            implied = np.linalg.solve(M.T, (dut - b).T).T
    r = (implied - ref)[inside] if inside.any() else np.zeros((0, 3))
    if r.shape[0] >= 20:
        sd = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
    else:
        sd = np.zeros(3)
    return implied, sd


def reference_guard(s: Session, usable: np.ndarray, include_saturated: bool) -> tuple[dict, np.ndarray]:
    """The reference-range guard of the diagnosis (module docs). Returns (summary, mask of rows left out or,
    with ``include_saturated``, counted but kept). The summary: ``reference``, ``range_uT``, ``assumed``,
    ``note``, ``saturated_rows`` (all rows the clip touches), ``saturated_excluded``, ``clipped`` (per axis
    and sign: level, plateau rows, the DUT's median reading there in reference units, how far beyond),
    ``excluded_by_reason`` (``at_range``, ``dut_beyond_range``, ``next_to_clipped``) and ``why``."""
    name, rng, note = reference_range(s.metadata)
    ref = np.asarray(s.ref_uT, dtype=float)
    usable = np.asarray(usable, bool)
    n = len(s)
    at_range = np.zeros(n, bool)
    beyond = np.zeros(n, bool)
    clipped, unpinned, agrees = [], [], []
    implied = sd = None
    with np.errstate(invalid="ignore"):
        for j in range(3):
            for sign in (1.0, -1.0):
                v = sign * ref[:, j]
                cand = usable & (v >= (1.0 - SATURATION_MARGIN) * rng)
                if not cand.any():
                    continue
                level = float(np.max(v[cand]))
                label = f"{'+' if sign > 0 else '-'}{'xyz'[j]}"
                if level > (1.0 + PINNED_LEVEL) * rng:
                    unpinned.append(label)
                    continue
                if cand.sum() < MIN_CANDIDATE_ROWS:      # too few to tell: the fit's rule stands
                    at_range |= cand
                    clipped.append({"axis": "xyz"[j], "sign": label[0], "level_uT": sign * level,
                                    "plateau_rows": int(cand.sum()), "reason": "too few rows to tell"})
                    continue
                plateau = cand & (v >= level - PLATEAU_TOL * rng)
                if plateau.sum() < PLATEAU_MIN_ROWS:
                    agrees.append(label)
                    continue
                if implied is None:
                    implied, sd = dut_implied_reference(s, usable, rng)
                dut_level = float(np.median(sign * implied[plateau, j]))
                excess = dut_level - level
                if not excess > max(EXCESS_FRACTION * rng, 5.0 * float(sd[j])):
                    agrees.append(label)
                    continue
                at_range |= cand
                beyond |= usable & (sign * implied[:, j] >= (1.0 - SATURATION_MARGIN) * rng)
                clipped.append({"axis": "xyz"[j], "sign": label[0], "level_uT": sign * level,
                                "plateau_rows": int(plateau.sum()), "dut_reads_uT": sign * dut_level,
                                "excess_uT": excess})
    beyond &= ~at_range
    near = _next_to(at_range | beyond, s.t_s, s.session) & usable & ~at_range & ~beyond
    sat = at_range | beyond | near
    counts = {"at_range": int(at_range.sum()), "dut_beyond_range": int(beyond.sum()),
              "next_to_clipped": int(near.sum())}
    msgs = [note] if note else []
    if unpinned:
        msgs.append(f"the reference reads at or beyond its range (+-{rng:g} uT, {name}) on {', '.join(unpinned)} "
                    f"up to more than {1 + PINNED_LEVEL:g}x of it and follows the DUT there (not pinned: the "
                    "range is not this instrument's): those rows are kept")
    if agrees:
        msgs.append(f"the reference reaches its range (+-{rng:g} uT, {name}) on {', '.join(agrees)} where the DUT "
                    "agrees with it (no plateau with the DUT beyond it: not clipped): those rows are kept")
    why = ""
    if sat.any():
        levels = ", ".join(f"{c['sign']}{c['axis']} at {c['level_uT']:+.1f} uT"
                           + (f" while the DUT reads {c['dut_reads_uT']:+.1f} uT" if "dut_reads_uT" in c else
                              f" ({c['reason']})") for c in clipped)
        why = (f"the {name} reference clips (range +-{rng:g} uT): {levels}; {counts['at_range']} rows at its range, "
               f"{counts['dut_beyond_range']} where the DUT reads the field beyond it before the reference gets "
               f"there, {counts['next_to_clipped']} next to them (reference interpolated across a clipped sample)")
    return {"reference": name, "range_uT": float(rng), "assumed": note is not None and "assuming" in note,
            "note": "; ".join(msgs) or None, "saturated_rows": int(sat.sum()),
            "saturated_excluded": bool(sat.any() and not include_saturated), "clipped": clipped,
            "excluded_by_reason": counts, "why": why}, sat


def _next_to(rows: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> np.ndarray:
    """Rows adjacent (in session-then-time order, same contiguous run) to a marked row."""
    from magstack.ground.diagnose.nonlinear import runs
    out = np.zeros(rows.size, bool)
    if not rows.any():
        return out
    t = np.asarray(t_s, dtype=float)
    ok = np.isfinite(t)
    idx = np.flatnonzero(ok)
    order = idx[np.lexsort((t[idx], np.asarray(session)[idx]))]
    run = runs(t[order], np.asarray(session)[order])
    m = rows[order]
    near = np.zeros(order.size, bool)
    near[1:] |= m[:-1] & (run[1:] == run[:-1])
    near[:-1] |= m[1:] & (run[1:] == run[:-1])
    out[order] = near
    return out
