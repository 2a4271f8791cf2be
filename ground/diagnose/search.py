"""Which unmodelled effect: every testable catalogue effect, ranked on held-out blocks, with a test.

For each effect of :data:`magstack.firmware.effects.EFFECTS` that the simulator leaves out:

1. Its columns are built (the calibration term named by the effect's ``cal_term``; the non-linear
   estimators of :mod:`.nonlinear` for ``time_skew`` and ``hysteresis``; the joint per-session
   rotation of :mod:`.rotation` for ``mount_rotation``). Offset-like effects
   (per-session offsets, drift, temperature offset: :data:`OFFSET_LIKE`) get a constant column too when
   the base has no offset (mode (b): a drift since the table was fitted has a non-zero mean).
   It is *not testable* when the columns cannot be built (no temperature, no currents, one session),
   are all combinations of the base columns, or (temperature effects) the temperature spans less
   than ``MIN_TEMP_SPAN_C``.
2. Base + effect is fitted on four folds of time blocks and predicts the fifth (never in-sample);
   the figure of merit is the out-of-fold RMSE (vector norm of per-axis RMS).
3. Significance: per held-out block ``b`` the paired difference ``d_b = SSE_base(b) - SSE_effect(b)``
   (summed over axes). Blocks (default 60 s) are the unit, so residual autocorrelation inside a block
   does not inflate the evidence. One-sided sign-flip permutation test of ``mean(d_b) > 0`` (Student's
   t on fewer than SIGN_FLIP_MIN_UNITS units, see :func:`unit_p`); under
   "nothing unmodelled" the extra columns only add estimation noise, so ``d_b`` is symmetric minus a
   positive term: the test is conservative. Holm's step-down correction across the effects tested
   controls the family-wise false-alarm rate at ``alpha``; an effect must also shrink the RMSE by at
   least ``min_shrink`` (practical significance). Slow noise (1/f, random walk) is real slow structure
   that offset-like columns absorb on held-out blocks too: with ``Options.null == "surrogate"`` (the
   default) the unit is one block and every effect the block test lets through must also pass the
   surrogate test of :mod:`.surrogate` (noise with the residual's own spectrum; ``p_value`` = the
   larger). With ``"blocks"`` the block test stands alone and its unit is ``g`` consecutive blocks
   (:func:`block_group`), one ``g`` for all candidates, from the residual with the lowest held-out RMSE.
   The verdict's comparisons (parsimony, runner-up) use the grouped unit in both modes.
4. Verdict: the significant effect with the lowest held-out RMSE, else ``none``. The runner-up is the
   next in the ranking; the verdict is compared with it by the same block test and by the canonical
   correlation of their columns (after removing the base), and is declared indistinguishable when
   the data cannot separate them.
"""
from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.stats

from magstack.firmware.calibration.linalg import qr_r
from magstack.firmware.calibration.model import JOINT_TERMS, time_derivative
from magstack.firmware.effects import EFFECT_NAMES, EFFECTS
from magstack.firmware.errors import FitError
from magstack.ground.diagnose import lag as lg
from magstack.ground.diagnose import nonlinear as nl
from magstack.ground.diagnose import rotation as rot
from magstack.ground.diagnose.gap import (
    RCOND,
    Block,
    Gap,
    fold_products,
    out_of_fold,
    out_of_fold_blocks,
    predict,
    solve,
    solve_gram,
    solve_normal,
)
from magstack.ground.diagnose.lag import LAG_TERMS, lag_block, lagged_temperature  # noqa: F401
from magstack.ground.errors import DiagnosisError

#: Temperature effects need at least this temperature span (degC) to be tested.
MIN_TEMP_SPAN_C = 1.0
#: Columns whose part orthogonal to the base is below this fraction of their norm are not excited.
EXCITATION_RTOL = 1e-6
#: Canonical correlation above which two effects' columns are called confounded in this session.
CONFOUNDED_CORR = 0.95
#: Rows kept (evenly spaced) of each candidate's columns for the confounding check.
CONFOUND_ROWS = 20000


def SUB(n: int) -> slice:  # noqa: N802
    return slice(None, None, max(1, -(-n // CONFOUND_ROWS)))


#: Calibration terms tested together with a constant when the base has none.
OFFSET_LIKE = ("session_offset", "drift", "temperature_offset")
#: Fewer held-out blocks than this: no significance claimed.
MIN_BLOCKS = 6
#: Sign-flip resamples (p resolution 2.5e-4, ample for Holm over ~12 effects at alpha 0.05).
N_RESAMPLES = 3999


@dataclass
class Trial:
    """One effect tried on held-out blocks."""

    effect: str
    kind: str                      # "linear", "delay", "hysteresis" or "joint" (mount_rotation)
    rmse_uT: np.ndarray            # (3,) out-of-fold
    resid: np.ndarray              # (N,3) out-of-fold residual
    block_sse: np.ndarray          # (B,) per block, uT^2
    p_value: float = 1.0
    p_holm: float = 1.0
    significant: bool = False
    shrink: float = 0.0
    columns: np.ndarray | None = None   # (N,k) the effect's own columns (for confounding checks)
    note: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def rmse_norm_uT(self) -> float:
        return float(np.linalg.norm(self.rmse_uT))

    @property
    def n_params(self) -> int:
        return int(self.extra.get("n_params", 0))


@dataclass
class Options:
    #: held-out block length in s; None: chosen from the data (blocks.choose_block_s)
    block_s: float | None = None
    exclude_bends: float | None = 10.0
    n_folds: int = 5
    alpha: float = 0.05
    min_shrink: float = 0.005
    seed: int = 0
    #: null model for slow noise: "surrogate" (the block test and the surrogate test must both reject,
    #: see surrogate.py) or "blocks" (the block test alone)
    null: str = "surrogate"
    #: keep rows with the reference at or beyond its range (default: left out and counted, as ``fit``)
    include_saturated: bool = False
    #: part whose datasheet priors decide what the session cannot (default: the session's ``dut_chip``)
    chip: str | None = None
    #: attitude knowledge (1 sd per axis, deg) in the reference error budget of orbit telemetry (orbit.py)
    attitude_sd_deg: float = 0.1


@dataclass
class Candidate:
    effect: str
    kind: str
    terms: tuple = ()                   # linear: calibration terms (columns built when evaluated)
    thresholds: list | None = None      # hysteresis candidates per axis
    lag_tau_s: float | None = None      # thermal lag: the time constant chosen on all rows (set by evaluate)


@dataclass
class SearchResult:
    baseline: Trial
    trials: list[Trial]
    not_testable: list[dict]
    modelled: list[str]
    verdict: str = "none"
    runner_up: str | None = None
    p_vs_runner_up: float | None = None
    distinguishable: bool | None = None
    confounded_with: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: the surrogate test's noise model (surrogate.SurrogateSource.summary) and its template, when it ran
    null_model: dict | None = None


# ----------------------------------------------------------------------------- helpers
def rms3(r: np.ndarray) -> np.ndarray:
    ok = np.all(np.isfinite(r), axis=1)
    return np.sqrt(np.mean(r[ok] ** 2, axis=0)) if ok.any() else np.full(3, np.nan)


def block_sse(r: np.ndarray, blocks: np.ndarray, nb: int) -> np.ndarray:
    sq = np.where(np.isfinite(r), r, 0.0) ** 2
    return np.bincount(blocks, weights=sq.sum(axis=1), minlength=nb)


def sign_flip_p(d: np.ndarray, seed: int = 0) -> float:
    """One-sided p-value of mean(d) > 0 by random sign flips of the block differences
    (``(1 + #{flipped mean >= observed}) / (1 + N_RESAMPLES)``), drawn in batches so memory stays
    bounded for any number of blocks (scipy.stats.permutation_test draws every flip at once)."""
    d = np.asarray(d, dtype=float)
    d = d[np.isfinite(d)]
    if d.size < MIN_BLOCKS or not np.any(d):
        return 1.0
    obs = float(np.mean(d))
    tol = 1e-12 * float(np.mean(np.abs(d)))
    batch = max(1, min(N_RESAMPLES, 2_000_000 // d.size))
    if batch == N_RESAMPLES and isinstance(seed, (int, np.integer)):   # one batch: the same signs for every
        # test with this seed and size (an int seed: the same draw every time)
        return (1 + int(np.sum(flip_signs(seed, d.size) @ d / d.size >= obs - tol))) / (1 + N_RESAMPLES)
    rng = np.random.default_rng(seed)
    hits, done = 0, 0
    while done < N_RESAMPLES:
        k = min(batch, N_RESAMPLES - done)
        signs = rng.integers(0, 2, size=(k, d.size), dtype=np.int8) * 2 - 1
        hits += int(np.sum(signs @ d / d.size >= obs - tol))
        done += k
    return (1 + hits) / (1 + N_RESAMPLES)


@functools.lru_cache(maxsize=4)
def flip_signs(seed: int, n: int) -> np.ndarray:
    """(N_RESAMPLES, n) random signs (int8, read-only): the first batch :func:`sign_flip_p` draws from ``seed``.
    A diagnosis tests a dozen effects on the same blocks with the same seed: drawn once, not per test."""
    s = np.random.default_rng(seed).integers(0, 2, size=(N_RESAMPLES, n), dtype=np.int8) * 2 - 1
    s.setflags(write=False)
    return s


#: Below this many test units the sign-flip test's attainable minimum (2^-n) cannot reach Holm's
#: levels (n = 6: 0.016 against 0.0056 for the first of 9 effects at alpha 0.05): Student's t on
#: the unit sums is used instead.
SIGN_FLIP_MIN_UNITS = 12


def unit_p(d: np.ndarray, seed: int = 0) -> float:
    """One-sided p-value of mean(d) > 0 over test units ``d``: the sign-flip test
    (:func:`sign_flip_p`) with at least SIGN_FLIP_MIN_UNITS units, else Student's one-sample t
    (``scipy.stats.ttest_1samp``), whose p is not bounded below by the number of units; fewer than
    MIN_BLOCKS units: 1."""
    d = np.asarray(d, dtype=float)
    d = d[np.isfinite(d)]
    if d.size >= SIGN_FLIP_MIN_UNITS or d.size < MIN_BLOCKS:
        return sign_flip_p(d, seed)
    if np.ptp(d) == 0:
        return 1.0 if d[0] <= 0 else 0.0
    return float(scipy.stats.ttest_1samp(d, 0.0, alternative="greater").pvalue)


def block_group(r: np.ndarray, blocks: np.ndarray, block_session: np.ndarray) -> int:
    """Blocks per test unit: ``ceil((1 + rho) / (1 - rho))`` from the lag-1 correlation ``rho`` of the
    block means of residual ``r`` (consecutive blocks of one session, averaged over axes), the inverse
    of the effective-sample-size factor of an AR(1) series. 1 when the block means are uncorrelated
    (white residual); larger when slow noise (1/f, random walk) makes neighbouring blocks alike."""
    nb = block_session.size
    if nb < 10 or r is None:
        return 1
    x = np.asarray(r, dtype=float)
    ok = np.all(np.isfinite(x), axis=1)
    cnt = np.bincount(blocks[ok], minlength=nb)
    m = np.column_stack([np.bincount(blocks[ok], weights=x[ok, j], minlength=nb) for j in range(3)])
    m = m / np.maximum(cnt, 1)[:, None]
    pair = (block_session[1:] == block_session[:-1]) & (cnt[1:] > 0) & (cnt[:-1] > 0)
    if pair.sum() < 8:
        return 1
    rhos = []
    for j in range(3):
        a, b = m[:-1, j][pair], m[1:, j][pair]
        if np.std(a) > 0 and np.std(b) > 0:
            rhos.append(float(np.corrcoef(a, b)[0, 1]))
    rho = float(np.mean(rhos)) if rhos else 0.0
    if rho <= 2.0 / np.sqrt(pair.sum()):   # not distinguishable from independence
        return 1
    rho = min(rho, 0.95)
    return int(np.ceil((1 + rho) / (1 - rho)))


def grouped(d: np.ndarray, block_session: np.ndarray, g: int) -> np.ndarray:
    """Sums of ``d`` over runs of ``g`` consecutive blocks of one session (the test units)."""
    if g <= 1:
        return d
    gid = np.zeros(d.size, dtype=np.int64)
    nxt = 0
    for k in np.unique(block_session):
        idx = np.flatnonzero(block_session == k)
        gid[idx] = nxt + np.arange(idx.size) // g
        nxt = int(gid[idx].max()) + 1
    return np.bincount(gid, weights=d)


#: A simpler candidate is preferred only when it closes at least this fraction of what the best closes.
PARSIMONY_MIN_CLOSED = 0.9


def closes_as_much(rmse_simple: float, rmse_best: float, baseline: float) -> bool:
    """True when the simpler candidate closes at least PARSIMONY_MIN_CLOSED of the held-out gap the best
    closes (``baseline - rmse``): never prefer a fit several times worse for its fewer parameters."""
    return baseline - rmse_simple >= PARSIMONY_MIN_CLOSED * (baseline - rmse_best)


def paired_worse_p(d: np.ndarray) -> float:
    """One-sided p of "the simpler candidate is worse" from per-unit SSE differences ``d`` (simpler minus
    best): Wilcoxon's signed-rank test, whose ranks one outlier block cannot dominate (Student's t on a few
    heavy-tailed units can be flipped by one). Fewer than MIN_BLOCKS units or no difference: 1."""
    d = np.asarray(d, dtype=float)
    d = d[np.isfinite(d) & (d != 0)]
    if d.size < MIN_BLOCKS:
        return 1.0
    return float(scipy.stats.wilcoxon(d, alternative="greater").pvalue)


def holm(p: list[float]) -> list[float]:
    """Holm step-down adjusted p-values."""
    m = len(p)
    order = np.argsort(p)
    adj = np.empty(m)
    run = 0.0
    for k, i in enumerate(order):
        run = max(run, min(1.0, (m - k) * p[i]))
        adj[i] = run
    return adj.tolist()


def orth_part(X: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Part of the columns of X orthogonal to the base columns (least squares)."""
    if base.shape[1] == 0 or X.shape[1] == 0:
        return X - X.mean(axis=0) * 0
    coef, *_ = np.linalg.lstsq(base, X, rcond=None)
    return X - base @ coef


def canonical_corr(A: np.ndarray, B: np.ndarray) -> float:
    """Largest canonical correlation between column spaces of A and B (0 if either is empty)."""
    def basis(M):
        if M.size == 0:
            return None
        u, s, _ = np.linalg.svd(M, full_matrices=False)
        keep = s > s.max() * 1e-8 if s.size else []
        return u[:, keep] if np.any(keep) else None
    qa, qb = basis(A), basis(B)
    if qa is None or qb is None:
        return 0.0
    return float(np.linalg.svd(qa.T @ qb, compute_uv=False).max(initial=0.0))


# ----------------------------------------------------------------------------- candidates
def build_candidates(gap: Gap, base: Block) -> tuple[list[Candidate], list[dict], list[str]]:
    """Testable candidates, not-testable effects with reasons, effects the simulator models."""
    cands, not_testable, modelled = [], [], []
    s = gap.session
    temp_ok = np.isfinite(s.temp_c)
    temp_span = float(np.ptp(s.temp_c[temp_ok])) if temp_ok.any() else 0.0
    base_terms = set(gap.base_terms)
    for name in EFFECT_NAMES:
        e = EFFECTS[name]
        if name in gap.modelled:
            modelled.append(name)
            # mode (a) fits the modelled effects; mode (b) holds them fixed, so a changed one is a candidate
            if gap.mode == "model" or e.cal_term in gap.base_terms:
                continue
        if name == "thermal_lag":
            if temp_span < MIN_TEMP_SPAN_C:
                not_testable.append({"effect": name, "reason": f"temperature spans {temp_span:.2f} degC "
                                                               f"(need {MIN_TEMP_SPAN_C:g} degC)"})
            elif not temp_ok.all():
                not_testable.append({"effect": name, "reason": f"no temperature on {int((~temp_ok).sum())} rows"})
            else:
                cands.append(Candidate(name, "lag"))
            continue
        if e.cal_term is None:
            not_testable.append({"effect": name, "reason": "no correction term in the catalogue (cal_term None): "
                                                           "it is part of the noise floor / data limits"})
            continue
        if e.cal_term in ("temperature_gain", "temperature_offset") and temp_span < MIN_TEMP_SPAN_C:
            not_testable.append({"effect": name, "reason": f"temperature spans {temp_span:.2f} degC "
                                                           f"(need {MIN_TEMP_SPAN_C:g} degC)"
                                 + ("" if temp_ok.any() else ": no temp_c values")})
            continue
        if name == "time_skew":
            cands.append(Candidate(name, "delay"))
            continue
        if name == "hysteresis":
            thr = nl.hysteresis_thresholds(*gap.history())
            if not any(thr):
                not_testable.append({"effect": name, "reason": "no large excursions: no |B| level well above "
                                                               "the session's typical field splits the rows into "
                                                               "two remanence states"})
                continue
            cands.append(Candidate(name, "hysteresis", thresholds=thr))
            continue
        terms = (e.cal_term,)
        if e.cal_term in OFFSET_LIKE and "offset" not in base_terms:
            # with no offset in the base (a fixed table, --sim, --model gain) the effect carries its constant:
            # a drift built up since the table was fitted has a non-zero mean, a temperature offset about
            # another pivot is K (T - T0) plus a constant, per-session offsets are effect-coded about one
            terms = ("offset", e.cal_term)
        if e.cal_term == "temperature_gain" and "temperature_offset" not in base_terms and not gap.forward:
            # a gain applied before the offset, inverted, leaves K_S dT O: a dT column (the calibration
            # direction only; forward, the catalogue's temperature gain acts before the offset)
            terms = ("temperature_gain", "temperature_offset")
        if e.cal_term == "mount_rotation" and s.metadata.get("reference") == "igrf":
            not_testable.append({"effect": name, "reason": "orbit telemetry (IGRF + attitude reference): a rotation "
                                                           "per power cycle is attitude knowledge error, part of "
                                                           "the reference's error budget, not a remount"})
            continue
        if e.cal_term == "mount_rotation":
            mc = rot.mount_columns(gap)
            if isinstance(mc, str):
                not_testable.append({"effect": name, "reason": mc})
                continue
            cands.append(Candidate(name, "joint"))
            continue
        if e.cal_term in JOINT_TERMS:
            not_testable.append({"effect": name, "reason": f"calibration term {e.cal_term!r} has no design columns "
                                                           "(its parameters couple the output axes): no diagnosis "
                                                           "estimator"})
            continue
        if e.cal_term == "currents" and not s.currents_A:
            not_testable.append({"effect": name, "reason": "the session has no current columns"})
            continue
        try:
            blk = linear_block(gap, name, terms)
        except FitError as exc:
            not_testable.append({"effect": name, "reason": str(exc)})
            continue
        except ValueError as exc:   # a calibration term the model does not know (catalogue ahead of the model)
            not_testable.append({"effect": name, "reason": f"no estimator for cal_term {e.cal_term!r}: {exc}"})
            continue
        if blk.p == 0:
            why = {"session_offset": "only one session", "currents": "no current columns"}.get(
                e.cal_term, "no columns")
            not_testable.append({"effect": name, "reason": why})
            continue
        ok = np.all(np.isfinite(blk.X), axis=1)
        if not ok.all():
            not_testable.append({"effect": name, "reason": f"its columns are not finite on {int((~ok).sum())} "
                                                           "rows (missing temperature or currents)"})
            continue
        if base.p and not _excited(blk.X, base.X):
            not_testable.append({"effect": name, "reason": "its columns are combinations of the base model's "
                                                           "columns in this session (not excited)"})
            continue
        cands.append(Candidate(name, "linear", terms=terms))
        del blk
    return cands, not_testable, modelled


#: Forward gap: effects the catalogue applies to the sensor-axis field (after ``gain``), whose columns are built
#: from the reference mapped into DUT units (``Gap._dut_image``), not from the reference itself: the cross-axis
#: term of bridge x during a 150 uT Y excursion carries G[x,y] x 150 uT of the excursion (a B_y^3 shape that
#: products of reference components for output x do not hold).
SENSOR_SPACE = ("cross_axis", "nonlinearity")


def linear_block(gap: Gap, name: str, terms) -> Block:
    """Columns of a linear candidate: its calibration terms plus, where the catalogue's forward physics
    seen from the calibration side needs them, higher-order columns (nonlinear.py)."""
    field = gap.predictor_uT
    if gap.forward and name in SENSOR_SPACE:
        field = gap.predictor_uT @ gap._dut_image().T
    blk = gap.term_design(terms, field)
    if name == "temperature_gain" and blk.p and not gap.forward:
        blk = Block.join([blk, temperature_gain_higher_order(gap, gap.session.temp_c)], gap.n)
    if name == "cross_axis" and blk.p:
        q = nl.second_order_cross_axis(field)
        m = np.zeros((3, 6), bool)
        for k in range(6):
            m[k // 2, k] = True
        blk = Block.join([blk, Block(q, m, [[f"Q[{o},{c}]" for o in "xyz" for c in "xyz" if c != o]] * 3,
                                     ["1/uT^2"] * 6)], gap.n)
    return blk


def temperature_gain_higher_order(gap: Gap, temp_c: np.ndarray) -> Block:
    """Columns the catalogue's forward temperature gain leaves on the calibration side beyond the first
    order (nonlinear.higher_order_temperature_gain: on-axis ``B dT^2``, ``B dT^3``), plus ``dT^2`` per axis:
    a gain applied before a temperature offset leaves ``K_S K_O dT^2`` when inverted (0.24 uT at -2700 ppm/degC,
    -140 nT/degC and 25 degC from the pivot)."""
    q = nl.higher_order_temperature_gain(gap.predictor_uT, temp_c, gap.t0_c)
    d2 = (np.asarray(temp_c, dtype=float) - gap.t0_c) ** 2
    mask = np.hstack([np.eye(3, dtype=bool)] * 2 + [np.ones((3, 1), bool)])
    names = [[f"K_S2[{a}]" for a in "xyz"] + [f"K_S3[{a}]" for a in "xyz"] + [f"K_O2[{o}]"] for o in "xyz"]
    return Block(np.column_stack([q, d2]), mask, names, ["1/degC^2"] * 3 + ["1/degC^3"] * 3 + ["uT/degC^2"])


#: Rows per chunk of the excitation check's QR.
EXCITATION_CHUNK = 65536


def _excited(X: np.ndarray, base: np.ndarray) -> bool:
    """Whether some column of X has a part orthogonal to the base columns above EXCITATION_RTOL of its norm.
    From the R factor of ``[base X]`` built chunk by chunk (R of ``[R_prev; chunk]``): the norms of R's
    lower-right block are those of X's columns after projecting out the base (the least-squares residual,
    as stable as the QR, with memory of one chunk)."""
    p = base.shape[1]
    R = np.zeros((0, p + X.shape[1]))
    for a in range(0, X.shape[0], EXCITATION_CHUNK):
        R = qr_r(np.vstack([R, np.hstack([base[a:a + EXCITATION_CHUNK], X[a:a + EXCITATION_CHUNK]])]))
    resid = np.linalg.norm(R[p:, p:], axis=0)
    return bool(np.any(resid > EXCITATION_RTOL * np.maximum(np.linalg.norm(R[:, p:], axis=0), 1e-300)))


def hysteresis_block(gap: Gap, thresholds: np.ndarray, initial: np.ndarray | None = None) -> Block:
    """State columns (one per axis with a finite threshold) from the excursion history
    (:meth:`Gap.history`), ``initial`` the state before each axis' first excursion."""
    hist, idx = gap.history()
    st = nl.hysteresis_state(hist, thresholds, initial)[idx]
    # the remanence is a vector: the state of axis j (its last excursion's sign) shifts every output axis
    # (magnetised material near the sensor; an independent generator's 10 nT cross-remanence otherwise left
    # the hysteresis fit 1.4x the floor and per-session offsets, fitting each cycle's vector, ahead)
    mask = np.ones((3, 3), dtype=bool)
    names = [[f"H[{o}<-{a}]" for a in "xyz"] for o in "xyz"]
    blk = Block(st, mask, names, ["uT"] * 3)
    keep = np.isfinite(thresholds)
    blk = Block(st[:, keep], mask[:, keep], [[n for n, k in zip(r, keep, strict=True) if k] for r in names],
                [u for u, k in zip(blk.units, keep, strict=True) if k])
    if "offset" not in gap.base_terms:
        off = gap.term_design(("offset",))
        blk = Block.join([off, blk], gap.n)
    return blk


#: An axis' hysteresis state counts as used when some output's remanence coefficient is this many standard errors
#: (OLS, all rows) from 0.
HYSTERESIS_AXIS_T = 3.0


def hysteresis_axes_used(gap: Gap, base: Block, Y: np.ndarray, thr: np.ndarray, init: np.ndarray) -> list[int]:
    """Axes whose state column (thresholds ``thr``, initial states ``init``, all rows) carries a remanence: some
    output's coefficient beyond HYSTERESIS_AXIS_T OLS standard errors in base + hysteresis_block on all rows."""
    blk = hysteresis_block(gap, thr, init)
    # normal equations accumulated in row chunks (the joined N-row design is never formed)
    GC = fold_products([base.X, blk.X], [base.X, blk.X, Y], np.zeros(gap.n, dtype=np.int64), 1)[0]
    p = base.p + blk.p
    G, C = GC[:, :p], GC[:, p:]
    mask = np.hstack([base.mask, blk.mask])
    th = solve_gram(G, C, mask)
    yy = np.sum(Y ** 2, axis=0)
    axes = [j for j in range(3) if np.isfinite(thr[j])]
    first = p - len(axes)                       # the state columns come last, in axis order
    z = np.zeros((3, len(axes)))
    for i in range(3):
        cols = np.flatnonzero(mask[i])
        Gi = G[np.ix_(cols, cols)]
        t = th[i, cols]
        s2 = max(float(yy[i] - 2 * t @ C[cols, i] + t @ Gi @ t), 0.0) / max(gap.n - cols.size, 1)
        d = np.sqrt(np.diag(Gi))
        d[d == 0] = 1.0
        cov = np.linalg.pinv(Gi / np.outer(d, d), rcond=RCOND, hermitian=True) / np.outer(d, d)
        for k in range(len(axes)):
            c = int(np.flatnonzero(cols == first + k)[0])
            se = np.sqrt(max(cov[c, c], 0.0) * s2)
            z[i, k] = abs(t[c]) / se if se > 0 else 0.0
    return [j for k, j in enumerate(axes) if np.max(z[:, k]) >= HYSTERESIS_AXIS_T]


def hysteresis_options(gap: Gap, cands: list, j: int, which: Sequence[int] | None = None) -> np.ndarray:
    """(N, 2 x len(which)) axis j's state column (:func:`nonlinear.hysteresis_state`) on the gap's rows for
    the thresholds ``cands[j][which]`` (all by default), each with the initial state -1 then +1. The state is
    the same for both initial states after the axis' first excursion, so each threshold's history is scanned
    once. All of an axis' options are kept on the gap (the search asks for them once per fold) when they hold
    at most HYST_OPTION_FLOATS floats (short sessions)."""
    cache = gap.__dict__.setdefault("_hyst_options", {})
    key = (j, tuple(float(c) for c in cands[j]))
    if key in cache:
        return cache[key] if which is None else cache[key][:, [2 * k + m for k in which for m in (0, 1)]]
    which = list(range(len(cands[j]))) if which is None else list(which)
    whole = len(which) == len(cands[j]) and 2 * len(which) * gap.n + sum(v.size for v in cache.values()) \
        <= HYST_OPTION_FLOATS
    hist, idx = gap.history()
    out = np.empty((gap.n, 2 * len(which)))
    for i, k in enumerate(which):
        one = np.full(3, np.inf)
        one[j] = cands[j][k]
        st = nl.hysteresis_state(hist, one)[idx, j]           # 0 before the first excursion
        before = st == 0
        out[:, 2 * i] = np.where(before, -1.0, st)
        out[:, 2 * i + 1] = np.where(before, 1.0, st)
    if whole:
        cache[key] = out
    return out


#: Floats of hysteresis option columns a gap keeps between folds (:func:`hysteresis_options`), and at most
#: formed at once by :func:`choose_thresholds` (the options of a long session are taken a few at a time).
HYST_OPTION_FLOATS = 1_000_000


def choose_thresholds(gap: Gap, base: Block, Y: np.ndarray, cands: list, rows: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Per axis (axis by axis), the candidate threshold and the initial state (-1 or +1: the unknown
    remanence before the axis' first excursion) with the lowest training SSE on ``rows`` of base +
    hysteresis_block (the axes decided before and the trial one); the first option on ties.

    Every option adds one column ``u`` (the same to every output axis) to a design ``A`` that is the same for
    all of them (the base, the constant hysteresis_block adds when the base lacks one, the state columns of
    the axes decided before; kept as two blocks, its products formed block by block). So per output axis
    ``A`` is solved once, for its target and for all options' ``A^T u`` together, and each option's SSE
    reduction follows from the Schur complement:
    ``(u.y - (A^T u).theta)^2 / (u.u - (A^T u).(A^T A)^-1 A^T u)`` (none where the column lies in A's span to
    the solver's RCOND, as its pseudo-inverse gives). Options are formed in groups of at most
    HYST_OPTION_FLOATS floats (all at once for a short session)."""
    sel = np.flatnonzero(rows) if rows.dtype == bool else rows
    Xb, mb = base.X[sel], base.mask
    if "offset" not in gap.base_terms:      # hysteresis_block carries the constant the base lacks
        off = gap.term_design(("offset",))
        Xb, mb = np.hstack([Xb, off.X[sel]]), np.hstack([mb, off.mask])
    Yr = Y[sel]
    thr = np.full(3, np.inf)
    init = np.ones(3)
    Gb, Cb = Xb.T @ Xb, Xb.T @ Yr
    E = np.zeros((sel.size, 0))              # state columns of the axes decided so far (A = [Xb E], never joined)
    mA = mb
    for j in range(3):
        n_thr = len(cands[j])
        if not n_thr:
            continue
        XE = Xb.T @ E
        G = np.block([[Gb, XE], [XE.T, E.T @ E]])
        AY = np.vstack([Cb, E.T @ Yr])
        groups: dict[bytes, list[int]] = {}
        for i in range(3):
            groups.setdefault(mA[i].tobytes(), []).append(i)
        per = max(1, int(HYST_OPTION_FLOATS // (2 * max(gap.n, 1))))      # thresholds per group
        best_red, best_k, best_col = -np.inf, -1, None
        for g0 in range(0, n_thr, per):
            which = range(g0, min(g0 + per, n_thr))
            U = hysteresis_options(gap, cands, j, which if per < n_thr else None)[sel]      # (rows, K)
            AU = np.vstack([Xb.T @ U, E.T @ U])
            uu, uy = np.einsum("ij,ij->j", U, U), U.T @ Yr                                  # (K,), (K, 3)
            red = np.zeros(U.shape[1])
            for axes in groups.values():
                m = np.flatnonzero(mA[axes[0]])
                sol = solve_normal(G[np.ix_(m, m)], np.hstack([AY[np.ix_(m, axes)], AU[m]]))
                theta, W = sol[:, :len(axes)], sol[:, len(axes):]
                s = uu - np.einsum("ij,ij->j", AU[m], W)              # the new column's part outside span(A)
                z = uy[:, axes] - AU[m].T @ theta                     # (K, axes): its product with the residual
                inside = ~(s > RCOND * uu)
                red += np.where(inside, 0.0, np.sum(z * z, axis=1) / np.where(inside, 1.0, s))
            red = np.where(np.isfinite(red), red, -np.inf)
            k = int(np.argmax(red))
            if red[k] > best_red:                                     # the first option on ties
                best_red, best_k, best_col = red[k], 2 * g0 + k, U[:, k].copy()
        if best_col is None:
            continue
        thr[j], init[j] = cands[j][best_k // 2], (-1.0, 1.0)[best_k % 2]
        E = np.hstack([E, best_col[:, None]])
        mA = np.hstack([mA, np.ones((3, 1), bool)])
    return thr, init


def delay_sse_fn(gap: Gap, rows: np.ndarray):
    """Training SSE of the base refitted on the DUT reading de-skewed by delays ``d`` (3,) s.

    Where the de-skew moves only the target (the forward gap, a fixed prediction: ``Gap.deskew_J``), the
    base design is the same for every delay: its rows and Gram matrix are formed once, and each trial costs
    two products of the N x p design instead of rebuilding and re-factoring it (the same normal equations,
    the same residual)."""
    if gap.deskew_J is not None:
        base = gap.base_design()
        Xr = base.X[rows]
        G = Xr.T @ Xr

        def sse_fixed_design(d):
            _, Y = gap.deskewed(gap.skew_columns(d, nl.shift_axes), base)
            Yr = Y[rows]
            th = solve_gram(G, Xr.T @ Yr, base.mask)
            return float(np.sum((Yr - predict(Xr, th, base.mask)) ** 2))
        return sse_fixed_design

    def sse_of(d):
        blk, Y = gap.deskewed(gap.skew_columns(d, nl.shift_axes))
        th = solve(blk.X, Y, blk.mask, rows)
        return float(np.sum((Y[rows] - predict(blk.X[rows], th, blk.mask)) ** 2))
    return sse_of


def delay_searches(gap: Gap, fold: np.ndarray, grid: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Delays (3,) s minimising the training SSE with each fold left out (in ``np.unique(fold)`` order) and
    on all rows: what ``nonlinear.search_delays(delay_sse_fn(gap, rows), grid)`` finds for each row set.

    Where the de-skew moves only the target and each target axis only by its own delay (a diagonal
    ``Gap.deskew_J``: the forward gap, the simulator adapter), each axis' least squares and so its SSE
    depend on that axis' delay alone; the coordinate search then ends where one sweep per axis ends, and
    every row set needs the same grid columns. So each grid delay's shifted reference is formed once and
    reduced to per-fold sums (``X_f^T F``, ``t_f . F``, ``F . F``), from which every row set's SSE per axis
    follows by small solves: 15 interpolations instead of ~540 full-data refits. Otherwise (a table's
    gain matrix couples the axes) the coordinate search runs per row set."""
    folds = np.unique(fold)
    J = gap.deskew_J
    if J is None or np.any(J - np.diag(np.diag(J))):
        every = [delay_sse_fn(gap, fold != f) for f in folds] + [delay_sse_fn(gap, np.ones(gap.n, bool))]
        found = [nl.search_delays(fn, grid) for fn in every]
        return found[:-1], found[-1]
    jd = np.diag(J)
    base = gap.base_design()
    code = np.searchsorted(folds, fold)                              # fold index 0..folds-1 per row
    X, t0 = base.X, gap.target
    G = fold_products(X, X, code, folds.size)                        # (folds, p, p)
    Xt = fold_products(X, t0, code, folds.size)                      # (folds, p, 3)
    tt = np.column_stack([np.bincount(code, t0[:, i] ** 2, folds.size) for i in range(3)])
    sets = [np.arange(folds.size) != k for k in range(folds.size)] + [np.ones(folds.size, bool)]
    XF = np.empty((grid.size, folds.size, X.shape[1], 3))
    tF, FF = np.empty((grid.size, folds.size, 3)), np.empty((grid.size, folds.size, 3))
    for g, d in enumerate(grid):
        F = gap.skew_columns(np.full(3, d), nl.shift_axes, cache=False)
        XF[g] = fold_products(X, F, code, folds.size)                # (folds, p, 3)
        tF[g] = np.column_stack([np.bincount(code, t0[:, i] * F[:, i], folds.size) for i in range(3)])
        FF[g] = np.column_stack([np.bincount(code, F[:, i] ** 2, folds.size) for i in range(3)])
        del F
    sse = np.zeros((len(sets), 3, grid.size))
    for e, use in enumerate(sets):                  # per row set and axis one factorisation for every delay
        Ge = G[use].sum(axis=0)
        c = Xt[use].sum(axis=0)[None] + XF[:, use].sum(axis=1) * jd[None, None, :]          # (grid, p, 3)
        yy = tt[use].sum(axis=0) + 2 * jd * tF[:, use].sum(axis=1) + jd ** 2 * FF[:, use].sum(axis=1)
        for i in range(3):
            m = np.flatnonzero(base.mask[i])
            ci = c[:, m, i].T                                                                  # (p_i, grid)
            th = solve_normal(Ge[np.ix_(m, m)], ci) if m.size else np.zeros((0, grid.size))
            sse[e, i] = yy[:, i] - np.sum(th * ci, axis=0)
    found = [np.array([nl.parabola_minimum(grid, sse[e, i]) for i in range(3)]) for e in range(len(sets))]
    return found[:-1], found[-1]


# ----------------------------------------------------------------------------- evaluation
def oof_residual(gap: Gap, blk: Block | list[Block], Y: np.ndarray, fold: np.ndarray) -> np.ndarray:
    """Out-of-fold residual (N,3) of ``blk`` (or of the blocks of a list side by side, never joined into one
    N-row design; jointly with the modelled mount rotation, if any)."""
    if gap.rotation is None:
        return out_of_fold_blocks(blk if isinstance(blk, list) else [blk], Y, fold)
    mc, sigma = gap.rotation
    return rot.out_of_fold(Block.join(blk, gap.n) if isinstance(blk, list) else blk, mc, Y, fold, sigma)[0]


def fold_residual(gap: Gap, blk: Block, Y: np.ndarray, train: np.ndarray, test: np.ndarray) -> np.ndarray:
    """Residual on ``test`` rows of ``blk`` fitted on ``train`` rows (jointly with a modelled rotation)."""
    if gap.rotation is None:
        th = solve(blk.X, Y, blk.mask, train)
        return Y[test] - predict(blk.X[test], th, blk.mask)
    mc, sigma = gap.rotation
    return rot.train_test_residual(blk, mc, Y, sigma, train, test)


def evaluate(gap: Gap, cand: Candidate, base: Block, fold: np.ndarray, blocks: np.ndarray, nb: int,
             base_trial: Trial, opts: Options) -> Trial:
    Y = gap.target
    if cand.kind == "linear":
        own = linear_block(gap, cand.effect, cand.terms)
        r = oof_residual(gap, [base, own], Y, fold)
        cols = own.X
        n_par = int(own.mask.sum())
        del own
    elif cand.kind == "hysteresis":
        r = np.full(Y.shape, np.nan)
        fold_thr = []
        for f in np.unique(fold):
            test, train = fold == f, fold != f
            thr, init = choose_thresholds(gap, base, Y, cand.thresholds, train)
            fold_thr.append(thr)
            blk = Block.join([base, hysteresis_block(gap, thr, init)], gap.n)
            r[test] = fold_residual(gap, blk, Y, train, test)
        hist, idx = gap.history()
        thr_all = choose_thresholds(gap, base, Y, cand.thresholds, np.ones(gap.n, bool))
        cols = nl.hysteresis_state(hist, *thr_all)[idx]
        telling = nl.before_first_excursion(hist, idx, thr_all[0], gap.session.session)
        hyst_axes = hysteresis_axes_used(gap, base, Y, *thr_all)
    elif cand.kind == "joint":   # mount_rotation (rotation.py)
        mc = rot.mount_columns(gap)
        r, angles = rot.out_of_fold(base, mc, Y, fold, base_trial.rmse_uT)
        cols = mc.flat(np.arange(gap.n)[SUB(gap.n)])
        n_par = mc.q
    elif cand.kind == "lag":   # thermal lag: tau chosen per fold by training SSE, like the delay (lag.py)
        coarse = nl.lag_grid(gap.session.t_s, gap.session.session)
        tr = lg.train_sse(gap, base, Y, fold, coarse)
        # a fine grid between the neighbours of the best coarse point (summed over folds), where the
        # parabola's error is far below the held-out effect of a wrong time constant
        k = int(np.argmin(tr.sum(axis=0)))
        fine = np.geomspace(coarse[max(k - 1, 0)], coarse[min(k + 1, coarse.size - 1)], nl.LAG_FINE_POINTS)
        grid = np.unique(np.r_[coarse, fine])
        tr = np.hstack([tr, lg.train_sse(gap, base, Y, fold, fine)])[:, np.argsort(np.r_[coarse, fine])]
        keep = np.r_[True, np.diff(np.sort(np.r_[coarse, fine])) > 0]
        tr = tr[:, keep]
        folds = np.unique(fold)
        fold_tau = [nl.refine_log_minimum(grid, tr[i]) for i in range(folds.size)]
        r = np.full(Y.shape, np.nan)
        fold_delta = [None] * folds.size
        for tau in set(fold_tau):
            dz = lg.design(gap, tau)
            ft = lg.fits(gap, base, Y, fold, dz)
            for i, (f, t_f) in enumerate(zip(folds, fold_tau, strict=True)):
                if t_f == tau:
                    test = np.flatnonzero(fold == f)
                    r[test] = Y[test] - lg.predict(base, dz, ft.theta[i], ft.delta[i], test)
                    fold_delta[i] = ft.delta[i]
        # all rows: each row is in the training set of all folds but its own: the sum over folds orders the
        # time constants as the training SSE on all rows would, without another pass
        cand.lag_tau_s = nl.refine_log_minimum(grid, tr.sum(axis=0))
        dz = lg.design(gap, cand.lag_tau_s)
        cols = dz.lag.X
        n_par = int(dz.lag.mask.sum()) + 1 + dz.R
    else:   # delay
        r = np.full(Y.shape, np.nan)
        grid = nl.delay_grid(gap.session.t_s)
        fold_d, all_d = delay_searches(gap, fold, grid)
        folds = np.unique(fold)
        fixed = gap.deskew_J is not None and gap.rotation is None
        if fixed:   # the design does not move with the delay: its fold Gram matrices once, no N-row copies
            code = np.searchsorted(folds, fold)
            Gf = fold_products(base.X, base.X, code, folds.size)
        for k, (f, d) in enumerate(zip(folds, fold_d, strict=True)):
            test, train = fold == f, fold != f
            blk, Yd = gap.deskewed(gap.skew_columns(d, nl.shift_axes, cache=False), base)
            if fixed:
                Cf = fold_products(base.X, Yd, code, folds.size)
                th = solve_gram(Gf.sum(axis=0) - Gf[k], Cf.sum(axis=0) - Cf[k], base.mask)
                r[test] = Yd[test] - predict(base.X[test], th, base.mask)
            else:
                r[test] = fold_residual(gap, blk, Yd, train, test)
            del blk, Yd
        gap.__dict__.pop("_skew_cache", None)       # the searched delays' columns are not used again
        # the time_skew term's columns (dB/dt of the predictor), without the calibration model's full design
        cols = time_derivative(gap.predictor_uT, gap.session.t_s, gap.session.session)
    sse = block_sse(r, blocks, nb)
    # the confounding check's rows copied out (a strided view would keep the whole N x q design alive)
    t = Trial(cand.effect, cand.kind, rms3(r), r.astype(np.float32), sse,
              columns=cols if cand.kind == "joint" else np.array(cols[SUB(gap.n)]))
    if cand.kind == "linear":
        t.extra["terms"] = cand.terms
        t.extra["n_params"] = n_par
    elif cand.kind == "lag":
        t.extra.update(n_params=n_par, fold_tau_s=fold_tau, tau_s=cand.lag_tau_s, grid_s=grid,
                       fold_delta_c=fold_delta, restarts=dz.R)
    elif cand.kind == "joint":
        t.extra["n_params"] = n_par
        t.extra["fold_angles_rad"] = angles
        t.note = "; ".join(([mc.frame_note] if mc.frame_note else []) + [f"held at 0: {h}" for h in mc.held])
    elif cand.kind == "delay":
        t.extra["fold_delays_s"] = fold_d
        t.extra["delay_s"] = all_d
        t.extra["n_params"] = 3
        t.extra["grid_s"] = grid
    elif cand.kind == "hysteresis":
        t.extra["fold_thresholds_uT"] = fold_thr
        t.extra["telling_rows"] = telling
        # one remanence vector per axis whose state the fit uses (the threshold and the initial sign are choices
        # among a few options, like the delay grid), plus the constant when the base has none; an axis whose state
        # column fits nothing (its excursions leave no remanence) is not a parameter the explanation needs
        t.extra["hysteresis_axes"] = ["xyz"[j] for j in hyst_axes]
        t.extra["n_params"] = 3 * max(len(hyst_axes), 1) + (0 if "offset" in gap.base_terms else 3)
    b = base_trial.rmse_norm_uT
    t.shrink = float(1.0 - t.rmse_norm_uT / b) if b > 0 else 0.0
    return t


def surrogate_tests(gap: Gap, cands: list[Candidate], trials: list[Trial], base: Block, fold: np.ndarray,
                    template: np.ndarray, opts: Options) -> dict | None:
    """Second test for every candidate the block test lets through (raw p < alpha): noise with the
    residual's own spectrum must not explain its held-out shrink
    (surrogate.py). ``p_value`` becomes the larger of the two (both must reject). Returns the noise
    model's summary (None when no candidate needed the test)."""
    from magstack.ground.diagnose.surrogate import surrogate_tests as run
    # every effect with raw p < alpha, also below the practical threshold: an unchecked small p_blocks
    # would still take Holm's first slot and ease the others' correction
    todo = [(c, t) for c, t in zip(cands, trials, strict=True) if t.p_value < opts.alpha]
    if not todo:
        return None
    res, model = run(gap, [c for c, _ in todo], base, fold, template, opts.alpha / max(len(trials), 1),
                     seed=opts.seed)
    for (_, t), r in zip(todo, res, strict=True):
        t.extra["surrogate"] = r
        t.p_value = max(t.p_value, r.p_value)
    return model


def hysteresis_or_session_offset(h: Trial, so: Trial, blocks: np.ndarray, block_session: np.ndarray, alpha: float,
                                 baseline_rmse_uT: float) -> tuple[Trial | None, str | None, dict | None]:
    """Hysteresis against per-session offsets, both significant: they differ on the rows of a power cycle
    before its first excursion (the remanence carried over from the previous cycle against the cycle's
    own constant; after it both are constant until the next excursion). The signed-rank test on the
    per-block held-out SSE differences over those rows decides when it rejects either way. Otherwise they are
    compared on every held-out block (grouped units, both ways): when neither is better there the held-out errors
    tie (a near-tie: a state flipping once per power cycle is a per-session offset but for those few rows) and
    parsimony decides: the one with fewer parameters (hysteresis: one remanence vector per axis whose state the
    fit uses; per-session offsets: one vector per session beyond the first) is named; when one is better on
    every block it is named. Returns (choice or None: no decision here, note, the comparison for the JSON)."""
    tell = h.extra.get("telling_rows")
    if tell is None or h.resid is None or so.resid is None or not tell.any():
        return None, None, None
    nb = block_session.size
    sse = [np.bincount(blocks[tell], weights=np.sum(np.nan_to_num(np.asarray(t.resid, float)[tell]) ** 2, axis=1),
                       minlength=nb) for t in (h, so)]
    used = np.bincount(blocks[tell], minlength=nb) > 0
    d = (sse[1] - sse[0])[used]              # > 0: hysteresis better on the telling rows
    n_tell = int(tell.sum())
    p_tell = (paired_worse_p(d), paired_worse_p(-d))      # (session_offset worse, hysteresis worse)
    g = max(h.extra.get("group", 1), so.extra.get("group", 1))
    d_all = grouped(so.block_sse - h.block_sse, block_session, g)
    p_all = (paired_worse_p(d_all), paired_worse_p(-d_all))
    info = {"effects": ["hysteresis", "session_offset"], "rmse_nT": [h.rmse_norm_uT * 1e3, so.rmse_norm_uT * 1e3],
            "n_params": [h.n_params, so.n_params], "telling_rows": n_tell,
            "p_telling_rows": {"session_offset_worse": p_tell[0], "hysteresis_worse": p_tell[1]},
            "p_all_blocks": {"session_offset_worse": p_all[0], "hysteresis_worse": p_all[1]}}
    if p_tell[0] < alpha:
        info["decided_by"] = "telling rows"
        return h, (f"hysteresis and session_offset compared on the {n_tell} rows before the first excursion of each "
                   "power cycle (where they differ): hysteresis predicts them better"), info
    if p_tell[1] < alpha:
        info["decided_by"] = "telling rows"
        return so, (f"hysteresis and session_offset compared on the {n_tell} rows before the first excursion of "
                    "each power cycle (where they differ): session_offset predicts them better"), info
    if p_all[0] < alpha or p_all[1] < alpha:
        better = h if p_all[0] < alpha else so
        info["decided_by"] = "all held-out blocks"
        return better, (f"hysteresis and session_offset are not told apart on the {n_tell} rows before each power "
                        f"cycle's first excursion; on every held-out block {better.effect} is better "
                        f"(p = {min(p_all):.2g})"), info
    simple, rich = (h, so) if h.n_params < so.n_params else (so, h)
    info["near_tie"] = True
    if simple.n_params < rich.n_params:
        info["decided_by"] = "parsimony"
        what = {"hysteresis": "one remanence vector per axis with a state", "session_offset": "one offset vector per "
                "session beyond the first"}
        return simple, (f"near-tie: hysteresis {h.rmse_norm_uT * 1e3:.1f} nT and session_offset "
                        f"{so.rmse_norm_uT * 1e3:.1f} nT held out are not told apart on the {n_tell} rows before each "
                        f"power cycle's first excursion (p = {min(p_tell):.2g}) nor on all held-out blocks "
                        f"(p = {min(p_all):.2g}): parsimony names {simple.effect} ({simple.n_params} parameters, "
                        f"{what[simple.effect]}) over {rich.effect} ({rich.n_params}, {what[rich.effect]})"), info
    info["decided_by"] = None
    return None, (f"near-tie: hysteresis and session_offset ({h.n_params} parameters each) are not told apart "
                  f"(held out {h.rmse_norm_uT * 1e3:.1f} and {so.rmse_norm_uT * 1e3:.1f} nT)"), info


def choose_verdict(sig: list[Trial], baseline_rmse_uT: float, block_session: np.ndarray, alpha: float,
                   blocks: np.ndarray | None = None) -> tuple[Trial, str | None]:
    """The verdict among significant trials ``sig`` (sorted by held-out RMSE): the best, unless a
    candidate with fewer parameters closes as much of the gap (:func:`closes_as_much`) and is not
    significantly worse by the signed-rank test on the grouped block SSE differences
    (:func:`paired_worse_p`); then the simpler is named, with a note. Hysteresis against per-session
    offsets is decided on the rows that tell them apart (:func:`hysteresis_or_session_offset`; needs
    ``blocks``, the block id per row)."""
    v = sig[0]
    pair = {t.effect: t for t in sig if t.effect in ("hysteresis", "session_offset")}
    if len(pair) == 2 and v.effect in pair and blocks is not None:
        choice, note, info = hysteresis_or_session_offset(pair["hysteresis"], pair["session_offset"], blocks,
                                                          block_session, alpha, baseline_rmse_uT)
        if info is not None:
            v.extra["hysteresis_vs_session_offset"] = info
            if choice is not None:
                choice.extra["hysteresis_vs_session_offset"] = info
        if choice is not None:
            return choice, note
        tie_note = note
    else:
        tie_note = None
    for t in sorted(sig[1:], key=lambda t: (t.n_params, t.rmse_norm_uT)):
        g = max(t.extra.get("group", 1), v.extra.get("group", 1))
        if (t.n_params < v.n_params and closes_as_much(t.rmse_norm_uT, v.rmse_norm_uT, baseline_rmse_uT)
                and paired_worse_p(grouped(t.block_sse - v.block_sse, block_session, g)) >= alpha):
            return t, (f"{t.effect} ({t.n_params} parameters) explains the gap as well as {v.effect} "
                       f"({v.n_params}) on held-out blocks: the simpler one is named")
    return v, tie_note


#: Held-out residuals kept while searching: the lowest-RMSE ones (the test template, the noise floor) and
#: those choose_verdict compares row by row; a verdict's dropped residual is evaluated again.
RESID_KEPT_BEST = 2
RESID_KEPT_EFFECTS = ("hysteresis", "session_offset")


def drop_residuals(trials: list[Trial]) -> None:
    """Free the (N,3) held-out residuals no later step reads (memory: 12 B/row per candidate)."""
    best = sorted(trials, key=lambda t: t.rmse_norm_uT)[:RESID_KEPT_BEST]
    for t in trials:
        if t.effect not in RESID_KEPT_EFFECTS and not any(t is b for b in best):
            t.resid = None


def search(gap: Gap, blocks: np.ndarray, fold: np.ndarray, opts: Options) -> SearchResult:
    nb = int(blocks.max()) + 1
    base = gap.base_design()
    if base.p:
        r0, _ = out_of_fold(base.X, gap.target, base.mask, fold)
    else:
        r0 = gap.target.copy()
    if gap.mode == "model" and "mount_rotation" in gap.modelled:
        mc = rot.mount_columns(gap)
        if isinstance(mc, str):
            raise DiagnosisError(f"--model names mount_rotation, but it cannot be fitted on this data: {mc}")
        # weights of the stacked joint problem: the per-axis held-out RMS without the rotation
        gap.rotation = (mc, rms3(r0))
        r0 = oof_residual(gap, base, gap.target, fold)
    baseline = Trial("baseline", "base", rms3(r0), r0.astype(np.float32), block_sse(r0, blocks, nb))
    del r0
    bs = np.zeros(nb, dtype=np.int64)
    bs[blocks] = gap.session.session
    baseline.extra["block_session"] = bs
    cands, not_testable, modelled = build_candidates(gap, base)
    trials = []
    for c in cands:
        trials.append(evaluate(gap, c, base, fold, blocks, nb, baseline, opts))
        drop_residuals(trials)
    # one test unit for every candidate, from the residual closest to the noise (the lowest held-out
    # RMSE found): the unit describes the noise's autocorrelation under "nothing unmodelled"; taken
    # from each candidate's own residual, a candidate's remaining misfit would lengthen its own unit
    # and could make a large, real shrink untestable on a short session
    best = min([baseline, *trials], key=lambda t: t.rmse_norm_uT)
    template = np.asarray(best.resid, dtype=float)
    g_unit = block_group(template, blocks, bs)
    # with the surrogate null model the block test's unit is one block (the surrogates carry the slow noise)
    g_test = 1 if opts.null == "surrogate" else g_unit
    for t in trials:
        t.extra["group"] = g_unit
        t.extra["test_unit"] = g_test
        t.p_value = unit_p(grouped(baseline.block_sse - t.block_sse, bs, g_test), opts.seed)
        t.extra["p_blocks"] = t.p_value
    model = surrogate_tests(gap, cands, trials, base, fold, template, opts) if opts.null == "surrogate" else None
    res = SearchResult(baseline, trials, not_testable, modelled)
    if model is not None:
        res.null_model = {"template": best.effect, **model}
    if len(np.unique(blocks)) < MIN_BLOCKS:
        res.notes.append(f"only {len(np.unique(blocks))} held-out blocks of {opts.block_s:g} s: too few for a "
                         "significance claim (shorten --block-s or add data)")
    if trials:
        adj = holm([t.p_value for t in trials])
        for t, a in zip(trials, adj, strict=True):
            t.p_holm = a
            t.significant = bool(a < opts.alpha and t.shrink >= opts.min_shrink)
    trials.sort(key=lambda t: t.rmse_norm_uT)
    sig = [t for t in trials if t.significant]
    if sig:
        v, note = choose_verdict(sig, baseline.rmse_norm_uT, bs, opts.alpha, blocks)
        if note:
            res.notes.append(note)
        trials.remove(v)
        trials.insert(0, v)
        res.verdict = v.effect
        if v.resid is None:     # dropped while searching (drop_residuals): the same evaluation again
            v.resid = evaluate(gap, cands[[c.effect for c in cands].index(v.effect)], base, fold, blocks, nb,
                               baseline, opts).resid
        others = [t for t in trials if t is not v]
        if others:
            ru = others[0]
            res.runner_up = ru.effect
            g = max(ru.extra.get("group", 1), v.extra.get("group", 1))
            res.p_vs_runner_up = unit_p(grouped(ru.block_sse - v.block_sse, bs, g), opts.seed)
            bx = base.X[SUB(gap.n)]
            corr = canonical_corr(orth_part(v.columns, bx), orth_part(ru.columns, bx))
            res.distinguishable = bool(res.p_vs_runner_up < opts.alpha and corr < CONFOUNDED_CORR)
            for t in others:
                c = canonical_corr(orth_part(v.columns, bx), orth_part(t.columns, bx))
                if c >= CONFOUNDED_CORR:
                    res.confounded_with.append(t.effect)
    keep = {res.verdict, res.runner_up} | {t.effect for t in trials[:1]}
    for t in trials:
        if t.effect not in keep:
            t.resid = None
    return res
