"""Predictive uncertainty of a calibration table and the validity region it implies.

A table may carry a ``posterior`` block (:mod:`magstack.firmware.cal_table`) with what is needed to say how
wrong a calibrated sample can be. For an input (DUT field ``b`` uT, temperature ``T``, currents ``I``) the
calibrated axis ``i`` is ``f_i(b, T, I)^T theta_i``; the variance of its error against the true field is the
sum of three parts, each per axis (uT^2):

* **parameters** ``f_i^T C_i f_i``: the posterior covariance ``C_i`` of the table's flight parameters, its
  per-parameter inflation for slowly correlated residuals already applied by the fit, extended by the catalogue
  terms the model *leaves out* (``left_out`` names such as ``K_S2[x]``, ``K_S3[x]``, ``K_O2[x]``, ``c3[x]``,
  ``P[x,xy]``:
  value 0 in the table, covariance = their prior, capped by what the data would have shown, projected past what
  the fitted terms absorb: :mod:`magstack.firmware.calibration.predictive`). Inside the data that part is
  small; beyond it, it is what grows with distance (the physics decides).
* **discrepancy** ``delta_i^2(b, T)``: what held-out residuals showed the model misses beyond noise and
  parameters (slow drift, unmodelled structure), ``d0 + dB (|b|/field_ref)^2 + dT ((T - T_c)/temp_ref)^2``
  with ``|b|`` and ``T`` clamped to the fit data's range (the data say nothing beyond it).
* **noise** ``n_i^2``: the sensor's white noise on one sample (the fit's noise floor).

:class:`Predictive` evaluates them; ``apply`` writes the per-axis total (``cal_sigma_x_nT`` ...), its vector
root-sum-square ``cal_sigma_nT`` and the parameter part ``cal_param_sd_nT``. A table without the newer keys
(``noise_uT``, ``discrepancy``, ``left_out``) gives the parameter part alone, as it says.

**Validity region** (:func:`validity_region`): a temperature interval, a limit per calibrated axis
(``|B_j| <= F_j``) and on the calibrated magnitude (``|B| <= R``), where twice the predictive vector sd
``2 sqrt(sum_i sd_i^2)`` stays within the table's ``bound_uT`` (a vector error exceeded with ~1 % probability
for an honest Gaussian sd, chi-square with 3 dof). The region is stated in the calibrated field, so the
applier checks its own output against it. Its points are mapped to readings through the table's affine part
and the variance is evaluated there exactly (full covariance); with affine features the parameter part is a
convex quadratic and the discrepancy grows with ``|b|``, so the worst case is at the region's extreme
points (also with cross terms, convex along every coordinate line); cubic terms are searched on two inner
shells as well; temperature on a grid.
On board, evaluating ``f^T C f`` costs k^2 + k multiply-adds per axis (k ~ 10): optional, not done by the
fixed-point applier (docs/cal-table.md).
"""
from __future__ import annotations

import functools
import itertools
import math
import re
from collections.abc import Mapping, Sequence

import numpy as np

AXES = ("x", "y", "z")
_NAME = re.compile(r"^(S|K_S3|K_S2|K_S|O|K_O2|K_O|c3|P|D_[A-Za-z0-9_]+)\[([xyz])(?:,(x|y|z|xy|xz|yz))?\]$")
#: Parameters whose feature is affine in the field at a fixed temperature.
LINEAR_PARAMS = ("S", "K_S", "K_S2", "K_S3", "O", "K_O", "K_O2")
_PAIRS = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}


@functools.lru_cache(maxsize=1024)
def parse_name(name: str) -> tuple[str, int, str | None]:
    """``'K_S[x,y]'`` -> ("K_S", 0, "y"); ValueError for a name that is not a calibration parameter."""
    m = _NAME.match(name)
    if not m:
        raise ValueError(f"not a flight parameter name: {name!r}")
    return m.group(1), AXES.index(m.group(2)), m.group(3)


def features_t(names: Sequence[str], b_uT: np.ndarray, dT: np.ndarray,
               currents_A: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
    """(k, N) values of the features that multiply the parameters ``names`` (one axis's), one row per feature
    (each written and read contiguously)."""
    bt = np.ascontiguousarray(np.asarray(b_uT, dtype=float).reshape(-1, 3).T)
    n = bt.shape[1]
    dT = np.broadcast_to(np.asarray(dT, dtype=float), (n,))
    out = np.empty((len(names), n))
    powers = {1: dT}

    def dT_pow(k: int) -> np.ndarray:                    # dT^k, formed once per call
        if k not in powers:
            powers[k] = dT_pow(k - 1) * dT
        return powers[k]

    for k, nm in enumerate(names):
        p, i, j = parse_name(nm)
        if p == "S":
            out[k] = bt[AXES.index(j)]
        elif p == "K_S":
            np.multiply(bt[AXES.index(j)], dT, out=out[k])
        elif p in ("K_S2", "K_S3"):
            np.multiply(bt[i], dT_pow(2 if p == "K_S2" else 3), out=out[k])
        elif p == "O":
            out[k] = 1.0
        elif p == "K_O":
            out[k] = dT
        elif p == "K_O2":
            out[k] = dT_pow(2)
        elif p == "c3":
            np.multiply(bt[i], bt[i], out=out[k])
            out[k] *= bt[i]
        elif p == "P":
            a, c = _PAIRS[j]
            np.multiply(bt[a], bt[c], out=out[k])
        else:
            cur = (currents_A or {}).get(p[2:])
            if cur is None:
                raise ValueError(f"current {p[2:]!r} needed for {nm}")
            out[k] = np.broadcast_to(np.asarray(cur, dtype=float), (n,))
    return out


def feature_key(name: str) -> tuple:
    """What the feature of parameter ``name`` depends on, so that two parameters with the same key multiply the same
    feature (``P[x,xy]`` and ``P[y,xy]``: ``b_x b_y`` on two outputs; ``K_O2`` on every axis: ``dT^2``)."""
    p, i, j = parse_name(name)
    if p in ("S", "K_S", "P"):
        return p, j
    if p in ("K_S2", "K_S3", "c3"):
        return p, i
    return (p,)


def features(names: Sequence[str], b_uT: np.ndarray, dT: np.ndarray,
             currents_A: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
    """(N, k) values of the features that multiply the parameters ``names`` (one axis's)."""
    return features_t(names, b_uT, dT, currents_A).T


def _chol(C: np.ndarray) -> np.ndarray:
    C = 0.5 * (C + C.T)
    w, V = np.linalg.eigh(C)
    return V * np.sqrt(np.maximum(w, 0.0))          # L with L L^T = C (PSD, no jitter needed)


#: The polynomial features' monomials of the reading, by component: ``c3`` -> ``b_i^3``, ``P`` -> ``b_a b_c``.
_MONOMIALS = ((0, 0, 0), (1, 1, 1), (2, 2, 2), (0, 1), (0, 2), (1, 2))


def _feature_layout(names_per_axis: Sequence[Sequence[str]]) -> list[dict]:
    """Per axis, the features sorted by form: ``jf`` the affine ones (``dT^pw`` times entry ``col`` of
    ``[b_x, b_y, b_z, 1]``), ``jn`` the polynomial ones with their ``mono`` (index into ``_MONOMIALS``), ``jc``
    the currents with their names."""
    power = {"S": 0, "K_S": 1, "K_S2": 2, "K_S3": 3, "O": 0, "K_O": 1, "K_O2": 2}
    out = []
    for names in names_per_axis:
        lay: dict = {"col": [], "pw": [], "jf": [], "jn": [], "mono": [], "jc": [], "cur": []}
        for k, nm in enumerate(names):
            p, i, j = parse_name(nm)
            if p.startswith("D_"):
                lay["jc"].append(k)
                lay["cur"].append(p[2:])
            elif p in power:
                lay["jf"].append(k)
                lay["pw"].append(power[p])
                lay["col"].append(3 if p in ("O", "K_O", "K_O2") else AXES.index(j) if p in ("S", "K_S") else i)
            else:
                lay["jn"].append(k)
                lay["mono"].append(_MONOMIALS.index((i, i, i) if p == "c3" else _PAIRS[j]))
        out.append({k: np.array(v, dtype=np.int64) if k in ("col", "pw", "jf", "jn", "mono") else v
                    for k, v in lay.items()})
    return out


class Predictive:
    """The predictive variance of a table's calibrated samples, from its ``posterior`` block.

    ``posterior``: ``{"x": {"names", "cov"}, "y": ..., "z": ..., "noise_uT": [3], "discrepancy": {...}}``;
    ``t0_c`` the table's temperature reference (degC). The parts are functions of the DUT's reading; a validity
    region is stated in the calibrated field, so the worst cases over a region (:meth:`worst_vector_sd_uT`) map
    its points to readings through ``calibration`` = the table's ``(S, K_S, K_S2, O, K_O)`` (the inverse of its
    affine part at each temperature; None: readings and calibrated field taken as the same)."""

    def __init__(self, posterior: Mapping, t0_c: float, calibration: Sequence | None = None) -> None:
        self.t0_c = float(t0_c)
        self.calibration = None if calibration is None else tuple(np.asarray(x, dtype=float) for x in calibration)
        self.names = [list(posterior[a]["names"]) for a in AXES]
        self.cov = [0.5 * (np.asarray(posterior[a]["cov"], dtype=float) + np.asarray(posterior[a]["cov"]).T)
                    for a in AXES]
        self.L = [_chol(C) for C in self.cov]
        self.noise_uT = np.asarray(posterior.get("noise_uT", (0.0, 0.0, 0.0)), dtype=float).reshape(3)
        self.disc = dict(posterior["discrepancy"]) if posterior.get("discrepancy") else None
        self.complete = "noise_uT" in posterior and self.disc is not None
        self._layout = _feature_layout(self.names)
        self._qnn = np.zeros((len(_MONOMIALS), len(_MONOMIALS)))     # the polynomial features' form, all axes
        for C, lay in zip(self.cov, self._layout, strict=True):
            jf, jn, jc = lay["jf"], lay["jn"], np.array(lay["jc"], dtype=np.int64)
            lay["blocks"] = {"ff": C[np.ix_(jf, jf)], "fn": C[np.ix_(jf, jn)], "cf": C[np.ix_(jc, jf)],
                             "cn": C[np.ix_(jc, jn)], "cc": C[np.ix_(jc, jc)]}
            np.add.at(self._qnn, np.ix_(lay["mono"], lay["mono"]), C[np.ix_(jn, jn)])
        self._forms_memo: dict = {}
        self._forms_const: dict = {}

    def to_reading(self, b_cal_uT: np.ndarray, temp_c: float) -> np.ndarray:
        """(m, 3) the readings that calibrate to ``b_cal_uT`` (m, 3) at ``temp_c`` (the table's affine part)."""
        b = np.asarray(b_cal_uT, dtype=float).reshape(-1, 3)
        if self.calibration is None:
            return b
        S, K_S, K_S2, O, K_O = self.calibration
        dT = temp_c - self.t0_c
        G = S + K_S * dT + np.diag(K_S2) * dT * dT
        return np.linalg.solve(G, (b - (O + K_O * dT)[None, :]).T).T

    # ------------------------------------------------------------------ parts, per row
    def param_var_uT2(self, b_uT, temp_c, currents_A=None) -> np.ndarray:
        """(N, 3) parameter part (left-out terms included), uT^2; NaN where an input is missing."""
        b = np.asarray(b_uT, dtype=float).reshape(-1, 3)
        n = b.shape[0]
        t = np.full(n, self.t0_c) if temp_c is None else np.asarray(temp_c, dtype=float).reshape(n)
        out = np.empty((n, 3))
        with np.errstate(invalid="ignore"):
            for i in range(3):
                Ft = features_t(self.names[i], b, t - self.t0_c, currents_A)
                out[:, i] = np.maximum(np.einsum("kn,kn->n", self.cov[i] @ Ft, Ft), 0.0)   # f_n^T C f_n per row
            return out

    def disc_var_uT2(self, b_uT, temp_c) -> np.ndarray:
        """(N, 3) discrepancy part, uT^2 (0 when the table has none)."""
        b = np.asarray(b_uT, dtype=float).reshape(-1, 3)
        n = b.shape[0]
        if self.disc is None:
            return np.zeros((n, 3))
        d = self.disc
        fmax = float(d["field_max_uT"])
        mag = np.minimum(np.linalg.norm(b, axis=1), fmax) / float(d["field_ref_uT"])
        lo, hi = d["temp_range_c"]
        tc = float(d["temp_centre_c"])
        t = np.full(n, tc) if temp_c is None else np.asarray(temp_c, dtype=float).reshape(n)
        u = (np.clip(np.where(np.isfinite(t), t, tc), lo, hi) - tc) / float(d["temp_ref_c"])
        return (np.asarray(d["d0_uT2"])[None, :] + np.asarray(d["dB_uT2"])[None, :] * (mag * mag)[:, None]
                + np.asarray(d["dT_uT2"])[None, :] * (u * u)[:, None])

    def sd_axes_uT(self, b_uT, temp_c, currents_A=None) -> np.ndarray:
        """(N, 3) total predictive sd per axis (parameters + discrepancy + noise), uT."""
        v = self.param_var_uT2(b_uT, temp_c, currents_A) + self.disc_var_uT2(b_uT, temp_c) + self.noise_uT ** 2
        return np.sqrt(v)

    # ------------------------------------------------------------------ worst case over a field region
    def _region_cal_points(self, field_axes_uT, field_norm_uT) -> np.ndarray:
        """Calibrated-field points searched for a worst case: the region's extreme points (:func:`region_points`).
        A cross product ``b_a b_c`` keeps every feature affine along each axis, so the variance is convex along
        every coordinate line and the worst case stays on the region's boundary; the sphere is sampled 4x denser
        for it (a quadratic feature turns faster along the sphere). A cube ``b_i^3`` is not convex along its axis:
        two inner shells (x0.5, x0.75) are searched as well."""
        kinds = {parse_name(nm)[0] for names in self.names for nm in names}
        cal = region_points(field_axes_uT, field_norm_uT, dense="c3" in kinds or "P" in kinds)
        return np.vstack([cal, 0.75 * cal, 0.5 * cal]) if "c3" in kinds else cal

    def _current_corners(self, currents_A: Mapping[str, tuple[float, float]] | None) -> list[dict[str, float]]:
        """Every corner of the current box (a feature affine in each current: the worst case is at a corner)."""
        used = sorted({parse_name(nm)[0][2:] for names in self.names for nm in names
                       if parse_name(nm)[0].startswith("D_")})
        ivals = [tuple(sorted({float(x) for x in (currents_A or {}).get(c, (0.0, 0.0))})) for c in used]
        return [dict(zip(used, combo, strict=True)) for combo in itertools.product(*ivals)]

    def _worst_at(self, temp_c: float, cal: np.ndarray, currents_A) -> np.ndarray:
        """(m,) the predictive vector variance (uT^2) at the calibrated points ``cal`` (m, 3) at ``temp_c``, worst
        over the current corners."""
        return self._worst_var_forms(np.array([float(temp_c)]), cal, self._current_corners(currents_A))[0]

    # ------------------------------------------------------------------ worst case over a field region
    # ------------------------------------------------------------------ the worst case as quadratic forms
    def _reading_maps(self, temps_c: np.ndarray) -> np.ndarray:
        """(n_T, 4, 4) ``M(T)`` with ``[b; 1] = M(T) [B_cal; 1]``: the reading that calibrates to ``B_cal`` at each
        temperature (:meth:`to_reading`, affine)."""
        t = np.asarray(temps_c, dtype=float).reshape(-1)
        M = np.zeros((t.size, 4, 4))
        M[:, 3, 3] = 1.0
        if self.calibration is None:
            M[:, :3, :3] = np.eye(3)
            return M
        S, K_S, K_S2, O, K_O = self.calibration
        dT = (t - self.t0_c)[:, None, None]
        Gi = np.linalg.inv(S[None] + K_S[None] * dT + np.diag(K_S2)[None] * dT * dT)
        M[:, :3, :3] = Gi
        M[:, :3, 3] = -np.einsum("tij,tj->ti", Gi, O[None, :] + K_O[None, :] * dT[:, :, 0])
        return M

    def _forms(self, t: np.ndarray, corners: Sequence[Mapping[str, float]]) -> tuple:
        """``(M (n_T, 4, 4), QL (n_T, k + n_c, k), const (n_c,))`` of :meth:`_worst_var_forms` at temperatures ``t``:
        the reading maps, and the form over ``z = [v; n]`` (``k`` = 4, or 10 with the monomials) stacked over each
        current corner's affine row. They depend on the temperature and the current corners only, not on the
        field region, so each temperature's are computed once and kept (up to ``_FORMS_KEPT`` temperatures)."""
        ckey = tuple(tuple(sorted(c.items())) for c in corners)
        memo = self._forms_memo.setdefault(ckey, {})
        todo = np.unique(t[[x not in memo for x in t.tolist()]]) if memo else np.unique(t)
        if todo.size:
            if len(memo) + todo.size > _FORMS_KEPT:
                memo.clear()
            M, Qvv, Qvn, lin_v, lin_n, const = self._compute_forms(todo, corners)
            nt, nc, nm = todo.size, len(corners), len(_MONOMIALS)
            poly = any(lay["jn"].size for lay in self._layout)          # the same for every temperature
            k = 4 + nm if poly else 4
            cur = any(lay["jc"] for lay in self._layout)
            QL = np.zeros((nt, k + (nc if cur else 0), k))
            QL[:, :4, :4] = Qvv
            if poly:
                QL[:, :4, 4:k] = Qvn
                QL[:, 4:k, :4] = np.swapaxes(Qvn, 1, 2)
                QL[:, 4:k, 4:k] = self._qnn
            if cur:
                QL[:, k:, :4] = lin_v
                if poly:
                    QL[:, k:, 4:] = lin_n
            for j, x in enumerate(todo.tolist()):
                memo[x] = (M[j], QL[j])
            self._forms_const[ckey] = const
        rows = [memo[x] for x in t.tolist()]
        return np.stack([r[0] for r in rows]), np.stack([r[1] for r in rows]), self._forms_const[ckey]

    def _compute_forms(self, t: np.ndarray, corners: Sequence[Mapping[str, float]]) -> tuple:
        """:meth:`_forms` computed (every temperature of ``t``)."""
        nt, nc = t.size, len(corners)
        nm = len(_MONOMIALS)
        dT = t - self.t0_c
        M = self._reading_maps(t)
        Qvv = np.zeros((nt, 4, 4))
        Qvn = np.zeros((nt, 4, nm))
        lin_v = np.zeros((nt, nc, 4))
        lin_n = np.zeros((nc, nm))
        const = np.zeros(nc)
        for lay in self._layout:
            blk = lay["blocks"]
            B = (dT[:, None] ** lay["pw"][None, :])[:, :, None] * M[:, lay["col"], :]         # (n_T, k_f, 4)
            Bt = np.swapaxes(B, 1, 2)
            Qvv += Bt @ blk["ff"] @ B
            if lay["jn"].size:
                Qvn[:, :, lay["mono"]] += Bt @ blk["fn"]
            if lay["jc"]:
                cv = np.array([[c[name] for name in lay["cur"]] for c in corners])                 # (n_c, n_cur)
                lin_v += 2.0 * np.einsum("ck,tka->tca", cv @ blk["cf"], B)
                if lay["jn"].size:
                    lin_n[:, lay["mono"]] += 2.0 * (cv @ blk["cn"])
                const += np.einsum("cj,jl,cl->c", cv, blk["cc"], cv)
        return M, Qvv, Qvn, lin_v, lin_n, const

    def _worst_var_forms(self, temps_c: np.ndarray, cal: np.ndarray, corners: Sequence[Mapping[str, float]]
                         ) -> np.ndarray:
        """(n_T, m) the predictive vector variance (uT^2) at calibrated points ``cal`` (m, 3), worst over the
        current corners. With ``v = [B_cal; 1]`` and the reading ``b = M(T) v``, each axis's affine features are
        ``B(T) v`` (k x 4) and its polynomial features (``c3``, ``P``) pick from the six monomials ``n(b)``
        (``_MONOMIALS``), so the parameter part summed over axes is the quadratic form
        ``v'Q_vv v + 2 v'Q_vn n + n'Q_nn n = z'Qz`` (``z = [v; n]``) and each current corner adds a term affine in
        ``z``: one product per temperature of ``z`` with ``Q`` stacked over the corners' rows (:meth:`_forms`); ``|b|``
        for the discrepancy from the mapped reading. The same values as evaluating every feature at every mapped
        reading (:meth:`param_var_uT2`, :meth:`disc_var_uT2`), to rounding, at a fraction of the cost."""
        t = np.asarray(temps_c, dtype=float).reshape(-1)
        nt = t.size
        M, QL, const = self._forms(t, corners)
        k = QL.shape[2]                                       # 4 (v only) or 10 (v and the six monomials)
        v = np.hstack([np.asarray(cal, dtype=float).reshape(-1, 3), np.ones((cal.shape[0], 1))])   # (m, 4)
        m = v.shape[0]
        b = M[:, :3, :] @ v.T                                                                     # (n_T, 3, m)
        Z = np.empty((nt, k, m))                                                                  # z = [v; n(b)]
        Z[:, :4] = v.T
        if k > 4:
            for j, mono in enumerate(_MONOMIALS):
                np.multiply(b[:, mono[0]], b[:, mono[1]], out=Z[:, 4 + j])
                if len(mono) == 3:
                    Z[:, 4 + j] *= b[:, mono[2]]
        A = QL @ Z                                                        # (n_T, k + n_c, m): Q z, then L_c z
        var = np.einsum("tkm,tkm->tm", A[:, :k], Z)                                               # z'Qz
        var = np.maximum(var, 0.0) + float(np.sum(self.noise_uT ** 2))
        if self.disc is not None:
            d = self.disc
            b2 = np.einsum("tjm,tjm->tm", b, b)                                                    # |b|^2 (n_T, m)
            mag2 = np.minimum(np.sqrt(np.maximum(b2, 0.0)), float(d["field_max_uT"])) ** 2 \
                / float(d["field_ref_uT"]) ** 2
            lo, hi = d["temp_range_c"]
            u = (np.clip(t, lo, hi) - float(d["temp_centre_c"])) / float(d["temp_ref_c"])
            var += float(np.sum(d["d0_uT2"])) + float(np.sum(d["dB_uT2"])) * mag2 \
                + float(np.sum(d["dT_uT2"])) * (u * u)[:, None]
        if QL.shape[1] == k:                                  # no current terms
            return var
        cur = A[:, k:]
        cur += const[None, :, None]
        return var + cur.max(axis=1)

    def worst_vector_sd_uT(self, temp_c: float, field_axes_uT: Sequence[float], field_norm_uT: float = math.inf,
                           currents_A: Mapping[str, tuple[float, float]] | None = None) -> float:
        """The largest predictive vector sd ``sqrt(sum_i sd_i^2)`` (uT) over calibrated fields ``|B_i| <= F_i``,
        ``|B| <= R`` at temperature ``temp_c``, currents inside their intervals. The variance is evaluated
        exactly (the full covariance, correlations included) at the points of :meth:`_region_cal_points`
        mapped to readings by :meth:`to_reading` (affine, so extreme points stay extreme) and at every corner
        of the current box (each feature is affine in each current)."""
        v = self._worst_at(temp_c, self._region_cal_points(field_axes_uT, field_norm_uT), currents_A)
        return float(np.sqrt(v.max()))

    def worst_point(self, temps_c: Sequence[float], field_axes_uT: Sequence[float], field_norm_uT: float = math.inf,
                    currents_A: Mapping[str, tuple[float, float]] | None = None) -> tuple[float, np.ndarray]:
        """``(temperature, calibrated field (3,))`` where the worst predictive vector sd over the region lies."""
        best = (-1.0, float(temps_c[0]), np.zeros(3))
        cal = self._region_cal_points(field_axes_uT, field_norm_uT)
        for t in temps_c:
            v = self._worst_at(float(t), cal, currents_A)
            k = int(np.argmax(v))
            if v[k] > best[0]:
                best = (float(v[k]), float(t), cal[k])
        return best[1], best[2]

    def parts_nT(self, b_uT: Sequence[float], temp_c: float, currents_A: Mapping[str, float] | None = None,
                 top: int = 4) -> list[tuple[str, float]]:
        """The largest parts of the predictive vector variance at one calibrated field, as sd in nT: noise,
        discrepancy and each parameter's share ``f_k (C f)_k`` (a parameter's share can be negative:
        correlations)."""
        b = self.to_reading(np.asarray(b_uT, dtype=float).reshape(1, 3), temp_c)
        cur = {k: np.array([v]) for k, v in (currents_A or {}).items()}
        out = [("noise", float(np.sum(self.noise_uT ** 2))),
               ("discrepancy", float(self.disc_var_uT2(b, [temp_c]).sum()))]
        share: dict[str, float] = {}
        for i in range(3):
            F = features(self.names[i], b, np.array([temp_c - self.t0_c]), cur)[0]
            for nm, v in zip(self.names[i], F * (self.cov[i] @ F), strict=True):
                share[nm] = share.get(nm, 0.0) + float(v)
        out += sorted(share.items(), key=lambda kv: -abs(kv[1]))
        out = sorted(out, key=lambda kv: -abs(kv[1]))[:top]
        return [(k, float(np.sign(v) * np.sqrt(abs(v)) * 1e3)) for k, v in out]

    def worst_over_region_uT(self, temps_c: Sequence[float], field_axes_uT: Sequence[float],
                             field_norm_uT: float = math.inf,
                             currents_A: Mapping[str, tuple[float, float]] | None = None,
                             stop_above_uT: float = math.inf) -> float:
        """:meth:`worst_vector_sd_uT`'s largest value over the temperatures ``temps_c`` (uT); ``stop_above_uT``:
        return as soon as a value above it is found (see :meth:`worst_per_temperature_uT`)."""
        v = self.worst_per_temperature_uT(temps_c, field_axes_uT, field_norm_uT, currents_A, stop_above_uT)
        return max(v.values())

    def worst_per_temperature_uT(self, temps_c: Sequence[float], field_axes_uT: Sequence[float],
                                 field_norm_uT: float = math.inf,
                                 currents_A: Mapping[str, tuple[float, float]] | None = None,
                                 stop_above_uT: float = math.inf) -> dict[float, float]:
        """``{temperature: worst predictive vector sd there (uT)}``, :meth:`worst_vector_sd_uT` for many
        temperatures in a few vectorised passes (every current corner at once): the interval's ends first, then
        every 16th temperature, then the rest. ``stop_above_uT``: stop after the first pass with a value above it
        (the temperatures not reached are left out)."""
        t_all = np.asarray(temps_c, dtype=float).reshape(-1)
        n = t_all.size
        order = np.r_[[0, n - 1], np.arange(0, n, 16), np.arange(n)]
        order = order[np.sort(np.unique(order, return_index=True)[1])]
        cal = self._region_cal_points(field_axes_uT, field_norm_uT)
        m = cal.shape[0]
        corners = self._current_corners(currents_A)
        nc = len(corners)
        out: dict[float, float] = {}
        k = 4 + len(_MONOMIALS) if any(lay["jn"].size for lay in self._layout) else 4
        step = max(1, _VALUES_PER_PASS // max(m * (2 * k + nc + 4), 1))     # z, its products, b, the variance
        cuts = sorted({0, min(2, n), min(2 + (n + 15) // 16, n), *range(2 + (n + 15) // 16, n, step), n})
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            t = t_all[order[a:b]]
            var = self._worst_var_forms(t, cal, corners).max(axis=1)
            sd = np.sqrt(np.maximum(var, 0.0))
            out.update(zip(t.tolist(), sd.tolist(), strict=True))
            if sd.max() > stop_above_uT:
                break
        return out


#: Temperatures whose forms a :class:`Predictive` keeps (:meth:`Predictive._forms`).
_FORMS_KEPT = 4096

#: Values (float64) the arrays of one vectorised pass of :meth:`Predictive.worst_per_temperature_uT` hold at most
#: (32 MiB): per (temperature, point) ``z`` (4 or 10), its form and current rows, the reading and the variance.
_VALUES_PER_PASS = 1 << 22


def _sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly (Fibonacci sphere), both hemispheres."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5 ** 0.5) * k
    rho = np.sqrt(1.0 - z * z)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


_DIRS = _sphere(192)
_DIRS_DENSE = _sphere(768)
_CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))


def region_points(field_axes_uT: Sequence[float], field_norm_uT: float = math.inf, dense: bool = False) -> np.ndarray:
    """The extreme points of ``{|b_j| <= F_j, |b| <= R}``: the box's corners pulled onto the ball where they
    stick out, and 192 directions on the sphere of radius R clipped to the box. A convex function's maximum
    over this convex region is at an extreme point: exactly a corner when the ball does not cut the box, else
    on the sphere, found to about 1 % by the directions (768 with ``dense``). A limit ``F_j`` above ``R`` binds
    nothing (``|b_j| <= |b| <= R``) and is taken as ``R``: the same region, the same points."""
    R = float(field_norm_uT)
    F = np.minimum(np.maximum(np.asarray(field_axes_uT, dtype=float).reshape(3), 0.0), R)   # above R: no bind
    c = _CORNERS * F
    if not math.isfinite(R) or R >= float(np.linalg.norm(F)):
        return c
    nc = np.linalg.norm(c, axis=1)
    c = c * np.minimum(1.0, R / np.where(nc > 0, nc, 1.0))[:, None]
    return np.vstack([c, np.clip(R * (_DIRS_DENSE if dense else _DIRS), -F, F)])


def predictive_sd_uT(posterior: Mapping, t0_c: float, b_uT, temp_c, currents_A=None) -> np.ndarray:
    """(N, 3) total predictive sd of each calibrated axis (uT); NaN where an input is missing."""
    return Predictive(posterior, t0_c).sd_axes_uT(b_uT, temp_c, currents_A)


def norm_sd_uT(sd_axes_uT: np.ndarray, b_cal_uT: np.ndarray) -> np.ndarray:
    """(N,) sd of |B_cal| from per-axis sds: along the field direction, the vector sd below 1 uT."""
    b = np.asarray(b_cal_uT, dtype=float).reshape(-1, 3)
    s = np.asarray(sd_axes_uT, dtype=float).reshape(-1, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        mag = np.linalg.norm(b, axis=1)
        u2 = (b / mag[:, None]) ** 2
        along = np.sqrt(np.sum(u2 * s ** 2, axis=1))
    vec = np.sqrt(np.sum(s ** 2, axis=1))
    return np.where(mag >= 1.0, along, vec)


# ---------------------------------------------------------------------- the validity region
#: Temperature grid step of the validity search (degC).
TEMP_STEP_C = 0.25


def _grid(lo: float, hi: float) -> np.ndarray:
    """The interval's ends and the multiples of ``TEMP_STEP_C`` between them (spacing <= TEMP_STEP_C), so the
    grids of overlapping intervals share their temperatures."""
    k0, k1 = math.ceil(lo / TEMP_STEP_C - 1e-9), math.floor(hi / TEMP_STEP_C + 1e-9)
    return np.unique(np.r_[lo, TEMP_STEP_C * np.arange(k0, k1 + 1), hi])


#: Coarse temperature step of the validity search (degC): the interval's ends and the multiples of it are
#: evaluated first, the ``TEMP_STEP_C`` grid between two of them only where the coarse values and their
#: curvature leave room for a value above the limit (:func:`_ok`).
COARSE_STEP_C = 16 * TEMP_STEP_C


def _ok(pred: Predictive, lo: float, hi: float, F, R: float, sd_max: float, currents,
        memo: dict | None = None) -> bool:
    """Whether twice the worst predictive vector sd stays within the bound over ``[lo, hi]`` x the field
    region; ``memo`` keeps each field region's per-temperature values between calls.

    The interval's ends and the multiples of ``COARSE_STEP_C`` come first; between two neighbours ``a, b`` the
    fine grid is evaluated unless ``max(s_a, s_b) + K h^2 / 4 + 1 % of the limit`` stays below the limit, where
    ``K`` is the largest second divided difference of the coarse values next to the gap (the bound on a smooth
    function's excess over its chord, ``K h^2 / 8``, taken twice)."""
    temps = _grid(lo, hi).tolist()
    F = np.minimum(np.asarray(F, dtype=float), float(R))       # the same region: |b_j| <= |b| <= R
    seen = {} if memo is None else memo.setdefault((tuple(F.tolist()), float(R)), {})
    if any(seen.get(t, -math.inf) > sd_max for t in temps):
        return False

    def need(ts: list[float]) -> bool:
        todo = [t for t in ts if t not in seen]
        if todo:
            seen.update(pred.worst_per_temperature_uT(todo, F, R, currents, stop_above_uT=sd_max))
        return all(t in seen and seen[t] <= sd_max for t in ts)

    ta = np.asarray(temps)
    on = np.abs(ta / COARSE_STEP_C - np.round(ta / COARSE_STEP_C)) < 1e-9
    on[[0, -1]] = True
    coarse = ta[on].tolist()
    if len(coarse) < 3:
        return need(temps)
    if not need(coarse):
        return False
    c = ta[on]
    v = np.array([seen[t] for t in coarse])
    h = np.diff(c)
    dd = np.abs(2.0 * ((v[2:] - v[1:-1]) / h[1:] - (v[1:-1] - v[:-2]) / h[:-1]) / (h[1:] + h[:-1]))   # |f''| est.
    k_gap = np.maximum(np.r_[dd, dd[-1]], np.r_[dd[0], dd])          # each gap: the two estimates beside it
    room = np.maximum(v[:-1], v[1:]) + k_gap * h * h / 4.0 + 0.01 * sd_max
    gap = np.minimum(np.searchsorted(c, ta) - 1, h.size - 1)
    fine = ta[~on & (room[np.maximum(gap, 0)] > sd_max)].tolist()
    return need(fine) if fine else True


def _bisect(ok, lo: float, hi: float, tol: float) -> float:
    """The largest x in [lo, hi] with ok(x), given ok(lo) (ok monotone: true then false)."""
    if ok(hi):
        return hi
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return lo


def validity_region(pred: Predictive, bound_uT: float, *, centre_c: float, data_temp_c: tuple[float, float] | None,
                    data_field_uT: Sequence[float], data_norm_uT: float, temp_limits_c: tuple[float, float],
                    field_caps_uT: Sequence[float], norm_cap_uT: float,
                    currents_A: Mapping[str, tuple[float, float]] | None = None, has_temperature: bool = True,
                    data_field_max_uT: Sequence[float] | None = None, data_norm_max_uT: float | None = None
                    ) -> tuple[tuple[float, float] | None, np.ndarray | None, float | None, list[str]]:
    """``(temperature interval, field limit per input axis (3,), field-magnitude limit, notes)``: a region
    ``T in [lo, hi]``, ``|b_j| <= F_j``, ``|b| <= R`` where twice the worst predictive vector sd stays within
    ``bound_uT``; ``(None, None, None, notes)`` when no region around the data's centre does.

    The region starts from the data's own (temperature range, per-axis field extents and |b| the rows typically
    had: ``data_field_uT``, ``data_norm_uT``; the largest they had: ``data_field_max_uT``, ``data_norm_max_uT``):
    the largest fields when the bound holds there, else as far towards them as it does (one scale between the
    two); then it grows, first in every direction at once by one scale (the temperature interval towards
    ``temp_limits_c``, each axis's field limit towards ``field_caps_uT``, the magnitude limit towards
    ``norm_cap_uT``: temperature and field share the budget), then with what is left one direction at a time
    (temperature on a ``TEMP_STEP_C`` tolerance, fields to 0.5 uT; whole uT, never below the data's rounded up to
    0.01 uT). An axis the data did not pin stays near its data extent. Where the bound fails inside
    the data, the region first narrows its temperature interval towards the centre (the data's fields kept), and
    only when the data's fields fail at the centre temperature itself its fields towards zero: narrower than the
    data, said in ``notes``.
    Without temperature terms the interval is the data's range (the table says nothing about temperature
    beyond it)."""
    sd_max = 0.5 * bound_uT
    notes: list[str] = []
    memo: dict = {}                 # per field region, the worst sd at each temperature evaluated so far
    extremes = {k: max(abs(lo), abs(hi)) for k, (lo, hi) in (currents_A or {}).items()}
    tlo_lim, thi_lim = temp_limits_c
    c = min(max(centre_c, tlo_lim), thi_lim)
    dlo, dhi = data_temp_c if data_temp_c is not None else (c, c)
    dlo, dhi = max(dlo, tlo_lim), min(dhi, thi_lim)
    caps = np.maximum(np.asarray(field_caps_uT, dtype=float).reshape(3), 0.0)
    Fd = np.minimum(np.maximum(np.asarray(data_field_uT, dtype=float).reshape(3), 0.0), caps)
    Rd = min(max(float(data_norm_uT), 0.0), float(norm_cap_uT))
    Fm = Fd if data_field_max_uT is None else np.maximum(np.minimum(np.asarray(data_field_max_uT, dtype=float)
                                                                     .reshape(3), caps), Fd)
    Rm = Rd if data_norm_max_uT is None else max(min(float(data_norm_max_uT), float(norm_cap_uT)), Rd)
    at_c = pred.worst_vector_sd_uT(c, np.zeros(3), 0.0, currents_A)
    if at_c > sd_max:
        notes.append(f"predictive sd at the data's centre ({at_c * 1e3:.0f} nT, zero field) exceeds the sd limit "
                     f"{sd_max * 1e3:.0f} nT (half the bound {bound_uT * 1e3:.0f} nT): no validity region; largest "
                     "parts there, nT: "
                     + ", ".join(f"{k} {v:.0f}" for k, v in pred.parts_nT(np.zeros(3), c, extremes)))
        return None, None, None, notes
    if _ok(pred, dlo, dhi, Fm, Rm, sd_max, currents_A, memo):
        Fd, Rd = Fm, Rm
    elif _ok(pred, dlo, dhi, Fd, Rd, sd_max, currents_A, memo):     # towards the largest fields the data had
        u = _bisect(lambda u: _ok(pred, dlo, dhi, Fd + u * (Fm - Fd), Rd + u * (Rm - Rd), sd_max, currents_A, memo),
                    0.0, 1.0, 0.01)
        Fd, Rd = Fd + u * (Fm - Fd), Rd + u * (Rm - Rd)
    else:
        t_w, b_w = pred.worst_point(np.linspace(dlo, dhi, 21), Fd, Rd, currents_A)
        if _ok(pred, c, c, Fd, Rd, sd_max, currents_A, memo):     # the data's fields hold at the centre: narrow T only
            s = _bisect(lambda s: _ok(pred, c + s * (dlo - c), c + s * (dhi - c), Fd, Rd, sd_max, currents_A, memo),
                        0.0, 1.0, 1e-3)
            what = f"{s:.0%} of its temperature half-width, its fields kept"
            dlo, dhi = c + s * (dlo - c), c + s * (dhi - c)
        else:                                                 # fields too, towards zero field at the centre
            s = _bisect(lambda s: _ok(pred, c, c, s * Fd, s * Rd, sd_max, currents_A, memo), 0.0, 1.0, 1e-3)
            what = f"its centre temperature only, {s:.0%} of its fields"
            dlo, dhi, Fd, Rd = c, c, s * Fd, s * Rd
        parts = ", ".join(f"{k} {v:.0f}" for k, v in pred.parts_nT(b_w, t_w, extremes))
        notes.append(f"the predictive sd exceeds the sd limit {sd_max * 1e3:.0f} nT (half the bound) inside the fit "
                     f"data's own range: the region is "
                     f"narrower than the data ({what}); the largest parts of the sd at its worst point "
                     f"({t_w:.1f} degC, B = {np.round(b_w, 1).tolist()} uT), nT: {parts}")
    lo, hi, F, R = dlo, dhi, Fd.copy(), Rd
    if not has_temperature:
        notes.append("no temperature terms: the validity temperature is the data's range")
    t_span = (tlo_lim - dlo, thi_lim - dhi) if has_temperature else (0.0, 0.0)
    F_cap = np.maximum(np.minimum(caps, float(norm_cap_uT)), Fd)
    R_cap = max(float(norm_cap_uT), Rd)

    def scaled(u: float) -> tuple[float, float, np.ndarray, float]:
        return dlo + u * t_span[0], dhi + u * t_span[1], Fd + u * (F_cap - Fd), Rd + u * (R_cap - Rd)

    u = _bisect(lambda u: _ok(pred, *scaled(u), sd_max, currents_A, memo), 0.0, 1.0, 1e-3)   # every direction at once
    lo, hi, F, R = scaled(u)
    if has_temperature:                                        # then what is left, one direction at a time
        lo = lo + _bisect(lambda v: _ok(pred, lo + v * (tlo_lim - lo), hi, F, R, sd_max, currents_A, memo), 0.0, 1.0,
                          TEMP_STEP_C / max(lo - tlo_lim, 1e-9)) * (tlo_lim - lo)
        hi = hi + _bisect(lambda v: _ok(pred, lo, hi + v * (thi_lim - hi), F, R, sd_max, currents_A, memo), 0.0, 1.0,
                          TEMP_STEP_C / max(thi_lim - hi, 1e-9)) * (thi_lim - hi)
    for j in range(3):
        def grow(x: float, j: int = j) -> bool:
            trial = F.copy()
            trial[j] = x
            return _ok(pred, lo, hi, trial, R, sd_max, currents_A, memo)
        F[j] = _bisect(grow, F[j], F_cap[j], 0.5)
    R = _bisect(lambda r: _ok(pred, lo, hi, F, r, sd_max, currents_A, memo), R,
                max(R, min(R_cap, float(np.linalg.norm(F)))), 0.5)
    if has_temperature:
        lo, hi = math.ceil(min(lo, dlo) * 100 - 1e-9) / 100, math.floor(max(hi, dhi) * 100 + 1e-9) / 100
    F = np.maximum(np.floor(F + 1e-9), np.ceil(Fd * 100 - 1e-9) / 100)
    R = max(math.floor(R + 1e-9), math.ceil(Rd * 100 - 1e-9) / 100)
    temp = (lo, hi) if has_temperature or data_temp_c is not None else None
    return temp, F, float(R), notes
