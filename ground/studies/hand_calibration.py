"""Simulated hand-rotation sessions and their scoring against the truth (tests, benchmarks, docs).

:func:`simulate_session` samples a hand programme (:mod:`magstack.sim.hand_rotation`) with a chip's error
model preset at ``rate_hz``; :func:`score` compares a calibration's output with the truth on the same rows:
the magnitude error against the site's field (held-out rows where the calibration was held out), the floor
that the exact inverse of the forward model leaves (noise, quantisation), the heading error in the level
turns, and the hard iron (offset in the symmetric gauge) against the truth's in posterior sds. The truth is
used only here, never by the calibration.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import polar

from magstack.firmware.calibration.handcal import heading_error_deg
from magstack.sim.hand_rotation import HAND_PROGRAMS, HandRotationTruth, exact_calibration, hand_program
from magstack.sim.measurement_sim import simulate_measurement
from magstack.sim.presets import preset

CHIPS = ("lis3mdl", "hmc5983", "lsm303dlhc")


@dataclass
class SimSession:
    """One simulated session: the truth programme, the chip's parameters and the sampled arrays."""

    chip: str
    program: str
    seed: int
    truth: HandRotationTruth
    params: object
    t_s: np.ndarray
    dut_uT: np.ndarray
    temp_c: np.ndarray

    @property
    def field_uT(self) -> float:
        return float(np.linalg.norm(self.truth.field_world_uT))

    def earth_body_uT(self) -> np.ndarray:
        return self.truth.earth_body_series_uT(self.t_s)

    def exact_uT(self) -> np.ndarray:
        return exact_calibration(self.params, self.truth, self.dut_uT, self.temp_c)

    def clean(self) -> np.ndarray:
        return ~self.truth.disturbed_series(self.t_s)

    def level(self) -> np.ndarray:
        return self.truth.level_turn_series(self.t_s)

    def true_offset_sym(self, temp_c: float) -> np.ndarray:
        """(3,) the exact calibration's offset at ``temp_c`` in the symmetric gauge (rotation removed by the
        polar decomposition of its gain), and the rotation angle (deg) that gauge hides."""
        Y = np.vstack([np.zeros(3), np.eye(3)])
        E = exact_calibration(self.params, self.truth, Y, np.full(4, temp_c))
        S = (E[1:] - E[0]).T
        Q, _ = polar(S)
        return Q.T @ E[0]

    def hidden_rotation_deg(self, temp_c: float) -> float:
        Y = np.vstack([np.zeros(3), np.eye(3)])
        E = exact_calibration(self.params, self.truth, Y, np.full(4, temp_c))
        Q, _ = polar((E[1:] - E[0]).T)
        return math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(Q) - 1) / 2))))


def simulate_session(chip: str, program: str = "hand", seed: int = 0, *, rate_hz: float = 100.0,
                     duration_s: float | None = None, **truth_kw) -> SimSession:
    """A hand-rotation session of ``chip`` (error-model preset) under programme ``program``."""
    d = HAND_PROGRAMS[program][0] if duration_s is None else float(duration_s)
    truth = hand_program(program, d, seed=seed, **truth_kw)
    params = preset(chip)
    run = simulate_measurement(params, truth, duration_s=d, rate_hz=rate_hz, seed=int(seed) + 1000)
    return SimSession(chip, program, seed, truth, params, run.t_s, run.dut_uT, run.temp_c)


def rms(x) -> float:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def score(sess: SimSession, cal_uT: np.ndarray, rows: np.ndarray | None = None) -> dict:
    """Figures of a calibrated output ``cal_uT`` (N, 3) on ``rows`` (default: rows without the laptop):
    magnitude error RMS (uT) and the floor's, heading error in the level turns (deg: RMS, RMS about the
    mean, the mean = the heading offset) and the exact inverse's heading RMS."""
    F = sess.field_uT
    rows = sess.clean() if rows is None else rows
    exact = sess.exact_uT()
    mag = np.linalg.norm(cal_uT, axis=1) - F
    floor = np.linalg.norm(exact, axis=1) - F
    out = {"mag_rms_uT": rms(mag[rows]), "floor_rms_uT": rms(floor[rows])}
    lv = sess.level() & rows
    if lv.any():
        truth = sess.earth_body_uT()
        h = heading_error_deg(cal_uT[lv], truth[lv])
        out.update({"heading_rms_deg": rms(h), "heading_sd_deg": float(np.std(h)),
                    "heading_offset_deg": float(np.mean(h)),
                    "heading_floor_deg": rms(heading_error_deg(exact[lv], truth[lv]))})
    return out


def holdout_score(sess: SimSession, res) -> dict:
    """The hand calibration's held-out magnitude error against the site's field (rows without the laptop that
    the fit used), next to the floor on the same rows, and the hard iron's distance from the truth in
    posterior sds (symmetric gauge, at the model's reference temperature or the session's mean)."""
    F = sess.field_uT
    h = res.holdout_residual_uT
    rows = np.isfinite(h) & sess.clean()
    exact = sess.exact_uT()
    # the held-out residual is F_fit - |B_cal|: against the known F the same thing
    out = {"holdout_mag_rms_uT": rms(h[rows]), "floor_rms_uT": rms(np.linalg.norm(exact[rows], axis=1) - F)}
    out["ratio"] = out["holdout_mag_rms_uT"] / out["floor_rms_uT"]
    t_ref = res.model.t0_c if res.model.name == "eq3" else float(np.mean(sess.temp_c[res.used]))
    o_true = sess.true_offset_sym(t_ref)
    post = res.posterior
    z = []
    for i, a in enumerate("xyz"):
        k = post.par.names.index(f"O[{a}]")
        z.append((post.phi[k] - o_true[i]) / post.sd[k])
    out["offset_z"] = [float(v) for v in z]
    out["offset_err_uT"] = [float(post.phi[post.par.names.index(f"O[{a}]")] - o_true[i]) for i, a in enumerate("xyz")]
    out["offset_sd_uT"] = [float(post.sd[post.par.names.index(f"O[{a}]")]) for a in "xyz"]
    out["hidden_rotation_deg"] = sess.hidden_rotation_deg(t_ref)
    return out
