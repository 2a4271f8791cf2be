"""Spectra as the report pages draw them: one unit (one-sided PSD, nT^2/Hz) and averaged into
log-spaced frequency bins, so that a raw periodogram (Lomb-Scargle of an unevenly sampled
session) stays readable at high frequency and both pages show the same kind of curve."""
from __future__ import annotations

import numpy as np

__all__ = ["log_binned_psd", "PSD_LABEL"]

#: Axis label of every spectrum on the report pages.
PSD_LABEL = "PSD (nT^2/Hz)"


def log_binned_psd(freq_hz, psd, bins_per_decade: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``psd`` (n,) or (n, k) over log-spaced frequency bins (empty bins dropped): the
    centre frequency (geometric mean of the bin's frequencies) and the averaged PSD. Averaging a
    PSD keeps its unit and its level for white noise."""
    f = np.asarray(freq_hz, float)
    p = np.asarray(psd, float)
    p2 = p.reshape(f.size, -1)
    ok = (f > 0) & np.all(np.isfinite(p2), axis=1)
    f, p2 = f[ok], p2[ok]
    if f.size == 0:
        return f, p2.reshape((0,) + p.shape[1:])
    lo, hi = np.log10(f.min()), np.log10(f.max())
    n = max(1, int(np.ceil((hi - lo) * bins_per_decade)))
    k = np.minimum(((np.log10(f) - lo) / max(hi - lo, 1e-12) * n).astype(int), n - 1)
    counts = np.bincount(k, minlength=n)
    keep = counts > 0
    fc = np.exp(np.bincount(k, weights=np.log(f), minlength=n)[keep] / counts[keep])
    pc = np.stack([np.bincount(k, weights=p2[:, j], minlength=n)[keep] / counts[keep] for j in range(p2.shape[1])],
                  axis=1)
    return fc, pc.reshape((fc.size,) + p.shape[1:])
