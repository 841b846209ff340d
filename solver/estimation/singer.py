"""Singer filter (spec filters.md section 1): per axis ``[p, p', p'']`` with
``p''' = -alpha p'' + w``, exact transition and Van Loan process noise.

``frame="cartesian"`` (default): north and east axes in one 6-state filter updated from each polar
plot (converted measurement or EKF). ``frame="polar"``: ground range and azimuth filtered as
separate channels, as in seed 001's comparison (azimuth manoeuvre sigma ``sigma_m / d``); it
needs the single radar at the plane's origin (with several sensors or a geodetic frame there is
no common polar origin: ``ValueError``).

Defaults: ``alpha = 1/20 s^-1`` (manoeuvre time constant 20 s: Singer's "lazy turn" is 60 s,
evasive 10-20 s) and ``sigma_m = 1 m/s^2``: the best pair of the sweep alpha in {1/60, 1/20,
1/10}, sigma_m in {0.5, 1, 2, 4} on the dev trajectories for all three radar profiles
(``python -m benchmarks.filters_seed001 --sweep``).
"""

from __future__ import annotations

import numpy as np

from ..results import FilterEstimate
from .common import (
    SIGMA_V0,
    cartesian_output,
    cartesian_prior,
    channels_to_cartesian,
    estimate,
    polar_channels,
)
from .gating import GATE_SIGMA
from .kalman import filter_track
from .measurements import PolarPlots, SensorPlots
from .models import singer, two_axes

ALPHA = 1 / 20
SIGMA_M = 1.0


def run_singer(meas: PolarPlots | SensorPlots, alpha: float = ALPHA, sigma_m: float = SIGMA_M,
               measurement: str = "ekf", frame: str = "cartesian",
               gate: float | None = GATE_SIGMA) -> FilterEstimate:
    """``gate``: plots further than this many sigmas from the prediction are not used
    (:mod:`.gating`); None uses every plot."""
    dt = np.diff(meas.t)
    if frame == "cartesian":
        Phi, Q = singer(dt, alpha, sigma_m)
        x0, P0 = cartesian_prior(meas, 3, (sigma_m**2,))
        xf, Pf, _, _, nis, gated = filter_track(x0, P0, two_axes(Phi), two_axes(Q), meas,
                                                (0, 3), measurement, gate)
        s, P = cartesian_output(xf, Pf, 3)
        return estimate("singer", meas.t, s, P, nis=nis, gated=gated)
    if frame == "polar":
        if isinstance(meas, SensorPlots):
            raise ValueError("frame='polar' filters range and azimuth of one radar at the "
                             "plane's origin; with several sensors or a geodetic frame use "
                             "frame='cartesian'")
        d_ref = float(np.median(meas.d))
        Phi_r, Q_r = singer(dt, alpha, sigma_m)
        Phi = np.stack([Phi_r, Phi_r], 1)
        Q = np.stack([Q_r, Q_r / d_ref**2], 1)
        prior = np.array([[0.0, SIGMA_V0**2, sigma_m**2],
                          [0.0, (SIGMA_V0 / d_ref) ** 2, (sigma_m / d_ref) ** 2]])
        xf, Pf, _, _, gated = polar_channels(meas, Phi, Q, prior, gate=gate)
        s, P = channels_to_cartesian(xf, Pf, 0, 1)
        return estimate("singer", meas.t, s, P, frame="polar", gated=gated.any(axis=1))
    raise ValueError(f"unknown frame {frame!r} (use 'cartesian' or 'polar')")
