"""Radar simulation (profiles.md): one plot per scan from the 3-D truth.

Scan times ``t0 + phase + k scan_s`` with a random phase in ``[0, scan_s)``; slant range
``sqrt(x^2 + z^2 + h^2) + N(0, sigma_r)``, azimuth ``atan2(z, x) + N(0, sigma_psi)``; each plot
kept with probability ``Pd`` (times ``keep_in_turns`` where ``|turn rate| > 1 deg/s`` if
``drop_in_turns``, mimicking the seed's track with many plots missing in the turns). Every draw
comes from ``numpy.random.default_rng((seed, crc32(truth name), crc32(profile name)))``, so a
(truth, profile, seed) triple always gives the same plots, independently of the run order.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from solver.inputs import FloatArray, Plots
from solver.results import StateSeries

from .profiles import RadarProfile
from .truth import Truth

MANOEUVRE_RATE = np.deg2rad(1.0)  # |turn rate| above this is a manoeuvre (rad/s)


@dataclass
class SimulatedTrack:
    """Plots of one simulated run and the truth at the plot times."""

    plots: Plots
    truth: StateSeries
    altitude: FloatArray
    turn_rate: FloatArray
    profile: RadarProfile
    seed: int
    truth_name: str

    @property
    def manoeuvre(self) -> FloatArray:
        """Boolean mask of plots in a manoeuvre (``|turn rate| > 1 deg/s`` in the truth)."""
        return np.abs(self.turn_rate) > MANOEUVRE_RATE


def rng_for(truth_name: str, profile_name: str, seed: int) -> np.random.Generator:
    """The generator of one (truth, profile, seed) triple."""
    return np.random.default_rng([seed, zlib.crc32(truth_name.encode()),
                                  zlib.crc32(profile_name.encode())])


def simulate(truth: Truth, profile: RadarProfile, seed: int, with_altitude: bool = False,
             drop_in_turns: bool = False, keep_in_turns: float = 0.5,
             t_max: float | None = None) -> SimulatedTrack:
    """Simulated plots of ``truth`` seen by ``profile``'s radar (see the module docstring).

    ``with_altitude`` puts the true altitude in ``plots.altitude_m`` (an SSR's Mode C);
    ``t_max`` cuts the track at that many seconds after its start (short tracks for tests).
    """
    rng = rng_for(truth.name, profile.name, seed)
    t_end = truth.t[-1] if t_max is None else min(truth.t[-1], truth.t[0] + t_max)
    phase = rng.uniform(0.0, profile.scan_s)
    t = np.arange(truth.t[0] + phase, t_end, profile.scan_s)
    n = t.size
    noise_r = rng.normal(0.0, profile.sigma_r, n)
    noise_psi = rng.normal(0.0, profile.sigma_psi, n)
    detect_draw = rng.uniform(size=n)
    state = truth.at(t)
    h = truth.altitude_at(t)
    rate = truth.turn_rate_at(t)
    p_keep = np.full(n, profile.pd)
    if drop_in_turns:
        p_keep = np.where(np.abs(rate) > MANOEUVRE_RATE, p_keep * keep_in_turns, p_keep)
    keep = detect_draw < p_keep
    r = np.sqrt(state.x**2 + state.z**2 + h**2) + noise_r
    psi = np.arctan2(state.z, state.x) + noise_psi
    plots = Plots.from_arrays(t[keep], r[keep], psi[keep], h[keep] if with_altitude else None)
    truth_at = StateSeries(t[keep], state.x[keep], state.z[keep], state.vx[keep], state.vz[keep])
    return SimulatedTrack(plots, truth_at, h[keep], rate[keep], profile, seed, truth.name)
