"""Degenerate parameter groups: parameters the data determine only in combination.

Coverage rules (temperature span, field per axis) cannot see every degeneracy. The classic one
is a thermal run at one constant field: ``K_S[i,x] B_x dT`` and ``K_O[i] dT`` are then the same
column up to the factor ``B_x``, their estimates correlate at about -0.998, each gets a small
formal standard error, and the table is off by microtesla at any other field.

This module measures it from the design itself: the columns of one output axis (as rows of the
R factor of the weighted design, so inner products are those of the data) have the constant
(offset) direction projected out -- a translation of the data is a gauge, not a degeneracy --
and are scaled to unit norm. For that correlation matrix ``C``:

* variance inflation ``VIF_j = (C^-1)_jj = 1 / (1 - R_j^2)``, where ``R_j^2`` is how well the
  other columns explain column ``j`` (1 = orthogonal, inf = collinear);
* parameter correlations ``corr = (C^-1)_jk / sqrt((C^-1)_jj (C^-1)_kk)`` (those of the
  least-squares estimates: near-copy columns give estimates correlated near -1).

Rule: while some *holdable* parameter (a nuisance or secondary term, never ``gain_matrix`` or
``offset``) has ``VIF >= VIF_LIMIT``, take the worst one and hold it **together with** every
holdable parameter whose estimate correlates with it at ``|corr| >= GROUP_CORR``: holding the
whole group puts the model back to "without those terms", which cannot be worse at a field
level the data did not visit (holding only one member would let its partner absorb the
combination, which is right only at the field that was measured).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: VIF at or above which a holdable parameter is degenerate: 100 ~ |corr| 0.995 for a pair
#: (standard error inflated 10x). A thermal run at one field gives ~7e4; a rich 36-parameter
#: synthetic design with drift and session offsets 82 (tests/test_calibration_identifiability.py).
VIF_LIMIT = 100.0
#: Holdable parameters correlated at least this strongly with the worst one are held with it.
GROUP_CORR = 0.9


@dataclass(frozen=True)
class Degeneracy:
    """One held group: column indices (into the caller's list), the worst member's VIF and its
    largest parameter correlation with a group member (or with any column when alone)."""

    members: tuple[int, ...]
    worst: int
    vif: float
    corr: float
    partner: int | None


def correlation_stats(cols_R: np.ndarray, offset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(vif (k,), corr (k, k))`` of the parameters of the columns ``cols_R`` (m, k) (rows of an
    R factor or raw design rows), after projecting out ``offset`` (m,) when given."""
    A = np.array(cols_R, dtype=float, copy=True)
    if offset is not None:
        o = np.asarray(offset, dtype=float)
        oo = float(o @ o)
        if oo > 0:
            A -= np.outer(o, (o @ A) / oo)
    k = A.shape[1]
    if k == 0:
        return np.zeros(0), np.zeros((0, 0))
    n = np.linalg.norm(A, axis=0)
    bad = n <= 0
    n[bad] = 1.0
    A /= n
    G = A.T @ A
    try:
        Ginv = np.linalg.inv(G)
        if not np.all(np.isfinite(Ginv)):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        Ginv = np.linalg.pinv(G)
    d = np.diag(Ginv).copy()
    d[bad] = np.inf
    vif = np.where(d > 0, d, np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.sqrt(np.where(np.isfinite(vif), vif, np.nan))
        corr = Ginv / np.outer(s, s)
    np.fill_diagonal(corr, 1.0)
    return vif, np.nan_to_num(corr, nan=1.0)


def degenerate_groups(cols_R: np.ndarray, holdable: Sequence[bool], offset: np.ndarray | None = None,
                      vif_limit: float = VIF_LIMIT, group_corr: float = GROUP_CORR) -> list[Degeneracy]:
    """Groups to hold, in the order found (see module docstring). ``cols_R`` (m, k): the active
    columns; ``holdable`` (k,): which may be held; ``offset``: the constant column (projected out)."""
    cols = np.asarray(cols_R, dtype=float)
    live = list(range(cols.shape[1]))
    hold = np.asarray(holdable, dtype=bool)
    out: list[Degeneracy] = []
    while True:
        vif, corr = correlation_stats(cols[:, live], offset)
        cand = [a for a, c in enumerate(live) if hold[c] and vif[a] >= vif_limit]
        if not cand:
            return out
        w = max(cand, key=lambda a: vif[a])
        group = [a for a, c in enumerate(live) if hold[c] and (a == w or abs(corr[w, a]) >= group_corr)]
        others = [a for a in range(len(live)) if a != w]
        partner = max(others, key=lambda a: abs(corr[w, a])) if others else None
        out.append(Degeneracy(tuple(live[a] for a in group), live[w], float(vif[w]),
                              float(corr[w, partner]) if partner is not None else float("nan"),
                              None if partner is None else live[partner]))
        live = [c for a, c in enumerate(live) if a not in group]
