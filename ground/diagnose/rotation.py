"""``mount_rotation`` in the diagnosis: a small per-session rotation of the mount, fitted jointly.

Catalogue (firmware_py/effects.py): a bench remount turns the sensor by ``R_s`` per session; relative
to the frame session (``R_frame = I``) and to first order in the angles, the reference field seen in
the sensor's frame of session ``s`` moves by ``delta_B = omega_s x B_ref``. That is linear in the three
angles ``omega_s`` (rad) per session beyond the frame: columns ``(e_a x B_ref)`` restricted to the
session's rows, one per angle, each entering all three output axes with the *same* coefficient. The
angles couple the output axes, so the base model's per-axis columns and the angles are solved as one
stacked least-squares problem (rows of axis i weighted by ``1/sigma_i``, the baseline's held-out RMS
of that axis), on normal equations accumulated axis by axis in row chunks (memory O(N), columns
built on demand).

Conventions shared with the calibration's own estimator (firmware_py/calibration/mount.py): the frame
session is chosen by its ``choose_frame`` (the first session whose field is perpendicular to every
axis), an angle about axis ``a`` in session ``s`` is testable only when the field perpendicular to
``a`` has an RMS of at least ``FitOptions.min_field_rms_uT`` there (``perpendicular_rms``); else it is
held at 0 with that reason. Testable only with >= 2 sessions. The columns are built from the
reference field (nearly noiseless; the same field in every mode, so mode (b) gaps use them as is).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magstack.firmware.calibration.fit import FitOptions
from magstack.firmware.calibration.mount import choose_frame, perpendicular_rms
from magstack.ground.diagnose.gap import Block, Gap, solve_gram

AXES = "xyz"


#: Rows per chunk when the stacked normal equations are accumulated (bounded memory for any N).
CHUNK_ROWS = 65536


@dataclass
class MountColumns:
    """Angles of the sessions beyond ``frame``: ``angles`` [(session, axis a)], the reference field
    ``ref_uT`` (N,3) and the session id per row; columns are built on demand (memory O(N))."""

    frame: int
    frame_note: str | None
    ref_uT: np.ndarray
    session: np.ndarray
    angles: list[tuple[int, int]]
    held: list[str] = field(default_factory=list)
    #: (3,3) the DUT-space image of the reference (forward gap: ``dut ~ A ref``), or None (reference space)
    image: np.ndarray | None = None
    _kept: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def q(self) -> int:
        return len(self.angles)

    @property
    def names(self) -> list[str]:
        return [f"omega[{k}][{AXES[a]}]" for k, a in self.angles]

    def axis_columns(self, i: int, rows=None) -> np.ndarray:
        """(n, q): output axis i's component of ``e_a x B_ref`` (``image[i] . (e_a x B_ref)`` with an image)
        on session k's rows, per angle (k, a). A short session's columns are formed once per axis and kept
        (read-only; the joint fit asks for them per fold and chunk); a long one's on demand."""
        if self.ref_uT.shape[0] * self.q * 3 <= KEPT_COLUMN_FLOATS:
            if i not in self._kept:
                self._kept[i] = self._columns(i, None)
                self._kept[i].setflags(write=False)
            return self._kept[i] if rows is None else self._kept[i][rows]
        return self._columns(i, rows)

    def _columns(self, i: int, rows) -> np.ndarray:
        ref = self.ref_uT if rows is None else self.ref_uT[rows]
        ses = self.session if rows is None else self.session[rows]
        out = np.zeros((ref.shape[0], self.q))
        rows_of: dict[int, np.ndarray] = {}
        for c, (k, a) in enumerate(self.angles):
            if k not in rows_of:
                rows_of[k] = np.flatnonzero(ses == k)
            m = rows_of[k]
            rot = axis_cross(a, ref[m])
            out[m, c] = rot[:, i] if self.image is None else rot @ self.image[i]
        return out

    def flat(self, rows=None) -> np.ndarray:
        """(n, 3q) the angle columns as seen by each output axis (for confounding checks)."""
        return np.hstack([self.axis_columns(i, rows) for i in range(3)])


#: Floats of angle columns a MountColumns keeps (all three axes of a short session).
KEPT_COLUMN_FLOATS = 1_000_000


def axis_cross(a: int, b: np.ndarray) -> np.ndarray:
    """(n,3) ``e_a x b`` for the unit vector of axis ``a`` and rows ``b`` (n,3): two components are +-b's
    others, one is zero (what np.cross gives, without its general product)."""
    j, k = (a + 1) % 3, (a + 2) % 3
    out = np.zeros_like(b)
    out[:, j] = -b[:, k]
    out[:, k] = b[:, j]
    return out


def mount_columns(gap: Gap, min_field_rms_uT: float | None = None) -> MountColumns | str:
    """The angle columns, or the reason the effect is not testable on this gap."""
    s = gap.session
    ids = sorted(int(k) for k in np.unique(s.session))
    if len(ids) < 2:
        return "one session: a mount rotation relative to a frame session needs >= 2 sessions"
    lim = FitOptions().min_field_rms_uT if min_field_rms_uT is None else float(min_field_rms_uT)
    ref = s.ref_uT
    w = np.ones(gap.n)
    frame, note = choose_frame(ref, s.session, w, None, lim)
    angles, held = [], []
    for k in ids:
        if k == frame:
            continue
        m = s.session == k
        perp = perpendicular_rms(ref[m], w[m])
        for a in range(3):
            if perp[a] < lim:
                held.append(f"session {k} about {AXES[a]}: field perpendicular to {AXES[a]} has RMS "
                            f"{perp[a]:.3g} uT (need {lim:g} uT)")
            else:
                angles.append((k, a))
    if not angles:
        return "no session has enough field perpendicular to any axis: " + "; ".join(held)
    # forward gap (dut = A R^-1 ref): the rotation acts before the gain, so its columns are mapped into DUT units
    image = gap._dut_image() if gap.forward else None
    return MountColumns(frame, note, ref, s.session, angles, held, image)


def _stack(base: Block, mc: MountColumns, i: int, rows) -> np.ndarray:
    """Axis i's rows of the stacked design: base columns of axis i in their own parameter slots (the
    other axes' slots zero), then the shared angle columns."""
    X = base.X[rows]
    nb = int(base.mask.sum())
    Z = np.zeros((X.shape[0], nb + mc.q))
    off = int(base.mask[:i].sum())
    used = np.flatnonzero(base.mask[i])
    Z[:, off:off + used.size] = X[:, used]
    Z[:, nb:] = mc.axis_columns(i, rows)
    return Z


def _chunks(rows: np.ndarray):
    idx = np.flatnonzero(rows)
    for k in range(0, idx.size, CHUNK_ROWS):
        yield idx[k:k + CHUNK_ROWS]


def _normal(base, mc, Y, w, rows):
    P = int(base.mask.sum()) + mc.q
    G, b = np.zeros((P, P)), np.zeros(P)
    for ch in _chunks(rows):
        for i in range(3):
            Z = _stack(base, mc, i, ch)
            G += w[i] ** 2 * (Z.T @ Z)
            b += w[i] ** 2 * (Z.T @ Y[ch, i])
    return G, b


def _solve(G, b):
    P = G.shape[0]
    return solve_gram(G, np.column_stack([b, b, b]), np.ones((3, P), bool))[0]


def _residual(base, mc, Y, theta, rows) -> np.ndarray:
    out = np.empty((int(np.count_nonzero(rows)), 3))
    k = 0
    for ch in _chunks(rows):
        out[k:k + ch.size] = Y[ch] - np.column_stack([_stack(base, mc, i, ch) @ theta for i in range(3)])
        k += ch.size
    return out


def out_of_fold(base: Block, mc: MountColumns, Y: np.ndarray, fold: np.ndarray, sigma_uT: np.ndarray):
    """Out-of-fold residual (N,3) and per-fold angle estimates (q,) of the joint fit."""
    w = 1.0 / np.maximum(np.asarray(sigma_uT, dtype=float), 1e-12)
    G, b = _normal(base, mc, Y, w, np.ones(Y.shape[0], bool))
    nb = int(base.mask.sum())
    r = np.full(Y.shape, np.nan)
    angles = []
    for f in np.unique(fold):
        test = fold == f
        if (~test).sum() <= G.shape[0] or not test.any():
            continue
        Gf, bf = _normal(base, mc, Y, w, test)
        th = _solve(G - Gf, b - bf)
        r[test] = _residual(base, mc, Y, th, test)
        angles.append(th[nb:])
    return r, angles


def train_test_residual(base: Block, mc: MountColumns, Y: np.ndarray, sigma_uT: np.ndarray,
                        train: np.ndarray, test: np.ndarray) -> np.ndarray:
    """Residual (n_test,3) on ``test`` rows of the joint fit (base columns + angles) on ``train`` rows."""
    w = 1.0 / np.maximum(np.asarray(sigma_uT, dtype=float), 1e-12)
    G, b = _normal(base, mc, Y, w, train)
    return _residual(base, mc, Y, _solve(G, b), test)


def _unstack(base: Block, th: np.ndarray) -> np.ndarray:
    """(3, p) per-axis base coefficients (0 where the mask is off) from the stacked parameter vector."""
    out = np.zeros(base.mask.shape)
    k = 0
    for i in range(3):
        used = np.flatnonzero(base.mask[i])
        out[i, used] = th[k:k + used.size]
        k += used.size
    return out


def joint_fit(base: Block, mc: MountColumns, Y: np.ndarray, sigma_uT: np.ndarray, rows=None):
    """Joint fit on ``rows`` (all by default): (base coefficients (3,p), their OLS standard errors (3,p),
    angles (q,) rad, their standard errors (q,)), from the weighted stacked problem."""
    w = 1.0 / np.maximum(np.asarray(sigma_uT, dtype=float), 1e-12)
    rows = np.ones(Y.shape[0], bool) if rows is None else rows
    G, b = _normal(base, mc, Y, w, rows)
    th = _solve(G, b)
    r = _residual(base, mc, Y, th, rows) * w
    dof = max(r.size - G.shape[0], 1)
    s2 = float(np.sum(r ** 2)) / dof
    d = np.sqrt(np.diag(G))
    d[d == 0] = 1.0
    cov = np.linalg.pinv(G / np.outer(d, d), hermitian=True) / np.outer(d, d) * s2
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    nb = int(base.mask.sum())
    return _unstack(base, th[:nb]), _unstack(base, se[:nb]), th[nb:], se[nb:]


def fit_all(base: Block, mc: MountColumns, Y: np.ndarray, sigma_uT: np.ndarray):
    """Angles (q,) rad on all rows with OLS standard errors of the weighted stacked problem."""
    _, _, ang, se = joint_fit(base, mc, Y, sigma_uT)
    return ang, se
