"""Pieces shared by the filters: priors built from the first plot, polar-channel filtering, and
packing the result as a :class:`~solver.results.FilterEstimate`."""

from __future__ import annotations

import numpy as np

from ..inputs import FloatArray
from ..results import FilterEstimate, StateSeries
from .gating import GATE_SIGMA
from .kalman import Gain, channel_filter
from .measurements import PolarPlots, SensorPlots, polar_state_to_cartesian

SIGMA_V0 = 300.0
"""Prior speed sigma (m/s) at the first plot: the default upper speed bound of the
reconstruction (330 m/s) rounded; the second plot then fixes the velocity."""


def cartesian_prior(meas: PolarPlots | SensorPlots, per_axis: int, extra_var: tuple[float, ...] = ()
                    ) -> tuple[FloatArray, FloatArray]:
    """Prior for blocks ``[x, vx, (ax)], [z, vz, (az)]`` at plot 0: the plot point with its
    converted covariance, zero velocity with variance ``SIGMA_V0^2``, zero higher derivatives with
    variances ``extra_var``."""
    m = per_axis
    x0 = np.zeros(2 * m)
    x0[0], x0[m] = meas.points()[0]
    P0 = np.zeros((2 * m, 2 * m))
    R0 = meas.converted_cov()[0]
    P0[np.ix_([0, m], [0, m])] = R0
    for axis in (0, m):
        P0[axis + 1, axis + 1] = SIGMA_V0**2
        for j, v in enumerate(extra_var):
            P0[axis + 2 + j, axis + 2 + j] = v
    return x0, P0


def cartesian_output(x: FloatArray, P: FloatArray, per_axis: int) -> tuple[FloatArray, FloatArray]:
    """Select ``(x, z, vx, vz)`` and their covariance from block states ``[x-axis, z-axis]``."""
    idx = [0, per_axis, 1, per_axis + 1]
    return x[:, idx], P[:, idx][:, :, idx]


def polar_channels(meas: PolarPlots, Phi: FloatArray, Q: FloatArray, prior_var: FloatArray,
                   gain: Gain | None = None, gate: float | None = GATE_SIGMA
                   ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Filter ground range and azimuth as ``B`` separate scalar channels (batch order: range
    channels then azimuth channels, ``B/2`` model variants each).

    ``Phi``, ``Q``: ``(n-1, B, m, m)``; ``prior_var (B, m)``: prior variances of the state
    derivatives (entry 0 is replaced by the measurement variance); ``gain``, ``gate``: as
    :func:`.kalman.channel_filter`. Returns the filtered ``xf (n, B, m)``, ``Pf``, the normalised
    innovations ``(n, B)``, the measurement variances ``(n, B)`` and ``(n, B)`` True where a
    channel left its measurement out (the gate).
    """
    half = prior_var.shape[0] // 2
    z = np.concatenate([np.repeat(meas.d[:, None], half, 1),
                        np.repeat(meas.psi[:, None], half, 1)], axis=1)
    R = np.concatenate([np.repeat(meas.sigma_d[:, None] ** 2, half, 1),
                        np.full((len(meas), half), meas.sigma_psi**2)], axis=1)
    return _run_channels(z, R, Phi, Q, prior_var, gain, gate)


def axis_channels(meas: SensorPlots, Phi: FloatArray, Q: FloatArray, prior_var: FloatArray,
                  gain: Gain | None = None, gate: float | None = GATE_SIGMA
                  ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`polar_channels` for several sensors: the plane axes ``x`` (north) and ``z`` (east)
    of the plot positions as ``B`` separate scalar channels (``B/2`` x-channels, then ``B/2``
    z-channels), each plot with its marginal variance ``R_xx`` or ``R_zz`` (the x-z correlation
    of a fix is not used: each channel is exact for its own axis). Same arguments and returns."""
    half = prior_var.shape[0] // 2
    pts, cov = meas.points(), meas.converted_cov()
    z = np.concatenate([np.repeat(pts[:, :1], half, 1), np.repeat(pts[:, 1:], half, 1)], axis=1)
    R = np.concatenate([np.repeat(cov[:, 0, 0, None], half, 1),
                        np.repeat(cov[:, 1, 1, None], half, 1)], axis=1)
    return _run_channels(z, R, Phi, Q, prior_var, gain, gate)


def axes_to_cartesian(xf: FloatArray, Pf: FloatArray, b_x: int, b_z: int
                      ) -> tuple[FloatArray, FloatArray]:
    """``(x, z, vx, vz)`` and covariance from x-axis channel ``b_x`` and z-axis channel ``b_z``
    (independent channels: no x-z covariance)."""
    n = xf.shape[0]
    s = np.column_stack([xf[:, b_x, 0], xf[:, b_z, 0], xf[:, b_x, 1], xf[:, b_z, 1]])
    P = np.zeros((n, 4, 4))
    ix, iz = [0, 2], [1, 3]
    P[np.ix_(np.arange(n), ix, ix)] = Pf[:, b_x, :2, :2]
    P[np.ix_(np.arange(n), iz, iz)] = Pf[:, b_z, :2, :2]
    return s, P


def channels_to_cartesian(xf: FloatArray, Pf: FloatArray, b_range: int, b_az: int
                          ) -> tuple[FloatArray, FloatArray]:
    """``(x, z, vx, vz)`` and covariance from range channel ``b_range`` and azimuth channel
    ``b_az`` (independent channels)."""
    n = xf.shape[0]
    m = np.column_stack([xf[:, b_range, 0], xf[:, b_range, 1], xf[:, b_az, 0], xf[:, b_az, 1]])
    P = np.zeros((n, 4, 4))
    P[:, :2, :2] = Pf[:, b_range, :2, :2]
    P[:, 2:, 2:] = Pf[:, b_az, :2, :2]
    return polar_state_to_cartesian(m, P)


def estimate(name: str, t: FloatArray, states: FloatArray, cov: FloatArray,
             **info: FloatArray | float | str) -> FilterEstimate:
    """Pack ``(n, 4)`` states and ``(n, 4, 4)`` covariances (symmetrised)."""
    cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))
    series = StateSeries.from_states(t, states, cov)
    return FilterEstimate(name=name, states=series, info=dict(info))


def _run_channels(z: FloatArray, R: FloatArray, Phi: FloatArray, Q: FloatArray,
                  prior_var: FloatArray, gain: Gain | None, gate: float | None
                  ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The channels' filter from the first measurement (its variance as the first state's,
    ``prior_var`` for the others)."""
    B, m = prior_var.shape
    x0 = np.zeros((B, m))
    x0[:, 0] = z[0]
    P0 = np.zeros((B, m, m))
    idx = np.arange(m)
    P0[:, idx, idx] = prior_var
    P0[:, 0, 0] = R[0]
    xf, Pf, nus, gated = channel_filter(x0, P0, Phi, Q, z, R, gain, gate)
    return xf, Pf, nus, R, gated
