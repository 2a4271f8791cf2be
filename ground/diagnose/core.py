"""``diagnose``: where the gap lies, which unmodelled effect causes it, how far it shrinks.

Input: a :class:`~magstack.ground.diagnose.gap.Gap` (mode (a) model fitted to the session, or mode
(b) fixed prediction). Output: a :class:`Diagnosis` whose :meth:`Diagnosis.to_dict` is the stable
JSON of ``magstack diagnose --json`` (keys ``verdict``, ``baseline_rmse_nT``, ``after_rmse_nT``,
``noise_floor_nT``, ``ranking``, ``not_testable``, ``where``, ``parameters``, plus context keys).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from magstack.firmware.calibration.model import time_derivative
from magstack.ground.diagnose import noise
from magstack.ground.diagnose import nonlinear as nl
from magstack.ground.diagnose import orbit as ob
from magstack.ground.diagnose import priors as pr
from magstack.ground.diagnose import rotation as rot
from magstack.ground.diagnose import search as sr
from magstack.ground.diagnose import where as wh
from magstack.ground.diagnose.blocks import choose_block_s
from magstack.ground.diagnose.gap import Block, Gap, folds_from_blocks, jackknife_se, solve, time_blocks

#: misalignment vs gain (same calibration term): a rotation / non-orthogonality changes no axis's
#: sensitivity to first order, so the fitted matrix change is called "gain" when its largest diagonal
#: element reaches this fraction of its largest off-diagonal element.
GAIN_DIAGONAL_RATIO = 0.25


@dataclass
class Diagnosis:
    gap: Gap
    result: sr.SearchResult
    noise_floor_uT: np.ndarray
    where: dict
    parameters: dict
    options: sr.Options
    verdict_note: str = ""
    notes: list[str] = field(default_factory=list)
    #: where.remainder: whether a held-out gap >= 1.5x the floor remains after the verdict, and where
    unexplained: dict = field(default_factory=dict)
    #: blocks.choose_block_s: the block length and why
    block_choice: dict = field(default_factory=dict)
    #: priors.base_identifiability: the base model by the calibration estimator with the chip's priors
    base_model: dict | None = None
    #: priors.prior_check of the verdict and the candidates confounded with it
    prior_check: list = field(default_factory=list)
    #: orbit.reference_budget of an IGRF + attitude reference (orbit telemetry), else None
    reference_budget: dict | None = None

    @property
    def verdict(self) -> str:
        return self.result.verdict

    @property
    def after_trial(self) -> sr.Trial:
        for t in self.result.trials:
            if t.effect == self.verdict:
                return t
        return self.result.baseline

    def to_dict(self) -> dict:
        r = self.result
        nf = float(np.linalg.norm(self.noise_floor_uT) * 1e3) if np.all(np.isfinite(self.noise_floor_uT)) else None
        return {
            "verdict": r.verdict,
            "baseline_rmse_nT": float(r.baseline.rmse_norm_uT * 1e3),
            "after_rmse_nT": float(self.after_trial.rmse_norm_uT * 1e3),
            "noise_floor_nT": nf,
            "reference_budget": self.reference_budget,
            "floor_with_reference_nT": self.floor_total_nT(nf),
            "floor": self.floor_parts(nf, float(self.after_trial.rmse_norm_uT * 1e3)),
            "ranking": [{"effect": t.effect, "rmse_nT": float(t.rmse_norm_uT * 1e3), "shrink": float(t.shrink),
                         "significant": bool(t.significant), "p_value": float(t.p_value),
                         "p_holm": float(t.p_holm), "kind": t.kind,
                         "test_unit_blocks": int(t.extra.get("test_unit", t.extra.get("group", 1))),
                         **_surrogate_keys(t),
                         "rmse_axes_nT": [float(v * 1e3) for v in t.rmse_uT],
                         **({"note": t.note} if t.note else {})} for t in r.trials],
            "not_testable": r.not_testable,
            "where": self.where,
            "parameters": self.parameters,
            "runner_up": r.runner_up,
            "p_vs_runner_up": r.p_vs_runner_up,
            "distinguishable": r.distinguishable,
            "confounded_with": r.confounded_with,
            "hysteresis_vs_session_offset": self.after_trial.extra.get("hysteresis_vs_session_offset"),
            "verdict_note": self.verdict_note,
            "modelled": r.modelled,
            "mode": self.gap.mode,
            "simulator": self.gap.description,
            "baseline_rmse_axes_nT": [float(v * 1e3) for v in r.baseline.rmse_uT],
            "noise_floor_axes_nT": [float(v * 1e3) for v in self.noise_floor_uT],
            "n_rows": int(self.gap.n),
            "sessions": list(self.gap.sessions),
            "method": {"block_s": self.options.block_s, "n_folds": self.options.n_folds, "alpha": self.options.alpha,
                       "min_shrink": self.options.min_shrink, "block_choice": self.block_choice,
                       "null": self.options.null,
                       "test": ("one-sided sign-flip permutation test on held-out block SSE differences"
                                + (" and, for effects it lets through, a surrogate test against noise with the "
                                   "residual's spectrum (p = the larger)" if self.options.null == "surrogate" else "")
                                + ", Holm-corrected across effects")},
            "null_model": r.null_model,
            "reference": self.gap.reference,
            "gap_direction": ("forward: dut - model(ref, temp, currents)" if self.gap.forward
                              else "calibration: ref - model(dut)"),
            "base_model": self.base_model,
            "prior_check": self.prior_check,
            "unexplained": self.unexplained,
            "notes": self.gap.notes + r.notes + self.notes,
        }

    def floor_total_nT(self, nf: float | None) -> float | None:
        """The measured white floor and the reference's error budget (orbit) in root sum square, nT."""
        if nf is None or self.reference_budget is None:
            return nf
        return float(np.hypot(nf, self.reference_budget["total_nT"]))

    def floor_parts(self, nf: float | None, after_nT: float) -> dict | None:
        """The floor the after-gap is judged against, in its parts: the sensor's white level (measured: differences
        of the residual; on a bench it holds the reference's own noise too) and the reference's error budget (orbit:
        IGRF + attitude, :func:`orbit.reference_budget`; none on a bench), their root sum square, and the after-gap
        against it: its part beyond the white level (``slow_nT`` = sqrt(after^2 - white^2), what slow reference
        errors and unmodelled effects leave) against the budget."""
        if nf is None:
            return None
        b = self.reference_budget
        total = self.floor_total_nT(nf)
        slow = float(np.sqrt(max(after_nT ** 2 - nf ** 2, 0.0)))
        out = {"sensor_white_nT": nf, "sensor_white_axes_nT": [float(v * 1e3) for v in self.noise_floor_uT],
               "reference_budget_nT": None if b is None else b["total_nT"], "total_nT": total,
               "after_nT": after_nT, "after_over_total": after_nT / total if total else None, "slow_nT": slow,
               "slow_over_budget": (slow / b["total_nT"]) if b and b["total_nT"] > 0 else None}
        if b is None:
            out["text"] = (f"floor {nf:.1f} nT: the white level of the residual (sensor and bench reference noise "
                           f"together); after {after_nT:.1f} nT = {after_nT / nf:.2f}x it")
            return out
        att = float(np.linalg.norm(b["attitude_axes_nT"]))
        verdict = ("within the reference's budget" if slow <= b["total_nT"] else
                   "beyond the reference's budget: more than its errors explain")
        out["text"] = (f"floor {total:.1f} nT = sensor white {nf:.1f} nT (+) reference budget {b['total_nT']:.1f} nT "
                       f"(attitude {b['attitude_sd_deg']:g} deg {att:.1f} nT, crustal {b['crustal_nT_per_axis']:g} and "
                       f"external {b['external_nT_per_axis']:g} nT per axis, {b['auroral_nT_per_axis']:g} nT on the "
                       f"{b['auroral_rows']} auroral-zone rows) in root sum square; after {after_nT:.1f} nT = "
                       f"{after_nT / total:.2f}x it: white (+) a slow part of {slow:.1f} nT, "
                       f"{slow / b['total_nT']:.2f}x the budget, {verdict}")
        return out

    def text(self) -> str:
        d = self.to_dict()
        bc = d["method"]["block_choice"]
        L = [f"simulator: {d['simulator']} ({d['mode']}); {d['n_rows']} rows, sessions {d['sessions']}; held-out "
             f"blocks of {d['method']['block_s']:.3g} s ({bc.get('reason', '')}"
             + (f"; residual autocorrelation time {bc['autocorrelation_time_s']:.3g} s" if "autocorrelation_time_s"
                in bc else "") + ")",
             f"gap (held-out, norm of per-axis RMS): {d['baseline_rmse_nT']:.1f} nT; noise floor "
             f"{_f(d['noise_floor_nT'])} nT" + _budget_text(d), f"verdict: {d['verdict']}"]
        if d["verdict"] != "none":
            L.append(f"  after adding it: {d['after_rmse_nT']:.1f} nT (noise floor "
                     f"{_f(d['floor_with_reference_nT'])} nT)")
        if self.verdict_note:
            L.append("  " + self.verdict_note)
        if d["floor"] and d["reference_budget"]:
            L.append("  " + d["floor"]["text"])
        if self.unexplained.get("remains"):
            L.append(self.unexplained["text"])
        L.append(f"{'effect':20s}{'held-out nT':>12s}{'shrink':>9s}{'p blocks':>10s}{'p surr.':>9s}{'p':>9s}"
                 f"{'p(Holm)':>9s}  significant")
        for t in d["ranking"]:
            ps = "-" if t.get("p_surrogate") is None else f"{t['p_surrogate']:.4f}"
            L.append(f"{t['effect']:20s}{t['rmse_nT']:12.1f}{t['shrink']:9.1%}{t.get('p_blocks', t['p_value']):10.4f}"
                     f"{ps:>9s}{t['p_value']:9.4f}{t['p_holm']:9.4f}  {'yes' if t['significant'] else 'no'}")
        if d["null_model"]:
            m = d["null_model"]
            L.append(f"slow-noise null model: surrogates of the {m['template']} residual, slow components from "
                     f"white + 1/f^{m['slow_noise_exponent']:.2f}"
                     + (f" (capped at {m['slow_power_cap']:g}x the residual's own slow power on "
                        f"{', '.join(m['slow_power_capped_axes'])})" if m["slow_power_capped_axes"] else ""))
        bm = d["base_model"]
        if bm and bm["determined_by_prior"]:
            L.append(f"base model: {', '.join(bm['determined_by_prior'])} not determined by this session: set by "
                     f"the {bm['chip']} prior ({bm['prior_source']})")
        for c in d["prior_check"]:
            L.append(f"prior check ({c['effect']}): {c['parameter']} = {c['value']:.4g} {c['unit']}, "
                     f"{c['z']:.1f} prior sd from {c['prior_mean']:.4g} +- {c['prior_sd']:.3g} "
                     f"({'plausible' if c['plausible'] else 'implausible for the part'})"
                     + (f"; fitted within {pr.IMPLAUSIBLE_Z:g} prior sd: {c['constrained_rmse_nT']:.1f} nT held out"
                        if c.get("constrained_rmse_nT") is not None else ""))
        if d["parameters"]:
            L.append("parameters of the verdict's effect (value +- standard error):")
            for name, p in d["parameters"].items():
                L.append(f"  {name:18s}{p['value']:14.6g} +- {p['se']:.3g} {p['unit']}")
        for nt in d["not_testable"]:
            L.append(f"not testable: {nt['effect']}: {nt['reason']}")
        if d["modelled"]:
            L.append(f"modelled by the simulator: {', '.join(d['modelled'])}")
        if (d["where"].get("alternation") or {}).get("significant"):
            a = d["where"]["alternation"]
            L.append(a["text"] + (" (reported apart; its constant part removed before the noise floor)"
                                  if a.get("removed_before_floor") else " (reported apart)"))
        for tone in d["where"].get("tones", []):
            L.append(f"tone (reported apart, removed before the noise floor): {tone['freq_hz']:.5g} Hz, amplitude "
                     + "/".join(f"{a:.1f}" for a in tone["amplitude_nT"]) + " nT (x, y, z)"
                     + (f": {tone['note']}" if tone.get("kind") == "even_odd_alternation" else ""))
        L += [f"note: {n}" for n in d["notes"]]
        return "\n".join(L)


def _surrogate_keys(t) -> dict:
    """Ranking keys of the two tests: ``p_blocks`` (block sign-flip test) and, when it ran,
    ``p_surrogate`` with ``n_surrogates`` (surrogate.py)."""
    out = {}
    if "p_blocks" in t.extra:
        out["p_blocks"] = float(t.extra["p_blocks"])
    r = t.extra.get("surrogate")
    out["p_surrogate"] = None if r is None else float(r.p_value)
    if r is not None:
        out["n_surrogates"] = int(r.n_surrogates)
    return out


def _budget_text(d: dict) -> str:
    b = d["reference_budget"]
    if not b:
        return ""
    return (f" (measured white) + reference error budget {b['total_nT']:.1f} nT (IGRF + attitude: crustal, "
            f"external, attitude {b['attitude_sd_deg']:g} deg) = {d['floor_with_reference_nT']:.1f} nT")


def _f(x) -> str:
    return "n/a" if x is None else f"{x:.1f}"


def _params(gap: Gap, allb: Block, Y: np.ndarray, first: int, fold: np.ndarray) -> dict:
    """Parameters of ``allb``'s columns from ``first`` on, fitted on all rows, with the OLS and the
    delete-one-fold jackknife standard errors (``se`` the larger). When the model names mount_rotation
    the base, these columns and the per-session angles are solved jointly (rotation.joint_fit)."""
    if gap.rotation is None:
        th, se = solve(allb.X, Y, allb.mask, with_se=True)
        thetas = [solve(allb.X, Y, allb.mask, fold != f) for f in np.unique(fold)]
    else:
        mc, sigma = gap.rotation
        th, se, _, _ = rot.joint_fit(allb, mc, Y, sigma)
        thetas = [rot.joint_fit(allb, mc, Y, sigma, fold != f)[0] for f in np.unique(fold)]
    jk = sr_jack(thetas, th)
    out = {}
    for i in range(3):
        for c in range(first, allb.p):
            if allb.mask[i, c]:
                out[allb.names[i][c]] = {"value": float(th[i, c]), "se": float(np.nanmax([se[i, c], jk[i, c]])),
                                         "se_ols": float(se[i, c]), "se_jackknife": float(jk[i, c]),
                                         "unit": allb.units[c]}
    return out


def sr_jack(thetas, like):
    return jackknife_se(thetas) if len(thetas) >= 2 else np.full_like(like, np.nan)


def verdict_parameters(gap: Gap, res: sr.SearchResult, fold: np.ndarray, run: np.ndarray) -> dict:
    """Fitted parameters of the verdict's effect on all rows with standard errors (the larger of the
    OLS and the delete-one-fold jackknife, which is robust to autocorrelated residuals)."""
    v = next((t for t in res.trials if t.effect == res.verdict), None)
    if v is None:
        return {}
    base = gap.base_design()
    Y = gap.target
    if v.kind == "delay":
        d = v.extra["delay_s"]     # the search on all rows (search.delay_searches, with the folds')
        jk = jackknife_se([np.asarray(x) for x in v.extra["fold_delays_s"]])
        out = {f"dt[{a}]": {"value": float(d[j]), "se": float(jk[j]),
                            "se_jackknife": float(jk[j]), "unit": "s",
                            "meaning": "DUT axis reads the field at t + dt relative to the reference"}
               for j, a in enumerate("xyz")}
        return out
    if v.kind == "joint":
        mc = rot.mount_columns(gap)
        ang, se = rot.fit_all(base, mc, Y, res.baseline.rmse_uT)
        if gap.forward:     # dut ~ R^-1 ref: the fitted angles are minus the mount's rotation
            ang = -np.asarray(ang)
        jk = jackknife_se([np.asarray(a) for a in v.extra["fold_angles_rad"]])
        return {n: {"value": float(a), "se": float(max(e, j)) if np.isfinite(j) else float(e), "se_ols": float(e),
                    "se_jackknife": float(j), "unit": "rad",
                    "meaning": f"rotation of the mount relative to session {mc.frame} (small angle)"}
                for n, a, e, j in zip(mc.names, ang, se, jk, strict=True)}
    if v.kind == "hysteresis":
        thr, init = sr.choose_thresholds(gap, base, Y, _hyst_cands(gap), np.ones(gap.n, bool))
        blk = sr.hysteresis_block(gap, thr, init)
        allb = Block.join([base, blk], gap.n)
        out = _params(gap, allb, Y, base.p, fold)
        for j, a in enumerate("xyz"):
            if np.isfinite(thr[j]):
                out[f"threshold[{a}]"] = {"value": float(thr[j]), "se": float("nan"), "unit": "uT (chosen level)"}
                out[f"initial_state[{a}]"] = {"value": float(init[j]), "se": float("nan"),
                                              "unit": "sign of the remanence before the first excursion (chosen)"}
        return out
    if v.kind == "lag":      # the fit with each stretch's starting offset (lag.py), coefficients at those offsets
        from magstack.ground.diagnose import lag as lg
        dz = lg.design(gap, v.extra["tau_s"])
        fits = lg.fits(gap, base, Y, fold, dz)
        delta = fits.delta[-1]
        allb = Block.join([base, lg.lag_block(gap, dz.tau_s, temp=lg.die_temperature(gap, dz, delta))], gap.n)
        out = _params(gap, allb, Y, base.p, fold)
        jk = jackknife_se([np.array([x]) for x in v.extra["fold_tau_s"]])
        out["tau_s"] = {"value": float(v.extra["tau_s"]), "se": float(jk[0]), "se_jackknife": float(jk[0]), "unit": "s",
                        "meaning": "time constant of the die temperature behind the measured temperature (grid "
                                   f"{v.extra['grid_s'][0]:.3g}-{v.extra['grid_s'][-1]:.3g} s)"}
        lagged = lg.lagged_temperature(gap, dz.tau_s)
        djk = jackknife_se([d for d in fits.delta[:-1]])
        for r, row in enumerate(dz.first):
            t0 = float(gap.session.t_s[row])
            out[f"T_die_start[{r}]"] = {
                "value": float(lagged[row] + delta[r]), "se": float(djk[r]), "se_jackknife": float(djk[r]),
                "unit": "degC", "offset_from_continuous_c": float(delta[r]),
                "meaning": f"die temperature where the record (re)starts (session {gap.session.session[row]}, "
                           f"t = {t0:.1f} s): fitted, not carried across the pause"}
        return out
    blk = sr.linear_block(gap, v.effect, v.extra["terms"])
    allb = Block.join([base, blk], gap.n)
    return _params(gap, allb, Y, base.p, fold)


def _hyst_cands(gap: Gap):
    return nl.hysteresis_thresholds(*gap.history())


def _gain_or_misalignment(res: sr.SearchResult, params: dict) -> str | None:
    """Tell gain from misalignment when both were tried with the same columns (see GAIN_DIAGONAL_RATIO)."""
    names = {t.effect for t in res.trials}
    if res.verdict not in ("gain", "misalignment") or not {"gain", "misalignment"} <= names:
        return None
    dS = np.zeros((3, 3))
    for k, p in params.items():
        if k.startswith("S[") and len(k) == 6:
            i, j = "xyz".index(k[2]), "xyz".index(k[4])
            dS[i, j] = p["value"]   # the gap-side change of the matrix (identity gain or fixed table)
    diag = float(np.max(np.abs(np.diag(dS))))
    off = float(np.max(np.abs(dS - np.diag(np.diag(dS)))))
    return "gain" if diag >= GAIN_DIAGONAL_RATIO * off else "misalignment"


def diagnose(gap: Gap, options: sr.Options | None = None) -> Diagnosis:
    """Run the whole diagnosis on a gap (see the module docs of gap, search, where, nonlinear)."""
    opts = options or sr.Options()
    s = gap.session
    if opts.block_s is None:
        block_s, block_choice = choose_block_s(gap)
        opts = dataclasses.replace(opts, block_s=block_s)
    else:
        block_choice = {"block_s": opts.block_s, "reason": "given (--block-s)"}
    blocks = time_blocks(s.t_s, s.session, opts.block_s)
    fold = folds_from_blocks(blocks, s.session, opts.n_folds, gap.predictor_uT, opts.seed)
    run = nl.runs(s.t_s, s.session)
    res = sr.search(gap, blocks, fold, opts)
    notes: list[str] = []
    chip = pr.chip_priors(gap, opts.chip)
    checks, note = prior_choice(gap, res, chip, fold, blocks, opts.alpha)
    if note:
        notes.append(note)
    params = verdict_parameters(gap, res, fold, run)
    choice = _gain_or_misalignment(res, params)
    if choice is not None and choice != res.verdict:
        # same columns, same held-out figures: the matrix structure decides
        other = res.verdict
        res.verdict, res.runner_up = choice, other
        res.trials.sort(key=lambda t: (t.rmse_norm_uT, t.effect != choice))
        res.confounded_with = [e for e in res.confounded_with if e != choice] + [other]
    if choice is not None:
        notes.append("gain and misalignment share the calibration columns (gain_matrix); told apart by the fitted "
                     "matrix change: misalignment leaves the diagonal unchanged to first order")
    # noise floor: white level of the residual of the best description found (lowest held-out RMSE)
    best = min([res.baseline] + [t for t in res.trials if t.resid is not None], key=lambda t: t.rmse_norm_uT)
    # the reference's field and rate in DUT axes (dut ~ A ref), per session: what an alternation's cause is
    # proportional to
    A = gap._dut_image() if gap.forward else np.eye(3)

    def field_and_rate(m):
        image = gap.predictor_uT[m] @ A.T
        return image, time_derivative(image, s.t_s[m], s.session[m])
    nf, lag, tones, alt = noise.noise_floor(np.asarray(best.resid, dtype=float), s.t_s, s.session, field_and_rate)
    where = wh.breakdowns(res.baseline.resid, s, blocks)
    where["spectrum"] = wh.spectrum(res.baseline.resid, s.t_s, s.session)
    where["tones"] = tones
    where["alternation"] = alt
    where["noise_floor_lag_s"] = lag
    diag = Diagnosis(gap, res, nf, where, params, opts, notes=notes, block_choice=block_choice,
                     base_model=pr.base_identifiability(gap, chip), prior_check=checks,
                     reference_budget=ob.session_budget(s, opts.attitude_sd_deg))
    nf_nT = diag.floor_total_nT(diag.to_dict()["noise_floor_nT"])
    after = diag.after_trial
    diag.unexplained = wh.remainder(np.asarray(after.resid, dtype=float), s, after.rmse_norm_uT * 1e3, nf_nT,
                                    res.verdict)
    diag.verdict_note = verdict_note(diag)
    return diag


def prior_choice(gap: Gap, res: sr.SearchResult, chip, fold: np.ndarray, blocks: np.ndarray,
                 alpha: float = 0.05) -> tuple[list[dict], str | None]:
    """Confounded explanations weighed with the part's physics (priors.prior_check, priors.constrained_oof).

    When the verdict (a linear effect) is confounded with significant linear candidates that close as much
    (same columns in this session, e.g. a sensitivity tempco and an offset tempco at one field level), each
    one's parameters (MAP on all rows with the chip's prior on its columns) are checked against that prior, and
    each is fitted again on held-out blocks *within* the prior (MAP, parameters boxed to priors.IMPLAUSIBLE_Z
    prior sd). A prior conflict is evidence, not a veto: a verdict that needs a parameter beyond that many sd
    gives way only to a partner whose fit within its prior closes the gap as well as the verdict's own fit
    (closes as much, and is not worse by the signed-rank test on held-out blocks); among those the best fit
    within the prior, then the simplest. Otherwise the data's verdict stands and the note says what each
    alternative leaves within its prior. The checks (with ``constrained_rmse_nT``) are reported either way.
    Returns (checks, note)."""
    v = next((t for t in res.trials if t.effect == res.verdict), None)
    if v is None or v.kind != "linear" or not res.confounded_with:
        return [], None
    base_rmse = res.baseline.rmse_norm_uT
    group = [v] + [t for t in res.trials if t.effect in res.confounded_with and t.significant and t.kind == "linear"
                   and sr.closes_as_much(t.rmse_norm_uT, v.rmse_norm_uT, base_rmse)]
    if len(group) < 2:
        return [], None
    base = gap.base_design()
    checks = {}
    for t in group:
        c = pr.prior_check(gap, t, base, t.rmse_uT, chip)
        if c is not None:
            checks[t.effect] = c
    out = list(checks.values())
    if v.effect not in checks or checks[v.effect]["plausible"]:
        return out, None
    bs = res.baseline.extra["block_session"]
    nb = bs.size
    g = v.extra.get("group", 1)
    within = {}                 # effect -> (held-out RMSE uT, per-block SSE) of the fit within the prior
    for t in group:
        r = pr.constrained_oof(gap, t, base, fold, chip)
        within[t.effect] = ((t.rmse_norm_uT, t.block_sse) if r is None else
                            (float(np.linalg.norm(sr.rms3(r))), sr.block_sse(r, blocks, nb)))
        if t.effect in checks and r is not None:
            checks[t.effect]["constrained_rmse_nT"] = within[t.effect][0] * 1e3

    def worse_p(a_sse, b_sse):   # one-sided p of "a is worse than b" on held-out blocks (signed-rank)
        return sr.paired_worse_p(sr.grouped(a_sse - b_sse, bs, g))
    # a replacement must close the gap, within its prior, as well as the verdict does with its own parameters
    better = [t for t in group[1:] if sr.closes_as_much(within[t.effect][0], v.rmse_norm_uT, base_rmse)
              and worse_p(within[t.effect][1], v.block_sse) >= alpha]
    c = checks[v.effect]
    conflict = (f"{v.effect} would need {c['parameter']} = {c['value']:.4g} {c['unit']}, {c['z']:.1f} sd from the "
                f"{chip.chip} prior {c['prior_mean']:.4g} +- {c['prior_sd']:.3g}, beyond the {chip.chip} prior "
                f"({IMPLAUSIBLE_TEXT}); held within it {v.effect} leaves {within[v.effect][0] * 1e3:.1f} nT held out")
    if not better:
        others = ", ".join(f"{t.effect} {t.rmse_norm_uT * 1e3:.1f} nT (within its prior "
                           f"{within[t.effect][0] * 1e3:.1f} nT)" for t in group[1:])
        return out, (f"prior conflict weighed, not a veto: {conflict}; no alternative closes the gap as well "
                     f"({v.rmse_norm_uT * 1e3:.1f} nT held out) within its own prior ({others}): the data's verdict "
                     "stands")
    new = min(better, key=lambda t: (within[t.effect][0], t.n_params))
    res.verdict, res.runner_up = new.effect, v.effect
    res.trials.remove(new)
    res.trials.insert(0, new)
    res.confounded_with = [e for e in res.confounded_with if e != new.effect] + [v.effect]
    if new.resid is None:      # dropped while searching: the same out-of-fold fit again
        new.resid = sr.oof_residual(gap, [base, sr.linear_block(gap, new.effect, new.extra["terms"])],
                                    gap.target, fold).astype(np.float32)
    return out, (f"{new.effect} and {v.effect} are confounded in this session (held out {new.rmse_norm_uT * 1e3:.1f} "
                 f"and {v.rmse_norm_uT * 1e3:.1f} nT); {conflict}, while {new.effect} within its prior leaves "
                 f"{within[new.effect][0] * 1e3:.1f} nT: the part's physics names {new.effect}")


IMPLAUSIBLE_TEXT = f"more than {pr.IMPLAUSIBLE_Z:g} prior sd"


def verdict_note(d: Diagnosis) -> str:
    r = d.result
    if r.verdict == "none":
        best = r.trials[0] if r.trials else None
        if best is None:
            return "no testable effect"
        lead = ("no catalogue effect is significant" if d.unexplained.get("remains")
                else "nothing unmodelled found")
        if best.shrink >= d.options.min_shrink:
            return (f"no verdict: the best candidate, {best.effect}, closes {best.shrink:.1%} of the held-out gap "
                    f"({r.baseline.rmse_norm_uT * 1e3:.1f} -> {best.rmse_norm_uT * 1e3:.1f} nT) but cannot be "
                    f"confirmed: {_why_unconfirmed(d, best)}")
        return (f"{lead}: the best candidate, {best.effect}, changes the held-out gap by "
                f"{best.shrink:.1%} (p = {best.p_holm:.3g} after Holm)")
    v = d.after_trial
    txt = (f"{r.verdict} closes {v.shrink:.1%} of the held-out gap (p = {v.p_value:.2g}, Holm {v.p_holm:.2g})")
    if r.runner_up:
        ru = next(t for t in r.trials if t.effect == r.runner_up)
        txt += (f"; runner-up {ru.effect} ({ru.rmse_norm_uT * 1e3:.1f} nT, shrink {ru.shrink:.1%})")
        if r.distinguishable:
            txt += f"; the verdict beats it on held-out blocks (p = {r.p_vs_runner_up:.2g})"
        else:
            txt += (f"; NOT distinguishable from it on this data (p = {_f3(r.p_vs_runner_up)}"
                    f"{', columns confounded' if r.runner_up in r.confounded_with else ''})")
    if r.verdict == "time_skew":
        txt += ("; a delay common to all axes could also be latency of the reference pairing or a bandwidth limit "
                "(a first-order low-pass of time constant tau looks like a delay tau at low frequency)")
    return txt


def _why_unconfirmed(d: Diagnosis, t: sr.Trial) -> str:
    """Why a candidate that closes part of the gap is not significant, in words."""
    nb = int(d.block_choice.get("n_blocks", 0)) or len(d.result.baseline.block_sse)
    alpha = d.options.alpha
    pb = float(t.extra.get("p_blocks", t.p_value))
    sur = t.extra.get("surrogate")
    if nb < sr.MIN_BLOCKS:
        return (f"only {nb} held-out blocks of {d.options.block_s:.3g} s (at least {sr.MIN_BLOCKS} are needed; "
                f"{d.block_choice.get('reason', '')}): record longer or more sessions")
    if pb >= alpha:
        return (f"its shrink is not consistent across the {nb} held-out blocks (block test p = {pb:.2g}): a few "
                "blocks carry it")
    if sur is not None and sur.p_value >= alpha:
        return (f"noise with the residual's own spectrum closes as much in {sur.p_value:.0%} of surrogates "
                f"(p = {sur.p_value:.2g}): slow noise can do this on this record")
    if t.p_holm >= alpha:
        return (f"p = {t.p_value:.2g} does not survive Holm's correction over {len(d.result.trials)} effects "
                f"(Holm p = {t.p_holm:.2g})")
    return f"its shrink is below the practical threshold ({d.options.min_shrink:.1%})"


def _f3(x) -> str:
    return "n/a" if x is None else f"{x:.2g}"
