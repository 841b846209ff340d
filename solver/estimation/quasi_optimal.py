"""Quasi-optimal control-law filter of seed 001 (Kostoglotov, Penkov, Lazarenko 2023), per radar
coordinate ``s`` (ground range, azimuth):

    q'' = -sqrt(Lambda) q' + Lambda r,    r' = -alpha r + w,    z = q + v,

state ``[q, q', r]``, ``w`` white with density ``2 alpha sigma_M^2`` (``r`` stationary with RMS
``sigma_M``: metres on the range channel, ``sigma_M / d`` radians on the azimuth channel, ``d`` the
median ground range). Discretisation ``"exact"`` (matrix exponential, Van Loan) or ``"taylor"``
(the paper's ``Phi = I + F T + F^2 T^2/2``, ``Q = Gamma (2 alpha sigma_M^2 / T) Gamma^T``).

Several sensors (or a geodetic frame: :class:`SensorPlots`): the same model per plane axis
(``x`` north, ``z`` east) on the plots' plane positions, each with its marginal variance, and
``sigma_M`` in metres on both axes. There is no common polar origin then, and in plane axes a
straight flight has no acceleration, which suits the model better than range and azimuth.
``info`` then names the channels ``x`` and ``z`` (``lambda_x``, ``discrepancy_z``, ...).

``lam="auto"`` picks ``Lambda`` per channel by the discrepancy principle (paper eq. 5): among
``LAMBDA_GRID`` the smallest (most smoothing) value whose discrepancy functional ``J`` does not
exceed 1, the known (normalised) measurement variance, interpolated in ``log Lambda``; all grid
values run in one batched pass. ``criterion="residual"`` (the paper's literal functional):
``J = mean((z_k - q_k)^2 / sigma_k^2)`` with the filtered ``q_k``; it over-smooths (its expectation
under a correct model is ``1 - P_qq / sigma^2 < 1``; on the dev benchmark it picks Lambda ~ 3e-4
and is 10 % worse). ``criterion="innovation"``: ``J = mean(nu_k^2 / S_k)``, whose expectation
under a correct model is exactly 1; it lands on the benchmark optimum.
"""

from __future__ import annotations

import numpy as np

from ..inputs import FloatArray
from ..results import FilterEstimate
from .common import (
    SIGMA_V0,
    axes_to_cartesian,
    axis_channels,
    channels_to_cartesian,
    estimate,
    polar_channels,
)
from .gating import GATE_SIGMA
from .measurements import PolarPlots, SensorPlots
from .models import quasi_optimal

LAMBDA = 1e-3
"""Default ``Lambda`` (1/s^2): natural period ``2 pi / sqrt(Lambda)`` about 200 s."""
ALPHA = 0.01
"""Default ``alpha`` (1/s): residual correlation time 100 s."""
SIGMA_M = 2000.0
"""Default RMS of the residual drive ``r`` on the range channel (m). In steady flight the model
holds a rate ``q' = sqrt(Lambda) r``, so ``sigma_M sqrt(Lambda)`` (63 m/s) is the RMS coordinate
rate it expects. The three defaults are the best of the sweep Lambda in {3e-4 .. 0.1}, alpha in
{0.003 .. 0.05}, sigma_M in {300 .. 10000} on the dev trajectories, all three profiles; the
innovation discrepancy rule (``lam="auto"``, ``criterion="innovation"``) lands on the same
Lambda (1e-3 +- 30 %) and the same accuracy, at 5-8x the cost."""
LAMBDA_GRID = np.logspace(-4, 0, 17)


def _channels(meas: PolarPlots | SensorPlots, lams: FloatArray, alpha: float, sigma_m: float,
              method: str, criterion: str = "residual", gate: float | None = GATE_SIGMA
              ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Run range and azimuth channels (plane axes x and z for :class:`SensorPlots`) for every
    ``Lambda`` in ``lams`` (batch: ranges, azimuths); returns also each channel's discrepancy
    ``J`` over the measurements it used and ``(n, 2G)`` True where a channel left one out."""
    dt = np.diff(meas.t)
    axes = isinstance(meas, SensorPlots)
    d_ref = 1.0 if axes else float(np.median(meas.d))
    G = lams.size
    Phi = np.empty((dt.size, 2 * G, 3, 3))
    Q = np.empty_like(Phi)
    for g, lam in enumerate(lams):
        Ph, Qg = quasi_optimal(dt, float(lam), alpha, sigma_m, method)
        Phi[:, g], Phi[:, G + g] = Ph, Ph
        Q[:, g], Q[:, G + g] = Qg, Qg / d_ref**2
    prior = np.array([[0.0, SIGMA_V0**2, sigma_m**2]] * G
                     + [[0.0, (SIGMA_V0 / d_ref) ** 2, (sigma_m / d_ref) ** 2]] * G)
    if axes:
        assert isinstance(meas, SensorPlots)
        xf, Pf, nus, R, gated = axis_channels(meas, Phi, Q, prior, gate=gate)
    else:
        xf, Pf, nus, R, gated = polar_channels(meas, Phi, Q, prior, gate=gate)
    used = ~gated
    if criterion == "innovation":
        e2 = nus[1:] ** 2
        used = used[1:]
    elif axes:
        pts = meas.points()
        z = np.concatenate([np.repeat(pts[:, :1], G, 1), np.repeat(pts[:, 1:], G, 1)], 1)
        e2 = (z - xf[:, :, 0]) ** 2 / R
    else:
        z = np.concatenate([np.repeat(meas.d[:, None], G, 1),
                            np.repeat(meas.psi[:, None], G, 1)], 1)
        e2 = (z - xf[:, :, 0]) ** 2 / R
    J = np.sum(np.where(used, e2, 0.0), axis=0) / np.maximum(np.sum(used, axis=0), 1)
    return xf, Pf, J, gated


def discrepancy_lambda(lams: FloatArray, J: FloatArray) -> float:
    """Smallest ``Lambda`` with ``J(Lambda) <= 1`` (log-linear interpolation on the grid)."""
    ok = np.flatnonzero(J <= 1.0)
    if ok.size == 0:
        return float(lams[-1])
    i = int(ok[0])
    if i == 0:
        return float(lams[0])
    a, b = J[i - 1], J[i]
    f = (a - 1.0) / (a - b)
    return float(np.exp(np.log(lams[i - 1]) + f * (np.log(lams[i]) - np.log(lams[i - 1]))))


def run_quasi_optimal(meas: PolarPlots | SensorPlots, lam: float | str = LAMBDA,
                      alpha: float = ALPHA, sigma_m: float = SIGMA_M, discretisation: str = "exact",
                      criterion: str = "innovation", gate: float | None = GATE_SIGMA
                      ) -> FilterEstimate:
    """``gate``: a plot further than this many sigmas from the prediction (both coordinates'
    normalised innovations together) is not used (:mod:`.gating`) nor counted in the
    discrepancy; None: all."""
    info: dict[str, FloatArray | float | str] = {"discretisation": discretisation}
    if isinstance(lam, str):
        if lam != "auto":
            raise ValueError(f"lam must be a number or 'auto', not {lam!r}")
        if len(meas) < 3:
            lams = np.array([LAMBDA, LAMBDA])
        else:
            if criterion not in ("residual", "innovation"):
                raise ValueError(f"criterion must be 'residual' or 'innovation', not {criterion!r}")
            _, _, J, _ = _channels(meas, LAMBDA_GRID, alpha, sigma_m, discretisation, criterion,
                                   gate)
            G = LAMBDA_GRID.size
            lams = np.array([discrepancy_lambda(LAMBDA_GRID, J[:G]),
                             discrepancy_lambda(LAMBDA_GRID, J[G:])])
    else:
        if not lam > 0:
            raise ValueError(f"lam must be positive, not {lam!r}")
        lams = np.array([float(lam)])
    xf, Pf, J, gated = _channels(meas, lams, alpha, sigma_m, discretisation, gate=gate)
    G = lams.size
    # range channel 0; azimuth channel: its own Lambda (index G + last) when chosen per channel
    if isinstance(meas, SensorPlots):  # channels: x and z axes
        s, P = axes_to_cartesian(xf, Pf, 0, 2 * G - 1)
    else:
        s, P = channels_to_cartesian(xf, Pf, 0, 2 * G - 1)
    a, b = ("x", "z") if isinstance(meas, SensorPlots) else ("range", "azimuth")  # channels
    info.update({f"lambda_{a}": float(lams[0]), f"lambda_{b}": float(lams[-1]),
                 f"discrepancy_{a}": float(J[0]), f"discrepancy_{b}": float(J[-1])})
    return estimate("quasi_optimal", meas.t, s, P, gated=gated[:, 0] | gated[:, 2 * G - 1],
                    **info)
