"""The held-out block length, chosen from the data (``--block-s auto``, the default).

Blocks are the unit of the significance test: long enough that residual autocorrelation inside a block
does not leak across blocks, short enough that there are enough blocks for a claim. The choice:

* ``tau``: the residual's autocorrelation time, the first lag where the autocorrelation of the base
  model's in-sample residual, high-passed at ``HIGHPASS_ROWS`` rows (a running mean over that many rows
  removed per session), averaged over axes, falls below 1/e. The high-pass keeps an unmodelled slow effect
  (a thermal cycle, a drift: the signal the test looks for; on a 5 min thermal run even a 60 s high-pass left
  it dominant) from posing as noise correlation; it measures the noise's short memory (a filtered sensor,
  an averaging reference); slow noise is the surrogate null model's business (surrogate.py);
* at most ``MAX_BLOCK_S`` (60 s, the former fixed default, kept wherever the data allow it);
* shortened until the sessions hold at least ``TARGET_BLOCKS`` blocks (a 5-10 min session would otherwise
  give 5-10 blocks and no claim could ever be significant), but never below ``TAU_FACTOR`` x tau nor
  ``MIN_ROWS_PER_BLOCK`` rows.

The choice and its reasons are stated in the output (``method.block_choice``).
"""
from __future__ import annotations

import numpy as np
import scipy.fft
import scipy.ndimage

from magstack.ground.diagnose.gap import Gap, predict, solve, time_blocks

MAX_BLOCK_S = 60.0
TARGET_BLOCKS = 30
TAU_FACTOR = 5.0
MIN_ROWS_PER_BLOCK = 8
#: The residual is high-passed over this many rows before its autocorrelation time is measured.
HIGHPASS_ROWS = 33
#: Rows used for the autocorrelation estimate at most (the first ones; the time is a property of the noise).
ACF_ROWS = 2 ** 18


def autocorrelation_time_s(r: np.ndarray, t_s: np.ndarray, session: np.ndarray) -> float:
    """First lag (s) where the mean over axes of the autocorrelation of the residual, high-passed at
    HIGHPASS_ROWS rows, falls below 1/e."""
    x = np.where(np.isfinite(r), r, 0.0).astype(float)[:ACF_ROWS]
    sess = session[:ACF_ROWS]
    dt = np.diff(t_s[:ACF_ROWS])
    spacing = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    width = HIGHPASS_ROWS
    for k in np.unique(sess):
        m = sess == k
        x[m] -= scipy.ndimage.uniform_filter1d(x[m], size=min(width, int(m.sum())), axis=0, mode="nearest")
    n = x.shape[0]
    L = scipy.fft.next_fast_len(2 * n, real=True)
    F = scipy.fft.rfft(x, n=L, axis=0)
    acf = scipy.fft.irfft(np.abs(F) ** 2, n=L, axis=0)[: n // 4 + 1]
    var = acf[0]
    ok = var > 0
    if not ok.any():
        return spacing
    a = np.mean(acf[:, ok] / var[ok], axis=1)
    below = np.flatnonzero(a < np.exp(-1.0))
    return spacing * float(below[0] if below.size else a.size)


def choose_block_s(gap: Gap) -> tuple[float, dict]:
    """(block length in s, the reasons for the JSON)."""
    s = gap.session
    base = gap.base_design()
    r = gap.target if base.p == 0 else gap.target - predict(base.X, solve(base.X, gap.target, base.mask), base.mask)
    tau = autocorrelation_time_s(r, s.t_s, s.session)
    dt = np.diff(s.t_s)
    spacing = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    lo = max(TAU_FACTOR * tau, MIN_ROWS_PER_BLOCK * spacing)
    spans = [float(np.ptp(s.t_s[s.session == k])) for k in np.unique(s.session)]
    block = MAX_BLOCK_S

    def count(b):
        return int(time_blocks(s.t_s, s.session, b).max()) + 1
    why = "the default length: the sessions hold enough blocks"
    if count(block) < TARGET_BLOCKS:
        # shorten towards TARGET_BLOCKS (geometric steps), not below the autocorrelation limit
        floor = min(lo, MAX_BLOCK_S)
        while block > floor and count(block) < TARGET_BLOCKS:
            block = max(floor, block / 1.25)
        limit = f", limited by {TAU_FACTOR:g}x the autocorrelation time or {MIN_ROWS_PER_BLOCK} rows"
        why = (f"shortened from {MAX_BLOCK_S:g} s so that the sessions hold {count(block)} blocks (aim "
               f"{TARGET_BLOCKS})" + (limit if block <= lo else ""))
    block = float(block)
    return block, {"block_s": block, "autocorrelation_time_s": tau, "sessions": len(spans),
                   "session_length_s": spans, "n_blocks": count(block), "reason": why}
