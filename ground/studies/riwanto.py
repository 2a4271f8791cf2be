"""Reproduction of the simulation study of Riwanto et al. (2017), section IV-A, plus a
closed-form + least-squares comparison on the same data.

Truth (Table II "Reference"): ``S_mc``, ``off_mc``; forward model eq. (2a)
``b_meas = S_mc (b + off_mc + eta)`` (noise inside S_mc), 100 measurements per model, exact
rotation axes. Models (section IV-A):

====  ===================  ====================  ========
 M    loci                 |b| (nT)              delta nT
====  ===================  ====================  ========
 1    3 full circles       35 000                2000
 2    3 full circles       35 000                5500
 3    2 full circles       35 000                2000
 4    2 full circles       17 000 -> 48 000      2000
 5    3 incomplete circles 35 000                2000
====  ===================  ====================  ========

Not given by the paper, our choices (docs/refit-pso.md): the body turns about its x, y (and
z) axes in that order, right-handed, by equal angle steps; the field in the body frame is
perpendicular to the rotation axis (great circles) and starts along y, z, x respectively;
the 100 samples are split as evenly as possible over the loci (34/33/33, 50/50); a
"full circle" is 360 deg without repeating the first sample; M5's arcs span 120 deg;
M4's magnitude rises linearly with the global sample index; the noise is Gaussian, iid per
axis with standard deviation delta.

Seeds: ``numpy.random.SeedSequence(seed).spawn(2)`` gives the data generator and the PSO
generator, so a result is a function of ``(model, seed)`` alone.
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from magstack.firmware.calibration import pso as _pso
from magstack.firmware.calibration.scalar import fit_scalar
from magstack.firmware.errors import FitError
from magstack.ground.errors import GroundError

#: Table II reference (truth): compounded scale matrix and offset (eq. 2a).
TRUTH_S_MC = np.array([[0.749, 0.354, 0.677], [-0.242, 1.122, -0.209], [-0.395, -1.043, 2.433]])
TRUTH_OFF_NT = np.array([12600.0, -200.0, 1800.0])

N_SAMPLES = 100


def _s(s11, s22, s33, s12, s13, s23, s21, s31, s32) -> list[list[float]]:
    """Table II row order (11, 22, 33, 12, 13, 23, 21, 31, 32) -> matrix."""
    return [[s11, s12, s13], [s21, s22, s23], [s31, s32, s33]]


#: Table II PSO columns: best fitness F_g, estimated S_mc and off_mc (nT), as printed.
PAPER_TABLE_II: dict[int, dict[str, Any]] = {
    1: {"fitness": 199.05, "S_mc": _s(0.758, 1.129, 2.424, 0.378, 0.683, -0.18, -0.23, -0.403, -0.984),
        "offset_nT": [12586.0, -811.0, 1420.0]},
    2: {"fitness": 470.09, "S_mc": _s(0.784, 1.205, 2.583, 0.392, 0.719, -0.277, -0.204, -0.442, -0.993),
        "offset_nT": [12053.0, -1236.0, 1577.0]},
    3: {"fitness": 185.0, "S_mc": _s(0.725, 1.141, 2.49, 0.365, 0.665, -0.265, -0.239, -0.458, -1.03),
        "offset_nT": [12781.0, -182.0, 2309.0]},
    4: {"fitness": 179.39, "S_mc": _s(0.774, 1.098, 2.388, 0.324, 0.767, -0.112, -0.255, -0.428, -1.117),
        "offset_nT": [11590.0, -772.0, 1886.0]},
    5: {"fitness": 200.36, "S_mc": _s(0.82, 1.114, 2.578, 0.315, 0.608, -0.229, -0.212, -0.137, -0.999),
        "offset_nT": [11565.0, -263.0, 157.0]},
}


@dataclass(frozen=True)
class PaperModel:
    """One simulation model of section IV-A."""

    number: int
    n_loci: int
    b_nT: tuple[float, float]      # |b| at the first and last sample (equal = constant)
    delta_nT: float
    arc_deg: float = 360.0


PAPER_MODELS: dict[int, PaperModel] = {
    1: PaperModel(1, 3, (35000.0, 35000.0), 2000.0),
    2: PaperModel(2, 3, (35000.0, 35000.0), 5500.0),
    3: PaperModel(3, 2, (35000.0, 35000.0), 2000.0),
    4: PaperModel(4, 2, (17000.0, 48000.0), 2000.0),
    5: PaperModel(5, 3, (35000.0, 35000.0), 2000.0, arc_deg=120.0),
}


@dataclass(frozen=True)
class StudyData:
    """Simulated measurements (nT), labels and the truth that made them."""

    b_meas_nT: np.ndarray          # (N, 3) sensor output
    b_ref_norm_nT: np.ndarray      # (N,) reference magnitude |b|
    b_true_nT: np.ndarray          # (N, 3) field in the body frame
    locus: np.ndarray              # (N,) locus label 0..L-1
    omega: np.ndarray              # (L, 3) unit rotation axes (body frame)
    noise_nT: np.ndarray           # (N, 3) eta


def simulate(model: PaperModel, rng: np.random.Generator, n: int = N_SAMPLES) -> StudyData:
    """Measurements of ``model`` (module doc for the geometry)."""
    axes = np.eye(3)[: model.n_loci]
    start = np.eye(3)[[1, 2, 0]][: model.n_loci]            # field at the first sample, perpendicular to axis
    counts = [len(a) for a in np.array_split(np.arange(n), model.n_loci)]
    dirs, labels = [], []
    for l, n_l in enumerate(counts):
        full = model.arc_deg >= 360.0
        angle = np.deg2rad(model.arc_deg) * np.arange(n_l) / (n_l if full else max(n_l - 1, 1))
        # the body turns by +angle about omega; a fixed field turns by -angle in the body frame
        dirs.append(Rotation.from_rotvec(-angle[:, None] * axes[l]).apply(start[l]))
        labels.append(np.full(n_l, l))
    mag = np.linspace(model.b_nT[0], model.b_nT[1], n)
    b_true = np.vstack(dirs) * mag[:, None]
    eta = rng.normal(0.0, model.delta_nT, size=(n, 3))
    b_meas = (b_true + TRUTH_OFF_NT + eta) @ TRUTH_S_MC.T        # eq. (2a)
    return StudyData(b_meas, mag, b_true, np.concatenate(labels), axes, eta)


def _errors(S_mc: np.ndarray, off_nT: np.ndarray) -> dict[str, float]:
    return {"dS_fro": float(np.linalg.norm(S_mc - TRUTH_S_MC)),
            "doff_nT": float(np.linalg.norm(off_nT - TRUTH_OFF_NT))}


@dataclass(frozen=True)
class PaperModelResult:
    """PSO and least-squares answers for one ``(model, seed)``."""

    model: int
    seed: int
    pso: _pso.PsoResult
    fitness_at_truth: float
    scalar_K: np.ndarray
    scalar_k_nT: np.ndarray
    scalar_fitness: float
    scalar_runtime_s: float

    def to_dict(self) -> dict[str, Any]:
        m = PAPER_MODELS[self.model]
        r = self.pso
        S_ls = np.linalg.inv(self.scalar_K)
        paper = PAPER_TABLE_II[self.model]
        return {
            "model": self.model, "seed": self.seed,
            "fitness": r.fitness, "S_mc": r.S_mc.tolist(), "offset_nT": r.k_nT.tolist(),
            "runtime_s": r.runtime_s,
            "K_m": r.K.tolist(), "f1_term_nT": r.f1_term, "f2_term": r.f2_term, "mirrored": r.mirrored,
            "n_evaluations": r.n_evaluations, **_errors(r.S_mc, r.k_nT),
            "fitness_at_truth": self.fitness_at_truth,
            "noise_floor_nT": m.delta_nT / np.sqrt(N_SAMPLES),
            "paper": {"fitness": paper["fitness"], "S_mc": paper["S_mc"], "offset_nT": paper["offset_nT"],
                      **_errors(np.array(paper["S_mc"]), np.array(paper["offset_nT"]))},
            "truth": {"S_mc": TRUTH_S_MC.tolist(), "offset_nT": TRUTH_OFF_NT.tolist()},
            "least_squares": {"fitness": self.scalar_fitness, "S_mc": S_ls.tolist(),
                              "offset_nT": self.scalar_k_nT.tolist(), "runtime_s": self.scalar_runtime_s,
                              **_errors(S_ls, self.scalar_k_nT)},
        }


def _generators(seed: int) -> tuple[np.random.Generator, np.random.SeedSequence]:
    data_ss, pso_ss = np.random.SeedSequence(seed).spawn(2)
    return np.random.default_rng(data_ss), pso_ss


def run_paper_model(model: int, seed: int = 0, options: _pso.PsoOptions | None = None,
                    progress=None) -> PaperModelResult:
    """Simulate paper model ``model`` (1-5) with ``seed``; run the PSO and the closed-form +
    least-squares path (scalar fit, rotation from the loci's axes) on the same data."""
    if model not in PAPER_MODELS:
        raise GroundError(f"paper model must be one of {sorted(PAPER_MODELS)}, got {model}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise GroundError(f"seed must be a non-negative integer, got {seed!r}")
    opt = options or _pso.PsoOptions()
    rng, pso_ss = _generators(int(seed))
    data = simulate(PAPER_MODELS[model], rng)
    prob = _pso.Problem.build(data.b_meas_nT, data.b_ref_norm_nT, data.locus, data.omega, opt.sign_rule)
    res = _pso.run_pso(prob, seed=pso_ss, options=opt, progress=progress)
    truth = np.r_[np.linalg.inv(TRUTH_S_MC).ravel(), TRUTH_OFF_NT]
    t0 = time.perf_counter()
    ls = fit_scalar(data.b_meas_nT, data.b_ref_norm_nT, gauge="axes", locus=data.locus, omega=data.omega)
    t_ls = time.perf_counter() - t0
    f_ls = float(_pso.fitness(np.r_[ls.K.ravel(), ls.k], prob, opt)[0])
    pso_res = dataclasses.replace(res, seed=int(seed))
    return PaperModelResult(model=model, seed=int(seed), pso=pso_res,
                            fitness_at_truth=float(_pso.fitness(truth, prob, opt)[0]),
                            scalar_K=ls.K, scalar_k_nT=ls.k, scalar_fitness=f_ls, scalar_runtime_s=t_ls)


def study(models=(1, 2, 3, 4, 5), seeds=range(10), options: _pso.PsoOptions | None = None) -> list[dict]:
    """``to_dict()`` of every (model, seed)."""
    return [run_paper_model(m, s, options).to_dict() for m in models for s in seeds]


def summary_markdown(rows: list[dict]) -> str:
    """Per-model table: median (min-max) over seeds, PSO next to least squares, and Table II."""
    def mm(v) -> str:
        v = np.asarray(v, float)
        return f"{np.median(v):.4g} ({v.min():.4g}-{v.max():.4g})"
    out = ["| model | seeds | PSO F_g | F at truth | paper F_g | PSO ‖ΔS‖_F | LS ‖ΔS‖_F | paper ‖ΔS‖_F | "
           "PSO ‖Δoff‖ nT | LS ‖Δoff‖ nT | paper ‖Δoff‖ nT | LS F (eq. 10) | PSO s | LS s | mirror fixed |",
           "|" + "---|" * 15]
    for m in sorted({r["model"] for r in rows}):
        rs = [r for r in rows if r["model"] == m]
        ls = [r["least_squares"] for r in rs]
        p = rs[0]["paper"]
        out.append(f"| {m} | {len(rs)} | {mm([r['fitness'] for r in rs])} | {mm([r['fitness_at_truth'] for r in rs])}"
                   f" | {p['fitness']} | {mm([r['dS_fro'] for r in rs])} | {mm([x['dS_fro'] for x in ls])}"
                   f" | {p['dS_fro']:.3f} | {mm([r['doff_nT'] for r in rs])} | {mm([x['doff_nT'] for x in ls])}"
                   f" | {p['doff_nT']:.0f} | {mm([x['fitness'] for x in ls])}"
                   f" | {np.median([r['runtime_s'] for r in rs]):.3f}"
                   f" | {np.median([x['runtime_s'] for x in ls]):.4f}"
                   f" | {sum(r['mirrored'] for r in rs)}/{len(rs)} |")
    return "\n".join(out)


def parameter_markdown(rows: list[dict]) -> str:
    """Recovered parameters of one run per model next to Table II, in the paper's row order."""
    order = [("off1", None), ("off2", None), ("off3", None), ("S11", (0, 0)), ("S22", (1, 1)), ("S33", (2, 2)),
             ("S12", (0, 1)), ("S13", (0, 2)), ("S23", (1, 2)), ("S21", (1, 0)), ("S31", (2, 0)), ("S32", (2, 1))]
    models = sorted({r["model"] for r in rows})
    first = {m: next(r for r in rows if r["model"] == m) for m in models}
    head = "| param | truth | " + " | ".join(f"M{m} PSO (seed {first[m]['seed']}) | M{m} paper | M{m} LS"
                                            for m in models) + " |"
    out = [head, "|" + "---|" * (2 + 3 * len(models))]

    def val(d, name, ij):
        if ij is None:
            return d["offset_nT"][int(name[-1]) - 1]
        return d["S_mc"][ij[0]][ij[1]]
    truth = first[models[0]]["truth"]
    for name, ij in order:
        cells = [name, f"{val(truth, name, ij):.4g}"]
        for m in models:
            r = first[m]
            cells += [f"{val(r, name, ij):.4g}", f"{val(r['paper'], name, ij):.4g}",
                      f"{val(r['least_squares'], name, ij):.4g}"]
        out.append("| " + " | ".join(cells) + " |")
    out.append("| F_g | | " + " | ".join(f"{first[m]['fitness']:.2f} | {first[m]['paper']['fitness']} | "
                                         f"{first[m]['least_squares']['fitness']:.2f}" for m in models) + " |")
    return "\n".join(out)


def simulate_general(rng: np.random.Generator, n: int = N_SAMPLES, delta_nT: float = 2000.0,
                     b_nT: float = 35000.0) -> StudyData:
    """Beyond the paper's geometry: 2 or 3 loci about random axes, the field on a cone of 40-90 deg
    round each axis (small circles, as for a spinning spacecraft), arcs of 150-360 deg; same truth,
    forward model and noise as :func:`simulate`."""
    n_loci = int(rng.integers(2, 4))
    axes = Rotation.random(n_loci, random_state=rng).apply([0.0, 0.0, 1.0])
    counts = [len(a) for a in np.array_split(np.arange(n), n_loci)]
    dirs, labels = [], []
    for l, n_l in enumerate(counts):
        cone = np.deg2rad(rng.uniform(40.0, 90.0))
        perp = np.cross(axes[l], rng.normal(size=3))
        perp /= np.linalg.norm(perp)
        start = np.cos(cone) * axes[l] + np.sin(cone) * perp
        turn = np.deg2rad(rng.uniform(150.0, 360.0)) * np.arange(n_l) / n_l
        dirs.append(Rotation.from_rotvec(-turn[:, None] * axes[l]).apply(start))
        labels.append(np.full(n_l, l))
    b_true = np.vstack(dirs) * b_nT
    eta = rng.normal(0.0, delta_nT, size=(n, 3))
    b_meas = (b_true + TRUTH_OFF_NT + eta) @ TRUTH_S_MC.T
    return StudyData(b_meas, np.full(n, b_nT), b_true, np.concatenate(labels), axes, eta)


def general_markdown(seeds=range(20), options: _pso.PsoOptions | None = None) -> str:
    """PSO and least squares on :func:`simulate_general` data (seed -> same split as the paper runs)."""
    opt = options or _pso.PsoOptions()
    rows = []
    for seed in seeds:
        rng, pso_ss = _generators(seed)
        d = simulate_general(rng)
        prob = _pso.Problem.build(d.b_meas_nT, d.b_ref_norm_nT, d.locus, d.omega, opt.sign_rule)
        r = _pso.run_pso(prob, seed=pso_ss, options=opt)
        truth = np.r_[np.linalg.inv(TRUTH_S_MC).ravel(), TRUTH_OFF_NT]
        try:
            ls = fit_scalar(d.b_meas_nT, d.b_ref_norm_nT, gauge="axes", locus=d.locus, omega=d.omega)
            ls_row = (float(_pso.fitness(np.r_[ls.K.ravel(), ls.k], prob, opt)[0]),
                      *_errors(np.linalg.inv(ls.K), ls.k).values())
        except FitError:
            ls_row = (np.nan, np.nan, np.nan)
        rows.append((r.fitness, float(_pso.fitness(truth, prob, opt)[0]), *_errors(r.S_mc, r.k_nT).values(),
                     *ls_row, len(d.omega)))
    allrows = np.array(rows, dtype=float)

    def mm(v) -> str:
        ok = v[np.isfinite(v)]
        miss = len(v) - len(ok)
        return f"{np.median(ok):.4g} ({ok.min():.4g}-{ok.max():.4g})" + (f", {miss} refused" if miss else "")
    out = ["| loci | runs | quantity | PSO | least squares |", "|---|---|---|---|---|"]
    for n_loci in (2, 3):
        a = allrows[allrows[:, 7] == n_loci]
        if not len(a):
            continue
        head = f"| {n_loci} | {len(a)} |"
        out += [f"{head} eq.-10 fitness (F at truth {mm(a[:, 1])}) | {mm(a[:, 0])} | {mm(a[:, 4])} |",
                f"{head} ‖ΔS‖_F | {mm(a[:, 2])} | {mm(a[:, 5])} |",
                f"{head} ‖Δoff‖ nT | {mm(a[:, 3])} | {mm(a[:, 6])} |",
                f"{head} runs with ‖ΔS‖_F > 0.3 | {int(np.sum(a[:, 2] > 0.3))} | {int(np.sum(a[:, 5] > 0.3))} |"]
    return "\n".join(out)


#: Alternative readings of Table I / Fig. 2 compared in docs/refit-pso.md.
VARIANTS: dict[str, _pso.PsoOptions] = {
    "default (3 cycles of 0.1 k_max, v_lim 50, area sign rule)": _pso.PsoOptions(),
    "k_max = 1000": _pso.PsoOptions(k_max=1000),
    "5 cycles of 0.05 k_max": _pso.PsoOptions(w_v_frac=0.05, c_v_frac=0.05, n_cycles=5),
    "2 cycles of 0.2 k_max": _pso.PsoOptions(w_v_frac=0.2, c_v_frac=0.2, n_cycles=2),
    "1 cycle of 0.4 k_max": _pso.PsoOptions(w_v_frac=0.4, c_v_frac=0.4, n_cycles=1),
    "constriction reading of the end phase (c_e = 0.382 x 2.5)": _pso.PsoOptions(c_e=0.382 * 2.5),
    "v_lim = 10": _pso.PsoOptions(v_lim=10.0),
    "v_lim = 2 (the text's starting point)": _pso.PsoOptions(v_lim=2.0),
    "paper's pair sign rule (automatic q)": _pso.PsoOptions(sign_rule="pair"),
}


def variants_markdown(model: int = 1, seeds=range(10), variants: dict | None = None) -> str:
    """Eq.-(10) fitness of the PSO minus that of the least-squares answer on the same data
    (same sign rule), median / worst over ``seeds``, per PSO variant."""
    data = []
    for seed in seeds:
        rng, pso_ss = _generators(seed)
        d = simulate(PAPER_MODELS[model], rng)
        ls = fit_scalar(d.b_meas_nT, d.b_ref_norm_nT, gauge="axes", locus=d.locus, omega=d.omega)
        data.append((d, pso_ss, np.r_[ls.K.ravel(), ls.k]))
    out = ["| variant | median | worst |", "|---|---|---|"]
    for name, opt in (variants or VARIANTS).items():
        diff = []
        for d, pso_ss, x_ls in data:
            prob = _pso.Problem.build(d.b_meas_nT, d.b_ref_norm_nT, d.locus, d.omega, opt.sign_rule)
            diff.append(_pso.run_pso(prob, seed=pso_ss, options=opt).fitness - _pso.fitness(x_ls, prob, opt)[0])
        out.append(f"| {name} | {np.median(diff):+.1f} | {np.max(diff):+.1f} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="riwanto PSO simulation study (docs/refit-pso.md)")
    ap.add_argument("--models", default="1,2,3,4,5")
    ap.add_argument("--seeds", type=int, default=10, help="seeds 0..N-1")
    ap.add_argument("--variants", action="store_true", help="compare PSO readings on model 1 instead")
    ap.add_argument("--general", action="store_true", help="random small-circle geometries instead")
    a = ap.parse_args(argv)
    if a.general:
        print(general_markdown(range(a.seeds)))
        return 0
    if a.variants:
        print(variants_markdown(1, range(a.seeds)))
        return 0
    rows = study([int(x) for x in a.models.split(",")], range(a.seeds))
    print(summary_markdown(rows))
    print()
    print(parameter_markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
