"""The noise floor of a residual, for any sampling, with tones found and reported apart.

White level (:func:`noise_floor`): per axis the robust spread (1.4826 MAD) of differences of residual
samples ``lag`` apart within a session, divided by sqrt 2 (the calibration fit's estimator,
``calibration.fit.noise_floor``), with ``lag = max(1 s, LAG_SPACINGS x the median row spacing)``: at
0.5 Hz telemetry a 1 s lag finds no pairs, at 2.5 Hz it pairs neighbours. Differencing removes slow misfit;
the MAD ignores the few rows at field steps.

A periodic interference (a mains alias, a reaction wheel) is not white noise, but differences of a tone
``A sin(2 pi f t)`` at lag L have amplitude ``2 A |sin(pi f L)|``: near the alias frequencies that differencing
passes it inflates the "white" level (a mains alias took a real floor from 70 to 178 nT). Tones are found first
(:func:`find_tones`) and removed from the residual before the white level is estimated; they are reported
separately (frequency, amplitude per axis, how far above the local spectrum).

Tone detection: periodogram of the residual (rows in session-then-time order, per-session mean removed) by
FFT on a grid of the median spacing (each row at its nearest grid point, missing rows zero; long gaps
shortened), a
local level (median of the neighbouring ``LOCAL_BINS`` bins); a bin whose power exceeds ``TONE_RATIO`` x its
local median on some axis is a tone candidate (for Gaussian white noise a periodogram ordinate exceeds
R x its median with probability ``2^-R``: 30 gives 1e-9 per bin). Its frequency is refined on the real time
stamps (explained power of a sine + cosine per session, over a fine grid within one bin) and its fit is
subtracted; at most ``MAX_TONES`` tones, strongest first.
"""
from __future__ import annotations

import numpy as np
import scipy.fft
import scipy.ndimage

from magstack.firmware.calibration.fit import noise_floor as diff_floor

#: Differencing lag in median row spacings (at least 1 s).
LAG_SPACINGS = 1.5
MIN_LAG_S = 1.0
#: A periodogram bin this many times its local median (on some axis) is a tone candidate.
TONE_RATIO = 30.0
#: Bins of the local median.
LOCAL_BINS = 65
#: Tones removed at most.
MAX_TONES = 5
#: Lowest tone frequency, in cycles per record (slower structure is misfit, not a tone).
MIN_CYCLES = 8
#: Gaps in the detection grid are shortened to this many spacings.
MAX_GAP_SPACINGS = 4096
#: Grid points of the detection periodogram at most (evenly strided beyond: detection only).
DETECT_ROWS = 2 ** 20


def lag_s(t_s: np.ndarray) -> float:
    """The differencing lag for these time stamps: max(1 s, LAG_SPACINGS x the median spacing)."""
    dt = np.diff(np.sort(np.asarray(t_s, dtype=float)))
    pos = dt[dt > 0]
    return float(max(MIN_LAG_S, LAG_SPACINGS * (float(np.median(pos)) if pos.size else 0.0)))


def _explained(x: np.ndarray, z: np.ndarray, inv: np.ndarray, n_sess: int,
               want_fit: bool = True) -> tuple[float, np.ndarray | None]:
    """Least-squares fit of ``a sin + b cos`` per session (a phase per power cycle) to ``x`` (N,3), with
    ``z = exp(i 2 pi f t)`` (N,) and ``inv`` the session index of each row: (explained sum of squares, fit
    (N,3)). The sessions' columns are disjoint, so each session is its own 2 x 2 normal-equation solve
    (pseudo-inverse: a session too short to tell sine from cosine gets the minimum-norm fit)."""
    s, c = z.imag, z.real
    k = x.shape[1]
    W = np.empty((s.size, 3 + 2 * k))
    W[:, 0], W[:, 1], W[:, 2] = s * s, c * c, s * c
    np.multiply(s[:, None], x, out=W[:, 3:3 + k])
    np.multiply(c[:, None], x, out=W[:, 3 + k:])
    starts = np.r_[0, np.flatnonzero(np.diff(inv)) + 1]
    if np.all(np.diff(inv[starts]) > 0) and starts.size == n_sess:    # rows grouped by session: sums by slices
        S = np.add.reduceat(W, starts, axis=0)
    else:
        S = np.stack([np.bincount(inv, weights=W[:, q], minlength=n_sess) for q in range(W.shape[1])], axis=1)
    del W
    G = np.empty((n_sess, 2, 2))
    G[:, 0, 0], G[:, 1, 1] = S[:, 0], S[:, 1]
    G[:, 0, 1] = G[:, 1, 0] = S[:, 2]
    C = np.stack([S[:, 3:3 + k], S[:, 3 + k:]], axis=1)               # (sessions, 2, 3)
    coef = np.linalg.pinv(G, rcond=1e-12, hermitian=True) @ C           # (sessions, 2, 3)
    if not want_fit:
        return float(np.sum(coef * C)), None
    fit = s[:, None] * coef[inv, 0, :]
    fit += c[:, None] * coef[inv, 1, :]
    return float(np.sum(coef * C)), fit


def _scan(x: np.ndarray, t: np.ndarray, freqs: np.ndarray, inv: np.ndarray, n_sess: int) -> np.ndarray:
    """Explained power (:func:`_explained`) at evenly spaced ``freqs``: ``exp(i 2 pi f t)`` advanced by one
    complex product per step (no sin/cos per point)."""
    z, step = np.exp(2j * np.pi * freqs[0] * t), np.exp(2j * np.pi * (freqs[1] - freqs[0]) * t)
    vals = np.empty(freqs.size)
    for j in range(freqs.size):
        vals[j] = _explained(x, z, inv, n_sess, want_fit=False)[0]
        z = z * step
    return vals


def find_tones(resid_uT: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> tuple[list[dict], np.ndarray]:
    """Tones in a residual (N,3) uT (rows sorted by session then time): the list (``freq_hz``,
    ``amplitude_nT`` per axis, ``ratio`` to the local spectrum) and the residual with them removed."""
    x = np.where(np.isfinite(resid_uT), resid_uT, 0.0).astype(float)
    n = x.shape[0]
    dt = np.diff(t_s)
    pos = dt[dt > 0]
    if n < 4 * LOCAL_BINS or not pos.size:
        return [], x
    spacing = float(np.median(pos))
    ids, inv = np.unique(session, return_inverse=True)
    inv = inv.ravel()
    for k in ids:
        m = session == k
        x[m] -= x[m].mean(axis=0)
    t = t_s - t_s[0]
    # rows on a grid of the median spacing (left-out rows and short gaps stay as zeros, so frequencies are
    # right; a gap longer than MAX_GAP_SPACINGS, e.g. between sessions, is shortened to it)
    step = np.clip(np.rint(np.diff(t) / spacing), 1, MAX_GAP_SPACINGS).astype(np.int64)
    pos_i = np.r_[0, np.cumsum(step)]
    stride = max(1, -(-int(pos_i[-1] + 1) // DETECT_ROWS))
    tones: list[dict] = []
    for _ in range(MAX_TONES):
        y = np.zeros((int(pos_i[-1]) // stride + 1, 3))
        y[pos_i // stride] = x
        m = y.shape[0]
        L = scipy.fft.next_fast_len(m, real=True)
        P = np.abs(scipy.fft.rfft(y, n=L, axis=0)) ** 2
        freq = np.arange(P.shape[0]) / (L * spacing * stride)
        local = scipy.ndimage.median_filter(P, size=(LOCAL_BINS, 1), mode="nearest")
        ratio = P / np.maximum(local, 1e-300)
        lo = int(np.ceil(MIN_CYCLES * L / m))
        ratio[:lo] = 0.0
        ratio[-1] = 0.0
        score = ratio.max(axis=1)
        k = int(np.argmax(score))
        if score[k] < TONE_RATIO:
            break
        # the power maximum near the flagged bin (the ratio can peak on the flank), refined on the real times
        near = np.arange(max(k - 3, 0), min(k + 4, P.shape[0]))
        k = int(near[np.argmax(P[near].sum(axis=1))])
        del y, P, local, ratio          # the periodogram's arrays are not needed for the refinement
        df = 1.0 / (L * spacing * stride)
        # the explained power's maximum within 2 bins on a 0.1-bin grid (every point: two tones within 2 bins,
        # as on the real tests 3-7, make the function two-peaked, which a coarse-then-fine scan can miss)
        grid = freq[k] + df * np.linspace(-2, 2, 41)
        f_best = float(grid[int(np.argmax(_scan(x, t, grid, inv, ids.size)))])
        _, fit = _explained(x, np.exp(2j * np.pi * f_best * t), inv, ids.size)
        x -= fit                         # x is this function's own copy
        amp = np.sqrt(2.0 * np.mean(fit ** 2, axis=0))
        tones.append({"freq_hz": f_best, "amplitude_nT": [float(a * 1e3) for a in amp],
                      "ratio_to_local_spectrum": float(score[k])})
    return tones, x


def noise_floor(resid_uT: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> tuple[np.ndarray, float, list[dict]]:
    """(white level per axis (3,) uT, the differencing lag in s, tones found and removed first)."""
    tones, clean = find_tones(resid_uT, t_s, session)
    lag = lag_s(t_s)
    return diff_floor(clean, t_s, session, lag), lag, tones
