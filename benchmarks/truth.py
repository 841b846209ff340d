"""Truth trajectories: the ADS-B tracks of ``data/truth`` and a synthetic seed-like track.

Frame as in spec/reconstruction.md: ``x`` north, ``z`` east (m), radar at the origin, ``h``
altitude (m). Between samples the truth is a cubic spline (scipy ``CubicSpline``) of each column;
the turn rate is ``phi' = (vx vz' - vz vx') / (vx^2 + vz^2)`` from the velocity splines.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from scipy.interpolate import CubicSpline

from solver.inputs import FloatArray
from solver.motion import propagate, velocity
from solver.results import StateSeries

DATA_DIR = Path(__file__).parent / "data" / "truth"
SYNTHETIC = "synthetic__seed_like"


@dataclass
class Truth:
    """One trajectory sampled at times ``t`` (s, increasing) with position ``(x, z)``, altitude
    ``h`` (m) and velocity ``(vx, vz)`` (m/s)."""

    name: str
    t: FloatArray
    x: FloatArray
    z: FloatArray
    h: FloatArray
    vx: FloatArray
    vz: FloatArray
    _splines: dict[str, CubicSpline] = field(default_factory=dict, init=False, repr=False)

    def _spline(self, column: str) -> CubicSpline:
        if column not in self._splines:
            self._splines[column] = CubicSpline(self.t, getattr(self, column))
        return self._splines[column]

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def at(self, t: ArrayLike) -> StateSeries:
        """Horizontal state at times ``t`` (cubic interpolation; no covariance)."""
        tt = np.asarray(t, dtype=float)
        return StateSeries(tt, *(self._spline(c)(tt) for c in ("x", "z", "vx", "vz")))

    def altitude_at(self, t: ArrayLike) -> FloatArray:
        """Altitude (m) at times ``t``."""
        return self._spline("h")(np.asarray(t, dtype=float))

    def turn_rate_at(self, t: ArrayLike) -> FloatArray:
        """Turn rate ``phi'`` (rad/s, positive clockwise seen from above) at times ``t``."""
        tt = np.asarray(t, dtype=float)
        vx, vz = self._spline("vx")(tt), self._spline("vz")(tt)
        ax, az = self._spline("vx")(tt, 1), self._spline("vz")(tt, 1)
        return (vx * az - vz * ax) / np.maximum(vx * vx + vz * vz, 1e-9)


def truth_names() -> list[str]:
    """The ADS-B truth files (the dev set), sorted, then the synthetic seed-like track."""
    return [*sorted(p.stem for p in DATA_DIR.glob("*.csv")), SYNTHETIC]


@cache
def _load(name: str) -> Truth:
    if name == SYNTHETIC:
        return synthetic_seed_track()
    path = DATA_DIR / f"{name}.csv"
    if not path.exists():
        raise KeyError(f"unknown truth {name!r}; known: {truth_names()}")
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    with path.open() as f:
        header = f.readline().strip().split(",")
    cols = {c: data[:, i] for i, c in enumerate(header)}
    return Truth(name, cols["t"], cols["x"], cols["z"], cols["h"], cols["vx"], cols["vz"])


def load_truth(name: str) -> Truth:
    """Truth by name (a CSV stem of ``data/truth`` or ``synthetic__seed_like``); cached."""
    return _load(name)


# (duration s, u m/s^2, w m/s^2): straight legs, a ~220 deg right turn at 150 m/s, a ~180 deg
# left turn at 200 m/s, speed changes; 5000 s like seed 000's real track (5057 s).
SEED_LIKE_CONTROLS: tuple[tuple[float, float, float], ...] = (
    (800.0, 0.0, 0.0),      # cruise at 220 m/s
    (70.0, 0.0, -1.0),      # slow down to 150 m/s
    (400.0, 0.0, 0.0),
    (115.2, 5.0, 0.0),      # right turn, 5 m/s^2 at 150 m/s: 1.91 deg/s, 220 deg
    (600.0, 0.0, 0.0),
    (50.0, 0.0, 1.0),       # speed up to 200 m/s
    (900.0, 0.0, 0.0),
    (104.7, -6.0, 0.0),     # left turn, 6 m/s^2 at 200 m/s: 1.72 deg/s, 180 deg
    (300.0, 0.0, 0.0),
    (100.0, 0.0, -0.5),     # slow down to 150 m/s
    (1560.1, 0.0, 0.0),
)


def synthetic_seed_track(step_s: float = 1.0) -> Truth:
    """Piecewise-constant-control truth (``solver.motion.propagate``) shaped like seed 000's track.

    Controls :data:`SEED_LIKE_CONTROLS` from ``(x, z) = (-120 km, 40 km)`` heading north at
    220 m/s, altitude 3000 m (ranges 31-163 km; a holding-pattern altitude, low enough that the
    slant-range bias ``h^2 / 2r`` stays below 150 m); sampled every ``step_s`` seconds (the
    spline between 1-s samples is accurate to centimetres, except within a second of a control
    switch).
    """
    state = (-120e3, 40e3, 0.0, 220.0)
    ts, xs, zs, phis, vs = [np.array([0.0])], [np.array([state[0]])], [np.array([state[1]])], \
        [np.array([state[2]])], [np.array([state[3]])]
    t0 = 0.0
    for dur, u, w in SEED_LIKE_CONTROLS:
        tau = np.arange(step_s, dur + 1e-9, step_s)
        if tau.size == 0 or tau[-1] < dur - 1e-9:
            tau = np.append(tau, dur)
        x, z, phi, v = propagate(*state, u, w, tau)
        ts.append(t0 + tau)
        xs.append(x)
        zs.append(z)
        phis.append(phi)
        vs.append(v)
        state = (float(x[-1]), float(z[-1]), float(phi[-1]), float(v[-1]))
        t0 += dur
    t, x, z = np.concatenate(ts), np.concatenate(xs), np.concatenate(zs)
    vx, vz = velocity(np.concatenate(phis), np.concatenate(vs))
    keep = np.concatenate([[True], np.diff(t) > 1e-6])
    return Truth(SYNTHETIC, t[keep], x[keep], z[keep], np.full(keep.sum(), 3000.0),
                 vx[keep], vz[keep])
