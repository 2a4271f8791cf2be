"""An orbit truth for one-sample-at-a-time consumers: the smooth parts on a time grid, interpolated.

:class:`~magstack.sim.orbit_truth.OrbitTruth` is vectorised: one call over N instants costs a few microseconds
per instant (IGRF, frames, attitude), but a register-level simulator asks for one instant at a time, and then
every call pays the whole fixed cost (about 4 ms: an ERFA precession-nutation matrix, the Sun's position,
a degree-13 IGRF). :class:`GriddedOrbitTruth` evaluates the orbit truth's own vectorised code on a grid of
``step_s`` in blocks of ``block_s`` and interpolates per instant with the 4-point Lagrange cubic through the
nodes around it, in plain floats:

* the body-frame field (3 components), the Sun's x component in the body frame (solar current), and the two
  eclipse distances (along the Sun line, and off it) are interpolated: all smooth on the grid's scale;
* the eclipse flag is the same test as :func:`magstack.firmware.reference.frames.in_eclipse` on the
  interpolated distances; the torquer and heater square waves are evaluated exactly; the temperature is the
  thermal grid's linear interpolation (as ``temp_series_c``);
* error of the cubic: about (step_s / tau)^4 / 40 of the amplitude for a signal of time scale tau; with the
  default 0.25 s and the fastest programme (``orbit_spinning``, 6 deg/s: tau = 9.5 s), under 1e-3 nT
  (``tests/test_gridded_orbit.py`` measures it against the direct evaluation).

It is what ``magstack run --sim --sim-program orbit_*`` feeds the simulated sensors; ``magstack simulate``
evaluates :class:`OrbitTruth` directly (whole arrays at once).
"""
from __future__ import annotations

import bisect
import math
from typing import Any

import numpy as np

from magstack.firmware.reference import frames

#: Default grid step (s) and block length (s) of the interpolation.
STEP_S = 0.25
BLOCK_S = 64.0
#: Interpolated quantities, in column order.
_COLUMNS = ("bx", "by", "bz", "sun_x", "along", "perp")


class GriddedOrbitTruth:
    """The TruthSource protocol (scalar and series) of an OrbitTruth from interpolated grid blocks."""

    def __init__(self, orbit: Any, step_s: float = STEP_S, block_s: float = BLOCK_S) -> None:
        if not (math.isfinite(step_s) and step_s > 0 and block_s >= 4 * step_s):
            raise ValueError(f"need step_s > 0 and block_s >= 4 step_s, got {step_s}, {block_s}")
        self.orbit = orbit
        self.step_s = float(step_s)
        self.nodes = int(round(block_s / step_s))        # intervals per block
        self.duration_s = orbit.duration_s
        self.sessions = orbit.sessions
        self._blocks: dict[int, list[list[float]]] = {}   # block index -> rows of _COLUMNS at its nodes
        self._tgrid = orbit._tgrid.tolist()
        self._temp = orbit._temp.tolist()

    def __getattr__(self, name: str):
        # what telemetry carries and the programme's parameters (epoch_unix_s, pos_ecef_series_km, ...)
        if name == "orbit":
            raise AttributeError(name)
        return getattr(self.orbit, name)

    def at_epoch(self, epoch_unix_s: float) -> GriddedOrbitTruth:
        return GriddedOrbitTruth(self.orbit.at_epoch(epoch_unix_s), self.step_s, self.nodes * self.step_s)

    # ------------------------------------------------------------------ the grid
    def _block(self, b: int) -> list[list[float]]:
        rows = self._blocks.get(b)
        if rows is None:
            o = self.orbit
            # nodes -1 .. nodes + 2 of this block: every interval of it has its 4 Lagrange nodes
            t = (b * self.nodes + np.arange(-1, self.nodes + 3)) * self.step_s
            field = o.field_series_uT(t)
            ta = o._abs(t)
            r = o.pos_vel_gcrs_km(t)[0]
            s = frames.sun_direction_gcrs(ta)
            sun_x = o.attitude_series(t).apply(s).reshape(-1, 3)[:, 0]
            along = np.sum(r * s, axis=1)
            perp = np.linalg.norm(r - along[:, None] * s, axis=1)
            rows = np.column_stack([field, sun_x, along, perp]).tolist()
            if len(self._blocks) > 4:                  # consumers move forward: keep the last few blocks
                self._blocks.pop(min(self._blocks))
            self._blocks[b] = rows
        return rows

    def _interp(self, t: float) -> list[float]:
        x = t / self.step_s
        k = math.floor(x)
        u = x - k
        b, i = divmod(k, self.nodes)
        rows = self._block(b)
        p0, p1, p2, p3 = rows[i], rows[i + 1], rows[i + 2], rows[i + 3]    # nodes k-1, k, k+1, k+2
        w0 = -u * (u - 1.0) * (u - 2.0) / 6.0
        w1 = (u + 1.0) * (u - 1.0) * (u - 2.0) / 2.0
        w2 = -(u + 1.0) * u * (u - 2.0) / 2.0
        w3 = (u + 1.0) * u * (u - 1.0) / 6.0
        return [w0 * a + w1 * c + w2 * d + w3 * e for a, c, d, e in zip(p0, p1, p2, p3, strict=True)]

    def _temp_at(self, t: float) -> float:
        g, v = self._tgrid, self._temp
        if t <= g[0]:
            return v[0]
        if t >= g[-1]:
            return v[-1]
        j = bisect.bisect_right(g, t) - 1
        return v[j] + (v[j + 1] - v[j]) * (t - g[j]) / (g[j + 1] - g[j])

    def _currents(self, t: float, sun_x: float, eclipse: bool) -> dict[str, float]:
        o = self.orbit
        k = math.floor(t / o.torquer_period_s)
        on = t % o.torquer_period_s < o.torquer_width_s
        torquer = (o.torquer_A * (1.0 if k % 2 == 0 else -1.0)) if on else 0.0
        solar = 0.0 if eclipse else o.solar_max_A * max(sun_x, 0.0)
        heater = t % o.heater_period_s < o.heater_duty * o.heater_period_s
        battery = solar - o.load_A - o.heater_A * heater - abs(torquer)
        return {"battery": battery, "solar": solar, "torquer": torquer}

    def _session(self, t: float) -> int:
        idx = math.floor(min(max(t, 0.0), self.duration_s) / self.duration_s * self.sessions)
        return min(idx, self.sessions - 1)

    def _check(self, t: float) -> float:
        t = float(t)
        if not math.isfinite(t):
            from magstack.drivers.errors import ConfigurationError

            raise ConfigurationError("truth time t_s must be finite")
        return t

    # ------------------------------------------------------------------ one-sample consumers
    def sample_floats(self, ts: list[float]):
        """(field rows, temperatures, currents by name, sessions) at the instants ``ts`` as plain floats
        (the fast path of :func:`magstack.sim.error_truth.sample_truth_floats`)."""
        bs, temps, sessions = [], [], []
        cur: dict[str, list[float]] = {"battery": [], "solar": [], "torquer": []}
        for x in ts:
            t = self._check(x)
            bx, by, bz, sun_x, along, perp = self._interp(t)
            bs.append([bx, by, bz])
            temps.append(self._temp_at(t))
            for k, v in self._currents(t, sun_x, along < 0 and perp < frames.R_EARTH_KM).items():
                cur[k].append(v)
            sessions.append(self._session(t))
        return bs, temps, cur, sessions

    def field_uT(self, t_s: float) -> np.ndarray:
        return np.array(self._interp(self._check(t_s))[:3])

    def temp_c(self, t_s: float) -> float:
        return self._temp_at(self._check(t_s))

    def currents_A(self, t_s: float) -> dict[str, float]:
        t = self._check(t_s)
        v = self._interp(t)
        return self._currents(t, v[3], v[4] < 0 and v[5] < frames.R_EARTH_KM)

    def session(self, t_s: float) -> int:
        return self._session(self._check(t_s))

    # ------------------------------------------------------------------ series (same values, per instant)
    def field_series_uT(self, t_s) -> np.ndarray:
        return np.array([self._interp(self._check(x))[:3] for x in np.asarray(t_s, float).reshape(-1)]).reshape(-1, 3)

    def temp_series_c(self, t_s) -> np.ndarray:
        return np.array([self.temp_c(x) for x in np.asarray(t_s, float).reshape(-1)])

    def currents_series_A(self, t_s) -> dict[str, np.ndarray]:
        per = [self.currents_A(x) for x in np.asarray(t_s, float).reshape(-1)]
        return {k: np.array([p[k] for p in per]) for k in ("battery", "solar", "torquer")}

    def session_series(self, t_s) -> np.ndarray:
        return np.array([self._session(self._check(x)) for x in np.asarray(t_s, float).reshape(-1)], dtype=np.int64)
