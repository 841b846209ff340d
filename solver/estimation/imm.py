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
from . import imm_ct_step, imm_step
from .common import SIGMA_V0, estimate
from .gating import GATE_SIGMA
from .measurements import MEASUREMENT_MODES, PolarPlots, SensorPlots

Q_CV, Q_CT, Q_OMEGA, TAU_CV, TAU_CT = 0.5, 30.0, 1e-5, 120.0, 40.0
SIGMA_OMEGA0 = np.deg2rad(3.0)
OMEGA_MAX = np.deg2rad(6.0)
"""Turn-rate bound (rad/s): twice the standard rate turn. Without it a long scan lets the turn
model explain cross-range noise by spinning (aliasing ``omega T`` beyond pi): seen at 19 s scans."""


def prior(meas: PolarPlots | SensorPlots) -> tuple[FloatArray, FloatArray]:
    """The turn model's state at the first plot: its position and measurement covariance, an
    unknown velocity (``SIGMA_V0``) and turn rate (``SIGMA_OMEGA0``)."""
    x0 = np.zeros(5)
    x0[:2] = meas.points()[0]
    P0 = np.zeros((5, 5))
    P0[:2, :2] = meas.converted_cov()[0]
    P0[2, 2] = P0[3, 3] = SIGMA_V0**2
    P0[4, 4] = SIGMA_OMEGA0**2
    return x0, P0


def run_imm(meas: PolarPlots | SensorPlots, q_cv: float = Q_CV, q_ct: float = Q_CT,
            q_omega: float = Q_OMEGA, tau_cv: float = TAU_CV, tau_ct: float = TAU_CT,
            omega_max: float = OMEGA_MAX, measurement: str = "ekf",
            gate: float | None = GATE_SIGMA) -> FilterEstimate:
    """The filter over ``meas`` (polar plots, or several sensors' :class:`.SensorPlots`): each
    step one call of a compiled function (:mod:`.imm_ct_step`, the equations there), the
    combined estimate moment-matched over the modes at every plot. ``gate``: a plot further than
    this many sigmas from both modes' predictions is not used (:mod:`.gating`); None: all."""
    if measurement not in MEASUREMENT_MODES:
        raise ValueError(f"unknown measurement mode {measurement!r} (use 'converted' or 'ekf')")
    n = len(meas)
    t = meas.t
    x0, P0 = prior(meas)
    P_cv = P0.copy()
    P_cv[4, 4] = 1e-12  # the CV model's omega is 0
    x_cv = x0.copy()
    x_cv[4] = 0.0
    S = np.empty((n, imm_step.size(imm_ct_step.STATE)))  # row k: the state after plot k
    S[:1] = imm_step.pack(imm_ct_step.STATE, 1, x=np.stack([x_cv, x0]),
                             P=np.stack([P_cv, P0]),
                             mu=np.array([tau_cv, tau_ct]) / (tau_cv + tau_ct))
    gated = np.zeros(n, dtype=bool)
    if n > 1:
        A = imm_step.pack(imm_ct_step.STEP, n - 1, T=np.diff(t),
                          plot=imm_step.plot_rows(meas)[1:], q_cv=q_cv, q_ct=q_ct,
                          q_omega=q_omega, tau_cv=tau_cv, tau_ct=tau_ct, omega_max=omega_max,
                          lin=0.0, relin=0.0, use=1.0)
        gated = imm_step.gated_steps(imm_ct_step.step(measurement), S, A, None,
                                     imm_ct_step.STEP, imm_ct_step.STATE, imm_ct_step.N_X, gate)
    xs, Ps, mu = imm_ct_step.unpack(S)
    x = np.einsum("ni,nij->nj", mu, xs)
    d = xs - x[:, None, :]
    P = np.einsum("ni,nijk->njk", mu, Ps + d[..., :, None] * d[..., None, :])
    return estimate("imm", t, x[:, :4], P[:, :4, :4], model_probabilities=mu,
                    turn_rate=x[:, 4], gated=gated)
