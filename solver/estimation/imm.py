"""Interacting multiple models (Blom and Bar-Shalom 1988): constant velocity + coordinated turn
with unknown turn rate, state ``(x, z, vx, vz, omega)`` in both models (the CV model holds
``omega`` at 0), EKF for the turn model, polar plots as converted measurements or EKF updates.

Model switching is a continuous-time Markov chain with mean sojourn times ``tau_cv``, ``tau_ct``,
so ``Pi(T)`` follows the actual step. Outputs the combined estimate (moment-matched) and, in
``info``, the model probabilities ``(n, 2)`` (CV, CT) and the turn rate.

Defaults: CV ``q_cv = 0.5 m^2/s^3``; CT ``q_ct = 30 m^2/s^3`` and turn-rate random walk
``q_omega = 1e-5 rad^2/s^3``: best of the sweep q_cv in {0.5, 3, 10}, q_ct in {3, 10, 30},
q_omega in {1e-6, 1e-5, 1e-4} on the dev trajectories, all three profiles; mean sojourn times
``tau_cv = 120 s``, ``tau_ct = 40 s`` (a civil turn lasts 30-60 s); ``|omega| <= 6 deg/s``.
"""

from __future__ import annotations

import numpy as np

from ..inputs import FloatArray
from ..results import FilterEstimate
from .common import SIGMA_V0, estimate
from .kalman import position_update
from .measurements import PolarPlots
from .models import ct_predict

Q_CV, Q_CT, Q_OMEGA, TAU_CV, TAU_CT = 0.5, 30.0, 1e-5, 120.0, 40.0
SIGMA_OMEGA0 = np.deg2rad(3.0)
OMEGA_MAX = np.deg2rad(6.0)
"""Turn-rate bound (rad/s): twice the standard rate turn. Without it a long scan lets the turn
model explain cross-range noise by spinning (aliasing ``omega T`` beyond pi): seen at 19 s scans."""


def switching_matrix(T: float, tau_cv: float, tau_ct: float) -> FloatArray:
    """``Pi(T) = expm(G T)`` of the two-state chain with leaving rates ``1/tau``."""
    a, b = 1 / tau_cv, 1 / tau_ct
    s = a + b
    e = np.exp(-s * T)
    return np.array([[(b + a * e) / s, a * (1 - e) / s], [b * (1 - e) / s, (a + b * e) / s]])


def _cv_noise(T: float, q: float) -> FloatArray:
    Q = np.zeros((5, 5))
    for p, v in ((0, 2), (1, 3)):
        Q[p, p], Q[p, v], Q[v, p], Q[v, v] = q * T**3 / 3, q * T**2 / 2, q * T**2 / 2, q * T
    return Q


def run_imm(meas: PolarPlots, q_cv: float = Q_CV, q_ct: float = Q_CT, q_omega: float = Q_OMEGA,
            tau_cv: float = TAU_CV, tau_ct: float = TAU_CT, omega_max: float = OMEGA_MAX,
            measurement: str = "ekf") -> FilterEstimate:
    n = len(meas)
    t = meas.t
    x0 = np.zeros(5)
    x0[:2] = meas.points()[0]
    P0 = np.zeros((5, 5))
    P0[:2, :2] = meas.converted_cov()[0]
    P0[2, 2] = P0[3, 3] = SIGMA_V0**2
    P0[4, 4] = SIGMA_OMEGA0**2
    xs = np.stack([x0, x0])
    Ps = np.stack([P0, P0])
    P0[4, 4] = 1e-12  # the CV model's omega is 0
    Ps[0] = P0
    xs[0, 4] = 0.0
    mu = np.array([tau_cv, tau_ct]) / (tau_cv + tau_ct)
    out_x, out_P = np.empty((n, 4)), np.empty((n, 4, 4))
    probs, omega = np.empty((n, 2)), np.zeros(n)
    F_cv = np.eye(5)
    F_cv[4, 4] = 0.0

    def combine(k: int) -> None:
        x = mu @ xs
        d = xs - x
        P = np.einsum("i,ijk->jk", mu, Ps + d[:, :, None] * d[:, None, :])
        out_x[k], out_P[k] = x[:4], P[:4, :4]
        probs[k], omega[k] = mu, x[4]

    combine(0)
    for k in range(1, n):
        T = t[k] - t[k - 1]
        Pi = switching_matrix(T, tau_cv, tau_ct)
        c = mu @ Pi  # predicted model probabilities
        w = Pi * mu[:, None] / c[None, :]  # w[i, j] = P(was i | now j)
        xm = w.T @ xs
        Pm = np.empty_like(Ps)
        for j in range(2):
            d = xs - xm[j]
            Pm[j] = np.einsum("i,ijk->jk", w[:, j], Ps + d[:, :, None] * d[:, None, :])
        loglik = np.empty(2)
        F_cv[0, 2] = F_cv[1, 3] = T
        Q_cv = _cv_noise(T, q_cv)
        Q_cv[4, 4] = 1e-12
        xp, Pp = F_cv @ xm[0], F_cv @ Pm[0] @ F_cv.T + Q_cv
        xs[0], Ps[0], nis, logdet = position_update(xp, Pp, meas, k, (0, 1), measurement)
        loglik[0] = -0.5 * (nis + logdet)
        fx, J = ct_predict(xm[1], T)
        Q_ct = _cv_noise(T, q_ct)
        Q_ct[4, 4] = q_omega * T
        xs[1], Ps[1], nis, logdet = position_update(fx, J @ Pm[1] @ J.T + Q_ct, meas, k, (0, 1),
                                                    measurement)
        xs[1, 4] = np.clip(xs[1, 4], -omega_max, omega_max)  # projection on the bound
        loglik[1] = -0.5 * (nis + logdet)
        lik = np.exp(loglik - loglik.max())
        mu = c * lik
        mu = np.maximum(mu / mu.sum(), 1e-12)
        mu /= mu.sum()
        combine(k)
    return estimate("imm", t, out_x, out_P, model_probabilities=probs, turn_rate=omega)
