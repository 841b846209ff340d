"""The causal IMM's step (:mod:`.imm`) as one compiled CasADi function.

In numpy each plot's step is some sixty calls on 5x5 arrays (mixing, two predictions, the
turn model's Jacobian, two updates), and their overhead was the filter's cost: about 3,000
plots per CPU-second, the slowest of the filters (benchmarks/results/filter_speed.md). Here one
step is one function (:func:`solver.compiled.function`: compiled when a C compiler or the
compiled-object cache is at hand) called through its buffer on numpy memory, as the IMM
smoother's steps (:mod:`.imm_step`, whose position update it shares). The numpy step it replaced
is the tests' reference (``tests/imm_reference.py``).

Step ``k`` (``T = t_k - t_{k-1}``), the equations of :func:`.imm.run_imm`: the chain's
``Pi(T)`` (:func:`.imm_smoother.switching_matrices`), ``c = Pi^T mu``,
``W_ij = Pi_ij mu_i / c_j``, the mixed moments, the CV prediction (``omega`` held at 0) and
the coordinated turn's (:func:`.models.ct_predict`, its series near ``omega T = 0``), the
position update of each (:func:`.imm_step.update_terms`), the turn rate projected on
``|omega| <= omega_max`` and ``mu_j`` proportional to ``c_j L_j``, floored at ``1e-12``.
"""

from __future__ import annotations

from functools import cache

import casadi as ca
import numpy as np

from .. import compiled
from .imm_step import _blocks, _flat, _mat, size, update_terms
from .models import TURN_SERIES_WT

N_MODES = 2
"""CV, coordinated turn with unknown rate."""
N_X = 5
"""``(x, z, vx, vz, omega)``."""
MU_FLOOR = 1e-12
"""A mode's probability never falls below this (neither model is ever ruled out)."""

STATE = _blocks(x=N_MODES * N_X, P=N_MODES * N_X * N_X, mu=N_MODES)
"""The filter's state after a plot: each mode's mean and covariance, the probabilities."""
STEP = _blocks(T=1, plot=11, q_cv=1, q_ct=1, q_omega=1, tau_cv=1, tau_ct=1, omega_max=1,
              lin=N_MODES * 2, relin=N_MODES, use=1)
"""A step's inputs: the time step, the plot (:func:`.imm_step.plot_rows`), the settings, where
each mode's EKF update is linearised (:func:`.imm_step.update_terms`; ``relin`` 0: at the
prediction), ``use`` 0 where the validation gate leaves the plot out (:mod:`.gating`)."""


def _cv_noise(T: ca.SX, q: ca.SX) -> ca.SX:
    """White-acceleration ``Q`` of :func:`.models.cv` per axis (5x5, the ``omega`` row zero)."""
    Q = ca.SX.zeros(N_X, N_X)
    for p, v in ((0, 2), (1, 3)):
        Q[p, p], Q[p, v], Q[v, p], Q[v, v] = q * T**3 / 3, q * T**2 / 2, q * T**2 / 2, q * T
    return Q


def _turn(x: ca.SX, T: ca.SX) -> tuple[ca.SX, ca.SX]:
    """:func:`.models.ct_predict`: ``f(x)`` and its Jacobian."""
    px, pz, vx, vz, w = (x[i] for i in range(N_X))
    wT = w * T
    small = ca.fabs(wT) < TURN_SERIES_WT
    safe = ca.if_else(small, 1.0, w)  # the exact terms are not evaluated at w = 0
    sn, cs = ca.sin(wT), ca.cos(wT)
    s = ca.if_else(small, T * (1 - wT**2 / 6), sn / safe)
    c = ca.if_else(small, T * (wT / 2 - wT**3 / 24), (1 - cs) / safe)
    ds = ca.if_else(small, -T**2 * (wT / 3 - wT**3 / 30), (wT * cs - sn) / safe**2)
    dc = ca.if_else(small, T**2 * (0.5 - wT**2 / 8), (wT * sn - (1 - cs)) / safe**2)
    fx = ca.vertcat(px + s * vx - c * vz, pz + c * vx + s * vz, cs * vx - sn * vz,
                    sn * vx + cs * vz, w)
    J = ca.SX.eye(N_X)
    J[0, 2], J[0, 3], J[0, 4] = s, -c, ds * vx - dc * vz
    J[1, 2], J[1, 3], J[1, 4] = c, s, dc * vx + ds * vz
    J[2, 2], J[2, 3], J[2, 4] = cs, -sn, T * (-sn * vx - cs * vz)
    J[3, 2], J[3, 3], J[3, 4] = sn, cs, T * (cs * vx - sn * vz)
    return fx, J


def _step(measurement: str) -> ca.Function:
    s, a = ca.SX.sym("s", size(STATE)), ca.SX.sym("a", size(STEP))
    xs = [s[STATE["x"]][N_X * j: N_X * (j + 1)] for j in range(N_MODES)]
    Ps = [_mat(s[STATE["P"]][N_X * N_X * j: N_X * N_X * (j + 1)], N_X, N_X)
          for j in range(N_MODES)]
    mu = s[STATE["mu"]]
    T, plot = a[STEP["T"]], a[STEP["plot"]]
    lin, relin, use = a[STEP["lin"]], a[STEP["relin"]], a[STEP["use"]]
    q_cv, q_ct, q_omega = a[STEP["q_cv"]], a[STEP["q_ct"]], a[STEP["q_omega"]]
    tau_cv, tau_ct, omega_max = a[STEP["tau_cv"]], a[STEP["tau_ct"]], a[STEP["omega_max"]]
    ra, rb = 1 / tau_cv, 1 / tau_ct  # the chain's leaving rates
    e = ca.exp(-(ra + rb) * T)
    Pi = ca.vertcat(ca.horzcat(rb + ra * e, ra * (1 - e)),
                    ca.horzcat(rb * (1 - e), ra + rb * e)) / (ra + rb)
    c = ca.mtimes(Pi.T, mu)
    mixed = []
    for j in range(N_MODES):
        w = [Pi[i, j] * mu[i] / c[j] for i in range(N_MODES)]
        xm = sum(w[i] * xs[i] for i in range(N_MODES))
        Pm = sum(w[i] * (Ps[i] + ca.mtimes(xs[i] - xm, (xs[i] - xm).T)) for i in range(N_MODES))
        mixed.append((xm, Pm))
    F = ca.SX.eye(N_X)
    F[4, 4], F[0, 2], F[1, 3] = 0.0, T, T
    Q = _cv_noise(T, q_cv)
    Q[4, 4] = 1e-12
    xm, Pm = mixed[0]
    x_cv, P_cv, l_cv, a_cv, n_cv = update_terms(ca.mtimes(F, xm), ca.mtimes([F, Pm, F.T]) + Q,
                                                plot, measurement, lin[:2], relin[0], use)
    fx, J = _turn(mixed[1][0], T)
    Q = _cv_noise(T, q_ct)
    Q[4, 4] = q_omega * T
    x_ct, P_ct, l_ct, a_ct, n_ct = update_terms(fx, ca.mtimes([J, mixed[1][1], J.T]) + Q, plot,
                                                measurement, lin[2:], relin[1], use)
    x_ct[4] = ca.fmin(ca.fmax(x_ct[4], -omega_max), omega_max)  # projection on the bound
    ll = ca.vertcat(l_cv, l_ct)
    post = c * ca.exp(ll - ca.mmax(ll))
    deviance = -2 * (ca.mmax(ll) + ca.log(ca.sum1(post)))  # -2 log sum_j c_j L_j
    mun = ca.fmax(post / ca.sum1(post), MU_FLOOR)
    mun = mun / ca.sum1(mun)
    out = ca.vertcat(x_cv, x_ct, _flat(P_cv), _flat(P_ct), mun)
    again = ca.vertcat(ca.fmax(a_cv, a_ct), a_cv, a_ct)
    nis = ca.vertcat(ca.fmin(n_cv, n_ct), deviance, n_cv, n_ct)
    return compiled.function(f"imm_ct_{measurement}", [s, a], [out, again, nis], ["s", "a"],
                             ["s_next", "again", "nis"], derivatives=False)


@cache
def step(measurement: str) -> ca.Function:
    """One step: ``(s_{k-1}, inputs_k) -> (s_k, again_k, nis_k)`` (layouts :data:`STATE`,
    :data:`STEP`); ``again`` ``[any, per mode]`` asks for the step to be repeated
    (:func:`.imm_step.relinearise`); ``nis`` ``[least, deviance, per mode]`` for the validation gate
    (:func:`.imm_step.gated_steps`)."""
    return _step(measurement)


def unpack(S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of :data:`STATE` -> means ``(n, 2, 5)``, covariances ``(n, 2, 5, 5)``,
    probabilities ``(n, 2)``."""
    n = S.shape[0]
    return (S[:, STATE["x"]].reshape(n, N_MODES, N_X),
            S[:, STATE["P"]].reshape(n, N_MODES, N_X, N_X), S[:, STATE["mu"]])


def build() -> None:
    """Build (compile, or load from the cache) the step functions: a warm-up's work."""
    for measurement in ("ekf", "converted"):
        step(measurement)
