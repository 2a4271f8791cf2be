"""Streaming fit: QR accumulation by block, memory independent of the sample count.

Each block's weighted ``[X | Y]`` is stacked under the running upper-triangular ``R``
(``(p+3) x (p+3)``) and re-factorised, so ``R^T R`` always equals the Gram matrix of all
rows seen (QR avoids squaring the condition number, unlike normal equations). Solving
uses the same MAP estimator (:mod:`.estimator`), priors and gating as the batch :func:`fit`;
the residual autocorrelation cannot be measured from R alone, so rows count as independent
(``kappa`` 1) unless ``kappa`` is given to :meth:`StreamingFit.solve`.

Limits (raise FitError): the model is fixed before the first block (sessions for
``session_offset`` and ``t_ref_s`` for ``drift`` must be given up front); ``time_skew``
(needs neighbouring samples across blocks) and robust IRLS (needs all residuals)
are batch-only. Held-out errors and the noise floor need the data again: they are
not produced here.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from magstack.firmware.blas import single_thread
from magstack.firmware.cal_terms import TEMPERATURE_TERMS
from magstack.firmware.calibration.fit import (
    Coverage,
    FitOptions,
    FitResult,
    _prior_name,
    build_prior,
    gate_solve,
    identify,
    prior_determined,
    qr_r,
)
from magstack.firmware.calibration.identify import GATE_RULES
from magstack.firmware.calibration.model import CalModel
from magstack.firmware.errors import FitError


class StreamingFit:
    """Accumulate blocks with :meth:`add`, then :meth:`solve`."""

    def __init__(self, model: CalModel, options: FitOptions | None = None) -> None:
        if "time_skew" in model.terms:
            raise FitError("time_skew is batch-only (needs neighbouring samples)")
        if "mount_rotation" in model.terms:
            raise FitError("mount_rotation is batch-only (the angles couple the output axes)")
        self.options = options or FitOptions()
        if self.options.robust:
            raise FitError("robust IRLS is batch-only")
        self.model = model
        m = model.n_columns + 3
        self._R = np.zeros((m, m))
        self._raw_sq = np.zeros(3)
        self._n_raw = 0
        self.coverage = Coverage()
        self.n_used = 0
        self.n_excluded = 0

    def add(self, b_meas_uT, b_ref_uT, temp_c=None, currents_A=None, session=None, t_s=None,
            weights=None, design: np.ndarray | None = None, hist: bool = True) -> None:
        """One block of rows (same meanings and units as :class:`FitData`). Rows with a
        non-finite needed value or zero weight are counted as excluded. ``design``: the model's design of these rows
        when the caller has it; ``hist``: False leaves the coverage's field histograms out (another pass over the
        same rows has them)."""
        b = np.asarray(b_meas_uT, dtype=float).reshape(-1, 3)
        n = b.shape[0]
        y = np.asarray(b_ref_uT, dtype=float).reshape(n, 3)
        temp = np.full(n, np.nan) if temp_c is None else np.asarray(temp_c, dtype=float).reshape(n)
        sess = np.full(n, self.model.sessions[0] if self.model.sessions else 0) if session is None \
            else np.asarray(session).reshape(n)
        t = np.zeros(n) if t_s is None else np.asarray(t_s, dtype=float).reshape(n)
        cur = {k: np.asarray((currents_A or {})[k], dtype=float).reshape(n) for k in self.model.currents
               if k in (currents_A or {})}
        ok = np.all(np.isfinite(b), axis=1) & np.all(np.isfinite(y), axis=1)
        if set(TEMPERATURE_TERMS) & set(self.model.terms):
            ok &= np.isfinite(temp)
        for k in self.model.currents:
            if k not in cur:
                raise FitError(f"block has no current {k!r}")
            ok &= np.isfinite(cur[k])
        if "session_offset" in self.model.terms:
            unknown = set(np.unique(sess[ok]).tolist()) - set(self.model.sessions)
            if unknown:
                raise FitError(f"sessions {sorted(unknown)} not declared in the model {self.model.sessions}")
        w = np.ones(n) if weights is None else np.asarray(weights, dtype=float).reshape(n)
        if np.any(~np.isfinite(w)) or np.any(w < 0):
            raise FitError("weights must be finite and >= 0")
        ok &= w > 0
        self.n_excluded += int((~ok).sum())
        if not ok.any():
            return
        every = bool(ok.all())
        b, y, temp, sess, t, w = (b, y, temp, sess, t, w) if every else (b[ok], y[ok], temp[ok], sess[ok], t[ok], w[ok])
        cur = cur if every else {k: v[ok] for k, v in cur.items()}
        X = self.model.design(b, temp, cur, sess, t) if design is None else (
            np.asarray(design, dtype=float) if every else np.asarray(design, dtype=float)[ok])
        with single_thread():           # a block QR of ~16k x 30: 4-7x slower on threaded BLAS (bench_blas.py)
            self._R = qr_r(self._R, np.hstack([X, y]) * np.sqrt(w)[:, None])
        self.coverage.update(b, temp, cur, sess, t, self.options.field_present_uT, w, ref_uT=y, hist=hist)
        self._raw_sq += np.sum((y - b) ** 2, axis=0)
        self.n_used += b.shape[0]

    def merge(self, other: StreamingFit) -> StreamingFit:
        """Fold another accumulator of the same model in (blocks fitted elsewhere, e.g. on another
        worker): R^T R of the result is the sum of both Gram matrices. Coverage extremes combine."""
        if other.model != self.model:
            raise FitError("cannot merge streaming fits of different models")
        self._R = qr_r(self._R, other._R)
        self._raw_sq = self._raw_sq + other._raw_sq
        self.n_used += other.n_used
        self.n_excluded += other.n_excluded
        self.coverage.merge(other.coverage)
        return self

    @property
    def R(self) -> np.ndarray:
        """The accumulated R factor of the weighted ``[X | Y]`` ((p+3) x (p+3))."""
        return self._R

    @property
    def state_bytes(self) -> int:
        """Size of the accumulated state (constant in the number of rows)."""
        return self._R.nbytes + self._raw_sq.nbytes

    def solve(self, kappa=None) -> FitResult:
        """The MAP fit of the rows seen (``kappa`` (3,): residual variance inflation, default 1)."""
        p = self.model.n_columns
        if self.n_used <= p:
            raise FitError(f"{self.n_used} usable rows for {p} columns: not enough data")
        opts = self.options
        explain = identify(self.model, self._R, self.coverage,
                           dataclasses.replace(opts, on_unidentifiable="hold", priors={}))
        gated = [(h.axis, h.column) for h in explain if h.rule in GATE_RULES]
        prior = build_prior(self.model, opts)
        post = gate_solve(self._R, self.n_used, self.model, prior, gated, kappa, opts)
        if opts.use_priors and opts.prior is None and {"temperature_gain", "temperature_gain2"} & set(self.model.terms):
            prior = build_prior(self.model, opts, s_hint=self.model.unpack(post.theta)["S"])
            post = gate_solve(self._R, self.n_used, self.model, prior, gated, kappa, opts)
        held = prior_determined(post, explain)
        if held and opts.on_unidentifiable == "refuse":
            raise FitError("data cannot determine (the prior would): " + "; ".join(h.name for h in held))
        mask = self.model.axis_mask()
        rmse = np.sqrt(post.sse / np.maximum(post.dof, 1.0))
        res = FitResult(self.model, post.theta.copy(), np.where(mask, post.sd, np.nan), held, self.n_used,
                        self.n_excluded, rmse, np.sqrt(self._raw_sq / self.n_used), post.cond, np.full(3, np.nan),
                        np.full(3, np.nan), self.coverage)
        res.posterior = post
        res.prior_name = _prior_name(opts)
        res.chip = opts.chip
        res.notes.append("streaming fit: RMSE is the weighted in-sample value; no held-out or noise floor")
        return res
