"""Independent bench-session generator (pure numpy; shares no code with ``magstack.sim``).

Written from the effect catalogue's descriptions (firmware_py/effects.py), the belsten paper
(seed digest) and first principles, with its own parameterisations, its own stimulus and its own
session-file writer (docs/session-file.md), so that a diagnosis or calibration that passes on these
files is not passing because generator and analyser share code. Model equations:
docs/diagnosis-independent.md.

Units: fields uT, time s (Unix epoch in the file), temperature degC, currents A.

    >>> s = make_session(Scenario(effect="hysteresis", seed=3))
    >>> s.write(tmp_path / "h.csv")            # writes h.csv and h.truth.json
"""
from __future__ import annotations

import json
import os
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

#: Catalogue effects this generator can switch on (one at a time, on top of gain matrix + offset).
#: ``gain`` and ``misalignment`` replace the always-on matrix by a pure scale / pure rotation.
#: Each name is an effect of magstack's catalogue (firmware_py/effects.py).
EFFECTS = ("time_skew", "interference", "mount_rotation", "misalignment", "gain", "cross_axis", "nonlinearity",
           "temperature_gain", "hysteresis", "temperature_offset", "drift", "session_offset")

CURRENT_NAMES = ("heater", "payload", "solar")
FINE_DT_S = 0.01            # truth grid; every continuous quantity is piecewise linear on it
EPOCH0_S = 1_780_000_000.0  # 2026-05-28, arbitrary


@dataclass
class Scenario:
    """What to generate. ``strength`` scales the effect's realistic size (1 = realistic)."""

    effect: str | None = None
    strength: float = 1.0
    seed: int = 0
    n_sessions: int = 3
    session_s: float = 400.0
    pause_s: float = 90.0
    dut_period_s: float = 0.46          # bench logs: 0.456-0.462 s per row (hardware-facts 8.3)
    dut_jitter_s: float = 0.012
    ref_period_s: float = 0.244         # FVM400 log: median 0.246, mean 0.2437 s
    ref_jitter_s: float = 0.018
    white_nT: float = 25.0              # DUT white noise, per axis rms
    pink_nT: float = 12.0               # DUT 1/f component, per axis rms over the session
    env_nT: float = 40.0                # common-mode room field noise (seen by both instruments), rms
    ref_noise_nT: float = 3.0
    ref_lsb_uT: float = 0.001           # FVM400 files: 1 nT steps
    dut_lsb_uT: float = 0.005
    temp_lsb_c: float = 0.0625
    temp_noise_c: float = 0.02
    n_excursions: int = 6               # +-150 uT excursions, spread over the sessions
    excursion_uT: float = 150.0
    ref_dropouts: int = 2               # reference serial dropouts (2-5 s): empty ref cells, flag 1
    excursion_times: str = "even"       # "even": spread evenly over the powered time; "random"
    device_seed: int | None = None      # gain matrix and offset drawn from this (default: seed): one unit
    ref_range_uT: float | None = None   # reference full scale: rows beyond it logged empty with flag 1

    def __post_init__(self):
        if self.effect is not None and self.effect not in EFFECTS:
            raise ValueError(f"unknown effect {self.effect!r}; this generator knows {EFFECTS}")


@dataclass
class GeneratedSession:
    columns: dict                 # name -> (N,) arrays (file columns)
    metadata: dict
    truth: dict
    current_names: tuple = CURRENT_NAMES
    extras: dict = field(default_factory=dict)   # noise-free quantities for tests (not written)

    @property
    def n(self) -> int:
        return int(self.columns["t_s"].size)

    def write(self, path) -> Path:
        """Write the CSV (own writer) and ``<stem>.truth.json`` next to it; returns the CSV path."""
        path = Path(path)
        write_session_csv(path, self.columns, self.metadata, self.current_names)
        tmp = path.with_name(path.stem + ".truth.json.part")
        tmp.write_text(json.dumps(self.truth, indent=1, default=_jsonable))
        os.replace(tmp, path.with_name(path.stem + ".truth.json"))
        return path


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(type(x))


# --------------------------------------------------------------------------------------- writer
def _cell(x: float, decimals: int) -> str:
    return "" if not np.isfinite(x) else f"{x:.{decimals}f}"


def write_session_csv(path, columns: dict, metadata: dict, current_names=CURRENT_NAMES, *,
                      extra_columns: dict | None = None, closing_line: bool = True) -> None:
    """Session file v1 as docs/session-file.md describes it (not magstack's writer): metadata lines,
    header, rows (empty cell = no value), other numeric columns after the currents and before ``flag``,
    and the closing line ``# magstack-end: rows=N crc32=0x........`` (CRC-32 of the row bytes, header
    excluded; ``closing_line=False`` writes a file as older tools did)."""
    path = Path(path)
    extra_columns = extra_columns or {}
    head = ["t_s", "ref_x_uT", "ref_y_uT", "ref_z_uT", "dut_x_uT", "dut_y_uT", "dut_z_uT", "temp_c", "session"]
    head += [f"current_{n}_A" for n in current_names] + list(extra_columns) + ["flag"]
    dec = [6, 6, 6, 6, 6, 6, 6, 4, None] + [6] * len(current_names) + [6] * len(extra_columns) + [None]
    cols = [columns[h] if h in columns else extra_columns[h] for h in head]
    head_text = "\n".join(["# magstack-session: 1"] + [f"# {k}: {v}" for k, v in metadata.items()]
                          + [",".join(head)]) + "\n"
    rows = []
    for i in range(cols[0].size):
        cells = [str(int(c[i])) if d is None else _cell(float(c[i]), d) for c, d in zip(cols, dec, strict=True)]
        rows.append(",".join(cells) + "\n")
    body = "".join(rows).encode("ascii")
    tail = f"# magstack-end: rows={len(rows)} crc32=0x{zlib.crc32(body):08x}\n".encode() if closing_line else b""
    part = path.with_name(path.name + ".part")
    with open(part, "wb") as fh:
        fh.write(head_text.encode("utf-8") + body + tail)
    os.replace(part, path)


# --------------------------------------------------------------------------------------- stimulus
def _pink(rng, n: int, rms: float) -> np.ndarray:
    """1/f-power noise of ``rms`` on n uniform samples (FFT shaping, lowest bin 1/n)."""
    if n < 4 or rms == 0:
        return np.zeros(n)
    f = np.fft.rfftfreq(n)
    amp = np.zeros_like(f)
    amp[1:] = 1.0 / np.sqrt(f[1:])
    spec = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
    x = np.fft.irfft(spec, n)
    x -= x.mean()
    return x * rms / x.std()


def _lowfreq(rng, n: int, dt: float, rms: float, corner_hz: float) -> np.ndarray:
    """Room noise: 1/f below ``corner_hz``, falling as 1/f^2 above (most power below 1 Hz)."""
    f = np.fft.rfftfreq(n, dt)
    amp = np.zeros_like(f)
    amp[1:] = 1.0 / np.sqrt(f[1:]) / (1.0 + (f[1:] / corner_hz) ** 2)
    x = np.fft.irfft(amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)), n)
    x -= x.mean()
    return x * rms / x.std()


def _rand_vec(rng, lo: float, hi: float) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v) * rng.uniform(lo, hi)


def _coil_program(rng, t: np.ndarray, windows, sc: Scenario) -> tuple[np.ndarray, list]:
    """Coil field on the truth grid: dwell plateaus, steps (slew 0.2 s), multi-axis ramps, random
    walks, rotations of a constant-magnitude field, and +-150 uT single-axis excursions placed inside
    the sessions (axis and sign per excursion from a balanced shuffled list)."""
    n = t.size
    b = np.zeros((n, 3))
    # excursion schedule: evenly spread over the powered time, each axis both signs if >= 6
    pairs = [(ax, sg) for sg in (1, -1) for ax in range(3)]
    rng.shuffle(pairs)
    pairs = (pairs * ((sc.n_excursions + 5) // 6))[:sc.n_excursions]
    powered = np.concatenate([np.arange(a + min(30.0, 0.1 * (e - a)), e - min(40.0, 0.15 * (e - a)), 1.0)
                              for a, e in windows])
    if sc.excursion_times == "random":
        ex_t = np.sort(rng.choice(powered, sc.n_excursions, replace=False))
    else:
        ex_t = powered[np.linspace(0, powered.size - 1, sc.n_excursions + 2)[1:-1].astype(int)]
    ex_list = [(float(te), ax, sg) for te, (ax, sg) in zip(ex_t, pairs, strict=True)]
    keys_t, keys_b = [0.0], [_rand_vec(rng, 20, 55)]
    walk_segments = []   # (t0, t1): random walk added on top
    rot_segments = []    # (t0, t1, axis, rate, b0)
    tt = 0.0
    ex_i = 0
    end = float(t[-1])
    while tt < end:
        cur = keys_b[-1]
        if ex_i < len(ex_list) and tt >= ex_list[ex_i][0] - 1.0:
            _, ax, sg = ex_list[ex_i]
            peak = np.zeros(3)
            peak[ax] = sg * sc.excursion_uT
            for dt_, v in ((rng.uniform(3, 5), peak), (rng.uniform(4, 7), peak), (rng.uniform(3, 5), cur * 0.2)):
                tt += dt_
                keys_t.append(tt)
                keys_b.append(v)
            ex_i += 1
            continue
        kind = rng.choice(["dwell", "ramp", "step", "walk", "rot"], p=[0.25, 0.25, 0.2, 0.15, 0.15])
        if kind == "dwell":
            tt += rng.uniform(8, 25)
            keys_t.append(tt)
            keys_b.append(cur)
        elif kind == "ramp":
            tt += rng.uniform(8, 25)
            keys_t.append(tt)
            keys_b.append(np.clip(_rand_vec(rng, 15, 65), -65, 65))
        elif kind == "step":
            new = np.clip(cur + _rand_vec(rng, 5, 30), -65, 65)
            for dt_, v in ((rng.uniform(0.15, 0.3), new), (rng.uniform(6, 15), new)):
                tt += dt_
                keys_t.append(tt)
                keys_b.append(v)
        elif kind == "walk":
            d = rng.uniform(15, 35)
            walk_segments.append((tt, tt + d))
            tt += d
            keys_t.append(tt)
            keys_b.append(cur)
        else:
            d = rng.uniform(20, 40)
            axis = _rand_vec(rng, 1, 1)
            rot_segments.append((tt, tt + d, axis, np.deg2rad(rng.uniform(6, 12)) * rng.choice([-1, 1])))
            tt += d
            keys_t.append(tt)
            keys_b.append(cur)
    kt, kb = np.array(keys_t), np.array(keys_b)
    for j in range(3):
        b[:, j] = np.interp(t, kt, kb[:, j])
    for t0, t1, axis, rate in rot_segments:   # Rodrigues rotation of the held vector (own code)
        m = (t >= t0) & (t < t1)
        ang = rate * (t[m] - t0)
        v = b[m]
        c, s_ = np.cos(ang)[:, None], np.sin(ang)[:, None]
        b[m] = v * c + np.cross(axis, v) * s_ + axis * (v @ axis)[:, None] * (1 - c)
        # come back continuously: blend the last 3 s back to the held vector
        blend = np.clip((t[m] - (t1 - 3.0)) / 3.0, 0, 1)[:, None]
        b[m] = b[m] * (1 - blend) + v * blend
    for t0, t1 in walk_segments:
        m = (t >= t0) & (t < t1)
        k = int(m.sum())
        # setpoint random walk: knots every 2 s (1.5 uT rms per knot), smoothed over 2 s (coil + supply)
        knots = np.cumsum(rng.standard_normal((int((t1 - t0) / 2.0) + 2, 3)) * 1.5, axis=0)
        tk_ = t0 + 2.0 * np.arange(knots.shape[0])
        w = np.column_stack([np.interp(t[m], tk_, knots[:, j]) for j in range(3)])
        box = np.ones(int(2.0 / FINE_DT_S)) / int(2.0 / FINE_DT_S)
        w = np.column_stack([np.convolve(np.pad(w[:, j], box.size, mode="edge"), box, "same")[box.size:-box.size]
                             for j in range(3)])
        w -= w[0] + np.linspace(0, 1, k)[:, None] * (w[-1] - w[0])         # starts and ends at zero
        b[m] += w
    return b, ex_list


def _piecewise_levels(rng, t, levels_fn, dur_lo, dur_hi, slew_s=0.05) -> np.ndarray:
    keys_t, keys_v, tt = [0.0], [levels_fn()], 0.0
    while tt < t[-1]:
        tt += rng.uniform(dur_lo, dur_hi)
        keys_t.append(tt)
        keys_v.append(keys_v[-1])
        tt += slew_s
        keys_t.append(tt)
        keys_v.append(levels_fn())
    return np.interp(t, keys_t, keys_v)


def _currents(rng, t, windows) -> dict:
    """Heater: on/off 60-200 s at ~0.45 A (drives the temperature); payload: bursts 0.2-0.8 A of
    3-30 s; solar: slow sun-angle variation 0-1.2 A with a little ripple. All zero while powered off."""
    on = np.zeros(t.size, bool)
    for a, e in windows:
        on |= (t >= a) & (t < e)
    heater = _piecewise_levels(rng, t, lambda: rng.choice([0.0, rng.uniform(0.35, 0.5)], p=[0.45, 0.55]), 60, 200)
    payload = _piecewise_levels(rng, t, lambda: rng.choice([0.0, rng.uniform(0.2, 0.8)], p=[0.6, 0.4]), 3, 30)
    ph = rng.uniform(0, 2 * np.pi)
    solar = np.clip(0.6 + 0.55 * np.sin(2 * np.pi * t / rng.uniform(180, 320) + ph), 0, None)
    solar = solar + 0.02 * np.sin(2 * np.pi * t / 7.3)
    return {"heater": heater * on, "payload": payload * on, "solar": np.clip(solar, 0, None) * on}


def _temperature(rng, t, heater_A, windows) -> np.ndarray:
    """Die temperature: first-order thermal node (tau 200-280 s) driven by heater power (11-15 degC
    at 0.45 A into ~8 ohm, i.e. ~7 K/W), board self-heating when powered (2 degC) and a room drifting
    slowly (+-0.5 degC). Integrated at 1 s."""
    tc = np.arange(0.0, t[-1] + 1.0, 1.0)
    h = np.interp(tc, t, heater_A)
    powered = np.zeros(tc.size)
    for a, e in windows:
        powered[(tc >= a) & (tc < e)] = 1.0
    room = 21.5 + rng.uniform(-1, 1) + 0.5 * np.sin(2 * np.pi * tc / 3000 + rng.uniform(0, 6))
    rise_c = rng.uniform(11, 15) / 0.45 ** 2                         # degC per A^2 (heater ~8 ohm, ~7 K/W)
    target = room + 2.0 * powered + rise_c * h ** 2
    tau = rng.uniform(200, 280)
    temp = np.empty(tc.size)
    temp[0] = room[0] + rng.uniform(0, 3)
    a = 1.0 - np.exp(-1.0 / tau)
    for i in range(1, tc.size):
        temp[i] = temp[i - 1] + a * (target[i - 1] - temp[i - 1])
    return np.interp(t, tc, temp)


# --------------------------------------------------------------------------------------- sensor
def _rot(axis: np.ndarray, ang: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(ang) * k + (1 - np.cos(ang)) * k @ k


def _params(dev_rng, rng, sc: Scenario) -> dict:
    """Sensor parameters: always a gain matrix + offset (from ``dev_rng``: the unit), the scenario's
    effect at realistic size x strength (from ``rng``)."""
    s = sc.strength
    scale = 1.0 + dev_rng.uniform(-0.08, 0.12, 3)                      # belsten Table 2: 1.095-1.12
    nonorth = np.eye(3) + np.triu(dev_rng.normal(0, 0.01, (3, 3)), 1)   # a few mrad non-orthogonality
    rot = _rot(_rand_vec(dev_rng, 1, 1), np.deg2rad(dev_rng.uniform(0.5, 2.5)))
    soft = dev_rng.normal(0, 0.02, (3, 3)) * (1 - np.eye(3))           # Table 3 off-axis up to ~0.09
    M = np.diag(scale) @ nonorth @ rot + soft
    F = dev_rng.choice([-1, 1], 3) * dev_rng.uniform(0.3, 3.0, 3)       # uT, Table 1: -0.47..0.33
    p = {"M": M, "F_uT": F}
    e = sc.effect
    if e == "gain":        # pure per-axis scale (no rotation, no coupling): model must lack gain_matrix
        p["M"] = np.diag(1.0 + s * rng.choice([-1, 1], 3) * rng.uniform(0.04, 0.12, 3))
    elif e == "misalignment":   # pure small rotation + non-orthogonality, unit sensitivity
        p["M"] = _rot(_rand_vec(rng, 1, 1), s * np.deg2rad(rng.uniform(1.0, 2.0))) @ (
            np.eye(3) + s * np.triu(rng.normal(0, 0.004, (3, 3)), 1))
    elif e == "time_skew":   # set/reset, ADS1248 at 20 SPS: conversions 50.8 ms apart, X,Y,Z,T per state
        conv = 0.0508 * s
        p["conv_times_s"] = np.array([[0, 4 * conv], [conv, 5 * conv], [2 * conv, 6 * conv]])
    elif e == "interference":
        p["D_uT_per_A"] = {"heater": s * _rand_vec(rng, 0.03, 0.08), "payload": s * _rand_vec(rng, 0.3, 0.6),
                           "solar": s * _rand_vec(rng, 0.2, 0.4)}
    elif e == "mount_rotation":   # hand remount in a printed holder between power cycles: 0.2-0.6 deg
        ang = s * np.deg2rad(rng.uniform(0.2, 0.6, sc.n_sessions))
        p["mount_rotvec_rad"] = np.stack([_rand_vec(rng, 1, 1) * a for a in ang])
    elif e == "cross_axis":
        p["H0_uT"] = rng.uniform(1000, 1400, 3) / np.sqrt(s)            # anisotropy-like field scale
        p["set_reset_imbalance"] = 0.03 * rng.choice([-1, 1], 3)
        p["easy_axis"] = np.array([1, 0, 0])      # index of each bridge's easy axis: x -> y, y -> x, z -> x
    elif e == "nonlinearity":   # saturating bridge: Bs tanh(u/Bs); ~ -u^3/(3 Bs^2): 0.1 uT at 100 uT if s=1
        p["Bs_uT"] = rng.uniform(1600, 2000, 3) / np.sqrt(s)
    elif e == "temperature_gain":   # HMC1053 -2700 ppm/degC typ (-3000..-2400); small curvature
        p["alpha_per_c"] = s * -rng.uniform(2400e-6, 3000e-6, 3)
        p["beta_per_c2"] = s * rng.normal(0, 3e-6, 3)
    elif e == "temperature_offset":   # belsten -140 nT/degC on X, others "to a lesser degree"
        k_o = np.array([0.14, rng.uniform(0.03, 0.1), rng.uniform(0.03, 0.1)])
        p["K_O_uT_per_c"] = s * rng.choice([-1, 1], 3) * k_o
    elif e == "hysteresis":   # belsten 2.3.4: +50 nT after +-150 uT; remanent field of nearby material
        R = np.eye(3) * 0.05 + rng.normal(0, 0.01, (3, 3)) * (1 - np.eye(3))
        p["remanent_uT"] = s * R                  # column j: remanent field after a +excursion on axis j
        p["hyst_threshold_uT"] = rng.uniform(90, 120)
        p["hyst_initial_state"] = rng.choice([-1, 1], 3)
    elif e == "drift":   # 100-200 nT over the run per axis, slightly decelerating (settling)
        p["drift_total_uT"] = s * rng.choice([-1, 1], 3) * rng.uniform(0.1, 0.2, 3)
        p["drift_curvature"] = rng.uniform(0.0, 0.3)
    elif e == "session_offset":   # per power cycle bridge offset after set/reset: ~50-80 nT spread
        k = sc.n_sessions
        base = np.stack([rng.permutation(np.linspace(-1, 1, k)) for _ in range(3)], axis=1)
        p["session_offsets_uT"] = s * (0.07 * base + rng.normal(0, 0.015, (k, 3)))
    return p


def _hysteresis_field(t, b_true, p) -> np.ndarray:
    """Remanent field: per axis, the sign of the last |B_j| > threshold (initial state given)."""
    thr = p["hyst_threshold_uT"]
    out = np.zeros_like(b_true)
    idx = np.arange(t.size)
    for j in range(3):
        ev = np.where(np.abs(b_true[:, j]) > thr, np.sign(b_true[:, j]), 0.0)
        last = np.maximum.accumulate(np.where(ev != 0, idx, -1))
        state = np.where(last >= 0, ev[np.maximum(last, 0)], p["hyst_initial_state"][j])
        out += state[:, None] * p["remanent_uT"][:, j][None, :]
    return out


def make_session(sc: Scenario) -> GeneratedSession:
    # effect parameters keyed by the effect's name (stable when effects are added to EFFECTS)
    rng = np.random.default_rng([20261123, sc.seed, zlib.crc32(sc.effect.encode()) if sc.effect else 0])
    dev_rng = np.random.default_rng([4242, sc.seed if sc.device_seed is None else sc.device_seed])
    stim_rng = np.random.default_rng([777, sc.seed])    # stimulus depends on the seed only, not the effect
    windows = []
    t0 = 5.0
    for _ in range(sc.n_sessions):
        windows.append((t0, t0 + sc.session_s))
        t0 += sc.session_s + sc.pause_s
    t = np.arange(0.0, t0 + 5.0, FINE_DT_S)
    coil, ex_list = _coil_program(stim_rng, t, windows, sc)
    env = np.column_stack([_lowfreq(stim_rng, t.size, FINE_DT_S, sc.env_nT * 1e-3, 0.3) for _ in range(3)])
    cur = _currents(stim_rng, t, windows)
    temp = _temperature(stim_rng, t, cur["heater"], windows)
    p = _params(dev_rng, rng, sc)
    e = sc.effect

    b_room = coil + env                              # what the reference sees
    b_sensor = b_room.copy()                         # what the DUT's bridges see
    if e == "interference":
        for k, d in p["D_uT_per_A"].items():
            b_sensor += cur[k][:, None] * d[None, :]
    if e == "hysteresis":
        b_sensor += _hysteresis_field(t, b_room, p)

    # ---- DUT sample times (per session, uneven, jittered, an occasional missed cycle)
    t_rows, sess = [], []
    for k, (a, b_end) in enumerate(windows):
        tk, x = [], a + stim_rng.uniform(0.5, 1.5)
        while x < b_end:
            tk.append(x)
            x += sc.dut_period_s + stim_rng.uniform(-sc.dut_jitter_s, sc.dut_jitter_s)
            if stim_rng.random() < 0.01:
                x += sc.dut_period_s
        t_rows.append(np.array(tk))
        sess.append(np.full(len(tk), k + 1))
    tk = np.concatenate(t_rows)
    session = np.concatenate(sess)
    n = tk.size

    conv = p.get("conv_times_s", np.zeros((3, 2)))
    if e == "mount_rotation":   # the sensor senses R_s^T B in session s (R_s from the rotation vector)
        R = np.stack([_rot(v, np.linalg.norm(v)) for v in p["mount_rotvec_rad"]])
        M_row = np.einsum("ij,njk->nik", p["M"], np.transpose(R, (0, 2, 1))[session - 1])   # M R_s^T per row
    else:
        M_row = None
    T_die = np.interp(tk, t, temp)
    dT = T_die - 25.0
    M = p["M"]
    out = np.zeros((n, 3))
    for i in range(3):                       # bridge i, set and reset conversions
        acc = np.zeros(n)
        for c, sign in ((0, 1.0), (1, -1.0)):
            tc = tk + conv[i, c]
            bv = np.column_stack([np.interp(tc, t, b_sensor[:, j]) for j in range(3)])
            u = bv @ M.T if M_row is None else np.einsum("nij,nj->ni", M_row, bv)   # sensor-frame field
            if e == "temperature_gain":
                u = u * (1 + p["alpha_per_c"] * dT[:, None] + p["beta_per_c2"] * dT[:, None] ** 2)
            ui = u[:, i]
            if e == "cross_axis":   # set: H0 (1+eps), reset: H0 (1-eps); easy-axis field h flips sign with state
                h = u[:, p["easy_axis"][i]]
                h0 = p["H0_uT"][i] * (1 + sign * p["set_reset_imbalance"][i])
                ui = ui * h0 / (h0 + sign * h)
            if e == "nonlinearity":
                bs = p["Bs_uT"][i]
                ui = bs * np.tanh(ui / bs)
            acc += ui          # V_set = +S ui_set, V_reset = -S ui_reset: (V_set - V_reset)/2 averages them
        out[:, i] = acc / 2.0
    out += p["F_uT"]
    if e == "temperature_offset":
        out += dT[:, None] * p["K_O_uT_per_c"][None, :]
    if e == "drift":
        span = tk[-1] - tk[0]
        x = (tk - tk[0]) / span
        shape = (x - p["drift_curvature"] * x ** 2) / (1 - p["drift_curvature"])
        out += shape[:, None] * p["drift_total_uT"][None, :]
    if e == "session_offset":
        out += p["session_offsets_uT"][session - 1]
    clean = out.copy()
    noise = stim_rng.standard_normal((n, 3)) * sc.white_nT * 1e-3
    for k in range(sc.n_sessions):
        m = session == k + 1
        noise[m] += np.column_stack([_pink(stim_rng, int(m.sum()), sc.pink_nT * 1e-3) for _ in range(3)])
    dut = np.round((out + noise) / sc.dut_lsb_uT) * sc.dut_lsb_uT

    # ---- reference: own 4 Hz clock over each session, noise, 1 nT quantisation, linear interpolation
    ref = np.zeros((n, 3))
    ref_truth = np.column_stack([np.interp(tk, t, b_room[:, j]) for j in range(3)])
    for k, (a, b_end) in enumerate(windows):
        m = session == k + 1
        rt = np.cumsum(sc.ref_period_s + stim_rng.uniform(-sc.ref_jitter_s, sc.ref_jitter_s,
                                                            int((b_end - a + 4) / sc.ref_period_s) + 10)) + a - 1.0
        rv = np.column_stack([np.interp(rt, t, b_room[:, j]) for j in range(3)])
        rv += stim_rng.standard_normal(rv.shape) * sc.ref_noise_nT * 1e-3
        rv = np.round(rv / sc.ref_lsb_uT) * sc.ref_lsb_uT
        ref[m] = np.column_stack([np.interp(tk[m], rt, rv[:, j]) for j in range(3)])

    flag = np.zeros(n, dtype=int)
    if sc.ref_range_uT is not None:      # over-range reference (belsten 2.3.4: the +-150 uT run saturated it)
        over = np.any(np.abs(ref) > sc.ref_range_uT, axis=1)
        ref[over] = np.nan
        flag[over] = 1
    for _ in range(sc.ref_dropouts):
        a = stim_rng.uniform(tk[0], tk[-1] - 6.0)
        gone = (tk >= a) & (tk < a + stim_rng.uniform(2.0, 5.0))
        ref[gone] = np.nan
        flag[gone] = 1                   # bit value 1: no reference (as the AV-MagEval importer)
    temp_col = np.round((T_die + stim_rng.standard_normal(n) * sc.temp_noise_c) / sc.temp_lsb_c) * sc.temp_lsb_c
    cols = {"t_s": EPOCH0_S + sc.seed * 86400.0 + tk,
            "ref_x_uT": ref[:, 0], "ref_y_uT": ref[:, 1], "ref_z_uT": ref[:, 2],
            "dut_x_uT": dut[:, 0], "dut_y_uT": dut[:, 1], "dut_z_uT": dut[:, 2],
            "temp_c": temp_col, "session": session, "flag": flag}
    for k in CURRENT_NAMES:
        cols[f"current_{k}_A"] = np.interp(tk, t, cur[k]) + stim_rng.normal(0, 0.002, n)
    noise_total = np.sqrt(sc.white_nT ** 2 + sc.pink_nT ** 2 + sc.ref_noise_nT ** 2
                           + (sc.dut_lsb_uT * 1e3) ** 2 / 12)
    truth = {"generator": "tests/independent/generator.py", "scenario": asdict(sc), "effect": e or "none",
             "model_dut": "dut = avg_set/reset[f_i(M(T) (B_room + effect fields)(t + conv_i))] + F + offsets + noise",
             "parameters": p, "expected_cal": {"S": np.linalg.inv(M), "O_uT": -np.linalg.inv(M) @ p["F_uT"],
                                               "note": "B_ref = S B_dut + O for the gain+offset part"},
             "noise_rms_nT_per_axis": noise_total, "excursions": ex_list, "n_rows": n,
             "temp_span_c": float(np.ptp(T_die))}
    meta = {"dut_chip": "hmc1053", "device_id": f"indep:seed{sc.seed}", "reference": "fvm400",
            "generator": "magstack tests/independent (not magstack.sim)", "effect": e or "none"}
    extras = {"clean_dut_uT": clean, "ref_truth_uT": ref_truth, "t_rel_s": tk, "noise_uT": noise}
    return GeneratedSession(cols, meta, truth, CURRENT_NAMES, extras)
