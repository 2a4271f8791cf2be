"""Calibration measurement equation: named terms, parameters with units, design matrix.

Eq. 3/4 of belsten (B_meas is the predictor, the reference field the target)::

    B_act = (S + K_S dT) B_meas + O + K_O dT + sum_k D_k I_k  [+ optional terms]

The optional ``temperature_gain2`` term adds the sensitivity tempco's second order on each axis,
``K_S2,i dT^2 B_meas,i`` (a bridge's sensitivity s0 / (1 + a dT) is linear in dT to first order only).

with ``dT = T - t0_c`` (degC). The model is linear in its parameters: every output axis
``i`` is ``B_act,i = X[:, cols_i] @ theta_i`` with one shared design matrix ``X`` whose
columns are named features; ``cols_i`` selects the columns axis ``i`` uses (on-axis
terms such as ``cubic`` use only their own axis).

Term names are the ``cal_term`` values of :mod:`magstack.firmware.effects` (the single
catalogue); this module defines only how each term enters the equation.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from magstack.firmware.cal_terms import (
    CAL_TERMS,
    FLIGHT_TERMS,
    FLOAT_ONLY_TERMS,
    GROUND_ONLY_TERMS,
    JOINT_TERMS,
    TEMPERATURE_TERMS,
)
from magstack.firmware.errors import FitError

AXES = ("x", "y", "z")

#: Named models (sets of terms). ``currents`` is added when currents are named.
MODELS: Mapping[str, tuple[str, ...]] = {
    "eq3": ("gain_matrix", "temperature_gain", "offset", "temperature_offset"),
    "gain_offset": ("gain_matrix", "offset"),
}

__all__ = ["AXES", "CAL_TERMS", "FLIGHT_TERMS", "FLOAT_ONLY_TERMS", "GROUND_ONLY_TERMS", "JOINT_TERMS", "MODELS",
           "Column", "CalModel", "resolve_terms", "time_derivative"]


@dataclass(frozen=True)
class Column:
    """One design-matrix column (feature) and the parameter that multiplies it.

    ``param`` is the parameter's name in its term (e.g. ``S``, ``K_S``, ``D_solar``),
    ``index`` its input index (input axis j for matrices, None for vectors), ``unit``
    the parameter's unit, ``axes`` the output axes that use the column.
    """

    feature: str
    term: str
    param: str
    index: int | None
    unit: str
    axes: tuple[bool, bool, bool] = (True, True, True)


def _check_terms(terms) -> tuple[str, ...]:
    terms = tuple(terms)
    bad = [t for t in terms if t not in CAL_TERMS]
    if bad:
        raise FitError(f"unknown calibration term(s) {bad}; valid: {', '.join(CAL_TERMS)}")
    # canonical order = catalogue order, no duplicates
    return tuple(t for t in CAL_TERMS if t in terms)


def resolve_terms(model: str = "eq3", terms=None, currents=()) -> tuple[str, ...]:
    """Terms of a named model, plus/with ``terms``; ``currents`` adds the currents term."""
    if model not in MODELS:
        raise FitError(f"unknown model {model!r}; valid: {', '.join(MODELS)}")
    out = list(MODELS[model]) + list(terms or ())
    if currents:
        out.append("currents")
    return _check_terms(out)


@dataclass(frozen=True)
class CalModel:
    """A measurement equation: which terms, which currents, reference temperature.

    ``sessions``: session ids for ``session_offset`` (effect coding: the per-session
    offsets sum to zero, so ``O`` is their mean and is what a new session gets).
    ``t_ref_s``: epoch of the ``drift`` term's zero.  ``t0_c``: temperature reference
    in degC (a multiple of 0.01 degC so the fixed-point applier represents it exactly).
    """

    terms: tuple[str, ...] = MODELS["eq3"]
    currents: tuple[str, ...] = ()
    sessions: tuple[int, ...] = ()
    t0_c: float = 25.0
    t_ref_s: float = 0.0
    name: str = "eq3"
    columns: tuple[Column, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "terms", _check_terms(self.terms))
        object.__setattr__(self, "currents", tuple(self.currents))
        object.__setattr__(self, "sessions", tuple(int(s) for s in self.sessions))
        if not np.isfinite(self.t0_c) or abs(round(self.t0_c * 100) - self.t0_c * 100) > 1e-6:
            raise FitError(f"t0_c must be a finite multiple of 0.01 degC, got {self.t0_c!r}")
        if "currents" in self.terms and not self.currents:
            raise FitError("term 'currents' needs at least one named current")
        if self.currents and "currents" not in self.terms:
            object.__setattr__(self, "terms", _check_terms(self.terms + ("currents",)))
        if len(set(self.currents)) != len(self.currents):
            raise FitError(f"duplicate current names {self.currents}")
        if "gain_matrix" not in self.terms:
            raise FitError("every model needs the gain_matrix term")
        object.__setattr__(self, "columns", tuple(self._build_columns()))

    def _build_columns(self) -> list[Column]:
        cols: list[Column] = []
        on = lambda i: tuple(k == i for k in range(3))  # noqa: E731
        for term in self.terms:
            if term == "gain_matrix":
                cols += [Column(f"B_{a}", term, "S", j, "1") for j, a in enumerate(AXES)]
            elif term == "temperature_gain":
                cols += [Column(f"B_{a}*dT", term, "K_S", j, "1/degC") for j, a in enumerate(AXES)]
            elif term == "temperature_gain2":
                cols += [Column(f"B_{a}*dT^2", term, "K_S2", j, "1/degC^2", on(j)) for j, a in enumerate(AXES)]
            elif term == "offset":
                cols.append(Column("1", term, "O", None, "uT"))
            elif term == "temperature_offset":
                cols.append(Column("dT", term, "K_O", None, "uT/degC"))
            elif term == "currents":
                cols += [Column(f"I_{n}", term, f"D_{n}", None, "uT/A") for n in self.currents]
            elif term == "cubic":
                cols += [Column(f"B_{a}^3", term, "c3", j, "1/uT^2", on(j)) for j, a in enumerate(AXES)]
            elif term == "cross_products":
                cols += [Column(f"B_{AXES[j]}*B_{AXES[k]}", term, "P", n, "1/uT")
                         for n, (j, k) in enumerate(((0, 1), (0, 2), (1, 2)))]
            elif term == "time_skew":
                cols += [Column(f"dB_{a}/dt", term, "tau", j, "s") for j, a in enumerate(AXES)]
            elif term == "session_offset":
                cols += [Column(f"session_{s}", term, f"dO_s{s}", None, "uT") for s in self.sessions[1:]]
            elif term == "drift":
                cols.append(Column("t-t_ref", term, "r", None, "uT/s"))
        return cols

    # ------------------------------------------------------------------ helpers
    @property
    def n_columns(self) -> int:
        return len(self.columns)

    def axis_mask(self) -> np.ndarray:
        """(3, p) bool: column c used by output axis i."""
        return np.array([[c.axes[i] for c in self.columns] for i in range(3)], dtype=bool).reshape(3, -1)

    def param_name(self, i: int, c: int) -> str:
        col = self.columns[c]
        if col.param in ("S", "K_S", "tau"):
            idx = f",{AXES[col.index]}"
        elif col.param == "P":
            idx = "," + ("xy", "xz", "yz")[col.index]
        else:
            idx = ""
        return f"{col.param}[{AXES[i]}{idx}]"

    def prior(self) -> np.ndarray:
        """(3, p) default prior: S = identity, every other parameter 0."""
        pr = np.zeros((3, self.n_columns))
        for c, col in enumerate(self.columns):
            if col.param == "S":
                pr[col.index, c] = 1.0
        return pr

    def design(self, b_meas_uT, temp_c=None, currents_A: Mapping[str, np.ndarray] | None = None,
               session=None, t_s=None, out: np.ndarray | None = None) -> np.ndarray:
        """(N, p) design matrix. Inputs: b_meas_uT (N,3) uT, temp_c (N,) degC,
        currents_A {name: (N,) A}, session (N,) ints, t_s (N,) s (sorted within a session). ``out``: an (N, p)
        array to fill instead (column order, ``np.empty((N, p), order="F")``, fills column by column without
        strides: several times faster for blocks of many rows)."""
        b = np.asarray(b_meas_uT, dtype=float).reshape(-1, 3)
        n = b.shape[0]
        need_t = set(TEMPERATURE_TERMS) & set(self.terms)
        if need_t and temp_c is None:
            raise FitError(f"terms {sorted(need_t)} need temperature")
        dT = (np.asarray(temp_c, dtype=float).reshape(n) - self.t0_c) if temp_c is not None else None
        X = np.empty((n, self.n_columns)) if out is None else out
        if X.shape != (n, self.n_columns):
            raise ValueError(f"out has shape {X.shape}, the design {(n, self.n_columns)}")
        deriv = None
        for c, col in enumerate(self.columns):
            t, j = col.term, col.index
            if t == "gain_matrix":
                X[:, c] = b[:, j]
            elif t == "temperature_gain":
                X[:, c] = b[:, j] * dT
            elif t == "temperature_gain2":
                X[:, c] = b[:, j] * dT * dT
            elif t == "offset":
                X[:, c] = 1.0
            elif t == "temperature_offset":
                X[:, c] = dT
            elif t == "currents":
                name = col.param[2:]
                if currents_A is None or name not in currents_A:
                    raise FitError(f"data has no current {name!r} (have {sorted(currents_A or {})})")
                X[:, c] = np.asarray(currents_A[name], dtype=float).reshape(n)
            elif t == "cubic":
                X[:, c] = b[:, j] ** 3
            elif t == "cross_products":
                jj, kk = ((0, 1), (0, 2), (1, 2))[j]
                X[:, c] = b[:, jj] * b[:, kk]
            elif t == "time_skew":
                if deriv is None:
                    deriv = time_derivative(b, t_s, session)
                X[:, c] = deriv[:, j]
            elif t == "session_offset":
                if session is None:
                    raise FitError("term session_offset needs the session column")
                s = np.asarray(session).reshape(n)
                k = int(col.param[4:])
                X[:, c] = (s == k).astype(float) - (s == self.sessions[0]).astype(float)
            elif t == "drift":
                if t_s is None:
                    raise FitError("term drift needs time stamps")
                X[:, c] = np.asarray(t_s, dtype=float).reshape(n) - self.t_ref_s
        return X

    def unpack(self, theta: np.ndarray) -> dict[str, np.ndarray | dict]:
        """Named parameter arrays from (3, p) coefficients (unused entries read 0).

        Keys: S (3,3), K_S (3,3), K_S2 (3,), O (3,), K_O (3,), D {name: (3,)}, c3 (3,), P (3,3: columns
        xy, xz, yz), tau (3,3), dO {session: (3,)}, r (3,).
        """
        th = np.where(self.axis_mask(), np.asarray(theta, dtype=float), 0.0)
        out: dict = {"S": np.zeros((3, 3)), "K_S": np.zeros((3, 3)), "K_S2": np.zeros(3), "O": np.zeros(3),
                     "K_O": np.zeros(3),
                     "D": {}, "c3": np.zeros(3), "P": np.zeros((3, 3)), "tau": np.zeros((3, 3)),
                     "dO": {}, "r": np.zeros(3)}
        for c, col in enumerate(self.columns):
            if col.param in ("S", "K_S", "P", "tau"):
                out[col.param][:, col.index] = th[:, c]
            elif col.param in ("c3", "K_S2"):
                out[col.param][col.index] = th[col.index, c]
            elif col.param in ("O", "K_O", "r"):
                out[col.param] = th[:, c].copy()
            elif col.term == "currents":
                out["D"][col.param[2:]] = th[:, c].copy()
            elif col.term == "session_offset":
                out["dO"][int(col.param[4:])] = th[:, c].copy()
        if self.sessions and "session_offset" in self.terms:
            out["dO"][self.sessions[0]] = -sum(out["dO"].values(), np.zeros(3))
        return out

    def predict(self, theta: np.ndarray, X: np.ndarray) -> np.ndarray:
        """(N, 3) model field in uT."""
        th = np.where(self.axis_mask(), theta, 0.0)
        return X @ th.T


def time_derivative(b_uT: np.ndarray, t_s, session=None, gap_factor: float = 3.0) -> np.ndarray:
    """dB/dt in uT/s by central differences inside contiguous runs.

    Runs break at a session change, a non-increasing time or a step above ``gap_factor``
    times the median step; run ends use one-sided differences, single-sample runs get 0.
    """
    if t_s is None:
        raise FitError("term time_skew needs time stamps")
    t = np.asarray(t_s, dtype=float).reshape(-1)
    b = np.asarray(b_uT, dtype=float).reshape(-1, 3)
    n = t.size
    out = np.zeros((n, 3))
    if n < 2:
        return out
    dt = np.diff(t)
    pos = dt[dt > 0]
    med = np.median(pos) if pos.size else 1.0
    brk = (dt <= 0) | (dt > gap_factor * med)
    if session is not None:
        s = np.asarray(session).reshape(-1)
        brk |= s[1:] != s[:-1]
    fwd = np.where(brk[:, None], np.nan, np.diff(b, axis=0) / np.where(brk, 1.0, dt)[:, None])
    left = np.vstack([np.full((1, 3), np.nan), fwd])   # derivative over (k-1, k)
    right = np.vstack([fwd, np.full((1, 3), np.nan)])  # derivative over (k, k+1)
    both = np.isfinite(left) & np.isfinite(right)
    out = np.where(both, 0.5 * (left + right), np.where(np.isfinite(left), left,
                                                        np.where(np.isfinite(right), right, 0.0)))
    return out
