"""The demo's HTML report: one self-contained page with PNG plots (``report.html`` in the output directory).

Built with the same report module as ``magstack diagnose --report`` (:mod:`magstack.ground.report`):

* raw vs calibrated error over the held-out session (per axis, against the reference);
* calibrated residual vs temperature and vs field on the held-out session;
* |B| before and after calibration against the reference's |B| (held-out session);
* the fitted parameters with their standard errors, and the coverage of the field sphere;
* the fit's residual spectrum (Welch PSD in nT^2/Hz, log-binned, as on the diagnose page);
* the flight loop's telemetry with its fault events marked;
* the summary table of every step.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from magstack.data.session import read_session
from magstack.ground.apply_session import calibrate_session
from magstack.ground.report import PSD_LABEL, Report, figure, log_binned_psd

AXES = "xyz"

#: Residual axes are linear and show the bulk of the points: +- this many robust standard deviations
#: (1.4826 x the median absolute deviation) of the residual, at least :data:`MIN_LIMIT_nT`. The few points
#: beyond (DUT and reference cannot be paired across a coil step) are drawn on the edge and counted.
LIMIT_SIGMAS = 8.0
MIN_LIMIT_nT = 20.0


def residual_limit_nT(*values_nT) -> float:
    """Half-height (nT) of a linear residual axis that shows the bulk of ``values_nT`` (finite values)."""
    v = np.concatenate([np.asarray(x, float).ravel() for x in values_nT])
    v = v[np.isfinite(v)]
    if not v.size:
        return MIN_LIMIT_nT
    sigma = 1.4826 * float(np.median(np.abs(v - np.median(v))))
    return float(max(MIN_LIMIT_nT, LIMIT_SIGMAS * sigma))


def plot_clipped(ax, x, y_nT, limit_nT: float, style: str = "-", **kw) -> int:
    """Plot ``y_nT`` on a linear axis of +-``limit_nT``: values beyond are drawn on the edge as open triangles
    (pointing out); returns how many were clipped."""
    y = np.asarray(y_nT, float)
    ax.plot(x, np.clip(y, -limit_nT, limit_nT), style, **kw)
    out = np.abs(y) > limit_nT
    if out.any():
        color = ax.lines[-1].get_color()
        xs = np.asarray(x)[out]
        ax.plot(xs, np.sign(y[out]) * limit_nT, ls="none", marker=6, mfc="none", color=color, ms=5)
    ax.set_ylim(-1.04 * limit_nT, 1.04 * limit_nT)
    return int(out.sum())


def _clip_note(ax, n_clipped: int, limit_nT: float) -> None:
    if n_clipped:
        ax.text(0.01, 0.02, f"{n_clipped} points beyond +-{limit_nT:.0f} nT drawn on the edge (triangles)",
                transform=ax.transAxes, fontsize=7, va="bottom", ha="left", color="0.2",
                bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.85, "pad": 1.5})


def _paired_rows(s):
    ok = np.all(np.isfinite(s.ref_uT), axis=1) & np.all(np.isfinite(s.dut_uT), axis=1)
    return s.select(ok)


def _holdout_error_figure(raw, cal):
    fig, ax = figure(9.0, 5.0, nrows=2)
    t0 = raw.t_s[0]
    res_nT = (cal.dut_uT - cal.ref_uT) * 1e3
    lim = residual_limit_nT(res_nT)
    clipped = 0
    for i, a in enumerate(AXES):
        ax[0][0].plot(raw.t_s - t0, raw.dut_uT[:, i] - raw.ref_uT[:, i], lw=0.7, label=f"{a}")
        clipped += plot_clipped(ax[1][0], cal.t_s - t0, res_nT[:, i], lim, lw=0.7, label=f"{a}")
    ax[0][0].set_ylabel("raw - ref (uT)")
    ax[1][0].set_ylabel("calibrated - ref (nT)")
    _clip_note(ax[1][0], clipped, lim)   # spikes at coil steps: DUT and reference cannot pair there
    ax[1][0].set_xlabel("time in held-out session (s)")
    for a in (ax[0][0], ax[1][0]):
        a.legend(loc="upper right", ncol=3, fontsize=8)
        a.grid(alpha=0.3)
    ax[0][0].set_title("held-out session: error against the reference, before and after calibration")
    return fig


def _residual_vs_figure(cal):
    fig, ax = figure(9.0, 3.6, ncols=2)
    res_nT = (cal.dut_uT - cal.ref_uT) * 1e3
    lim = residual_limit_nT(res_nT)
    clipped = [0, 0]
    for i, a in enumerate(AXES):
        clipped[0] += plot_clipped(ax[0][0], cal.temp_c, res_nT[:, i], lim, ".", ms=2, alpha=0.5, label=a)
        clipped[1] += plot_clipped(ax[0][1], cal.ref_uT[:, i], res_nT[:, i], lim, ".", ms=2, alpha=0.5, label=a)
    ax[0][0].set_xlabel("temperature (degC)")
    ax[0][1].set_xlabel("reference field on the same axis (uT)")
    for k, a in enumerate(ax[0]):
        a.set_ylabel("calibrated - ref (nT)")
        _clip_note(a, clipped[k], lim)   # coil-step pairing spikes
        a.legend(fontsize=8, loc="upper right")
        a.grid(alpha=0.3)
    ax[0][0].set_title("held-out residual vs temperature")
    ax[0][1].set_title("held-out residual vs field")
    return fig


def _magnitude_figure(raw, cal):
    """|B| of the raw and the calibrated DUT against the reference's |B| on the held-out session."""
    fig, ax = figure(9.0, 5.0, nrows=2)
    t0 = raw.t_s[0]
    b_ref = np.linalg.norm(raw.ref_uT, axis=1)
    ax[0][0].plot(raw.t_s - t0, b_ref, lw=1.0, color="k", label="reference")
    ax[0][0].plot(raw.t_s - t0, np.linalg.norm(raw.dut_uT, axis=1), lw=0.7, color="C1", label="raw DUT")
    ax[0][0].plot(cal.t_s - t0, np.linalg.norm(cal.dut_uT, axis=1), lw=0.7, ls="--", color="C2", label="calibrated")
    ax[0][0].set_ylabel("|B| (uT)")
    ax[0][0].set_title("held-out session: field magnitude before and after calibration")
    d_raw = np.linalg.norm(raw.dut_uT, axis=1) - b_ref
    d_cal = (np.linalg.norm(cal.dut_uT, axis=1) - np.linalg.norm(cal.ref_uT, axis=1)) * 1e3
    rms_raw, rms_cal = np.sqrt(np.mean(d_raw ** 2)), np.sqrt(np.mean(d_cal ** 2))
    ax[1][0].plot(raw.t_s - t0, d_raw, lw=0.7, color="C1", label=f"raw (RMS {rms_raw:.2f} uT)")
    ax[1][0].set_ylabel("raw |B| - |B ref| (uT)")
    twin = ax[1][0].twinx()   # the calibrated difference is some 100x smaller: its own linear axis, in nT
    lim = residual_limit_nT(d_cal)
    clipped = plot_clipped(twin, cal.t_s - t0, d_cal, lim, lw=0.7, color="C2",
                           label=f"calibrated (RMS {rms_cal:.0f} nT)")
    twin.set_ylabel("calibrated |B| - |B ref| (nT)", color="C2")
    _clip_note(twin, clipped, lim)
    lines = ax[1][0].get_lines()[:1] + twin.get_lines()[:1]
    ax[1][0].legend(lines, [ln.get_label() for ln in lines], loc="upper right", fontsize=8, ncol=2)
    ax[1][0].set_xlabel("time in held-out session (s)")
    ax[0][0].legend(loc="upper right", fontsize=8, ncol=3)
    for a in (ax[0][0], ax[1][0]):
        a.grid(alpha=0.3)
    return fig


#: Equal-area cells of the field sphere: bands of equal sin(elevation) x azimuth sectors.
SPHERE_BANDS, SPHERE_SECTORS = 8, 16


def sphere_cells(ref_uT, min_field_uT: float = 5.0) -> np.ndarray:
    """Rows per equal-area cell of the field sphere, (``SPHERE_BANDS``, ``SPHERE_SECTORS``): the reference field's
    direction on rows with |B| >= ``min_field_uT``; bands of equal width in sin(elevation), sectors of azimuth."""
    b = np.asarray(ref_uT, float)
    n = np.linalg.norm(b, axis=1)
    b = b[np.isfinite(n) & (n >= min_field_uT)]
    counts = np.zeros((SPHERE_BANDS, SPHERE_SECTORS), dtype=int)
    if len(b):
        u = b / np.linalg.norm(b, axis=1, keepdims=True)
        az = np.degrees(np.arctan2(u[:, 1], u[:, 0]))
        band = np.minimum(((u[:, 2] + 1) / 2 * SPHERE_BANDS).astype(int), SPHERE_BANDS - 1)
        sector = np.minimum(((az + 180) / 360 * SPHERE_SECTORS).astype(int), SPHERE_SECTORS - 1)
        np.add.at(counts, (band, sector), 1)
    return counts


def _coverage_figure(ref_uT):
    """The equal-area cells of the field sphere, shaded by how many rows reached them (white: none)."""
    counts = sphere_cells(ref_uT)
    hit, total, rows = int((counts > 0).sum()), counts.size, int(counts.sum())
    fig, ax = figure(9.0, 3.8)
    az_edges = np.linspace(-180.0, 180.0, SPHERE_SECTORS + 1)
    el_edges = np.degrees(np.arcsin(np.linspace(-1.0, 1.0, SPHERE_BANDS + 1)))
    mesh = ax[0][0].pcolormesh(az_edges, el_edges, np.ma.masked_equal(counts, 0), cmap="Blues", vmin=0,
                               edgecolors="0.75", linewidth=0.5)
    fig.set_layout_engine("constrained")   # before the colour bar takes its room (Report.image lays out with it)
    fig.colorbar(mesh, ax=ax[0][0], label="rows in the cell")
    ax[0][0].set_xlim(-180, 180)
    ax[0][0].set_ylim(-90, 90)
    ax[0][0].set_xticks(np.arange(-180, 181, 45))
    ax[0][0].set_xlabel("azimuth of the reference field (deg)")
    ax[0][0].set_ylabel("elevation (deg)")
    ax[0][0].set_title(f"field-sphere coverage of the fit session: {hit} of {total} equal-area cells "
                       f"({rows} rows with |B| >= 5 uT)")
    return fig, hit, total


def parameter_rows(result) -> list[list[str]]:
    """(parameter, value, std err, unit) rows of a calibration fit (held parameters say so)."""
    m = result.model
    mask = m.axis_mask()
    held = {(h.axis, h.column) for h in result.held}
    rows = []
    for i in range(3):
        for c, col in enumerate(m.columns):
            if mask[i, c]:
                se = "held (prior)" if (i, c) in held else f"{result.se[i, c]:.3g}"
                rows.append([m.param_name(i, c), f"{result.theta[i, c]:.6g}", se, col.unit])
    return rows


def _counts_text(counts: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) or "none"


def _spectrum_figure(fit_cal):
    from scipy.signal import welch

    fig, ax = figure(9.0, 3.4)
    dt = float(np.median(np.diff(fit_cal.t_s)))
    res = (fit_cal.ref_uT - fit_cal.dut_uT) * 1e3
    f, p = welch(res - np.mean(res, axis=0), fs=1.0 / dt, nperseg=min(256, len(res)), axis=0)
    fb, pb = log_binned_psd(f[1:], p[1:])
    for i, a in enumerate(AXES):
        ax[0][0].loglog(fb, pb[:, i], lw=0.9, label=a)
    ax[0][0].set_xlabel("frequency (Hz)")
    ax[0][0].set_ylabel(PSD_LABEL)
    ax[0][0].set_title(f"fit residual spectrum (Welch, log-binned; DUT rows every {dt:.3f} s)")
    ax[0][0].legend(fontsize=8)
    ax[0][0].grid(alpha=0.3, which="both")
    return fig


def _flight_figure(loop_path: Path, events_path: Path, truth_uT):
    """Raw (uT) and calibrated (nT) published minus truth, each on its own linear axis, fault events marked."""
    tlm = read_session(loop_path)
    fig, ax = figure(9.0, 5.0, nrows=2)
    t = tlm.t_s - tlm.t_s[0]
    cal = np.column_stack([tlm.extra.get(f"cal_{a}_uT", np.full(len(tlm), np.nan)) for a in AXES])
    cal_nT = (cal - np.asarray(truth_uT)) * 1e3
    lim = residual_limit_nT(cal_nT)
    clipped = 0
    for i, a in enumerate(AXES):
        ax[0][0].plot(t, tlm.dut_uT[:, i] - truth_uT[i], ".-", ms=3, lw=0.6, color=f"C{i}", label=f"raw {a}")
        clipped += plot_clipped(ax[1][0], t, cal_nT[:, i], lim, ".-", ms=3, lw=0.8, color=f"C{i}",
                                label=f"calibrated {a}")
    events = [json.loads(x) for x in events_path.read_text().splitlines() if x.strip()]
    for e in events:
        if e["name"].startswith("CHAN_"):
            for a in (ax[0][0], ax[1][0]):
                a.axvline(e["t_s"] - tlm.t_s[0], color="red", lw=1.0, alpha=0.7)
            ax[0][0].annotate(e["name"], (e["t_s"] - tlm.t_s[0], 0.98), xycoords=("data", "axes fraction"),
                              rotation=90, va="top", ha="right", fontsize=7, color="red")
    _clip_note(ax[1][0], clipped, lim)
    ax[0][0].set_ylabel("raw - truth (uT)")
    ax[1][0].set_ylabel("calibrated - truth (nT)")
    ax[1][0].set_xlabel("flight time (s)")
    ax[0][0].set_title("flight executive telemetry (fault events in red)")
    for a in (ax[0][0], ax[1][0]):
        a.legend(fontsize=7, ncol=3, loc="upper left")
        a.grid(alpha=0.3)
    return fig


def report_title(cfg) -> str:
    """The page title: what the run was made from (the demo's inputs are its configuration)."""
    return (f"magstack demo: seed {cfg.seed}, {cfg.seconds:g} s of coil program '{cfg.program}', held-out "
            f"{cfg.holdout_s:g} s of '{cfg.holdout_program}' (seed {cfg.seed + 1}), {cfg.loop_cycles} flight cycles")


def write_demo_report(res, path: Path, summary_rows: list[tuple[str, str]]) -> Path:
    """Write ``report.html`` from the demo's results and output files."""
    out = Path(path).parent
    rep = Report(report_title(res.config))
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
    rep.image(_magnitude_figure(raw, cal), "field magnitude before and after calibration")
    rep.image(_residual_vs_figure(cal), "held-out residual vs temperature and field")
    rep.heading("Fit")
    fit_session = read_session(res.align.paired_path)
    fig, hit, total = _coverage_figure(fit_session.ref_uT)
    rep.image(fig, "field-sphere coverage", caption=f"Directions of the reference field in the fit session: {hit} "
              f"of {total} equal-area cells of the sphere reached (a calibration is determined only along "
              "directions the field visited).")
    if res.fit.result is not None:
        rep.text(f"Fitted parameters ({res.fit.model}; standard errors from the fit's covariance):")
        rep.table(["parameter", "value", "std err", "unit"], parameter_rows(res.fit.result))
    fit_cal = _paired_rows(calibrate_session(res.table.table, fit_session, "float"))
    rep.image(_spectrum_figure(fit_cal), "fit residual spectrum")
    rep.heading("Flight executive")
    lp = res.loop
    rep.text(f"{lp.cycles} cycles; injected faults: {_counts_text(lp.injected)}; counted "
             f"{lp.health['error_count']}; calibrated "
             f"error vs truth {lp.cal_error_norm_uT * 1e3:.1f} nT (raw {lp.raw_error_norm_uT:.3f} uT).")
    rep.image(_flight_figure(lp.path, lp.events_path, lp.truth_uT), "flight telemetry with fault events")
    return rep.write(out / Path(path).name)
