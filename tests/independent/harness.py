"""Cross-check harness: independent sessions (generator.py) -> ``magstack diagnose --json`` -> judged
against the generator's truth. Used by test_diagnosis_independent.py and run_matrix.py.

Only magstack's public entry point is used (``magstack.cli.main.main``) and only the JSON keys the diagnosis
documents (``verdict``, ``baseline_rmse_nT``, ``after_rmse_nT``, ``noise_floor_nT``, ``ranking``,
``not_testable``, ``where``, ``parameters``); ``runner_up`` and ``distinguishable`` are read when present
(the diagnosis names its runner-up and says how sure it is).
"""
from __future__ import annotations

import contextlib
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from generator import Scenario, make_session

#: ``--model`` under which each effect is withheld. Gain and misalignment share the calibration's gain
#: matrix, so they can only be withheld from a model without it (offset only).
MODEL_FOR = {"gain": "offset", "misalignment": "offset"}
DEFAULT_MODEL = "gain_offset"

#: JSON keys the diagnosis documents (top level and per ranking entry).
STABLE_KEYS = ("verdict", "baseline_rmse_nT", "after_rmse_nT", "noise_floor_nT", "ranking", "not_testable", "where",
               "parameters")
RANKING_KEYS = ("effect", "rmse_nT", "shrink", "significant")

#: Targets (1.2x on the project's own generator; 1.3x on this harness's).
AFTER_OVER_NOISE_MAX = 1.3


@dataclass
class Outcome:
    effect: str                  # true effect or "none"
    seed: int
    strength: float
    model: str
    verdict: str
    outcome: str                 # "hit", "runner_up" (indistinguishable, true one named), "miss", "ok", "false_alarm"
    after_over_noise: float
    excess_nT: float             # size of the effect the base model cannot absorb (noise-free oracle)
    doc: dict
    stdout: str

    def row(self) -> dict:
        d = self.doc
        return {"effect": self.effect, "seed": self.seed, "strength": self.strength, "model": self.model,
                "verdict": self.verdict, "outcome": self.outcome, "runner_up": d.get("runner_up"),
                "distinguishable": d.get("distinguishable"), "baseline_rmse_nT": d["baseline_rmse_nT"],
                "after_rmse_nT": d["after_rmse_nT"], "noise_floor_nT": d["noise_floor_nT"],
                "after_over_noise": self.after_over_noise, "excess_nT": self.excess_nT,
                "ranking": [(r["effect"], round(r["rmse_nT"], 1), r["significant"]) for r in d["ranking"]]}


def run_cli(argv: list[str]) -> str:
    """``magstack ARGV`` in-process through magstack.cli.main.main; returns stdout, raises on exit != 0."""
    from magstack.cli.main import main
    buf = io.StringIO()
    err = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    if rc != 0:
        raise AssertionError(f"magstack {argv[0]} exited {rc}: {err.getvalue().strip()}\n{buf.getvalue()[-2000:]}")
    return buf.getvalue()


def run_diagnose(paths, model: str | None, json_out: Path, table: Path | None = None) -> tuple[dict, str]:
    """``magstack diagnose PATHS (--model MODEL | --table cal.json) --json OUT``; returns (JSON, stdout)."""
    how = ["--table", table] if table is not None else ["--model", model]
    out = run_cli(["diagnose", *paths, *how, "--json", json_out])
    return json.loads(Path(json_out).read_text()), out


def judge(doc: dict, effect: str | None) -> str:
    v = doc["verdict"]
    if effect is None:
        return "ok" if v == "none" else "false_alarm"
    if v == effect:
        return "hit"
    if doc.get("distinguishable") is False and doc.get("runner_up") == effect:
        return "runner_up"
    return "miss"


def excess_nT(g, model: str) -> float:
    """Oracle effect size: the noise-free DUT reading after what ``model``'s base absorbs in-sample
    when fitted on the true room field (gain_offset: gain matrix + offset; offset: identity gain +
    offset); norm of per-axis RMS, nT. Tells "diagnosis wrong" from "effect below what the data can
    show" (docs/diagnosis-independent.md). Includes the rows at coil steps the diagnosis leaves out."""
    rt = g.extras["ref_truth_uT"]
    y = g.extras["clean_dut_uT"]
    if model == "gain_offset":
        X = np.column_stack([rt, np.ones(len(rt))])
    elif model == "offset":
        X, y = np.ones((len(rt), 1)), y - rt
    else:
        raise ValueError(model)
    th, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(np.linalg.norm(np.sqrt(np.mean((y - X @ th) ** 2, axis=0))) * 1e3)


def fit_table(tmp: Path, seed: int, device_seed: int) -> Path:
    """Mode (b) "last month's model": a gain+offset table fitted (``magstack fit``, transition rows
    excluded) on a clean session of unit ``device_seed``."""
    path = make_session(Scenario(effect=None, seed=seed, device_seed=device_seed)).write(Path(tmp) / f"cal_{seed}.csv")
    out = Path(tmp) / f"cal_{seed}.json"
    run_cli(["fit", path, "--model", "gain_offset", "--exclude-steps", "3", "--out", out])
    return out


def case(tmp: Path, effect: str | None, seed: int, strength: float = 1.0, table: Path | None = None,
         **scenario) -> Outcome:
    """Generate one session, diagnose it (``--model`` withholding the effect, or ``--table``), judge it."""
    sc = Scenario(effect=effect, seed=seed, strength=strength, **scenario)
    g = make_session(sc)
    name = f"{effect or 'none'}_s{seed}_x{strength:g}"
    path = g.write(Path(tmp) / f"{name}.csv")
    model = MODEL_FOR.get(effect, DEFAULT_MODEL)
    doc, out = run_diagnose([path], model, Path(tmp) / f"{name}.diag.json", table)
    if table is not None:
        model = f"--table {Path(table).name}"
    missing = [k for k in STABLE_KEYS if k not in doc]
    missing += [f"ranking[].{k}" for k in RANKING_KEYS if any(k not in r for r in doc.get("ranking", []))]
    assert not missing, f"diagnose --json lacks the stable keys {missing}"
    nf = doc["noise_floor_nT"]
    ratio = float(doc["after_rmse_nT"] / nf) if nf else float("nan")
    return Outcome(effect or "none", seed, strength, model, doc["verdict"], judge(doc, effect), ratio,
                   excess_nT(g, "gain_offset" if table is not None else model), doc, out)
