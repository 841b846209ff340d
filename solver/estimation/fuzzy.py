"""Fuzzy-gain linear filter of seed 003 (Vu Chi Thanh 2013).

Kalman structure on a Singer channel per radar coordinate (ground range, azimuth), but the gain
comes from a Mamdani knowledge base instead of the Riccati equation:

- input: the normalised innovation magnitude ``u = |nu| / sqrt(S)`` on ``[0, U_MAX]`` (clamped);
- output: the gain level ``g`` on ``[0, 1]``, mapped to the gain vector
  ``K = K_low + g (K_high - K_low)``, ``K_low`` / ``K_high`` the steady-state Kalman gains of a
  quiet (``sigma_low``) and a manoeuvring (``sigma_high``) Singer model for the actual step;
- ``n_terms`` (3, 5 or 7) evenly spaced terms on both universes, triangular or Gaussian, adjacent
  terms crossing at ``crossover`` (0.3, 0.5, 0.7); rule ``i``: "innovation is term i -> gain is
  term i" (small innovation, small gain);
- Mamdani max-min inference (each consequent clipped at its firing strength, aggregated by max)
  and centroid defuzzification on a 401-point grid, rescaled so the gain level spans [0, 1].

Track initiation: while the Kalman gain of the reported covariance still exceeds ``K_high``
(the first two or three plots, broad prior) that Kalman gain is used.
The covariance reported is the Joseph-form covariance of the gain actually used under the
nominal Singer model (``sigma_m``).

Several sensors (or a geodetic frame: :class:`SensorPlots`): one channel per plane axis (``x``
north, ``z`` east) on the plots' plane positions with their marginal variances. The gain bounds
are then the *time-varying* Kalman gains of the quiet and manoeuvring models along the actual
sequence of steps and plot variances (:func:`kalman_gains`): when sensors of different accuracy
and rate alternate there is no steady state, and two plots at one instant (a zero step, whose
steady gain is 0) must both count. On one regular sensor they converge to the steady gains.

Inference is a few vectorised numpy lines (:class:`FuzzyGain`); scikit-fuzzy/simpful build a
rule object per call and are far slower per step.
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
from .models import singer

U_MAX = 3.0
"""Innovation universe ``[0, 3]`` sigma: beyond 3 sigma the innovation is "largest"."""
N_TERMS, SHAPE, CROSSOVER = 3, "triangular", 0.5
ALPHA, SIGMA_LOW, SIGMA_HIGH, SIGMA_M = 1 / 20, 0.3, 2.0, 1.0
"""Singer ``alpha`` as the Singer filter; quiet / manoeuvring / nominal ``sigma_m`` (m/s^2): best
of sigma_low in {0.1, 0.3}, sigma_high in {2, 5, 10}, sigma_m in {1, 3} on the dev trajectories;
3 triangular terms crossing at 0.5 is the thesis' base case."""


def _memberships(x: FloatArray, centres: FloatArray, shape: str, crossover: float) -> FloatArray:
    """``(..., n_terms)`` memberships of ``x`` in terms centred at ``centres`` whose neighbours
    cross at level ``crossover``."""
    h = centres[1] - centres[0]
    dx = np.abs(x[..., None] - centres)
    if shape == "triangular":
        return np.clip(1.0 - dx / (h / (2 * (1 - crossover))), 0.0, 1.0)
    if shape == "gaussian":
        s = (h / 2) / np.sqrt(-2 * np.log(crossover))
        return np.exp(-0.5 * (dx / s) ** 2)
    raise ValueError(f"unknown membership shape {shape!r} (use 'triangular' or 'gaussian')")


class FuzzyGain:
    """Mamdani max-min knowledge base ``innovation term i -> gain term i`` with centroid output."""

    def __init__(self, n_terms: int = N_TERMS, shape: str = SHAPE, crossover: float = CROSSOVER,
                 u_max: float = U_MAX, grid: int = 401):
        if n_terms not in (3, 5, 7):
            raise ValueError(f"n_terms must be 3, 5 or 7, not {n_terms!r}")
        if not 0 < crossover < 1:
            raise ValueError(f"crossover must be in (0, 1), not {crossover!r}")
        self.shape, self.crossover, self.u_max = shape, crossover, u_max
        self.in_centres = np.linspace(0.0, u_max, n_terms)
        self.y = np.linspace(0.0, 1.0, grid)
        self.out_mu = _memberships(self.y, np.linspace(0.0, 1.0, n_terms), shape, crossover).T

        lo, hi = self.centroid(np.array([0.0, u_max]))
        self._lo, self._span = float(lo), float(hi - lo)

    def centroid(self, u: FloatArray) -> FloatArray:
        """Mamdani max-min output for innovation magnitudes ``u`` (any shape), defuzzified by
        centroid; the aggregated set is integrated exactly as piecewise linear on the grid."""
        u = np.clip(np.abs(np.asarray(u, dtype=float)), 0.0, self.u_max)
        fire = _memberships(u, self.in_centres, self.shape, self.crossover)  # (..., terms)
        agg = np.minimum(fire[..., :, None], self.out_mu).max(axis=-2)  # (..., grid)
        y, fa, fb = self.y, agg[..., :-1], agg[..., 1:]
        area = np.sum(fa + fb, axis=-1)
        moment = np.sum(fa * (2 * y[:-1] + y[1:]) + fb * (y[:-1] + 2 * y[1:]), axis=-1) / 3
        return moment / area

    def __call__(self, u: FloatArray) -> FloatArray:
        """Gain level: the centroid rescaled so that no innovation gives 0 and the largest gives
        1 (a centroid never reaches the ends of its universe; without the rescaling the
        knowledge base could not produce ``K_low`` or ``K_high``)."""
        return np.clip((self.centroid(u) - self._lo) / self._span, 0.0, 1.0)


def steady_gain(Phi: FloatArray, Q: FloatArray, R: FloatArray, iterations: int = 40
                ) -> FloatArray:
    """Steady-state Kalman gains ``(..., m)`` of ``x+ = Phi x + w``, ``z = x_0 + v`` for stacks
    ``Phi``, ``Q`` ``(..., m, m)`` and ``R`` ``(...)``, by the structure-preserving doubling
    algorithm for the predicted-covariance Riccati equation
    ``P = Phi P Phi^T - Phi P H^T (H P H^T + R)^-1 H P Phi^T + Q`` (quadratic convergence: 40
    doublings cover 2^40 steps). ``A_0 = Phi^T``, ``G_0 = H^T R^-1 H``, ``H_0 = Q``;
    ``W = (I + G H)^-1``; ``A <- A W A``, ``G <- G + A W G A^T``, ``H <- H + A^T H W A``;
    ``H -> P``. Batched numpy instead of one ``scipy.linalg.solve_discrete_are`` per step (which
    the tests use as the reference)."""
    m = Phi.shape[-1]
    eye = np.eye(m)
    A = np.swapaxes(Phi, -1, -2).copy()
    G = np.zeros_like(A)
    G[..., 0, 0] = 1.0 / np.asarray(R)
    Hm = Q.copy()
    for _ in range(iterations):
        W = np.linalg.inv(eye + G @ Hm)
        AW = A @ W
        G, Hm, A = (G + AW @ G @ np.swapaxes(A, -1, -2),
                    Hm + np.swapaxes(A, -1, -2) @ Hm @ W @ A, AW @ A)
    P = 0.5 * (Hm + np.swapaxes(Hm, -1, -2))
    return P[..., :, 0] / (P[..., 0, 0] + np.asarray(R))[..., None]


def kalman_gains(P0: FloatArray, Phi: FloatArray, Q: FloatArray, R: FloatArray) -> FloatArray:
    """``(n, B, m)`` Kalman gains of ``B`` scalar-measurement channels (``z = x_0 + v``) along
    steps ``Phi``, ``Q`` ``(n-1, B, m, m)`` with variances ``R (n, B)`` from the prior ``P0``
    at plot 0 (gain 0 there): ``P- = Phi P Phi^T + Q``, ``K = P-[:, 0] / (P-[0, 0] + R)``,
    ``P = (I - K H) P-`` (the data do not enter)."""
    n, (B, m) = R.shape[0], P0.shape[:2]
    K = np.zeros((n, B, m))
    P = P0.copy()
    for k in range(1, n):
        F = Phi[k - 1]
        P = F @ P @ np.transpose(F, (0, 2, 1)) + Q[k - 1]
        K[k] = P[:, :, 0] / (P[:, 0, 0] + R[k])[:, None]
        P = P - K[k][:, :, None] * P[:, 0, None, :]
        P = 0.5 * (P + np.transpose(P, (0, 2, 1)))
    return K


def _run_fuzzy_axes(meas: SensorPlots, kb: FuzzyGain, alpha: float, sigma_low: float,
                    sigma_high: float, sigma_m: float, gate: float | None) -> FilterEstimate:
    """Per plane axis with time-varying gain bounds (module docstring)."""
    n = len(meas)
    dt = np.diff(meas.t)
    cov = meas.converted_cov()
    R = np.column_stack([cov[:, 0, 0], cov[:, 1, 1]])

    def model(sigma: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        Phi, Q = singer(dt, alpha, sigma)
        P0 = np.zeros((2, 3, 3))
        P0[:, 0, 0], P0[:, 1, 1], P0[:, 2, 2] = R[0], SIGMA_V0**2, sigma**2
        return np.stack([Phi, Phi], 1), np.stack([Q, Q], 1), P0

    Phi_lo, Q_lo, P_lo = model(sigma_low)
    _, Q_hi, P_hi = model(sigma_high)
    K_lo, K_hi = np.split(kalman_gains(np.concatenate([P_lo, P_hi]),  # one batched pass
                                       np.concatenate([Phi_lo, Phi_lo], 1),
                                       np.concatenate([Q_lo, Q_hi], 1),
                                       np.concatenate([R, R], 1)), 2, axis=1)
    levels = np.zeros((n, 2))

    def gain(k: int, lanes: np.ndarray | slice, u: FloatArray, K_kalman: FloatArray
             ) -> FloatArray:
        g = kb(u)
        levels[k, lanes] = g
        lo, hi = K_lo[k][lanes], K_hi[k][lanes]
        K = lo + g[:, None] * (hi - lo)
        initiating = K_kalman[:, 0] > hi[:, 0]  # track initiation: prior still broad
        return np.where(initiating[:, None], K_kalman, K)

    Phi2, Q2, _ = model(sigma_m)
    prior = np.array([[0.0, SIGMA_V0**2, sigma_m**2]] * 2)
    xf, Pf, _, _, gated = axis_channels(meas, Phi2, Q2, prior, gain, gate)
    s, P = axes_to_cartesian(xf, Pf, 0, 1)
    return estimate("fuzzy", meas.t, s, P, gain_level=levels, gated=gated.any(axis=1))


def run_fuzzy(meas: PolarPlots | SensorPlots, n_terms: int = N_TERMS, shape: str = SHAPE,
              crossover: float = CROSSOVER, alpha: float = ALPHA, sigma_low: float = SIGMA_LOW,
              sigma_high: float = SIGMA_HIGH, sigma_m: float = SIGMA_M,
              gate: float | None = GATE_SIGMA) -> FilterEstimate:
    """``gate``: a plot further than this many sigmas from the prediction (both coordinates'
    normalised innovations together) is not used (:mod:`.gating`), before the knowledge base
    sees it; None: all."""
    kb = FuzzyGain(n_terms, shape, crossover)
    if isinstance(meas, SensorPlots):
        return _run_fuzzy_axes(meas, kb, alpha, sigma_low, sigma_high, sigma_m, gate)
    dt = np.diff(meas.t)
    d_ref = float(np.median(meas.d))
    r_metric = np.array([np.median(meas.sigma_d) ** 2, (d_ref * meas.sigma_psi) ** 2])
    # gain bounds per distinct step and channel (metric units; the azimuth channel is the range
    # model scaled by 1/d_ref, which leaves the gains unchanged)
    steps, inverse = np.unique(np.round(dt, 9), return_inverse=True)
    Phi_lo, Q_lo = singer(steps, alpha, sigma_low)
    _, Q_hi = singer(steps, alpha, sigma_high)
    Phi_b = np.repeat(Phi_lo[:, None], 2, 1)
    K_lo = steady_gain(Phi_b, np.repeat(Q_lo[:, None], 2, 1), r_metric[None, :])  # (steps, 2, 3)
    K_hi = steady_gain(Phi_b, np.repeat(Q_hi[:, None], 2, 1), r_metric[None, :])
    levels = np.zeros((len(meas), 2))

    def gain(k: int, lanes: np.ndarray | slice, u: FloatArray, K_kalman: FloatArray
             ) -> FloatArray:
        g = kb(u)
        levels[k, lanes] = g
        j = inverse[k - 1]
        lo, hi = K_lo[j][lanes], K_hi[j][lanes]
        K = lo + g[:, None] * (hi - lo)
        initiating = K_kalman[:, 0] > hi[:, 0]  # track initiation: prior still broad
        return np.where(initiating[:, None], K_kalman, K)

    Phi, Q = singer(dt, alpha, sigma_m)
    Phi2 = np.stack([Phi, Phi], 1)
    Q2 = np.stack([Q, Q / d_ref**2], 1)
    prior = np.array([[0.0, SIGMA_V0**2, sigma_m**2],
                      [0.0, (SIGMA_V0 / d_ref) ** 2, (sigma_m / d_ref) ** 2]])
    xf, Pf, _, _, gated = polar_channels(meas, Phi2, Q2, prior, gain, gate)
    s, P = channels_to_cartesian(xf, Pf, 0, 1)
    return estimate("fuzzy", meas.t, s, P, gain_level=levels, gated=gated.any(axis=1))
