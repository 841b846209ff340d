"""Constant-velocity Kalman filter (white-noise acceleration, spectral density ``q``) on the polar
plots, and its Rauch-Tung-Striebel smoother (spec filters.md section 5). The smoothed states are
returned; the filtered ones are in ``info["filtered"]``.

Default ``q = 30 m^2/s^3`` (acceleration RMS about ``sqrt(q / T)`` = 1.7 m/s^2 over a 10 s scan):
the best of the sweep q in {0.1 .. 100} on the dev trajectories (manoeuvring calibration and
survey flights) for the seed000 and seed001 profiles; the ssr profile prefers 10 (1 % better).
"""

from __future__ import annotations

import numpy as np

from ..results import FilterEstimate
from .common import cartesian_output, cartesian_prior, estimate
from .kalman import filter_track, rts_smoother
from .measurements import PolarPlots
from .models import cv, two_axes

Q_CV = 30.0


def run_cv_rts(meas: PolarPlots, q: float = Q_CV, measurement: str = "ekf",
               smooth: bool = True) -> FilterEstimate:
    Phi, Q = cv(np.diff(meas.t), q)
    Phi, Q = two_axes(Phi), two_axes(Q)
    x0, P0 = cartesian_prior(meas, 2)
    xf, Pf, xp, Pp, nis = filter_track(x0, P0, Phi, Q, meas, (0, 2), measurement)
    sf, Cf = cartesian_output(xf, Pf, 2)
    if not smooth:
        return estimate("cv_rts", meas.t, sf, Cf, nis=nis)
    xs, Ps = rts_smoother(xf, Pf, xp, Pp, Phi)
    s, C = cartesian_output(xs, Ps, 2)
    return estimate("cv_rts", meas.t, s, C, filtered=sf, nis=nis)
