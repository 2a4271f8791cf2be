"""Where the gap lies: breakdowns by axis, temperature, field magnitude, rate of change, time and
session, and by frequency; and the noise floor estimated from the data.

The noise floor the verdict is judged against is in :mod:`.noise` (tones apart); ``spectral_white_nT``
here is a cross-check: the white level implied by the median residual PSD over the upper half of the
band, ``sqrt(median PSD * f_nyquist)``.

Spectrum: Welch (scipy.signal.welch, Hann, 50 % overlap) averaged over contiguous uniformly sampled
runs when every run has the same sample spacing to 1 %; otherwise Lomb-Scargle
(scipy.signal.lombscargle) over the whole record, scaled to a one-sided PSD.
"""
from __future__ import annotations

import numpy as np
import scipy.signal

from magstack.data.session import Session
from magstack.ground.diagnose.nonlinear import runs

FIELD_EDGES_uT = (0.0, 5.0, 20.0, 40.0, 60.0, 100.0, 200.0, np.inf)
RATE_EDGES_uT_PER_S = (0.0, 0.1, 1.0, 10.0, np.inf)
N_TEMP_BANDS = 5


def _band(r: np.ndarray, m: np.ndarray, lo: float, hi: float) -> dict:
    rr = r[m]
    return {"lo": _num(lo), "hi": _num(hi), "n": int(m.sum()),
            "rms_nT": [float(v) for v in np.sqrt(np.mean(rr ** 2, axis=0)) * 1e3],
            "mean_nT": [float(v) for v in np.mean(rr, axis=0) * 1e3],
            "rms_norm_nT": float(np.linalg.norm(np.sqrt(np.mean(rr ** 2, axis=0))) * 1e3)}


def _num(x: float):
    return None if not np.isfinite(x) else float(x)


def _bands(r: np.ndarray, v: np.ndarray, edges) -> list[dict]:
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (v >= lo) & (v < hi) & np.isfinite(v)
        if m.sum() >= 5:
            out.append(_band(r, m, lo, hi))
    return out


def field_rate_uT_per_s(b_uT: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> np.ndarray:
    """|dB/dt| (uT/s) by differences inside contiguous runs (0 at single-sample runs): ``np.gradient`` of each
    run (first-order one-sided at its ends, central inside; its uniform-spacing formula where the run's
    spacings are all equal), evaluated for all runs at once with the same arithmetic (a session with many
    short runs called np.gradient once per run)."""
    n = t_s.size
    out = np.zeros(n)
    if n < 2:
        return out
    run = runs(t_s, session)
    same = run[1:] == run[:-1]                          # rows i, i+1 in one run
    dt = np.diff(t_s)
    first = np.r_[True, ~same]
    last = np.r_[~same, True]
    starts = np.flatnonzero(first)
    # per run: its first spacing, and whether all of its spacings equal it (np.gradient's uniform case)
    dx0 = dt[np.minimum(starts, n - 2)]
    uneven = np.bincount(run[:-1][same], weights=(dt[same] != dx0[run[:-1][same]]), minlength=starts.size) > 0
    g = np.zeros((n, 3))
    i = np.flatnonzero(first & ~last)                   # a run's first row: (f1 - f0) / dx_0
    g[i] = (b_uT[i + 1] - b_uT[i]) / dt[i][:, None]
    i = np.flatnonzero(last & ~first)                   # its last row: (f[-1] - f[-2]) / dx_n
    dx_n = np.where(uneven[run[i]], dt[i - 1], dx0[run[i]])
    g[i] = (b_uT[i] - b_uT[i - 1]) / dx_n[:, None]
    inner = np.flatnonzero(~first & ~last)
    i = inner[~uneven[run[inner]]]                      # evenly spaced run: (f[i+1] - f[i-1]) / (2 dx)
    g[i] = (b_uT[i + 1] - b_uT[i - 1]) / (2. * dx0[run[i]])[:, None]
    i = inner[uneven[run[inner]]]                       # unevenly spaced: second-order weights
    dx1, dx2 = dt[i - 1][:, None], dt[i][:, None]
    a = -(dx2) / (dx1 * (dx1 + dx2))
    b = (dx2 - dx1) / (dx1 * dx2)
    c = dx1 / (dx2 * (dx1 + dx2))
    g[i] = a * b_uT[i - 1] + b * b_uT[i] + c * b_uT[i + 1]
    out[:] = np.linalg.norm(g, axis=1)
    out[first & last] = 0.0
    return out


def run_slices(run: np.ndarray) -> list[slice]:
    """The rows of each contiguous run as slices (``nonlinear.runs`` numbers runs in row order)."""
    start = np.r_[0, np.flatnonzero(np.diff(run)) + 1]
    return [slice(int(a), int(b)) for a, b in zip(start, np.r_[start[1:], run.size], strict=True)]


def breakdowns(r: np.ndarray, s: Session, blocks: np.ndarray) -> dict:
    """The gap ``r`` (N,3) uT broken down; every figure in nT."""
    out: dict = {"axis": {a: {"rms_nT": float(np.sqrt(np.mean(r[:, i] ** 2)) * 1e3),
                              "mean_nT": float(np.mean(r[:, i]) * 1e3)} for i, a in enumerate("xyz")}}
    t = s.temp_c
    tok = np.isfinite(t)
    if tok.sum() >= 5 and np.ptp(t[tok]) > 0:
        edges = np.unique(np.quantile(t[tok], np.linspace(0, 1, N_TEMP_BANDS + 1)))
        edges[-1] = np.nextafter(edges[-1], np.inf)
        out["temperature_c"] = _bands(r, t, edges)
    else:
        out["temperature_c"] = []
    out["field_magnitude_uT"] = _bands(r, np.linalg.norm(s.ref_uT, axis=1), FIELD_EDGES_uT)
    out["field_rate_uT_per_s"] = _bands(r, field_rate_uT_per_s(s.ref_uT, s.t_s, s.session), RATE_EDGES_uT_PER_S)
    out["session"] = [{"session": int(k), **_band(r, s.session == k, np.nan, np.nan)}
                      for k in np.unique(s.session)]
    for d in out["session"]:
        d.pop("lo")
        d.pop("hi")
    ids, first, inv, cnt = np.unique(blocks, return_index=True, return_inverse=True, return_counts=True)
    inv = inv.ravel()

    def per_block(w):
        return np.bincount(inv, weights=w, minlength=ids.size) / cnt
    t_mid = per_block(s.t_s)
    ms = np.column_stack([per_block(r[:, i] ** 2) for i in range(3)])
    mean = np.column_stack([per_block(r[:, i]) for i in range(3)]) * 1e3
    out["time_blocks"] = [{"t_mid_s": float(t_mid[b]), "session": int(s.session[first[b]]),
                           "rms_norm_nT": float(np.linalg.norm(np.sqrt(ms[b])) * 1e3),
                           "mean_nT": [float(v) for v in mean[b]]} for b in range(ids.size)]
    return out


def spectrum(r: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> dict:
    """One-sided PSD (nT^2/Hz) per axis of the residual (mean removed per session)."""
    x = r.copy()
    for k in np.unique(session):
        m = session == k
        x[m] -= x[m].mean(axis=0)
    x *= 1e3
    run = runs(t_s, session)
    uniform, dts = True, []
    slices = run_slices(run)
    for idx in slices:
        if idx.stop - idx.start < 2:
            continue
        d = np.diff(t_s[idx])
        med = float(np.median(d))
        dts.append(med)
        if med <= 0 or np.max(np.abs(d - med)) > 0.01 * med:
            uniform = False
    if dts and (max(dts) - min(dts)) > 0.01 * min(dts):
        uniform = False
    if uniform and dts:
        fs = 1.0 / float(np.median(dts))
        lens = {k: sl.stop - sl.start for k, sl in enumerate(slices)}
        nper = 256
        while nper > 16 and sum(v for v in lens.values() if v >= nper) < 0.5 * t_s.size:
            nper //= 2
        acc, wsum, f = None, 0.0, None
        for k, n_k in lens.items():
            if n_k < nper:
                continue
            idx = slices[k]
            f, p = scipy.signal.welch(x[idx], fs=fs, nperseg=nper, axis=0)
            acc = p * n_k if acc is None else acc + p * n_k
            wsum += n_k
        if acc is not None:
            return _spec_out("welch", f[1:], (acc / wsum)[1:], fs / 2)
    # uneven sampling: Lomb-Scargle over the record
    tt = t_s - t_s.min()
    span = float(np.ptp(tt))
    if span <= 0 or t_s.size < 8:
        return {"method": "none", "freq_hz": [], "psd_nT2_per_hz": [[], [], []], "spectral_white_nT": [None] * 3}
    dt_med = float(np.median(np.diff(np.sort(t_s))[np.diff(np.sort(t_s)) > 0]))
    fny = 0.5 / dt_med
    f = np.linspace(1.0 / span, fny, 400)
    psd = np.empty((f.size, 3))
    for j in range(3):
        xj = x[:, j] - x[:, j].mean()      # what precenter=True did (deprecated in SciPy 1.17)
        pg = scipy.signal.lombscargle(tt, xj, 2 * np.pi * f)
        # unnormalised Lomb-Scargle of white noise of variance s2 averages s2; its one-sided PSD is s2/fny
        psd[:, j] = pg / fny
    return _spec_out("lombscargle", f, psd, fny)


def _spec_out(method: str, f: np.ndarray, psd: np.ndarray, fny: float) -> dict:
    upper = f >= 0.5 * fny
    white = [float(np.sqrt(np.median(psd[upper, j]) * fny)) if upper.any() else None for j in range(3)]
    return {"method": method, "freq_hz": [float(v) for v in f],
            "psd_nT2_per_hz": [[float(v) for v in psd[:, j]] for j in range(3)], "spectral_white_nT": white}


#: A held-out gap at or above this multiple of the noise floor after the verdict is called unexplained.
UNEXPLAINED_RATIO = 1.5
#: Frequency bands (per decade) for locating an unexplained remainder in the spectrum.
BANDS_PER_DECADE = 2


def _worst(bands: list[dict], n_all: int, overall_nT: float) -> dict | None:
    """The band (with at least 5 % of the rows) where the remainder is largest, and its ratio to overall."""
    ok = [b for b in bands if b["n"] >= 0.05 * n_all]
    if not ok or overall_nT <= 0:
        return None
    b = max(ok, key=lambda b: b["rms_norm_nT"])
    return {"lo": b["lo"], "hi": b["hi"], "n": b["n"], "rms_norm_nT": b["rms_norm_nT"],
            "ratio_to_overall": b["rms_norm_nT"] / overall_nT}


def _excess_band(spec: dict, white_nT: float) -> dict | None:
    """The frequency band (BANDS_PER_DECADE per decade) whose mean PSD (summed over axes) is largest
    against the white level ``white_nT`` (norm over axes) spread over the band to Nyquist."""
    f = np.asarray(spec.get("freq_hz", []), dtype=float)
    if f.size < 4 or not np.isfinite(white_nT) or white_nT <= 0:
        return None
    psd = np.sum(np.asarray(spec["psd_nT2_per_hz"], dtype=float), axis=0)
    fny = float(f.max())
    white_psd = white_nT ** 2 / fny
    edges = 10 ** np.arange(np.floor(np.log10(f[f > 0].min()) * BANDS_PER_DECADE),
                            np.ceil(np.log10(fny) * BANDS_PER_DECADE) + 1) / BANDS_PER_DECADE
    best = None
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (f >= lo) & (f < hi)
        if m.sum() < 2:
            continue
        r = float(np.mean(psd[m]) / white_psd)
        if best is None or r > best["psd_over_white"]:
            best = {"lo_hz": float(lo), "hi_hz": float(hi), "psd_over_white": r}
    return best


def remainder(r_after: np.ndarray, s: Session, after_nT: float, floor_nT: float | None, effect: str) -> dict:
    """Whether a held-out gap remains that the verdict (``effect``, "none": the base) leaves unexplained
    (``after_nT >= UNEXPLAINED_RATIO x floor_nT``), and where the breakdowns put it: the |B| band and
    temperature band with the largest remainder, and the frequency band with the most power above white."""
    out: dict = {"after_over_floor": None if not floor_nT else float(after_nT / floor_nT),
                 "threshold": UNEXPLAINED_RATIO, "remains": False}
    if not floor_nT or after_nT < UNEXPLAINED_RATIO * floor_nT:
        return out
    r = np.where(np.isfinite(r_after), r_after, 0.0).astype(float)
    overall = float(np.linalg.norm(np.sqrt(np.mean(r ** 2, axis=0))) * 1e3)
    out["remains"] = True
    out["field_band_uT"] = _worst(_bands(r, np.linalg.norm(s.ref_uT, axis=1), FIELD_EDGES_uT), r.shape[0], overall)
    t = s.temp_c
    tok = np.isfinite(t)
    temp = None
    if tok.sum() >= 5 and np.ptp(t[tok]) > 0:
        edges = np.unique(np.quantile(t[tok], np.linspace(0, 1, N_TEMP_BANDS + 1)))
        edges[-1] = np.nextafter(edges[-1], np.inf)
        temp = _worst(_bands(r, t, edges), r.shape[0], overall)
    out["temperature_band_c"] = temp
    out["frequency_band"] = _excess_band(spectrum(r, s.t_s, s.session), floor_nT)
    where = []
    if out["field_band_uT"]:
        b = out["field_band_uT"]
        where.append(f"|B| {b['lo']:g}-{_hi(b['hi'])} uT ({b['rms_norm_nT']:.0f} nT, {b['ratio_to_overall']:.1f}x "
                     "the overall)")
    if temp:
        where.append(f"temperature {temp['lo']:.1f}-{temp['hi']:.1f} degC ({temp['rms_norm_nT']:.0f} nT, "
                     f"{temp['ratio_to_overall']:.1f}x)")
    if out["frequency_band"]:
        fb = out["frequency_band"]
        where.append(f"frequencies {fb['lo_hz']:.3g}-{fb['hi_hz']:.3g} Hz (PSD {fb['psd_over_white']:.0f}x the "
                     "white level)")
    base = "the base model" if effect == "none" else effect
    out["text"] = (f"UNEXPLAINED: after {base} a held-out gap of {after_nT:.1f} nT remains, "
                   f"{after_nT / floor_nT:.1f}x the noise floor ({floor_nT:.1f} nT), that no catalogue effect "
                   "explains" + (f"; largest at {'; '.join(where)}" if where else ""))
    return out


def _hi(x) -> str:
    return "inf" if x is None else f"{x:g}"
