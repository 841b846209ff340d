"""IMM fixed-interval smoother: a forward interacting-multiple-model filter with three linear motion
models and a backward pass per mode pair (Kim 1994's smoother for Markov-switching linear
models, as the IMM-RTS smoother of Nadarajah, Tharmarasa, McDonald and Kirubarajan 2012), on the
polar plots through the EKF (or converted) position update of :mod:`.kalman`.

Models, state ``(x, z, vx, vz)`` (x north, z east), white acceleration of spectral density ``q``:

- ``0`` constant velocity (``q_cv``);
- ``1`` coordinated turn to the right at the fixed rate ``+omega`` (clockwise from north);
- ``2`` coordinated turn to the left at ``-omega``; both with ``q_ct``.

Fixed-rate turns keep every model linear, so each mode pair's backward step is an exact
Rauch-Tung-Striebel step and only the measurement update is linearised. Mode switching is a
continuous-time Markov chain: CV is left at rate ``1/tau_cv`` for either turn (half each), a
turn is left at rate ``1/tau_ct`` for CV, so ``Pi(T)`` follows every actual step (missed plots).

Outputs the smoothed, moment-matched estimate; ``info``: ``model_probabilities`` (smoothed,
``(n, 3)``: CV, right, left), ``filtered_model_probabilities``, ``filtered`` (the forward IMM's
``(x, z, vx, vz)``) and ``turn_rate`` (smoothed expected turn rate, rad/s, clockwise positive).

Defaults (``q_cv = 3``, ``q_ct = 30 m^2/s^3``, ``omega = 1 deg/s``, ``tau_cv = 600 s``,
``tau_ct = 60 s``): the grid point with the lowest mean over the profiles seed000, seed001 and ssr
of the RMS position error relative to each profile's best, on the six dev ADS-B tracks with the
dev seeds 100 and 101 (``python -m benchmarks.tune imm_smoother``, 72 points, then ``--fine``
around its best, 24 points; ``benchmarks/results/tuning_imm_smoother*.json``): RMS 385.7 /
342.8 / 75.3 m, the best of the fine grid in every profile (ssr's best of the first stage,
``q_cv = 1``, ``q_ct = 10``, sojourn 200 s, is 1 % better there). The optimum is flat (the next
points are within 0.5 %). Kim's mode weights (``future_modes=False``) are 0-4 % less accurate at
their own best points and about 1.5 times faster.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..inputs import FloatArray
from ..results import FilterEstimate
from . import imm_step
from .common import SIGMA_V0, estimate
from .discretize import van_loan
from .gating import GATE_SIGMA
from .measurements import MEASUREMENT_MODES, PolarPlots, SensorPlots

N_MODES = imm_step.N_MODES
MODE_NAMES = ("cv", "right", "left")

Q_CV, Q_CT, OMEGA_DEG, TAU_CV, TAU_CT = 3.0, 30.0, 1.0, 600.0, 60.0
DEFAULTS = {"q_cv": Q_CV, "q_ct": Q_CT, "omega_deg": OMEGA_DEG, "tau_cv": TAU_CV,
            "tau_ct": TAU_CT}
"""``q_cv``, ``q_ct`` (m^2/s^3), turn rate of the turn models ``omega_deg`` (deg/s), mean
sojourn times ``tau_cv``, ``tau_ct`` (s)."""


def switching_matrices(dt: FloatArray, tau_cv: float, tau_ct: float) -> FloatArray:
    """``Pi(T) = expm(G T)``, ``(len(dt), 3, 3)``, ``Pi[i, j] = P(mode j at t + T | mode i at t)``,
    for the generator ``G = [[-a, a/2, a/2], [b, -b, 0], [b, 0, -b]]``, ``a = 1/tau_cv``,
    ``b = 1/tau_ct`` (``tau = inf`` makes a mode absorbing). Closed form: with ``s = a + b``,

        Pi[0, 0] = (b + a e^{-sT}) / s,   Pi[0, 1] = Pi[0, 2] = a (1 - e^{-sT}) / (2 s),
        Pi[1, 0] = Pi[2, 0] = b (1 - e^{-sT}) / s,
        Pi[1, 1] = Pi[2, 2] = ((a + b e^{-sT}) / s + e^{-bT}) / 2,
        Pi[1, 2] = Pi[2, 1] = ((a + b e^{-sT}) / s - e^{-bT}) / 2

    (the turn share decays with ``e^{-sT}`` as in the two-state chain; the difference between
    the two turns with ``e^{-bT}``)."""
    T = np.asarray(dt, dtype=float)
    a, b = 1.0 / tau_cv, 1.0 / tau_ct
    s = a + b
    out = np.zeros((T.size, 3, 3))
    if s == 0.0:  # nothing ever switches
        out[:] = np.eye(3)
        return out
    e = np.exp(-s * T)
    em1 = -np.expm1(-s * T)  # 1 - e^{-sT} without cancellation
    ct_share = (a + b * e) / s
    eb = np.exp(-b * T)
    out[:, 0, 0] = (b + a * e) / s
    out[:, 0, 1] = out[:, 0, 2] = a * em1 / (2 * s)
    out[:, 1, 0] = out[:, 2, 0] = b * em1 / s
    out[:, 1, 1] = out[:, 2, 2] = 0.5 * (ct_share + eb)
    out[:, 1, 2] = out[:, 2, 1] = np.maximum(0.5 * (ct_share - eb), 0.0)
    return out


def stationary(tau_cv: float, tau_ct: float) -> FloatArray:
    """Stationary mode probabilities ``(b, a/2, a/2) / (a + b)`` of the chain (``a = 1/tau_cv``,
    ``b = 1/tau_ct``); ``(1, 0, 0)`` when CV is absorbing."""
    a, b = 1.0 / tau_cv, 1.0 / tau_ct
    if a + b == 0.0:
        return np.array([1.0, 0.0, 0.0])
    return np.array([b, a / 2, a / 2]) / (a + b)


def transitions(dt: FloatArray, q_cv: float, q_ct: float, omega: float
                ) -> tuple[FloatArray, FloatArray]:
    """``Phi``, ``Q`` of the three models, ``(len(dt), 3, 4, 4)``. CV: ``Phi = [[I, T I], [0, I]]``,
    ``Q = q [[T^3/3 I, T^2/2 I], [T^2/2 I, T I]]``. Turn at rate ``w``: ``p' = v``,
    ``v' = w [[0, -1], [1, 0]] v + a``, ``E[a a^T] = q I delta``: exact ``Phi = e^{F T}`` and
    ``Q = int_0^T e^{F s} G q G^T e^{F^T s} ds`` by Van Loan (``discretize.van_loan``)."""
    T = np.asarray(dt, dtype=float)
    n = T.size
    Phi = np.zeros((n, 3, 4, 4))
    Q = np.zeros((n, 3, 4, 4))
    eye2 = np.eye(2)
    Phi[:, 0] = np.eye(4)
    Phi[:, 0, :2, 2:] = T[:, None, None] * eye2
    Q[:, 0, :2, :2] = (q_cv * T**3 / 3)[:, None, None] * eye2
    Q[:, 0, :2, 2:] = Q[:, 0, 2:, :2] = (q_cv * T**2 / 2)[:, None, None] * eye2
    Q[:, 0, 2:, 2:] = (q_cv * T)[:, None, None] * eye2
    G = np.zeros((4, 2))
    G[2:, :] = eye2
    for m, w in ((1, omega), (2, -omega)):
        F = np.zeros((4, 4))
        F[:2, 2:] = eye2
        F[2, 3], F[3, 2] = -w, w
        Phi[:, m], Q[:, m] = van_loan(F, G, q_ct, T)
    return Phi, Q


def _prior(meas: PolarPlots | SensorPlots) -> tuple[FloatArray, FloatArray]:
    """The first plot point with its converted covariance, velocity 0 +- ``SIGMA_V0``."""
    x0 = np.zeros(4)
    x0[:2] = meas.points()[0]
    P0 = np.zeros((4, 4))
    P0[:2, :2] = meas.converted_cov()[0]
    P0[2, 2] = P0[3, 3] = SIGMA_V0**2
    return x0, P0


class ForwardPass(NamedTuple):
    """What the forward IMM leaves for the backward pass (``n`` plots, 3 modes, 4 states)."""

    x: FloatArray
    """``(n, 3, 4)`` mode-conditioned filtered states ``E[x_k | m_k = i, Z^k]``."""
    P: FloatArray
    """``(n, 3, 4, 4)`` their covariances."""
    mu: FloatArray
    """``(n, 3)`` mode probabilities ``P(m_k = i | Z^k)``."""
    W: FloatArray
    """``(n - 1, 3, 3)`` mixing weights ``W[k, i, j] = P(m_k = i | m_{k+1} = j, Z^k)``."""
    xp: FloatArray
    """``(n - 1, 3, 4)`` mixed predictions ``E[x_{k+1} | m_{k+1} = j, Z^k]``."""
    Pp: FloatArray
    """``(n - 1, 3, 4, 4)`` their covariances."""
    gated: np.ndarray
    """``(n,)`` True where the validation gate left the plot out (:mod:`.gating`)."""


def imm_forward(meas: PolarPlots | SensorPlots, Phi: FloatArray, Q: FloatArray, Pi: FloatArray,
                mu0: FloatArray, measurement: str = "ekf", gate: float | None = GATE_SIGMA
                ) -> ForwardPass:
    """The forward IMM (Blom and Bar-Shalom 1988). Per step ``k`` (``T = t_k - t_{k-1}``):

    - predicted mode probabilities ``c_j = sum_i Pi_ij mu_i``, mixing weights
      ``W_ij = P(m_{k-1} = i | m_k = j, Z^{k-1}) = Pi_ij mu_i / c_j``;
    - mixed ``x0_j = sum_i W_ij x_i``, ``P0_j = sum_i W_ij (P_i + (x_i - x0_j)(x_i - x0_j)^T)``;
    - model ``j``: ``x_j = Phi_j x0_j``, ``P_j = Phi_j P0_j Phi_j^T + Q_j``, then the position
      update with plot ``k`` (``kalman.position_update``, Joseph form), likelihood
      ``L_j = exp(-(nu^T S^-1 nu + log det S) / 2)``;
    - ``mu_j = c_j L_j / sum_l c_l L_l``.

    A mode with ``c_j = 0`` (absorbing chain) is mixed with ``mu`` and keeps probability 0. A
    plot that no mode expects within ``gate`` sigmas is left out (:mod:`.gating`): the step is
    the prediction, ``mu_j = c_j``.

    Each step is one call of a compiled function (:mod:`.imm_step`).
    """
    if measurement not in MEASUREMENT_MODES:
        raise ValueError(f"unknown measurement mode {measurement!r} (use 'converted' or 'ekf')")
    n = len(meas)
    x0, P0 = _prior(meas)
    m = max(n - 1, 0)
    xf = np.empty((n, N_MODES, 4))
    Pf = np.empty((n, N_MODES, 4, 4))
    mu = np.empty((n, N_MODES))
    xf[0], Pf[0], mu[0] = x0, P0, mu0
    if m == 0:
        return ForwardPass(xf, Pf, mu, np.empty((0, N_MODES, N_MODES)),
                           np.empty((0, N_MODES, 4)), np.empty((0, N_MODES, 4, 4)),
                           np.zeros(n, dtype=bool))
    A = imm_step.pack(imm_step.STEP, m, Phi=Phi, Q=Q, Pi=Pi, plot=imm_step.plot_rows(meas)[1:],
                      lin=0.0, relin=0.0, use=1.0)
    S = np.empty((n, imm_step.size(imm_step.STATE)))  # row k: the state after plot k
    S[:1] = imm_step.pack(imm_step.STATE, 1, x=np.repeat(x0[None], N_MODES, 0),
                          P=np.repeat(P0[None], N_MODES, 0), mu=mu0)
    E = np.empty((m, imm_step.size(imm_step.EXTRA)))
    gated = imm_step.gated_steps(imm_step.forward_step(measurement), S, A, E, imm_step.STEP,
                                 imm_step.STATE, 4, gate)
    xf[1:], Pf[1:], mu[1:] = _states(S[1:])
    ex = imm_step.EXTRA
    return ForwardPass(xf, Pf, mu, E[:, ex["W"]].reshape(m, N_MODES, N_MODES),
                       E[:, ex["xp"]].reshape(m, N_MODES, 4),
                       E[:, ex["Pp"]].reshape(m, N_MODES, 4, 4), gated)


def _states(S: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rows laid out as :data:`.imm_step.STATE` as ``x (n, 3, 4)``, ``P (n, 3, 4, 4)``,
    ``mu (n, 3)``."""
    n, lay = S.shape[0], imm_step.STATE
    return (S[:, lay["x"]].reshape(n, N_MODES, 4), S[:, lay["P"]].reshape(n, N_MODES, 4, 4),
            S[:, lay["mu"]])


def pair_terms(fw: ForwardPass, Phi: FloatArray, Q: FloatArray
               ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The backward pass's mode-pair terms known from the forward pass, for all steps at once
    (pairs ``(k, i, j)``: model ``j`` applied to the filtered ``x_k^i``): the predictions
    ``x^{ij}`` ``(n-1, i, j, 4)`` and ``P^{ij}``, the gains ``C^{ij}``, and ``a^{ij}``, ``B^{ij}``
    with ``xs^{ij} = a^{ij} + C^{ij} xs_{k+1}^j``, ``Ps^{ij} = B^{ij} + C^{ij} Ps_{k+1}^j
    C^{ij T}``."""
    xf, Pf = fw.x, fw.P
    Phj = Phi[:, None]  # (n-1, 1, j, 4, 4)
    Pk = Pf[:-1, :, None]  # (n-1, i, 1, 4, 4)
    PhiP = Phj @ Pk  # Phi_j P_k^i
    xpair = (Phj @ xf[:-1, :, None, :, None])[..., 0]  # (n-1, i, j, 4)
    Ppair = PhiP @ np.swapaxes(Phj, -1, -2) + Q[:, None]
    Ppair = 0.5 * (Ppair + np.swapaxes(Ppair, -1, -2))
    C = np.swapaxes(np.linalg.solve(Ppair, PhiP), -1, -2)  # P_k^i Phi_j^T (P^{ij})^-1
    CT = np.swapaxes(C, -1, -2)
    a = xf[:-1, :, None, :] - (C @ xpair[..., None])[..., 0]
    B = Pk - C @ Ppair @ CT
    return xpair, Ppair, C, a, B


def imm_backward(fw: ForwardPass, Phi: FloatArray, Q: FloatArray, future_modes: bool = True
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Backward pass per mode pair (Kim 1994), ``i`` the mode at ``k``, ``j`` at ``k + 1``. With the
    forward mode-conditioned ``x_k^i``, ``P_k^i``:

    - states: ``x^{ij} = Phi_j x_k^i``, ``P^{ij} = Phi_j P_k^i Phi_j^T + Q_j``,
      ``C^{ij} = P_k^i Phi_j^T (P^{ij})^-1``; ``xs_k^{ij} = x_k^i + C^{ij} (xs_{k+1}^j - x^{ij})``,
      ``Ps_k^{ij} = P_k^i + C^{ij} (Ps_{k+1}^j - P^{ij}) C^{ij T}`` (exact RTS steps: the models
      are linear);
    - modes: ``P(m_k = i, m_{k+1} = j | Z^N) = b_ij mus_{k+1}(j)``, ``mus_k(i) = sum_j`` of it,
      ``b_ij = P(m_k = i | m_{k+1} = j, Z^N)``;
    - ``xs_k^i = sum_j w_ij xs_k^{ij}``, ``Ps_k^i = sum_j w_ij (Ps_k^{ij} + dd^T)``,
      ``w_ij = b_ij mus_{k+1}(j) / mus_k(i)``, ``d = xs_k^{ij} - xs_k^i``.

    Kim's ``b_ij`` is the forward ``W_ij = P(m_k = i | m_{k+1} = j, Z^k)``: it ignores what the
    plots after ``k`` say about ``m_k``, so a turn the filter noticed late starts late in the
    smoothed modes too, and a stiff CV model then carries the turned heading backwards
    (measured: on tracks drawn from the model itself with ``q_cv = 0.5``, twice the forward
    filter's error). With ``future_modes`` (default) ``b_ij`` is ``W_ij L_ij`` normalised over
    ``i``, ``L_ij`` the likelihood of the later plots given the pair:

        L_ij = int N(x; xs_{k+1}^j, Ps_{k+1}^j) / N(x; xp_{k+1}^j, Pp_{k+1}^j)
                   N(x; x^{ij}, P^{ij}) dx

    (the later plots' information about ``x_{k+1}``: the smoothed over the forward mixed
    prediction ``xp``, ``Pp``, kept where it is positive; closed form in
    :func:`.imm_step.backward_step`).

    The pair gains depend on the forward pass only and are computed for all steps at once.
    Returns the smoothed mode-conditioned states, covariances and mode probabilities.
    """
    xf, Pf, mu, W = fw.x, fw.P, fw.mu, fw.W
    n = xf.shape[0]
    if n < 2:
        return xf.copy(), Pf.copy(), mu.copy()
    xpair, Ppair, C, a, B = pair_terms(fw, Phi, Q)
    # whitening by the forward prediction: Pp = U U^T, so the later plots' information is
    # compared with the prediction's in a metric that does not depend on units
    white = np.linalg.inv(np.linalg.cholesky(fw.Pp)) if future_modes else np.zeros_like(fw.Pp)
    # the recursion proper runs in CasADi (imm_step.backward_step), one call per step around
    # numpy's eigh of the whitened smoothed covariances (the future-mode likelihoods' split)
    m = n - 1
    white_prev = np.concatenate([np.zeros_like(white[:1]), white[:-1]])  # white of step k - 1
    lay = imm_step.BACK
    A = imm_step.pack(lay, m, W=W, xp=fw.xp, white=white, xpair=xpair, Ppair=Ppair, a=a, B=B,
                      C=C, white_prev=white_prev, future=float(future_modes))
    S = np.empty((n, imm_step.size(imm_step.STATE)))  # row k: the smoothed state at plot k
    S[-1:] = imm_step.pack(imm_step.STATE, 1, x=xf[-1], P=Pf[-1], mu=mu[-1])
    eigen = np.zeros(imm_step.size(imm_step.EIGEN))
    Ws = white[-1] @ Pf[-1] @ np.swapaxes(white[-1], -1, -2)  # then written by each step
    buf, evaluate = imm_step.backward_step().buffer()
    buf.set_arg(1, memoryview(eigen))
    buf.set_res(1, memoryview(Ws.reshape(-1)))
    for k in range(n - 2, -1, -1):
        if future_modes:
            if np.isfinite(Ws).all():
                ev, V = np.linalg.eigh(Ws)  # ascending; reads one triangle
                eigen[imm_step.EIGEN["s"]], eigen[imm_step.EIGEN["V"]] = ev.ravel(), V.ravel()
            else:  # absurd sigmas: no usable information, Kim's weights at this step
                A[k, lay["future"]] = 0.0
        buf.set_arg(0, memoryview(S[k + 1]))
        buf.set_arg(2, memoryview(A[k]))
        buf.set_res(0, memoryview(S[k]))
        evaluate()
    xs, Ps, mus = _states(S)
    Ps = 0.5 * (Ps + np.swapaxes(Ps, -1, -2))
    return xs, Ps, mus


def combine(x: FloatArray, P: FloatArray, mu: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Moment matching over the modes: ``x = sum_i mu_i x_i``,
    ``P = sum_i mu_i (P_i + (x_i - x)(x_i - x)^T)``; ``(n, 4)``, ``(n, 4, 4)``."""
    xc = np.einsum("ki,kia->ka", mu, x)
    d = x - xc[:, None, :]
    Pc = np.einsum("ki,kiab->kab", mu, P) + np.einsum("ki,kia,kib->kab", mu, d, d)
    return xc, Pc


def run_imm_smoother(meas: PolarPlots | SensorPlots, q_cv: float = Q_CV, q_ct: float = Q_CT,
                     omega_deg: float = OMEGA_DEG, tau_cv: float = TAU_CV,
                     tau_ct: float = TAU_CT, measurement: str = "ekf",
                     smooth: bool = True, future_modes: bool = True,
                     gate: float | None = GATE_SIGMA) -> FilterEstimate:
    """IMM (CV, right turn, left turn) filter and fixed-interval smoother on the plots;
    ``smooth=False`` returns the forward IMM; ``future_modes=False`` smooths the mode
    probabilities as Kim 1994 (see :func:`imm_backward`). The prior at the first plot is the plot
    point with its converted covariance, velocity 0 +- ``SIGMA_V0``, the chain's stationary
    probabilities. ``gate``: plots further than this many sigmas from every mode's prediction
    are not used (:mod:`.gating`; the backward pass bridges them), None uses every plot."""
    for name, v in (("q_cv", q_cv), ("q_ct", q_ct), ("tau_cv", tau_cv), ("tau_ct", tau_ct)):
        if not v > 0:
            raise ValueError(f"{name} must be positive, got {v}")
    if not np.isfinite(omega_deg):
        raise ValueError(f"omega_deg must be finite, got {omega_deg}")
    if measurement not in ("ekf", "converted"):
        raise ValueError(f"unknown measurement mode {measurement!r} (use 'converted' or 'ekf')")
    t = meas.t
    dt = np.diff(t)
    Phi, Q = transitions(dt, q_cv, q_ct, np.deg2rad(omega_deg))
    Pi = switching_matrices(dt, tau_cv, tau_ct)
    fw = imm_forward(meas, Phi, Q, Pi, stationary(tau_cv, tau_ct), measurement, gate)
    mu = fw.mu
    sf, Cf = combine(fw.x, fw.P, mu)
    omega = np.deg2rad(omega_deg) * np.array([0.0, 1.0, -1.0])
    if not smooth:
        return estimate("imm_smoother", t, sf, Cf, model_probabilities=mu, turn_rate=mu @ omega,
                        gated=fw.gated)
    xs, Ps, mus = imm_backward(fw, Phi, Q, future_modes)
    s, C = combine(xs, Ps, mus)
    return estimate("imm_smoother", t, s, C, model_probabilities=mus,
                    filtered_model_probabilities=mu, filtered=sf, turn_rate=mus @ omega,
                    gated=fw.gated)
