"""Calibration tables written in other systems' conventions (autopilot parameters, source headers).

Each format is an :class:`Exporter` in :data:`EXPORTERS` (name -> exporter), registered with
:func:`register_exporter`; ``magstack table export`` offers one ``--<name> FILE`` option per registered
exporter, so a new format (a C header for the C applier, say) only registers itself here. An exporter turns a
:class:`~magstack.firmware.cal_table.CalTable` into the text of a file, says which terms its convention cannot
hold and, given a session's samples, what dropping them costs there in nT (:class:`Export`).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Dropped:
    """A term (or part of one) the convention cannot hold, why, and its cost on the session (nT RMS: vector
    and magnitude of the difference to the table's own output; None without a session)."""

    term: str
    why: str
    vector_rms_nT: float | None = None
    magnitude_rms_nT: float | None = None


@dataclass
class Export:
    """An exported calibration: ``text`` (the file), ``params`` (name -> value), the convention's formula in
    words, and the terms it dropped."""

    format: str
    text: str
    params: dict[str, float]
    formula: str
    dropped: list[Dropped] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    check: tuple[np.ndarray, np.ndarray] | None = None   # (table output, exported formula's) on the session

    def lines(self) -> list[str]:
        out = [f"{self.format}: {self.formula}"]
        for d in self.dropped:
            cost = ("" if d.vector_rms_nT is None else
                    f"; on the session: {d.vector_rms_nT:.1f} nT RMS vector, {d.magnitude_rms_nT:.1f} nT RMS |B|")
            out.append(f"  dropped {d.term}: {d.why}{cost}")
        out += [f"  note: {n}" for n in self.notes]
        return out


@dataclass(frozen=True)
class Exporter:
    """``build(table, b_uT, temp_c, **options) -> Export``; ``suffix`` the usual file suffix; ``help``."""

    name: str
    build: Callable[..., Export]
    suffix: str
    help: str


EXPORTERS: dict[str, Exporter] = {}


def register_exporter(exporter: Exporter) -> None:
    """Add a format; a duplicate name raises ValueError."""
    if exporter.name in EXPORTERS:
        raise ValueError(f"exporter {exporter.name!r} already registered")
    EXPORTERS[exporter.name] = exporter


def table_output(table, b_uT: np.ndarray, temp_c: np.ndarray | None) -> np.ndarray:
    """(N, 3) the table's own calibration of ``b_uT`` (float applier, every flight term)."""
    from magstack.firmware.float_applier import apply_float

    out = apply_float(table, b_uT, temp_c)
    return out[0] if isinstance(out, tuple) else out


def cost_nT(reference_uT: np.ndarray, other_uT: np.ndarray) -> tuple[float, float]:
    """(vector RMS, magnitude RMS) of ``other - reference`` in nT over rows where both are finite."""
    ok = np.all(np.isfinite(reference_uT), axis=1) & np.all(np.isfinite(other_uT), axis=1)
    d = other_uT[ok] - reference_uT[ok]
    m = np.linalg.norm(other_uT[ok], axis=1) - np.linalg.norm(reference_uT[ok], axis=1)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))) * 1e3), float(np.sqrt(np.mean(m * m)) * 1e3)


def load_exporters() -> dict[str, Exporter]:
    """Every built-in format registered (each module registers itself on import); the registry."""
    from magstack.ground.export import ardupilot, px4  # noqa: F401

    return EXPORTERS


def read_params(text: str) -> dict[str, float]:
    """Parameters from a PX4 (QGroundControl, tab-separated) or ArduPilot (``NAME,VALUE`` or ``NAME VALUE``)
    parameter file; comment lines start with ``#``."""
    out: dict[str, float] = {}
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split("\t") if "\t" in line else line.replace(",", " ").split()
        if len(parts) >= 5:                   # QGC: vehicle, component, name, value, type
            out[parts[2]] = float(parts[3])
        elif len(parts) == 2:
            out[parts[0]] = float(parts[1])
    return out


__all__ = ["Dropped", "Export", "Exporter", "EXPORTERS", "register_exporter", "table_output", "cost_nT", "held_linear",
           "load_exporters", "read_params"]


def held_linear(table, b_uT: np.ndarray | None, temp_c: np.ndarray | None, *, symmetric: bool,
                sensor_bounds: str) -> tuple[np.ndarray, np.ndarray, float, list[Dropped], np.ndarray | None]:
    """What a ``B = M b + c`` convention with a symmetric ``M`` can hold of ``table``: ``(M, c, T_ref,
    dropped, table output on the session)``. Temperature terms are evaluated at ``T_ref`` (the session's mean
    temperature, else ``t0``) and dropped; currents and non-linear terms are dropped; a non-symmetric gain
    (a rotation in it) keeps its symmetric polar factor ``P`` (``S = U P``), the rotation ``U`` is dropped
    and the offset turned by ``U^T``. Costs on the session when ``b_uT`` is given."""
    from scipy.linalg import polar

    temps = None if temp_c is None else np.asarray(temp_c, dtype=float)
    if temps is not None and np.isfinite(temps).any():
        t_ref = float(np.nanmean(temps))
    else:
        t_ref = float(table.t0_c)
    dT = t_ref - table.t0_c
    S = np.asarray(table.S) + np.asarray(table.K_S) * dT
    O = np.asarray(table.O) + np.asarray(table.K_O) * dT
    dropped: list[Dropped] = []
    ref = None
    if b_uT is not None:
        need_t = bool({"temperature_gain", "temperature_offset"} & set(table.terms))
        tt = temps if (need_t and temps is not None) else (None if not need_t else np.full(len(b_uT), t_ref))
        cur = {k: np.zeros(len(b_uT)) for k in table.currents}
        from magstack.firmware.float_applier import apply_float

        ref = apply_float(table, b_uT, tt, cur)[0]

    def linear(Mx, cx):
        return None if b_uT is None else b_uT @ Mx.T + cx

    if {"temperature_gain", "temperature_offset"} & set(table.terms) and (
            np.any(table.K_S) or np.any(table.K_O)):
        c = (None, None) if ref is None else cost_nT(ref, linear(S, O))
        dropped.append(Dropped("temperature terms (K_S, K_O)", f"{sensor_bounds} holds no temperature dependence: "
                               f"the table is evaluated at {t_ref:.2f} degC", *c))
    for name, _ in table.D:
        dropped.append(Dropped(f"current D_{name}", f"{sensor_bounds} holds no per-current term here (evaluated at "
                               "0 A)"))
    for term in ("cubic", "cross_products"):
        if term in table.terms:
            dropped.append(Dropped(term, f"{sensor_bounds} is linear"))
    M, c = S, O
    if symmetric and not np.allclose(S, S.T, atol=1e-12):
        U, P = polar(S)
        M, c = P, U.T @ O
        ang = float(np.degrees(np.arccos(np.clip((np.trace(U) - 1) / 2, -1, 1))))
        before = linear(S, O)
        cc = (None, None) if ref is None else cost_nT(before, linear(M, c))
        dropped.append(Dropped(f"rotation of the gain matrix ({ang:.3f} deg)",
                               f"{sensor_bounds} stores a symmetric matrix: the symmetric polar factor is kept "
                               "(the output turns by the rotation; |B| is unchanged)", *cc))
    return M, c, t_ref, dropped, ref
