"""Live coverage of the field sphere while a board is turned by hand (what the terminal view draws).

Samples arrive one by one (:meth:`LiveCoverage.add`); every ``refit_s`` of samples the centre and shape of the
readings are re-estimated (a sphere fit, then the closed-form ellipsoid of :mod:`.scalar` once there are
enough directions), and the cells of the 192-cell equal-area sphere (:mod:`.coverage_bins`) are recounted from
the corrected directions: a hard-iron offset as large as the field itself (common on boards) would put raw
directions in the wrong cells. :meth:`state` gives the filled cells, the spread of the corrected magnitude,
the cell the board points the field into now, the emptiest region to turn towards and whether the coverage
is enough (the thresholds of :mod:`.handcal`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magstack.firmware.calibration.coverage_bins import N_BANDS, N_BINS, N_SECTORS, bin_center, bin_index
from magstack.firmware.calibration.handcal import ENOUGH_CELL_FRACTION, ENOUGH_DIRECTION_EIG

#: Samples kept for the shape estimate (thinned evenly when there are more).
MAX_FIT_SAMPLES = 1500


@dataclass
class CoverageState:
    """One snapshot: ``filled`` (192,) bool, ``current`` cell (-1 unknown), ``target`` cell to turn towards
    (-1 none), ``spread_uT`` RMS of the corrected magnitude about its mean, ``magnitude_uT`` its mean,
    ``min_eig`` of the directions' mean outer product, ``enough``, ``samples``, ``shape`` ("raw", "sphere",
    "ellipsoid")."""

    filled: np.ndarray
    current: int
    target: int
    spread_uT: float
    magnitude_uT: float
    min_eig: float
    enough: bool
    samples: int
    shape: str

    @property
    def cells_filled(self) -> int:
        return int(self.filled.sum())

    @property
    def fraction(self) -> float:
        return self.cells_filled / N_BINS


class LiveCoverage:
    """Accumulates readings (uT) and answers :meth:`state` cheaply between re-estimates."""

    def __init__(self, refit_every: int = 100, capacity: int = 200_000) -> None:
        self._b = np.empty((capacity, 3))
        self.n = 0
        self.refit_every = int(refit_every)
        self._since = 0
        self.centre = np.zeros(3)
        self.K = np.eye(3)
        self.shape = "raw"
        self._counts = np.zeros(N_BINS, dtype=np.int64)
        self._mags = np.zeros(0)
        self._last = np.full(3, np.nan)

    def add(self, b_uT) -> None:
        b = np.asarray(b_uT, dtype=float).reshape(3)
        if not np.all(np.isfinite(b)):
            return
        if self.n == len(self._b):                     # grow
            self._b = np.vstack([self._b, np.empty_like(self._b)])
        self._b[self.n] = b
        self.n += 1
        self._since += 1
        self._last = b
        if self._since >= self.refit_every:
            self._refit()

    def _corrected(self, b: np.ndarray) -> np.ndarray:
        return (b - self.centre) @ self.K.T

    def _refit(self) -> None:
        from magstack.firmware.blas import single_thread

        with single_thread():
            self._refit_now()

    def _refit_now(self) -> None:
        self._since = 0
        b = self._b[:self.n]
        if self.n > MAX_FIT_SAMPLES:
            b = b[np.linspace(0, self.n - 1, MAX_FIT_SAMPLES).astype(int)]
        if len(b) >= 20:
            # sphere: |b|^2 = 2 c.b + (r^2 - |c|^2), linear in (c, k)
            A = np.column_stack([2 * b, np.ones(len(b))])
            sol, *_ = np.linalg.lstsq(A, np.sum(b * b, axis=1), rcond=None)
            u = b - sol[:3]
            if np.linalg.eigvalsh(u.T @ u / len(u))[0] > 0.02 * np.mean(np.sum(u * u, axis=1)):
                self.centre, self.K, self.shape = sol[:3], np.eye(3), "sphere"
                self._try_ellipsoid(b)
        cb = self._corrected(self._b[:self.n])
        k = bin_index(cb)
        self._counts = np.bincount(k[k >= 0], minlength=N_BINS)
        self._mags = np.linalg.norm(cb, axis=1)

    def _try_ellipsoid(self, b: np.ndarray) -> None:
        """The algebraic ellipsoid through the points (the shape quadric of :mod:`.scalar`), from the 10x10
        scatter matrix: its smallest eigenvector, scaled to a unit-determinant gain."""
        from scipy.linalg import sqrtm

        u = self._corrected(b)
        d = u / np.linalg.norm(u, axis=1, keepdims=True)
        if np.linalg.eigvalsh(d.T @ d / len(d))[0] < 0.1:
            return                                     # too few directions for 9 shape parameters
        s = float(np.median(np.linalg.norm(b - self.centre, axis=1))) or 1.0
        x, y, z = (b / s).T
        D = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, -2 * x, -2 * y, -2 * z,
                             np.ones(len(b))])
        col = np.linalg.norm(D, axis=0)
        Dn = D / col
        _, vecs = np.linalg.eigh(Dn.T @ Dn)
        th = vecs[:, 0] / col
        A = np.array([[th[0], th[3], th[4]], [th[3], th[1], th[5]], [th[4], th[5], th[2]]])
        if np.trace(A) < 0:
            A, th = -A, -th
        if np.linalg.eigvalsh(A)[0] <= 0:
            return
        c = np.linalg.solve(A, th[6:9]) * s
        K = np.real(sqrtm(A))
        K = 0.5 * (K + K.T) / np.cbrt(np.linalg.det(K))
        if np.all(np.isfinite(K)) and np.all(np.isfinite(c)) and np.all(np.linalg.eigvalsh(K) > 0.2):
            self.centre, self.K, self.shape = c, K, "ellipsoid"

    def state(self) -> CoverageState:
        counts = self._counts.copy()
        mags = self._mags
        cur = -1
        if np.all(np.isfinite(self._last)):
            cur = int(bin_index(self._corrected(self._last[None, :]))[0])
        filled = counts > 0
        if self.n and self._since and cur >= 0:
            filled[cur] = True                         # the cell under the board now, before the next recount
        eig = 0.0
        if mags.size > 3:
            cb = self._corrected(self._b[:self.n:max(1, self.n // 2000)])
            dd = cb / np.linalg.norm(cb, axis=1, keepdims=True)
            eig = float(np.linalg.eigvalsh(dd.T @ dd / len(dd))[0])
        spread = float(np.sqrt(np.mean((mags - mags.mean()) ** 2))) if mags.size else math.nan
        frac = filled.sum() / N_BINS
        enough = bool(frac >= ENOUGH_CELL_FRACTION and eig >= ENOUGH_DIRECTION_EIG and self.shape == "ellipsoid")
        mean = float(mags.mean()) if mags.size else math.nan
        return CoverageState(filled, cur, target_cell(filled, cur), spread, mean, eig, enough, self.n, self.shape)


def target_cell(filled: np.ndarray, current: int) -> int:
    """The empty cell farthest from every filled cell (ties: nearest to ``current``); -1 when all are filled."""
    if filled.all():
        return -1
    centres = bin_center(np.arange(N_BINS))
    empty = np.flatnonzero(~filled)
    if not filled.any():
        return int(empty[0])
    cos = centres[empty] @ centres[filled].T
    gap = -np.max(cos, axis=1)                         # larger = farther from the nearest filled cell
    best = np.flatnonzero(gap >= gap.max() - 1e-9)
    if current >= 0 and best.size > 1:
        best = best[np.argsort(-(centres[empty[best]] @ centres[current]))]
    return int(empty[best[0]])


def turn_hint(current: int, target: int) -> str:
    """Words for the turn that moves the field from cell ``current`` to ``target`` in the board frame: the board
    turns the opposite way about the same axis, so the hint names the board axis and the angle."""
    if target < 0:
        return "every cell is covered"
    c = bin_center([target])[0]
    face = _face(c)
    if current < 0:
        return f"point the board's {face} along the field (for most sites: down and towards the pole)"
    a = bin_center([current])[0]
    axis = np.cross(a, c)
    ang = math.degrees(math.acos(float(np.clip(a @ c, -1.0, 1.0))))
    if np.linalg.norm(axis) < 1e-6:
        return f"flip the board over ({ang:.0f} deg): point its {face} along the field"
    axis = -axis / np.linalg.norm(axis)                # the board turns opposite to the field in its frame
    return (f"turn the board ~{ang:.0f} deg about its {_face(axis)} axis (right hand), so its {face} points "
            "along the field")


def _face(v: np.ndarray) -> str:
    names = []
    for k, a in enumerate("XYZ"):
        if abs(v[k]) >= 0.38:
            names.append(("+" if v[k] > 0 else "-") + a)
    return "/".join(names) if names else "+" + "XYZ"[int(np.argmax(np.abs(v)))]


__all__ = ["LiveCoverage", "CoverageState", "target_cell", "turn_hint", "N_BANDS", "N_SECTORS", "N_BINS"]
