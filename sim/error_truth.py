"""Sampling a truth source for the error model: arrays for the vector path, floats for one sample.

A :class:`~magstack.sim.truth_source.TruthSource` gives the true field (uT), temperature (degC),
named currents (A) and session id at an instant. :func:`sample_truth` uses the optional vectorised
methods (``field_series_uT``, ``temp_series_c``, ``currents_series_A``, ``session_series``) when the
source has them, else the scalar protocol; :func:`sample_truth_floats` does the same for a few
instants as plain floats. Non-finite truth is refused, never passed on.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from magstack.drivers.errors import ConfigurationError

__all__ = ["TruthSamples", "sample_truth", "sample_truth_floats"]


@dataclass
class TruthSamples:
    """Truth sampled at N instants: b_uT (N,3) body frame, temp_c (N,), currents_A name->(N,), session (N,) int."""

    b_uT: np.ndarray
    temp_c: np.ndarray
    currents_A: dict[str, np.ndarray]
    session: np.ndarray


def sample_truth(truth: Any, t_s: np.ndarray) -> TruthSamples:
    """Sample a TruthSource at the instants ``t_s`` (N,).

    Uses the optional vectorised methods ``field_series_uT``, ``temp_series_c``,
    ``currents_series_A`` and ``session_series`` when the source has them (see
    :mod:`magstack.sim.coil_programs`), otherwise loops over the scalar protocol. Non-finite truth raises
    ConfigurationError naming the instant.
    """
    t = np.asarray(t_s, dtype=float).reshape(-1)
    n = t.size
    if hasattr(truth, "field_series_uT"):
        b = np.asarray(truth.field_series_uT(t), dtype=float).reshape(n, 3)
    else:
        b = np.array([np.asarray(truth.field_uT(float(x)), dtype=float).reshape(3) for x in t]).reshape(n, 3)
    if hasattr(truth, "temp_series_c"):
        temp = np.asarray(truth.temp_series_c(t), dtype=float).reshape(n)
    else:
        temp = np.array([float(truth.temp_c(float(x))) for x in t], dtype=float).reshape(n)
    if hasattr(truth, "currents_series_A"):
        cur = {k: np.asarray(v, dtype=float).reshape(n) for k, v in truth.currents_series_A(t).items()}
    else:
        per = [truth.currents_A(float(x)) for x in t]
        keys = sorted({k for p in per for k in p})
        cur = {k: np.array([float(p.get(k, 0.0)) for p in per], dtype=float) for k in keys}
    if hasattr(truth, "session_series"):
        sess = np.asarray(truth.session_series(t)).reshape(n).astype(np.int64)
    else:
        sess = np.array([int(truth.session(float(x))) for x in t], dtype=np.int64)
    for name, arr in (("field_uT", b), ("temp_c", temp), *((f"currents_A[{k!r}]", v) for k, v in cur.items())):
        bad = ~np.isfinite(arr)
        if bad.any():
            idx = np.argwhere(bad)[0][0]
            raise ConfigurationError(f"truth source returned non-finite {name} at t_s={t[idx]!r}")
    return TruthSamples(b, temp, cur, sess)



def sample_truth_floats(truth: Any, ts: list[float]):
    """:func:`sample_truth` at a few instants as plain floats: (b rows, temps, currents, sessions).

    Calls the truth source exactly as :func:`sample_truth` does (series methods when present, in
    the same order); returns None when any value is non-finite (the caller then raises). A source with its
    own ``sample_floats(ts)`` (a gridded orbit truth) answers directly.
    """
    fast = getattr(truth, "sample_floats", None)
    if fast is not None:
        got = fast(ts)
        ok = all(math.isfinite(v) for row in got[0] for v in row) and all(math.isfinite(v) for v in got[1]) \
            and all(math.isfinite(v) for vs in got[2].values() for v in vs)
        return got if ok else None
    if (hasattr(truth, "field_series_uT") or hasattr(truth, "temp_series_c")
            or hasattr(truth, "currents_series_A") or hasattr(truth, "session_series")):
        try:
            s = sample_truth(truth, np.array(ts))
        except ConfigurationError:
            return None
        return (s.b_uT.tolist(), s.temp_c.tolist(), {k: v.tolist() for k, v in s.currents_A.items()},
                s.session.tolist())
    isfinite = math.isfinite
    bs = []
    for x in ts:
        b = np.asarray(truth.field_uT(x), dtype=float).reshape(3).tolist()
        if not (isfinite(b[0]) and isfinite(b[1]) and isfinite(b[2])):
            return None
        bs.append(b)
    temps = [float(truth.temp_c(x)) for x in ts]
    per = [truth.currents_A(x) for x in ts]
    if len(per) == 1:
        cur = {k: [float(v)] for k, v in per[0].items()}
    else:
        cur = {k: [float(q.get(k, 0.0)) for q in per] for k in sorted({k for q in per for k in q})}
    sessions = [int(truth.session(x)) for x in ts]
    for v in temps:
        if not isfinite(v):
            return None
    for vs in cur.values():
        for v in vs:
            if not isfinite(v):
                return None
    return bs, temps, cur, sessions

