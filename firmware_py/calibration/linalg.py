"""Small linear-algebra helpers shared by the batch, streaming and mount solvers."""
from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

#: Rank tolerance: a column whose part orthogonal to the columns accepted before it is
#: below this fraction of its own norm is numerically undetermined.
RANK_RTOL = 1e-9


def qr_r(*blocks: np.ndarray) -> np.ndarray:
    """Square upper-triangular R with R^T R = A^T A, ``A`` the row blocks ``blocks`` stacked (zero-padded if
    ``A`` has few rows). Householder QR (LAPACK ``dgeqrf``) of ``A`` built once in column order: the blocks are
    copied once, not stacked and then transposed."""
    m = blocks[0].shape[1]
    rows = sum(b.shape[0] for b in blocks)
    if rows == 0:
        return np.zeros((m, m))
    A = np.empty((rows, m), order="F")
    at = 0
    for b in blocks:
        A[at:at + b.shape[0]] = b
        at += b.shape[0]
    qr, _, _, info = lapack.dgeqrf(A, lwork=max(64 * m, 1), overwrite_a=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"dgeqrf failed (info {info})")
    R = np.triu(qr[:min(rows, m)])
    if R.shape[0] < m:
        R = np.vstack([R, np.zeros((m - R.shape[0], m))])
    return R
