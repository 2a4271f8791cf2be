"""Coverage of the calibration's accuracy figures on benches the fit never saw (docs/calibration-coverage.md).

magstack is used only as a user uses it: session files written with :mod:`magstack.data.session`, then
``magstack fit BENCH.csv --out cal.json`` (defaults) and ``magstack apply cal.json HELD.csv --out x.csv
--extrapolate`` run in-process through :func:`magstack.cli.main.main`. The data come from the independent
generator :mod:`bench_generator`.

The predictive sd of each held-out sample is read from ``apply``'s per-axis columns ``cal_sigma_{x,y,z}_nT``
(the total predictive sd: ``mode = "total"``, compared with the error of the noisy sample). Without them it is
the table's parameter posterior (:func:`magstack.firmware.cal_uncertainty.predictive_sd_uT`, ``mode =
"param"``): that figure claims only the error of the calibration itself, so it is compared with the error of
the same sample without noise. The parameter part is also always checked that way (``param_*`` keys).

Per bench (:func:`run_bench`): shares of per-axis errors within 1 and 2 sd (honest 0.68 / 0.95) and of the
vector error within 1 and 2 vector sd (chi-square(3): 0.61 / 0.993) on (i) a fresh realisation of the
bench (where the data are) and (ii) the box grid's points inside the table's validity box (the ``apply``
flag decides; shares weighted to area shares); the share of box points whose vector error exceeds the
table's ``posterior.bound_uT`` (noise-free and noisy samples); the exit code of ``fit``, whether the box
held any point, and its extent.
"""
from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

from magstack.cli.main import main
from magstack.data.dictionary import FLAG
from magstack.data.session import Session, read_session, write_session


def _sibling(name: str):
    """The module ``name`` beside this file, loaded by path (``sys.path`` is left alone: other test folders
    have modules of the same names)."""
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().with_name(f"{name}.py"))
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return sys.modules[name]


gen = _sibling("bench_generator")

OUT_OF_BOX = FLAG["APPLY_OUT_OF_VALIDITY"].value
SESSION_METADATA = {"dut_chip": "hmc1053", "reference": "fvm400"}
AXIS_SD_COLUMNS = ("cal_sigma_x_nT", "cal_sigma_y_nT", "cal_sigma_z_nT")
#: Honest shares: per axis |e| <= 1, 2 sd (normal); vector |e| <= 1, 2 vector sd (chi-square(3), equal axes).
HONEST_AXIS = (0.6827, 0.9545)
HONEST_VECTOR = (0.6084, 0.9926)


def cli(argv: list[str]) -> tuple[int, str]:
    """Run ``magstack ARGV`` in-process; (exit code, what it printed)."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        rc = main(argv)
    return rc, buf.getvalue()


def _write(path: Path, p: gen.Programme, dut_uT: np.ndarray) -> Path:
    write_session(path, Session(p.t_s, p.b_uT, dut_uT, p.temp_c, p.session, metadata=dict(SESSION_METADATA)))
    return path


def _held(b: gen.Bench, clean: bool) -> tuple[gen.Programme, np.ndarray]:
    """The held-out session: the fresh realisation's rows, then the box grid's."""
    p = gen.Programme(*(np.concatenate([getattr(b.again, f), getattr(b.grid, f)])
                        for f in ("t_s", "b_uT", "temp_c", "session")))
    dut = np.concatenate([b.again_clean_uT, b.grid_clean_uT] if clean else [b.again_dut_uT, b.grid_dut_uT])
    return p, dut


def _shares(z: np.ndarray, w: np.ndarray | None = None) -> list[float | None]:
    """Weighted shares of finite z <= 1 and <= 2 (None when there is none)."""
    w = np.ones_like(z) if w is None else np.broadcast_to(w, z.shape)
    ok = np.isfinite(z)
    if not ok.any() or w[ok].sum() <= 0:
        return [None, None]
    return [float(np.sum(w[ok] * (z[ok] <= k)) / np.sum(w[ok])) for k in (1.0, 2.0)]


def _coverage(err: np.ndarray, sd: np.ndarray, rows: np.ndarray, w: np.ndarray | None = None) -> dict:
    """Per-axis and vector shares over ``rows`` (err, sd (N, 3) uT)."""
    e, s = err[rows], sd[rows]
    ww = None if w is None else w[rows]
    with np.errstate(divide="ignore", invalid="ignore"):
        z_axis = np.abs(e) / s
        z_vec = np.linalg.norm(e, axis=1) / np.sqrt(np.sum(s ** 2, axis=1))
    vsd = np.sqrt(np.sum(s ** 2, axis=1))
    vsd = vsd[np.isfinite(vsd)]
    return {"axis": _shares(z_axis, None if ww is None else ww[:, None]), "vector": _shares(z_vec, ww),
            "median_sd_nT": float(np.median(vsd)) * 1e3 if vsd.size else None}


def _apply(table: Path, held: Path, out: Path) -> Session:
    rc, text = cli(["apply", str(table), str(held), "--out", str(out), "--extrapolate", "-q"])
    if rc != 0:
        raise RuntimeError(f"magstack apply exited {rc}: {text.strip()[-400:]}")
    return read_session(out)


def run_bench(shape: str, index: int, seed: int = 0, workdir: str | Path | None = None) -> dict:
    """Fit one bench with defaults, apply the table to its held-out data, and measure the coverage."""
    from magstack.firmware.cal_uncertainty import predictive_sd_uT

    b = gen.make_bench(shape, index, seed)
    with contextlib.ExitStack() as stack:
        d = Path(workdir) if workdir is not None else Path(stack.enter_context(tempfile.TemporaryDirectory()))
        d.mkdir(parents=True, exist_ok=True)
        stem = f"{shape}-{seed}-{index}"
        bench = _write(d / f"{stem}-bench.csv", b.fit, b.fit_dut_uT)
        table = d / f"{stem}-cal.json"
        rc, text = cli(["fit", str(bench), "--out", str(table), "-q"])
        res: dict = {"shape": shape, "index": index, "seed": seed, "fit_exit": rc, "refused": not table.exists(),
                     "data_temp_c": [float(b.fit.temp_c.min()), float(b.fit.temp_c.max())],
                     "data_field_uT": float(np.abs(b.fit.b_uT).max()),
                     "big_offset_tempco": bool(abs(b.sensor.k_o_uT_per_c[0]) > 0.1)}
        if rc != 0:
            res["fit_message"] = text.strip().splitlines()[-1] if text.strip() else ""
        if res["refused"]:
            return res
        doc = json.loads(table.read_text())
        post = doc.get("posterior")
        res["box_temp_c"] = doc["validity"].get("temp_c")
        res["box_field_uT"] = doc["validity"].get("field_uT")
        res["bound_uT"] = None if post is None else post.get("bound_uT")
        noisy = _apply(table, _write(d / f"{stem}-held.csv", *_held(b, clean=False)), d / f"{stem}-held-cal.csv")
        clean = _apply(table, _write(d / f"{stem}-held-clean.csv", *_held(b, clean=True)), d / f"{stem}-clean-cal.csv")
    n_again = b.again.t_s.size
    again = np.arange(noisy.t_s.size) < n_again
    w = np.concatenate([np.zeros(n_again), b.grid_weight])
    ref = noisy.ref_uT
    err_noisy, err_clean = noisy.dut_uT - ref, clean.dut_uT - ref
    in_box_noisy = (noisy.flag & OUT_OF_BOX) == 0
    in_box_clean = (clean.flag & OUT_OF_BOX) == 0
    res["no_box"] = not (in_box_noisy.any() or in_box_clean.any())
    res["box_points"] = int(np.sum(~again & in_box_noisy))
    res["box_area_share"] = float(np.sum(w[in_box_noisy]) / np.sum(w))

    param_sd = None
    if post is not None:
        _, raw_clean = _held(b, clean=True)
        param_sd = predictive_sd_uT(post, doc["model"]["t0_c"], raw_clean, clean.temp_c)
    if all(c in noisy.extra for c in AXIS_SD_COLUMNS):
        res["mode"] = "total"
        sd = np.column_stack([noisy.extra[c] for c in AXIS_SD_COLUMNS]) * 1e-3
        err, in_box = err_noisy, in_box_noisy
    else:
        res["mode"] = "param"
        sd, err, in_box = param_sd, err_clean, in_box_clean
    res["sd_missing_rows"] = None if sd is None else int(np.sum(~np.all(np.isfinite(sd), axis=1)))
    g, f = b.grid, b.fit
    grid_in_range = np.zeros(again.size, bool)    # inside the fit data's temperature and per-axis field range
    grid_in_range[n_again:] = ((g.temp_c >= f.temp_c.min()) & (g.temp_c <= f.temp_c.max())
                               & np.all((g.b_uT >= f.b_uT.min(axis=0)) & (g.b_uT <= f.b_uT.max(axis=0)), axis=1))
    if sd is not None:
        res["in_range"] = _coverage(err, sd, again)
        res["in_box"] = _coverage(err, sd, ~again & in_box, w)
        res["grid_in_range"] = _coverage(err, sd, grid_in_range, w)
    if param_sd is not None:
        res["param_in_range"] = _coverage(err_clean, param_sd, again)
        res["param_in_box"] = _coverage(err_clean, param_sd, ~again & in_box_clean, w)
    bound = res["bound_uT"]
    for name, e, inb in (("clean", err_clean, in_box_clean), ("noisy", err_noisy, in_box_noisy)):
        rows = ~again & inb & np.all(np.isfinite(e), axis=1)
        ev = np.linalg.norm(e[rows], axis=1)
        res[f"box_max_error_{name}_uT"] = float(ev.max()) if ev.size else None
        res[f"box_above_bound_{name}"] = (None if bound is None or not ev.size
                                          else float(np.sum(w[rows] * (ev > bound)) / np.sum(w[rows])))
    return res


# ---------------------------------------------------------------------------------------- summary

def _mean(vals) -> float | None:
    v = [x for x in vals if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return float(np.mean(v)) if v else None


def _get(r: dict, *keys):
    for k in keys:
        if not isinstance(r, dict) or r.get(k) is None:
            return None
        r = r[k]
    return r


def _largest(field) -> float | None:
    """The box's field limit as one number: the limit, or the largest of per-axis / per-direction limits."""
    if isinstance(field, dict):
        field = list(field.values())
    try:
        return float(np.max(np.asarray(field, dtype=float)))
    except (TypeError, ValueError):
        return None


def summarise(results: list[dict]) -> dict:
    """Per shape: mean over its benches of each share (benches without the figure skipped), counts, box extent."""
    out: dict = {}
    for shape in dict.fromkeys(r["shape"] for r in results):
        rs = [r for r in results if r["shape"] == shape]
        s: dict = {"benches": len(rs), "refused": sum(r["refused"] for r in rs),
                   "fit_exit_nonzero": sum(r["fit_exit"] != 0 for r in rs),
                   "no_box": sum(bool(r.get("no_box")) for r in rs),
                   "modes": sorted({r["mode"] for r in rs if "mode" in r}),
                   "sd_missing_rows": sum(r.get("sd_missing_rows") or 0 for r in rs)}
        for part in ("in_range", "in_box", "grid_in_range", "param_in_range", "param_in_box"):
            for kind in ("axis", "vector"):
                for j, k in enumerate((1, 2)):
                    vals = [_get(r, part, kind) for r in rs]
                    s[f"{part}_{kind}_{k}sd"] = _mean([None if v is None else v[j] for v in vals])
            v2 = [_get(r, part, "axis") for r in rs]
            v2 = [v[1] for v in v2 if v is not None and v[1] is not None]
            s[f"{part}_axis_min_2sd"] = min(v2) if v2 else None
        for name in ("clean", "noisy"):
            s[f"box_above_bound_{name}"] = _mean([r.get(f"box_above_bound_{name}") for r in rs])
            s[f"box_above_bound_{name}_max"] = max((r[f"box_above_bound_{name}"] for r in rs
                                                    if r.get(f"box_above_bound_{name}") is not None), default=None)
        temps = [r["box_temp_c"] for r in rs if r.get("box_temp_c")]
        fields = [r["box_field_uT"] for r in rs if r.get("box_field_uT") is not None]
        s["box_temp_c_median"] = [float(np.median([t[0] for t in temps])), float(np.median([t[1] for t in temps]))] \
            if temps else None
        fields = [f for f in (_largest(f) for f in fields) if f is not None]
        s["box_field_uT_median"] = float(np.median(fields)) if fields else None
        s["box_area_share_median"] = (float(np.median([r["box_area_share"] for r in rs if "box_area_share" in r]))
                                      if any("box_area_share" in r for r in rs) else None)
        out[shape] = s
    return out


def _f(x, fmt="{:.2f}") -> str:
    return "-" if x is None else fmt.format(x)


def table_text(summary: dict) -> str:
    """The per-shape table (markdown)."""
    lines = ["| bench shape | n | refused / exit!=0 / no box | sd | in range 1 / 2 sd | in box 1 / 2 sd (min 2 sd) "
             "| vector in box 1 / 2 | box above bound clean / noisy (max) | box degC | box uT |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for shape, s in summary.items():
        t = s["box_temp_c_median"]
        lines.append(
            f"| {shape} | {s['benches']} | {s['refused']} / {s['fit_exit_nonzero']} / {s['no_box']} | "
            f"{'+'.join(s['modes']) or '-'} | "
            f"{_f(s['in_range_axis_1sd'])} / {_f(s['in_range_axis_2sd'])} | "
            f"{_f(s['in_box_axis_1sd'])} / {_f(s['in_box_axis_2sd'])} ({_f(s['in_box_axis_min_2sd'])}) | "
            f"{_f(s['in_box_vector_1sd'])} / {_f(s['in_box_vector_2sd'])} | "
            f"{_f(s['box_above_bound_clean'])} / {_f(s['box_above_bound_noisy'])} "
            f"({_f(s['box_above_bound_noisy_max'])}) | "
            f"{'-' if t is None else f'{t[0]:.0f}..{t[1]:.0f}'} | {_f(s['box_field_uT_median'], '{:.0f}')} |")
    return "\n".join(lines)
