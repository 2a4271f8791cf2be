"""The diagnosis as one HTML page (``diagnose --report DIR``): verdict text, residual against time,
temperature and field with the verdict's fit overlaid, spectrum, before/after bars per effect."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from magstack.ground.diagnose import where as wh
from magstack.ground.report import PSD_LABEL, Report, figure, log_binned_psd

_AX = "xyz"


def write_report(diag, out_dir, inputs=()) -> Path:
    """Write ``out_dir``/diagnosis.html; returns the path. ``inputs``: the session files diagnosed (the page's
    title names them). The directory is created only when the page is ready to be written (an interrupted
    report leaves no empty folder behind)."""
    out = Path(out_dir)
    d = diag.to_dict()
    s = diag.gap.session
    base = diag.result.baseline.resid * 1e3
    after = diag.after_trial.resid * 1e3
    explained = base - after
    names = ", ".join(Path(p).name for p in inputs)
    rep = Report(f"magstack diagnose {names}: {d['simulator']}" if names else f"magstack diagnose: {d['simulator']}")
    rep.text(f"Verdict: {d['verdict']}", "verdict")
    rep.text(diag.verdict_note)
    if d["unexplained"].get("remains"):
        rep.text(d["unexplained"]["text"], "unexplained")
    rep.table(["", "nT"], headline_rows(d))
    rep.heading("Ranking (held-out blocks)")
    rep.table(["effect", "held-out RMSE nT", "shrink", "p blocks", "p surrogates", "p", "p (Holm)", "significant"],
              [[r["effect"], f"{r['rmse_nT']:.1f}", f"{r['shrink']:.1%}", f"{r.get('p_blocks', r['p_value']):.3g}",
                "-" if r.get("p_surrogate") is None else f"{r['p_surrogate']:.3g}", f"{r['p_value']:.3g}",
                f"{r['p_holm']:.3g}", "yes" if r["significant"] else "no"] for r in d["ranking"]])
    if d.get("null_model"):
        m = d["null_model"]
        rep.text(f"Slow-noise null model: surrogates of the {m['template']} residual; components slower than "
                 f"{m['replaced_below_cycles_per_record']} cycles per record from white + 1/f^"
                 f"{m['slow_noise_exponent']:.2f}" + (f", capped at {m['slow_power_cap']:g}x the residual's own slow "
                                                       f"power on {', '.join(m['slow_power_capped_axes'])}"
                                                       if m["slow_power_capped_axes"] else "") + ".")
    rep.image(_bars(d), "before/after bars per effect")
    rep.heading("Where the gap lies")
    t = s.t_s - s.t_s.min()
    rep.image(_scatter(t, base, explained, "time since start (s)", d["verdict"], "time"), "residual vs time")
    if np.isfinite(s.temp_c).any() and np.ptp(s.temp_c[np.isfinite(s.temp_c)]) > 0:
        rep.image(_scatter(s.temp_c, base, explained, "temperature (degC)", d["verdict"], "temperature"),
                  "residual vs temperature")
    rep.image(_scatter(np.linalg.norm(s.ref_uT, axis=1), base, explained, "|B| reference (uT)", d["verdict"],
                       "field magnitude"), "residual vs field")
    rate = wh.field_rate_uT_per_s(s.ref_uT, s.t_s, s.session)
    rep.image(_scatter(np.log10(np.maximum(rate, 1e-3)), base, explained, "log10 |dB/dt| (uT/s)", d["verdict"],
                       "field rate of change"), "residual vs rate")
    rep.image(_spectrum(d, diag), "spectrum")
    if d["parameters"]:
        rep.heading("Parameters of the verdict's effect")
        rep.table(["parameter", "value", "std err", "unit"],
                  [[k, f"{v['value']:.6g}", f"{v['se']:.3g}", v["unit"]] for k, v in d["parameters"].items()])
    if d["not_testable"]:
        rep.heading("Not testable with these columns")
        rep.table(["effect", "reason"], [[n["effect"], n["reason"]] for n in d["not_testable"]])
    rep.heading("Text report")
    rep.preformatted(diag.text())
    out.mkdir(parents=True, exist_ok=True)
    return rep.write(out / "diagnosis.html")


def _f(x):
    return "n/a" if x is None else f"{x:.1f}"


def headline_rows(d: dict) -> list[list[str]]:
    """The page's headline table: the gap before and after, and the floor they are judged against. Against an
    IGRF + attitude reference (orbit telemetry) the floor is the sensor's measured white level and the reference's
    error budget together (root sum square), as in the text report."""
    rows = [["gap before (held-out)", f"{d['baseline_rmse_nT']:.1f}"],
            ["gap after the verdict's effect (held-out)", f"{d['after_rmse_nT']:.1f}"]]
    b = d.get("reference_budget")
    if not b:
        return rows + [["noise floor (from the data)", _f(d["noise_floor_nT"])]]
    return rows + [["sensor white level (from the data)", _f(d["noise_floor_nT"])],
                   [f"reference error budget (IGRF + attitude {b['attitude_sd_deg']:g} deg)", f"{b['total_nT']:.1f}"],
                   ["noise floor: sensor white + reference budget (root sum square)",
                    _f(d["floor_with_reference_nT"])]]


def _bars(d):
    fig, axs = figure(9, 3.5)
    ax = axs[0, 0]
    names = ["(baseline)"] + [r["effect"] for r in d["ranking"]]
    vals = [d["baseline_rmse_nT"]] + [r["rmse_nT"] for r in d["ranking"]]
    colors = ["0.5"] + ["tab:green" if r["significant"] else "tab:blue" for r in d["ranking"]]
    ax.bar(range(len(vals)), vals, color=colors)
    ax.set_ylim(bottom=0.0)     # bar lengths are read from zero
    floor = d.get("floor_with_reference_nT") if d.get("reference_budget") else d["noise_floor_nT"]
    if floor:
        ax.axhline(floor, color="k", ls="--", lw=1,
                   label="noise floor (sensor + reference budget)" if d.get("reference_budget") else "noise floor")
        ax.legend()
    ax.set_xticks(range(len(vals)), names, rotation=30, ha="right")
    ax.set_ylabel("held-out RMSE (nT)")
    ax.set_title("gap with each effect added (green: significant)")
    return fig


def _scatter(x, base, explained, xlabel, verdict, against):
    fig, axs = figure(9, 6, 3, 1)
    fig.suptitle(f"held-out gap against {against}" + ("" if verdict == "none" else f", with the {verdict} fit"))
    order = np.argsort(x)
    for i in range(3):
        ax = axs[i, 0]
        ax.set_title(f"{_AX[i]} axis", fontsize=9, loc="left")
        ax.plot(x, base[:, i], ".", ms=1.5, color="0.4", label="gap (held-out)")
        if verdict != "none":
            ax.plot(x[order], explained[order, i], ".", ms=1.5, color="tab:red", label=f"{verdict} fit")
        ax.set_ylabel(f"{_AX[i]} (nT)")
        lim = float(np.nanquantile(np.abs(base[:, i]), 0.995)) * 1.5
        if np.isfinite(lim) and lim > 0:   # a few step rows must not flatten the rest
            ax.set_ylim(-lim, lim)
        if i == 0:
            ax.legend(loc="upper right", markerscale=6)
    axs[2, 0].set_xlabel(xlabel)
    return fig


def _spectrum(d, diag):
    fig, axs = figure(9, 3.5)
    ax = axs[0, 0]
    sp = d["where"]["spectrum"]
    f = np.asarray(sp["freq_hz"])
    if f.size:
        fb, pb = log_binned_psd(f, np.asarray(sp["psd_nT2_per_hz"]).T)
        for i in range(3):
            ax.loglog(fb, np.maximum(pb[:, i], 1e-12), lw=1, color=f"C{i}", label=f"gap {_AX[i]}")
        s = diag.gap.session
        spa = wh.spectrum(diag.after_trial.resid, s.t_s, s.session) if d["verdict"] != "none" else {"freq_hz": []}
        if spa["freq_hz"]:   # "after" only when an effect was named
            fa, pa = log_binned_psd(spa["freq_hz"], np.asarray(spa["psd_nT2_per_hz"]).T)
            for i in range(3):
                ax.loglog(fa, np.maximum(pa[:, i], 1e-12), lw=0.8, ls=":", color=f"C{i}",
                          label=f"after {d['verdict']} {_AX[i]}")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel(PSD_LABEL)
    ax.set_title(f"residual spectrum ({sp['method']}, averaged in log-spaced frequency bins)")
    ax.legend(fontsize=7, ncol=2)
    return fig
