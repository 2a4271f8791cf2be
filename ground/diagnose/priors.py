"""Datasheet priors in the diagnosis: the calibration's chip priors and MAP estimator.

A session cannot always determine the simulator's base parameters (one field level: gain and offset are one
number per axis) nor tell two candidate effects apart (at one field level ``B_x dT`` *is* ``44 uT x dT``, so a
sensitivity tempco and an offset tempco fit equally). What the data cannot decide, the part's physics does:

* :func:`base_identifiability`: the base model fitted on all rows by the calibration estimator
  (:func:`magstack.firmware.calibration.fit.gate_solve`: MAP with the chip's priors, degenerate directions
  left to the prior), per parameter value, posterior sd, prior and who determined it ("data", "prior",
  "data+prior"); the report names the parameters the prior alone set.
* :func:`prior_check`: each confounded candidate's parameters (MAP with the chip's prior on its columns)
  against that prior (``z`` in prior sd). A verdict that would need a parameter beyond :data:`IMPLAUSIBLE_Z`
  prior sd gives way to a confounded candidate that closes as much with plausible parameters (a -130 nT/degC
  offset tempco on an HMC1053, +-6 nT/degC with set/reset, against a -2.95e-3 /degC sensitivity tempco,
  -2.7e-3 +- 0.6e-3).

Priors are in the calibration direction (``drivers/cal_priors.py``); a forward gap (``dut - model(ref)``)
sees a sensitivity tempco with the opposite sign (``(1 + K dT)^-1 = 1 - K dT`` to first order), offsets and
their tempco with the opposite sign (mean 0 except the tempco's), gains as their inverse (mean identity).
An effect the simulator already models is a *change* (mean 0, the prior's sd).
"""
from __future__ import annotations

import numpy as np

from magstack.drivers.cal_priors import GENERIC, CalPriors, priors_for
from magstack.firmware.calibration.model import CalModel
from magstack.firmware.errors import FitError

#: A fitted parameter beyond this many prior sd is implausible for the part.
IMPLAUSIBLE_Z = 3.0
#: Terms whose forward (sensor-side) mean is the negative of the calibration-side one.
_SIGN_FLIP = ("temperature_gain", "temperature_offset", "offset", "currents", "cubic", "cross_products",
              "session_offset", "drift")


def chip_priors(gap, chip: str | None = None) -> CalPriors:
    """The part's priors: ``chip`` (``--chip``), else the session's ``dut_chip``; GENERIC when unknown."""
    return priors_for(chip or gap.session.metadata.get("dut_chip"))


def directed_prior(cm: CalModel, chip: CalPriors, forward: bool):
    """``model_prior(cm, chip)`` with its means in the gap's direction: forward, the sign-flipped terms
    (:data:`_SIGN_FLIP`) change sign (the calibration-side priors of drivers/cal_priors.py)."""
    from magstack.firmware.calibration.estimator import model_prior

    pr = model_prior(cm, chip)
    if not forward:
        return pr
    mean = pr.mean.copy()
    for c, col in enumerate(cm.columns):
        if col.term in _SIGN_FLIP:
            mean[:, c] = -mean[:, c]
    return type(pr)(mean, pr.cov, pr.source)


def term_prior(gap, cm: CalModel, keep: list[int], chip: CalPriors, modelled: bool) -> tuple[np.ndarray, np.ndarray]:
    """(mean, sd) (3, k) of the columns ``keep`` of ``cm`` in the gap's direction; ``modelled``: the effect is
    in the simulator already, so the candidate is a change (mean 0)."""
    pr = directed_prior(cm, chip, gap.forward)
    mean = pr.mean[:, keep].copy()
    sd = np.sqrt(np.diagonal(pr.cov, axis1=1, axis2=2))[:, keep]
    for k, c in enumerate(keep):
        if modelled or (cm.columns[c].term == "gain_matrix" and (gap.identity_gain or gap.mode != "model")):
            # a change of what the simulator has (a gain column of an identity-gain base, target dut - ref, or
            # of a fixed prediction is a change of gain)
            mean[:, k] = 0.0
    return mean, sd


def base_identifiability(gap, chip: CalPriors) -> dict | None:
    """The base model (mode (a)) on all rows by the calibration estimator with ``chip``'s priors.

    None for a fixed gap or a base with no calibration terms. Hysteresis state columns and mount angles in the
    base are not part of this analysis (they have their own estimators)."""
    from magstack.firmware.calibration.estimator import autocorr_inflation, names_of
    from magstack.firmware.calibration.fit import FitOptions, gate_solve
    from magstack.firmware.calibration.linalg import qr_r

    if gap.mode != "model" or not gap.base_terms:
        return None
    s = gap.session
    cm, _keep = gap.term_model(gap.base_terms)
    X = cm.design(gap.predictor_uT, s.temp_c, s.currents_A, s.session, s.t_s)
    Y = gap.target + (gap.predictor_uT if gap.identity_gain else 0.0)    # the DUT reading
    prior = directed_prior(cm, chip, forward=True)
    mean = prior.mean.copy()
    cov = prior.cov.copy()
    for c, col in enumerate(cm.columns):
        if col.term == "gain_matrix" and gap.identity_gain:   # held at identity by the model
            for i in range(3):
                mean[i, c] = 1.0 if i == col.index else 0.0
                cov[i, c, :] = 0.0
                cov[i, :, c] = 0.0
    prior = type(prior)(mean, cov, prior.source)
    opts = FitOptions(holdout=False)
    try:
        R = qr_r(np.hstack([X, Y]))
        post = gate_solve(R, len(s), cm, prior, [], options=opts)
        kappa = autocorr_inflation(Y - cm.predict(post.theta, X), s.t_s, s.session)
        post = gate_solve(R, len(s), cm, prior, [], kappa, opts)
    except (FitError, np.linalg.LinAlgError) as exc:   # the analysis explains; it never stops a diagnosis
        return {"direction": "forward: dut = model(ref, temp, currents) + gap", "chip": chip.chip,
                "error": f"the base model's identifiability could not be computed: {exc}", "parameters": {},
                "determined_by_prior": []}
    params = {}
    from_prior = []
    sd = post.sd
    share = post.data_share
    for i, c, name in names_of(cm):
        by = post.determined_by(i, c)
        if by == "fixed":
            continue
        params[name] = {"value": float(post.theta[i, c]), "sd": _num(sd[i, c]), "unit": cm.columns[c].unit,
                        "prior_mean": float(mean[i, c]) + 0.0, "prior_sd": _num(np.sqrt(cov[i, c, c])),
                        "data_share": _num(share[i, c]), "determined_by": by}
        if by == "prior":
            from_prior.append(name)
    return {"direction": "forward: dut = model(ref, temp, currents) + gap", "chip": chip.chip,
            "prior_source": chip.source if chip is not GENERIC else "generic wide priors (no dut_chip, no --chip)",
            "parameters": params, "determined_by_prior": from_prior,
            "kappa": [float(k) for k in post.kappa]}


def prior_check(gap, trial, base, sigma_uT: np.ndarray, chip: CalPriors) -> dict | None:
    """The worst |z| of a linear trial's parameters against ``chip``'s prior, with the parameter, value and
    prior; None when no column of the trial has a prior.

    The parameters are the MAP estimate of ``base`` (flat) plus the trial's columns (the chip's prior) on
    all rows, residual scale ``sigma_uT`` (3,) (the trial's held-out RMS per axis): what the session does
    not determine stays at the prior (z ~ 0), a split the data leave open (two columns equal at one field
    level) follows the prior, and a value the data force beyond the prior shows as a large z."""
    from magstack.ground.diagnose.gap import Block
    from magstack.ground.diagnose.search import linear_block

    terms = trial.extra.get("terms")
    if trial.kind != "linear" or not terms:
        return None
    blk = linear_block(gap, trial.effect, terms)
    cm, keep = gap.term_model(terms)
    mean_t, sd_t = term_prior(gap, cm, keep, chip, trial.effect in gap.modelled)
    k = len(keep)
    allb = Block.join([base, blk], gap.n)
    mean = np.zeros((3, allb.p))
    sd = np.full((3, allb.p), np.inf)
    mean[:, base.p:base.p + k] = mean_t          # term columns first in the block; extra columns stay flat
    sd[:, base.p:base.p + k] = sd_t
    theta = map_block(allb.X, gap.target, allb.mask, mean, sd, sigma_uT)
    worst = None
    for j, c in enumerate(keep):
        col = base.p + j
        for i in range(3):
            if not allb.mask[i, col] or not (0 < sd[i, col] < np.inf):
                continue
            z = abs(theta[i, col] - mean[i, col]) / sd[i, col]
            if worst is None or z > worst["z"]:
                worst = {"effect": trial.effect, "parameter": cm.param_name(i, c), "value": float(theta[i, col]),
                         "unit": cm.columns[c].unit, "prior_mean": float(mean[i, col]) + 0.0,
                         "prior_sd": float(sd[i, col]), "z": float(z), "plausible": bool(z <= IMPLAUSIBLE_Z)}
    return worst


def map_block(X: np.ndarray, Y: np.ndarray, mask: np.ndarray, mean: np.ndarray, sd: np.ndarray,
              sigma_uT: np.ndarray) -> np.ndarray:
    """(3, p) MAP coefficients of ``Y`` (N,3) on ``X`` (N,p) per output axis (``mask`` (3,p)), Gaussian priors
    ``mean`` / ``sd`` (3,p) (``inf`` = flat), residual sd ``sigma_uT`` (3,): least squares of the stacked,
    column-equilibrated data and prior rows (minimum norm where neither determines a direction)."""
    theta = np.zeros(mask.shape)
    for i in range(3):
        cols = np.flatnonzero(mask[i])
        if cols.size == 0:
            continue
        s = max(float(sigma_uT[i]), 1e-12)
        A = X[:, cols] / s
        b = Y[:, i] / s
        fin = np.isfinite(sd[i, cols])
        P = np.zeros((int(fin.sum()), cols.size))
        P[np.arange(P.shape[0]), np.flatnonzero(fin)] = 1.0 / sd[i, cols][fin]
        A = np.vstack([A, P])
        b = np.concatenate([b, mean[i, cols][fin] / sd[i, cols][fin]])
        scale = np.linalg.norm(A, axis=0)
        scale[scale == 0] = 1.0
        sol, *_ = np.linalg.lstsq(A / scale, b, rcond=1e-10)
        theta[i, cols] = sol / scale
    return theta


def _num(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def constrained_oof(gap, trial, base, fold: np.ndarray, chip: CalPriors, z_max: float = IMPLAUSIBLE_Z):
    """Held-out residual (N,3) of a linear trial fitted **within the part's prior**: per training set (every fold
    left out in turn) the MAP fit of :func:`prior_check` (base flat, the trial's term columns with the chip's
    Gaussian prior, residual scale the trial's held-out RMS) with each prior-bearing parameter also boxed to
    ``mean +- z_max sd`` (scipy.optimize.lsq_linear), so no parameter the data force beyond the prior survives.
    The fold systems come from per-fold normal equations (gap.fold_products). None when the trial has no
    prior-bearing column, or with a modelled mount rotation (its joint estimator has no prior)."""
    import scipy.linalg
    import scipy.optimize

    from magstack.ground.diagnose.gap import Block, fold_products, predict
    from magstack.ground.diagnose.search import linear_block

    terms = trial.extra.get("terms")
    if trial.kind != "linear" or not terms or gap.rotation is not None:
        return None
    blk = linear_block(gap, trial.effect, terms)
    cm, keep = gap.term_model(terms)
    mean_t, sd_t = term_prior(gap, cm, keep, chip, trial.effect in gap.modelled)
    allb = Block.join([base, blk], gap.n)
    p = allb.p
    mean = np.zeros((3, p))
    sd = np.full((3, p), np.inf)
    mean[:, base.p:base.p + len(keep)] = mean_t
    sd[:, base.p:base.p + len(keep)] = sd_t
    has = allb.mask & np.isfinite(sd) & (sd > 0)
    if not has.any():
        return None
    Y = gap.target
    folds = np.unique(fold)
    code = np.searchsorted(folds, fold)
    GC = fold_products([allb.X], [allb.X, Y], code, folds.size)
    G, C = GC[:, :, :p], GC[:, :, p:]
    sigma = np.maximum(np.asarray(trial.rmse_uT, dtype=float), 1e-9)
    thetas = []
    for f in range(folds.size):
        Gt, Ct = G.sum(axis=0) - G[f], C.sum(axis=0) - C[f]
        th = np.zeros((3, p))
        for i in range(3):
            cols = np.flatnonzero(allb.mask[i])
            if cols.size == 0:
                continue
            w = has[i, cols]
            A = Gt[np.ix_(cols, cols)] / sigma[i] ** 2
            b = Ct[cols, i] / sigma[i] ** 2
            A[np.flatnonzero(w), np.flatnonzero(w)] += 1.0 / sd[i, cols][w] ** 2
            b[w] += mean[i, cols][w] / sd[i, cols][w] ** 2
            d = np.sqrt(np.clip(np.diag(A), 1e-300, None))
            An = A / np.outer(d, d) + 1e-10 * np.eye(cols.size)   # equilibrated; the ridge keeps it definite
            R = scipy.linalg.cholesky(An, lower=False)
            q = scipy.linalg.solve_triangular(R, b / d, trans="T")
            lo = np.where(w, (mean[i, cols] - z_max * sd[i, cols]) * d, -np.inf)
            hi = np.where(w, (mean[i, cols] + z_max * sd[i, cols]) * d, np.inf)
            sol = scipy.optimize.lsq_linear(R, q, bounds=(lo, hi), method="bvls")
            th[i, cols] = sol.x / d
        thetas.append(th)
    resid = np.full(Y.shape, np.nan)
    for f in range(folds.size):
        m = code == f
        resid[m] = Y[m] - predict(allb.X[m], thetas[f], allb.mask)
    return resid
