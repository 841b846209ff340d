"""Growing-memory alpha-beta and alpha-beta-gamma filters with a memory cap (seed 004, spec
filters.md section 4), per axis on the plot points.

Until the cap the gains are those of the least-squares polynomial fit (line, or parabola for
``order=3``) to all past plots at their actual times, computed as a Kalman filter with no
process noise and unit measurement noise from an exact first fit (2 or 3 plots). For a constant
step ``T`` they equal the closed forms ``alpha_k = 2(2k+1)/((k+1)(k+2))``,
``beta_k = 6/((k+1)(k+2))`` (and ``g, h, kappa`` for ``order=3``, acceleration gain
``2 kappa / T^2``). From plot ``k_max`` on the gains stay at the closed-form values for
``k_max`` (velocity gain ``beta / T`` with the actual step, at least half the median step)
so the filter keeps following manoeuvres. Both axes use the same scalar gains (unweighted
fit, as the paper). A gap longer than ``k_max - 1/2`` median steps starts the memory afresh
(:func:`memory_starts`).

The covariance reported is that of these gains under the straight-line model with the plots'
converted measurement covariances (Joseph form, no process noise): honest on straight legs,
optimistic in turns.

Several sensors (or a geodetic frame: :class:`SensorPlots`): the same least-squares polynomial,
now weighted, as the paper's unweighted fit would let a coarse fast sensor outweigh an accurate
slow one. At each plot, the generalised least-squares line (parabola) in both plane axes through
each sensor's plots of its last ``(k_max - 1/2) T_j`` seconds (``T_j`` its median update period:
its last ``k_max`` plots, so a fast sensor's memory stays as short as alone and a gap leaves no
stale plots; every past plot for ``k_max=None``), each plot weighted by the inverse of its full
2x2 covariance::

    N = sum_i (a_i a_i^T) (x) R_i^-1,   b = sum_i a_i (x) R_i^-1 y_i,
    s_k = N^-1 b,   cov(s_k) = N^-1,   a_i = (1, tau_i, tau_i^2 / 2)

with ``tau_i = t_i - t_k``: growing memory until the window is full, then a finite memory of
the same length (instead of the frozen gains, which have no meaning when the plots' weights
differ). A window with fewer distinct times than the polynomial's coefficients gets a weak
prior (velocity 0 +- ``SIGMA_V0``, acceleration 0 +- 10 m/s^2). All windows are solved at once
(batched normal equations); the covariance is exact for the polynomial model.
"""

from __future__ import annotations

import numpy as np

from ..inputs import FloatArray
from ..results import FilterEstimate
from .common import SIGMA_V0, cartesian_output, estimate
from .measurements import PolarPlots, SensorPlots

K_MAX = 4
"""Default memory cap (plots): best of {3, 4, 6, 8, 12, 20} on the dev trajectories for the
seed001 and ssr profiles (3 is better at 19 s scans, 6+ lags in turns)."""


def closed_form_gains(k: int | FloatArray, order: int = 2) -> FloatArray:
    """Growing-memory gains for a constant step: ``(alpha, beta)`` or ``(g, h, kappa)``."""
    k = np.asarray(k, dtype=float)
    if order == 2:
        den = (k + 1) * (k + 2)
        return np.stack([2 * (2 * k + 1) / den, 6 / den], -1)
    den = (k + 1) * (k + 2) * (k + 3)
    return np.stack([3 * (3 * k**2 + 3 * k + 2) / den, 18 * (2 * k + 1) / den, 30 / den], -1)


def transition(T: float, order: int) -> FloatArray:
    """Per-axis polynomial transition ``[p, v(, a)]``."""
    if order == 2:
        return np.array([[1.0, T], [0.0, 1.0]])
    return np.array([[1.0, T, T * T / 2], [0.0, 1.0, T], [0.0, 0.0, 1.0]])


def memory_starts(t: FloatArray, k_max: int | None = K_MAX) -> np.ndarray:
    """``(n,)`` True where the filter's memory starts afresh: at the first plot, and (capped
    memory) at a plot more than ``(k_max - 1/2)`` median steps after the one before, i.e. when
    none of the last ``k_max`` plots' span is left (the window of the several-sensor filter,
    :func:`memory_spans`). With the frozen gains a gap was extrapolated at the old velocity and
    only ``alpha`` of the miss corrected: after a 900-s hold the seed track's state stayed 79 km
    from its plot."""
    starts = np.zeros(t.shape[0], dtype=bool)
    if t.shape[0]:
        starts[0] = True
    if k_max is not None and t.shape[0] > 1:
        T = np.diff(t)
        starts[1:] = T > (k_max - 0.5) * float(np.median(T))
    return starts


def gain_sequence(t: FloatArray, order: int = 2, k_max: int | None = K_MAX) -> FloatArray:
    """``(n, order)`` per-axis gains ``K_k`` such that ``x_k = x_pred + K_k (y_k - p_pred)``.

    Counting ``j`` from the last start of the memory (:func:`memory_starts`): ``K = e_0`` at a
    start; the next fits the line through two plots; for ``order=3`` the one after fits the
    parabola through three; then the recursive least-squares (unit-noise Kalman) gains until
    ``j = k_max``, the capped closed-form gains after, with the actual step ``T`` but at least
    half the median step: a plot 19 us after the one before (a split plot) made the velocity
    gain ``beta / T`` turn its few hundred metres of noise into 4e6 m/s.
    """
    n, m = t.shape[0], order
    K = np.zeros((n, m))
    if n == 0:
        return K
    starts = memory_starts(t, k_max)
    step = float(np.median(np.diff(t))) if n > 1 else 0.0
    M: FloatArray | None = None  # unit-noise covariance of the current fit
    j = 0
    for k in range(n):
        j = 0 if starts[k] else j + 1
        if j == 0:
            K[k, 0] = 1.0
            continue
        T = t[k] - t[k - 1]
        if k_max is not None and j >= k_max:
            g = closed_form_gains(k_max, order)
            Tg = max(T, 0.5 * step)  # the gains' step: a split plot's noise is not a velocity
            K[k] = g / np.array([1.0, Tg, Tg * Tg / 2][:m])
            continue
        if j == 1:
            K[k, 0], K[k, 1] = 1.0, 1.0 / T
            if m == 2:
                M = np.linalg.inv(np.array([[1.0, -T], [1.0, 0.0]]).T
                                  @ np.array([[1.0, -T], [1.0, 0.0]]))
            continue
        if m == 3 and j == 2:
            tau = t[k - 2:k + 1] - t[k]
            A = np.column_stack([np.ones(3), tau, tau**2 / 2])
            # state after the update = A^-1 y; with x_pred built from the line through plots 0, 1,
            # the gain is the column of A^-1 acting on the new plot's residual
            Ainv = np.linalg.inv(A)
            K[k] = Ainv[:, 2]
            M = Ainv @ Ainv.T
            continue
        assert M is not None
        F = transition(T, m)
        Mp = F @ M @ F.T
        K[k] = Mp[:, 0] / (Mp[0, 0] + 1.0)
        M = Mp - np.outer(K[k], Mp[0])
    return K


def memory_spans(meas: SensorPlots, k_max: int | None) -> FloatArray:
    """Per sensor ``(k_max - 1/2)`` times its median update period (s): its last ``k_max``
    plots; a sensor with one plot takes the longest span of the others; infinite for
    ``k_max=None``."""
    spans = np.full(meas.n_sensors, np.inf)
    if k_max is None:
        return spans
    for j in range(meas.n_sensors):
        tj = meas.t[meas.sensor == j]
        if tj.size > 1:
            spans[j] = (k_max - 0.5) * float(np.median(np.diff(tj)))
    finite = np.isfinite(spans)
    if finite.any():
        spans[~finite] = spans[finite].max()
    return spans


def window_fits(meas: SensorPlots, order: int, spans: FloatArray, chunk: int = 200_000
                ) -> tuple[FloatArray, FloatArray]:
    """Weighted least-squares polynomials (module docstring) at every plot ``k`` through the
    plots ``i`` of sensor ``j`` with ``t_k - spans[j] < t_i <= t_k`` (plots at ``t_k`` all
    included): states ``(n, 2 order)`` ordered ``(x, z, vx, vz, ax, az)`` and covariances."""
    t, n, m = meas.t, len(meas), order
    y = meas.points()
    Ri = np.linalg.inv(meas.converted_cov())
    end = meas.same_instant()
    start = np.searchsorted(t, t - np.max(spans), side="right")
    W = int(np.max(end - start + 1))
    fact = np.array([1.0, 1.0, 2.0])[:m]
    prior = np.repeat(np.array([0.0, 1 / SIGMA_V0**2, 1 / 100.0])[:m], 2)
    states, cov = np.empty((n, 2 * m)), np.empty((n, 2 * m, 2 * m))
    step = max(1, chunk // W)
    cols = np.arange(W)
    for lo in range(0, n, step):
        k = np.arange(lo, min(n, lo + step))
        idx = np.minimum(start[k, None] + cols, n - 1)
        tau = t[idx] - t[k, None]
        valid = (start[k, None] + cols <= end[k, None]) & (tau > -spans[meas.sensor[idx]])
        tau = np.where(valid, tau, 0.0)
        # distinct times among the valid plots (fewer than m: a weak prior makes N regular)
        last = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
        prev = np.concatenate([np.full((k.size, 1), -1), last[:, :-1]], axis=1)
        prev_t = np.take_along_axis(tau, np.maximum(prev, 0), axis=1)
        weak = np.sum(valid & ((prev < 0) | (tau != prev_t)), axis=1) < m
        scale = np.maximum(np.max(np.abs(tau), axis=1), 1.0)  # conditioning: tau / scale
        A = (tau / scale[:, None])[..., None] ** np.arange(m) / fact * valid[..., None]
        N = np.einsum("kwi,kwj,kwab->kiajb", A, A, Ri[idx]).reshape(-1, 2 * m, 2 * m)
        b = np.einsum("kwi,kwab,kwb->kia", A, Ri[idx], y[idx]).reshape(-1, 2 * m)
        # coefficients c = D s with D = diag(scale^j): the prior on s becomes D^-1 prior D^-1
        d = np.repeat(scale[:, None] ** np.arange(m), 2, axis=1)  # (nk, 2m)
        N[weak] += (prior / d[weak] ** 2)[:, :, None] * np.eye(2 * m)
        C = np.linalg.inv(N)
        states[k] = np.einsum("kij,kj->ki", C, b) / d
        cov[k] = C / (d[:, :, None] * d[:, None, :])
    return states, cov


def run_alpha_beta(meas: PolarPlots | SensorPlots, order: int = 2, k_max: int | None = K_MAX
                   ) -> FilterEstimate:
    if order not in (2, 3):
        raise ValueError(f"order must be 2 (alpha-beta) or 3 (alpha-beta-gamma), not {order!r}")
    if k_max is not None and k_max < order:
        raise ValueError(f"k_max must be at least {order}, not {k_max!r}")
    if isinstance(meas, SensorPlots):
        spans = memory_spans(meas, k_max)
        s, C = window_fits(meas, order, spans)
        return estimate("alpha_beta", meas.t, s[:, :4], C[:, :4, :4], order=float(order),
                        memory_s=float(np.max(spans)))
    t = meas.t
    n, m = t.shape[0], order
    y = meas.points()
    R = meas.converted_cov()
    K = gain_sequence(t, order, k_max)
    starts = memory_starts(t, k_max)
    x = np.zeros((n, 2, m))  # axis, derivative
    P = np.zeros((n, 2 * m, 2 * m))  # blocks [x-axis, z-axis]
    H = np.zeros((2, 2 * m))
    H[0, 0] = H[1, m] = 1.0
    eye = np.eye(2 * m)
    for k in range(n):
        if starts[k]:  # the plot, the derivatives unknown (0 with the prior's sigmas)
            x[k, :, 0] = y[k]
            P[k][np.ix_([0, m], [0, m])] = R[k]
            for j in range(1, m):
                P[k, j, j] = P[k, m + j, m + j] = SIGMA_V0**2 if j == 1 else 100.0
            continue
        F = transition(t[k] - t[k - 1], m)
        xp = x[k - 1] @ F.T
        x[k] = xp + K[k][None, :] * (y[k] - xp[:, 0])[:, None]
        F2 = np.kron(np.eye(2), F)
        K2 = np.kron(np.eye(2), K[k][:, None])
        IKH = eye - K2 @ H
        Pk = IKH @ (F2 @ P[k - 1] @ F2.T) @ IKH.T + K2 @ R[k] @ K2.T
        P[k] = 0.5 * (Pk + Pk.T)
    s, C = cartesian_output(x.reshape(n, 2 * m), P, m)
    return estimate("alpha_beta", t, s, C, gains=K, order=float(order))
