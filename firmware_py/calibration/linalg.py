"""Small linear-algebra helpers shared by the batch, streaming and mount solvers."""
from __future__ import annotations

import numpy as np

#: Rank tolerance: a column whose part orthogonal to the columns accepted before it is
#: below this fraction of its own norm is numerically undetermined.
RANK_RTOL = 1e-9


def qr_r(A: np.ndarray) -> np.ndarray:
    """Square upper-triangular R with R^T R = A^T A (zero-padded if A has few rows)."""
    m = A.shape[1]
    if A.shape[0] == 0:
        return np.zeros((m, m))
    R = np.linalg.qr(A, mode="r")
    if R.shape[0] < m:
        R = np.vstack([R, np.zeros((m - R.shape[0], m))])
    return R
