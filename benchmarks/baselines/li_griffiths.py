"""Li-Griffiths ellipsoid-specific least squares: the baseline of ``bench_handcal.py``.

Q. Li and J. G. Griffiths, "Least squares ellipsoid specific fitting", Proc. Geometric Modeling and
Processing 2004, written from the paper's description: the quadric ``a x^2 + b y^2 + c z^2 + 2f yz + 2g xz +
2h xy + 2p x + 2q y + 2r z + d = 0`` minimises ``||D v||^2`` under the ellipsoid constraint ``k J - I^2 = 1``
(``I = a + b + c``, ``J = ab + bc + ca - f^2 - g^2 - h^2``, ``k = 4``), a generalised eigenproblem in the six
quadratic coefficients after eliminating the four linear ones (``v2 = -S22^-1 S21 v1``); the eigenvector of
the positive eigenvalue. The calibration is then ``W (b - c)`` with ``W = F sqrtm(A)`` for the normalised
ellipsoid ``(b - c)^T A (b - c) = 1`` (as Magneto applies it with the expected field norm F). Not used by
magstack itself.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import sqrtm


def fit(b_uT: np.ndarray, field_uT: float, k: float = 4.0) -> tuple[np.ndarray, np.ndarray, float]:
    """(W (3x3), centre c (3,) uT, in-sample RMS of |W (b - c)| - F uT)."""
    b = np.asarray(b_uT, dtype=float)
    s = float(np.median(np.linalg.norm(b - b.mean(axis=0), axis=1)))
    x, y, z = ((b - b.mean(axis=0)) / s).T
    D = np.column_stack([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z, np.ones_like(x)])
    S = D.T @ D
    S11, S12, S22 = S[:6, :6], S[:6, 6:], S[6:, 6:]
    h = k / 2.0 - 1.0
    C1 = np.array([[-1, h, h, 0, 0, 0], [h, -1, h, 0, 0, 0], [h, h, -1, 0, 0, 0],
                   [0, 0, 0, -k, 0, 0], [0, 0, 0, 0, -k, 0], [0, 0, 0, 0, 0, -k]], dtype=float)
    M = np.linalg.solve(C1, S11 - S12 @ np.linalg.solve(S22, S12.T))
    w, V = np.linalg.eig(M)
    v1 = np.real(V[:, int(np.argmax(np.real(w)))])
    v2 = -np.linalg.solve(S22, S12.T @ v1)
    a, bb, c, f, g, hh = v1
    Q = np.array([[a, hh, g], [hh, bb, f], [g, f, c]])
    u = v2[:3]
    d = v2[3]
    centre = -np.linalg.solve(Q, u)
    A = Q / (centre @ Q @ centre - d)
    if np.trace(A) < 0:
        A = -A
    W = field_uT * np.real(sqrtm(A)) / s
    W = 0.5 * (W + W.T)
    c_uT = centre * s + b.mean(axis=0)
    res = np.linalg.norm((b - c_uT) @ W.T, axis=1) - field_uT
    return W, c_uT, float(np.sqrt(np.mean(res ** 2)))


def apply(W: np.ndarray, c_uT: np.ndarray, b_uT: np.ndarray) -> np.ndarray:
    return (np.asarray(b_uT, dtype=float) - c_uT) @ W.T
