"""The demo's HTML report: one self-contained page with PNG plots (``report.html`` in the output directory).

Built with the same report module as ``magstack diagnose --report`` (:mod:`magstack.ground.report`):

* raw vs calibrated error over the held-out session (per axis, against the reference);
* calibrated residual vs temperature and vs field on the held-out session;
* the fit's residual spectrum (Welch PSD of reference minus calibrated field on the fit session);
* the flight loop's telemetry with its fault events marked;
* the summary table of every step.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from magstack.data.session import read_session
from magstack.ground.apply_session import calibrate_session
from magstack.ground.report import Report, figure

AXES = "xyz"


def _paired_rows(s):
    ok = np.all(np.isfinite(s.ref_uT), axis=1) & np.all(np.isfinite(s.dut_uT), axis=1)
    return s.select(ok)


def _holdout_error_figure(raw, cal):
    fig, ax = figure(9.0, 5.0, nrows=2)
    t0 = raw.t_s[0]
    for i, a in enumerate(AXES):
        ax[0][0].plot(raw.t_s - t0, raw.dut_uT[:, i] - raw.ref_uT[:, i], lw=0.7, label=f"{a}")
        ax[1][0].plot(cal.t_s - t0, (cal.dut_uT[:, i] - cal.ref_uT[:, i]) * 1e3, lw=0.7, label=f"{a}")
    ax[0][0].set_ylabel("raw - ref (uT)")
    ax[1][0].set_ylabel("calibrated - ref (nT)")
    ax[1][0].set_yscale("symlog", linthresh=200.0)   # spikes at coil steps: DUT and reference cannot pair there
    ax[1][0].set_xlabel("time in held-out session (s)")
    for a in (ax[0][0], ax[1][0]):
        a.legend(loc="upper right", ncol=3, fontsize=8)
        a.grid(alpha=0.3)
    ax[0][0].set_title("held-out session: error against the reference, before and after calibration")
    return fig


def _residual_vs_figure(cal):
    fig, ax = figure(9.0, 3.6, ncols=2)
    res_nT = (cal.dut_uT - cal.ref_uT) * 1e3
    for i, a in enumerate(AXES):
        ax[0][0].plot(cal.temp_c, res_nT[:, i], ".", ms=2, alpha=0.5, label=a)
        ax[0][1].plot(cal.ref_uT[:, i], res_nT[:, i], ".", ms=2, alpha=0.5, label=a)
    ax[0][0].set_xlabel("temperature (degC)")
    ax[0][1].set_xlabel("reference field on the same axis (uT)")
    for a in ax[0]:
        a.set_ylabel("calibrated - ref (nT)")
        a.set_yscale("symlog", linthresh=200.0)   # linear within +-200 nT; coil-step pairing spikes beyond
        a.legend(fontsize=8)
        a.grid(alpha=0.3)
    ax[0][0].set_title("held-out residual vs temperature")
    ax[0][1].set_title("held-out residual vs field")
    return fig


def _spectrum_figure(fit_cal):
    from scipy.signal import welch

    fig, ax = figure(9.0, 3.4)
    dt = float(np.median(np.diff(fit_cal.t_s)))
    res = (fit_cal.ref_uT - fit_cal.dut_uT) * 1e3
    for i, a in enumerate(AXES):
        f, p = welch(res[:, i] - np.mean(res[:, i]), fs=1.0 / dt, nperseg=min(256, len(res)))
        ax[0][0].loglog(f[1:], np.sqrt(p[1:]), lw=0.9, label=a)
    ax[0][0].set_xlabel("frequency (Hz)")
    ax[0][0].set_ylabel("amplitude spectral density (nT/sqrt(Hz))")
    ax[0][0].set_title(f"fit residual spectrum (Welch; DUT rows every {dt:.3f} s)")
    ax[0][0].legend(fontsize=8)
    ax[0][0].grid(alpha=0.3, which="both")
    return fig


def _flight_figure(loop_path: Path, events_path: Path, truth_uT):
    tlm = read_session(loop_path)
    fig, ax = figure(9.0, 4.0)
    t0 = tlm.t_s[0]
    cal = np.column_stack([tlm.extra.get(f"cal_{a}_uT", np.full(len(tlm), np.nan)) for a in AXES])
    for i, a in enumerate(AXES):
        ax[0][0].plot(tlm.t_s - t0, (tlm.dut_uT[:, i] - truth_uT[i]) * 1e3, ".", ms=4, alpha=0.6, color=f"C{i}",
                      label=f"raw {a}")
        ax[0][0].plot(tlm.t_s - t0, (cal[:, i] - truth_uT[i]) * 1e3, "-", lw=1.2, color=f"C{i}",
                      label=f"calibrated {a}")
    events = [json.loads(x) for x in events_path.read_text().splitlines() if x.strip()]
    for e in events:
        if e["name"].startswith("CHAN_"):
            ax[0][0].axvline(e["t_s"] - t0, color="red", lw=1.0, alpha=0.7)
            ax[0][0].annotate(e["name"], (e["t_s"] - t0, 0.98), xycoords=("data", "axes fraction"), rotation=90,
                              va="top", ha="right", fontsize=7, color="red")
    ax[0][0].set_yscale("symlog", linthresh=100.0)
    ax[0][0].set_xlabel("flight time (s)")
    ax[0][0].set_ylabel("published - truth (nT)")
    ax[0][0].set_title("flight executive telemetry (fault events in red)")
    ax[0][0].legend(fontsize=7, ncol=2)
    ax[0][0].grid(alpha=0.3)
    return fig


def write_demo_report(res, path: Path, summary_rows: list[tuple[str, str]]) -> Path:
    """Write ``report.html`` from the demo's results and output files."""
    out = Path(path).parent
    rep = Report("magstack demo: simulated bench to calibrated flight loop")
    rep.text("Everything below ran on simulated hardware in virtual time (HMC1053 through the ADS1248, FVM400 "
             "reference over a serial URL), through the same drivers, calibration and flight code as on a Pi.")
    rep.heading("Summary")
    rep.table(["quantity", "value"], [[k, v] for k, v in summary_rows])
    raw = _paired_rows(read_session(res.holdout.align.paired_path))
    cal = _paired_rows(read_session(res.holdout.calibrated_path))
    rep.heading("Held-out session")
    rep.text(f"An independent session (seed {res.holdout.bench.seed}) calibrated with the fixed-point applier: "
             f"raw {res.holdout.raw_rmse_norm_uT:.3f} uT -> calibrated {res.holdout.cal_rmse_norm_uT * 1e3:.1f} nT "
             "RMS (vector norm of per-axis RMS) on rows away from coil transitions.")
    rep.image(_holdout_error_figure(raw, cal), "held-out error before and after calibration")
    rep.image(_residual_vs_figure(cal), "held-out residual vs temperature and field")
    rep.heading("Fit residual")
    fit_cal = _paired_rows(calibrate_session(res.table.table, read_session(res.align.paired_path), "float"))
    rep.image(_spectrum_figure(fit_cal), "fit residual spectrum")
    rep.heading("Flight executive")
    lp = res.loop
    rep.text(f"{lp.cycles} cycles; injected faults {lp.injected}; counted {lp.health['error_count']}; calibrated "
             f"error vs truth {lp.cal_error_norm_uT * 1e3:.1f} nT (raw {lp.raw_error_norm_uT:.3f} uT).")
    rep.image(_flight_figure(lp.path, lp.events_path, lp.truth_uT), "flight telemetry with fault events")
    return rep.write(out / Path(path).name)
