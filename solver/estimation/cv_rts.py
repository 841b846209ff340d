"""Constant-velocity Kalman filter (white-noise acceleration, spectral density ``q``) on the polar
plots, and its Rauch-Tung-Striebel smoother (spec filters.md section 5). The smoothed states are
returned; the filtered ones are in ``info["filtered"]``. :func:`smoothed_means` gives the same
smoother's means for linear position measurements in one banded solve (the refinement's start).

Default ``q = 30 m^2/s^3`` (acceleration RMS about ``sqrt(q / T)`` = 1.7 m/s^2 over a 10 s scan):
the best of the sweep q in {0.1 .. 100} on the dev trajectories (manoeuvring calibration and
survey flights) for the seed000 and seed001 profiles; the ssr profile prefers 10 (1 % better).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solveh_banded

from ..inputs import FloatArray
from ..results import FilterEstimate
from .common import cartesian_output, cartesian_prior, estimate
from .gating import GATE_SIGMA
from .kalman import filter_track, rts_smoother
from .measurements import PolarPlots
from .models import cv, two_axes

Q_CV = 30.0


def run_cv_rts(meas: PolarPlots, q: float = Q_CV, measurement: str = "ekf",
               smooth: bool = True, gate: float | None = GATE_SIGMA) -> FilterEstimate:
    """``gate``: plots further than this many sigmas from the prediction are not used
    (:mod:`.gating`; the smoother then bridges them); None uses every plot."""
    Phi, Q = cv(np.diff(meas.t), q)
    Phi, Q = two_axes(Phi), two_axes(Q)
    x0, P0 = cartesian_prior(meas, 2)
    xf, Pf, xp, Pp, nis, gated = filter_track(x0, P0, Phi, Q, meas, (0, 2), measurement, gate)
    sf, Cf = cartesian_output(xf, Pf, 2)
    if not smooth:
        return estimate("cv_rts", meas.t, sf, Cf, nis=nis, gated=gated)
    xs, Ps = rts_smoother(xf, Pf, xp, Pp, Phi)
    s, C = cartesian_output(xs, Ps, 2)
    return estimate("cv_rts", meas.t, s, C, filtered=sf, nis=nis, gated=gated)


def smoothed_means(t: FloatArray, centre: FloatArray, info: FloatArray, q: float = Q_CV
                   ) -> FloatArray:
    """Means ``(n, 4)`` ``(x, z, vx, vz)`` of the constant-velocity smoother for linear position
    measurements ``centre (n, 2)`` with information matrices ``info (n, 2, 2)`` (``R^-1``) and a
    flat prior: the minimiser of

        sum_k (p_k - c_k)^T info_k (p_k - c_k) + sum_k e_k^T Q_k^-1 e_k,  e_k = s_{k+1} - Phi_k s_k,

    i.e. the RTS smoother's means, as one banded solve (block-tridiagonal normal equations,
    LAPACK ``pbsv`` through :func:`scipy.linalg.solveh_banded`) instead of a Python loop over
    plots: for an initial guess, where the covariances are not needed. Per axis
    ``Q^-1 = [[12/T^3, -6/T^2], [-6/T^2, 4/T]] / q``. Needs ``n >= 2`` and increasing ``t``.
    """
    n = t.size
    T = np.diff(t)
    Phi = two_axes(cv(T, q)[0])
    qi = np.stack([np.stack([12 / T**3, -6 / T**2], -1), np.stack([-6 / T**2, 4 / T], -1)], -2)
    Qi = two_axes(qi / q)
    PtQi = Phi.transpose(0, 2, 1) @ Qi
    D = np.zeros((n, 4, 4))  # diagonal blocks; state per plot (x, vx, z, vz)
    D[:, 0::2, 0::2] = info
    D[:-1] += PtQi @ Phi
    D[1:] += Qi
    b = np.zeros((n, 4))
    b[:, 0::2] = np.einsum("kij,kj->ki", info, centre)
    ab = np.zeros((8, 4 * n))  # upper banded storage: ab[7 + i - j, j] = H[i, j]
    for i in range(4):
        for j in range(i, 4):
            ab[7 + i - j, j::4] = D[:, i, j]
        for j in range(4):  # block (k, k+1) = -Phi_k^T Q_k^-1, at offset 4 + j - i
            ab[3 + i - j, 4 + j::4] = -PtQi[:, i, j]
    s = solveh_banded(ab, b.ravel()).reshape(n, 4)
    return s[:, [0, 2, 1, 3]]
