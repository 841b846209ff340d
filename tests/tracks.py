"""Simulated tracks with piecewise-constant controls (truth from the closed-form motion model)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from solver.estimation.measurements import PolarPlots
from solver.inputs import FloatArray, Plots, Radar
from solver.motion import propagate

# (duration s, u m/s^2, w m/s^2): straight legs, a right turn of ~220 deg, speed changes,
# a left turn of ~180 deg; 5057 s in all like the seed's real track. Control switches are at
# least 40 s apart and turns never abut speed changes (see CLOSE_SWITCH_LEGS for that case).
SEED_LIKE_LEGS: list[tuple[float, float, float]] = [
    (1100.0, 0.0, 0.0),
    (60.0, 0.0, -1.0),       # 220 -> 160 m/s
    (400.0, 0.0, 0.0),
    (160 * np.deg2rad(220) / 6.0, 6.0, 0.0),  # 220 deg right at 6 m/s^2 and 160 m/s
    (700.0, 0.0, 0.0),
    (50.0, 0.0, 1.5),        # 160 -> 235 m/s
    (900.0, 0.0, 0.0),
    (235 * np.pi / 5.0, -5.0, 0.0),  # 180 deg left at 5 m/s^2
    (300.0, 0.0, 0.0),
    (40.0, 0.0, -2.0),       # 235 -> 155 m/s
]
SEED_LIKE_LEGS.append((5057.0 - sum(d for d, _, _ in SEED_LIKE_LEGS), 0.0, 0.0))
CLOSE_SWITCH_LEGS: list[tuple[float, float, float]] = [
    (600.0, 0.0, 0.0),
    (235 * np.pi / 5.0, -5.0, 0.0),  # 180 deg left, then at once
    (40.0, 0.0, -2.0),               # a 40-s deceleration: two switches inside one window
    (600.0, 0.0, 0.0),
]
SEED_LIKE_START = (-60_000.0, -150_000.0, np.deg2rad(80.0), 220.0)  # x, z, heading, speed

SEED_RADAR = Radar(range_error_m=500.0, azimuth_error_rad=np.deg2rad(1.5))
"""The seed's a priori errors (eps_r = 500 m, eps_psi = 1.5 deg), no altitude correction."""
SEED_RADAR_ALT = Radar(range_error_m=500.0, azimuth_error_rad=np.deg2rad(1.5),
                       max_altitude_m=15_000.0, max_elevation_rad=np.deg2rad(60.0))
"""The seed's radar with its unknown-altitude correction (h_max = 15 km, alpha_max = 60 deg)."""


@dataclass
class Track:
    """Truth at every kept plot time, the legs' switch times, and the plots."""

    t: FloatArray
    x: FloatArray
    z: FloatArray
    phi: FloatArray
    v: FloatArray
    switch_times: FloatArray
    plots: Plots


def truth(legs, start, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """State ``(x, z, phi, v)`` at times ``t`` of the piecewise-constant-control flight."""
    t = np.asarray(t, dtype=float)
    starts = [np.array(start, dtype=float)]
    t0 = [0.0]
    for dur, u, w in legs:
        s = starts[-1]
        starts.append(np.array(propagate(*s, u, w, dur), dtype=float))
        t0.append(t0[-1] + dur)
    k = np.clip(np.searchsorted(t0, t, side="right") - 1, 0, len(legs) - 1)
    s = np.array(starts)[k]
    u = np.array([leg[1] for leg in legs])[k]
    w = np.array([leg[2] for leg in legs])[k]
    return propagate(s[:, 0], s[:, 1], s[:, 2], s[:, 3], u, w, t - np.array(t0)[k])


def make_track(legs=None, start=SEED_LIKE_START, scan_s: float = 19.0,
               sigma_r: float = 0.0, sigma_psi: float = 0.0, drop_in_turns: bool = True,
               seed: int = 0, altitude_m: float = 0.0) -> Track:
    """Plots every ``scan_s`` over the legs; in turns (|u| > 0) every second plot is missing when
    ``drop_in_turns``; slant ranges at the given constant altitude; Gaussian range/azimuth noise
    with the given sigmas."""
    legs = SEED_LIKE_LEGS if legs is None else legs
    total = sum(d for d, _, _ in legs)
    t = np.arange(0.0, total + 1e-9, scan_s)
    edges = np.cumsum([0.0] + [d for d, _, _ in legs])
    if drop_in_turns:
        k = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(legs) - 1)
        turning = np.array([legs[i][1] != 0 for i in k])
        drop = turning & (np.cumsum(turning) % 2 == 0)
        t = t[~drop]
    x, z, phi, v = truth(legs, start, t)
    rng = np.random.default_rng(seed)
    r = np.sqrt(x * x + z * z + altitude_m**2) + sigma_r * rng.standard_normal(t.size)
    psi = np.arctan2(z, x) + sigma_psi * rng.standard_normal(t.size)
    plots = Plots.from_arrays(t, r, psi)
    return Track(t, x, z, phi, v, edges[1:-1], plots)


def held(meas: PolarPlots, after: int = 30, gap_s: float = 600.0) -> PolarPlots:
    """``meas`` with the plots after ``after`` ``gap_s`` later (the aircraft held): the first
    plot after the gap is kilometres from every model's prediction, so the EKF update
    iterates (``measurements.LINEARISATION_TOLERANCE``)."""
    t = meas.t.copy()
    t[after + 1:] += gap_s
    return replace(meas, t=t)
