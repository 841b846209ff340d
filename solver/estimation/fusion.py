"""Seed 004's fusion of two position sources (Misharin; spec filters.md section 4), reproduced
for comparison, per plane axis, on the plots' plane positions (:class:`SensorPlots`).

Source 1 is the accurate one (smaller median per-axis sigma ``sigma = sqrt(R_aa)`` of its
plots), source 2 the other; ``T_j`` is source ``j``'s median update period. Each variant feeds
one value per filter step into a growing-memory alpha-beta filter with the memory capped at
``k_max`` steps (step ``k = 0``: ``x = y``, ``v = 0``; then, with ``k' = min(k, k_max)`` and
``T`` the time since the previous step,

    alpha = 2 (2k' + 1) / ((k' + 1)(k' + 2)),   beta = 6 / ((k' + 1)(k' + 2)),
    x_pred = x + v T,   r = y - x_pred,   x = x_pred + alpha r,   v = v + (beta / T) r):

- ``fusion_a``: a step at every plot of the faster source (smaller ``T_j``; source 2 if equal:
  the filter's clock; a step at every instant either source reports would take velocities from
  two sensors' plots milliseconds apart); ``y = c1 y1 + c2 y2`` with each source's latest value
  (held, "aged", when stale) and ``c1 = s2 / (s1 + s2)``, ``c2 = s1 / (s1 + s2)`` (``s_j`` that
  value's sigma on the axis). Before both sources have reported, the one that has.
- ``fusion_b``: as A with ``c1 = s2 T2 / (s1 T1 + s2 T2)``, ``c2 = s1 T1 / (s1 T1 + s2 T2)``.
- ``fusion_c``: event-driven: a step at every instant source 1 reports; ``y = c1 y1 + c2 y2``
  (A's weights) when source 2 has a fresh value (reported since the previous step, the first
  step: ever), else ``y = y1``; source 2 alone triggers no step.

As in the paper the weights go as ``1/sigma`` (not ``1/sigma^2``) and a held value is never
predicted forward. The sound alternative is ``cv_rts`` on the same plots: every measurement at its
own time with its own covariance (Kalman filter and RTS smoother; ``smooth=False`` the filter).

Output at every plot: the state of the last step at or before its time, predicted to it
(``x + v dt``); before the first step: the plot with its covariance and an unknown velocity
(sigma ``SIGMA_V0``). The covariance is that of the gains with the step values
taken as independent with variance ``c1^2 s1^2 + c2^2 s2^2`` under a straight-line model: held
values are reused (correlated) and their age is a lag, neither of which it includes, so for A and B
it is optimistic.
"""

from __future__ import annotations

import numpy as np

from ..inputs import FloatArray
from ..results import FilterEstimate
from .alpha_beta import K_MAX, closed_form_gains
from .common import SIGMA_V0, estimate
from .measurements import PolarPlots, SensorPlots

VARIANTS = ("a", "b", "c")


def _source_split(meas: PolarPlots | SensorPlots, name: str
                  ) -> tuple[list[tuple[FloatArray, FloatArray, FloatArray]], int]:
    """Per source ``(t, y (n_j, 2), sigma (n_j, 2))``, the accurate source first, and the
    accurate source's sensor index."""
    count = meas.n_sensors if isinstance(meas, SensorPlots) else 1
    if count != 2:
        raise ValueError(f"{name} fuses exactly two sources (seed 004's variants are defined "
                         f"for an accurate and a coarse sensor); these plots come from "
                         f"{count} sensor{'s' if count != 1 else ''}")
    assert isinstance(meas, SensorPlots)
    sig = np.sqrt(np.stack([meas.cov[:, 0, 0], meas.cov[:, 1, 1]], -1))
    src = []
    for j in range(2):
        rows = meas.sensor == j
        src.append((meas.t[rows], meas.centre[rows], sig[rows]))
    acc = int(np.argmin([np.median(np.sqrt(np.mean(s**2, 1))) for _, _, s in src]))
    return [src[acc], src[1 - acc]], acc


def update_period(t: FloatArray) -> float:
    """Median step of one source's times (1 s with a single plot)."""
    if t.size > 1:
        return float(np.median(np.diff(t)))
    return 1.0


def alpha_beta_steps(tau: FloatArray, y: FloatArray, var: FloatArray, k_max: int | None
                     ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Capped growing-memory alpha-beta over steps at times ``tau (S,)`` with values
    ``y (S, 2)`` of variances ``var (S, 2)`` (per axis). Returns positions, velocities
    ``(S, 2)`` and per-axis covariances ``(S, 2, 2, 2)`` of ``(p, v)`` (Joseph form)."""
    S = tau.size
    x, v = np.empty((S, 2)), np.empty((S, 2))
    P = np.zeros((S, 2, 2, 2))
    x[0], v[0] = y[0], 0.0
    P[0, :, 0, 0], P[0, :, 1, 1] = var[0], SIGMA_V0**2
    for k in range(1, S):
        T = tau[k] - tau[k - 1]
        alpha, beta = closed_form_gains(k if k_max is None else min(k, k_max))
        xp = x[k - 1] + v[k - 1] * T
        r = y[k] - xp
        x[k], v[k] = xp + alpha * r, v[k - 1] + beta / T * r
        F = np.array([[1.0, T], [0.0, 1.0]])
        K = np.array([alpha, beta / T])
        IKH = np.array([[1.0 - alpha, 0.0], [-beta / T, 1.0]])
        Pk = IKH @ (F @ P[k - 1] @ F.T) @ IKH.T + var[k][:, None, None] * np.outer(K, K)
        P[k] = 0.5 * (Pk + np.swapaxes(Pk, -1, -2))
    return x, v, P


def run_fusion(meas: PolarPlots | SensorPlots, variant: str, k_max: int | None = K_MAX
               ) -> FilterEstimate:
    """Seed 004's fusion variant ``"a"``, ``"b"`` or ``"c"`` (module docstring)."""
    name = f"fusion_{variant}"
    if variant not in VARIANTS:
        raise ValueError(f"unknown fusion variant {variant!r} (use 'a', 'b' or 'c')")
    if k_max is not None and not k_max >= 1:
        raise ValueError(f"k_max must be at least 1, not {k_max!r}")
    ((t1, y1, s1), (t2, y2, s2)), acc = _source_split(meas, name)
    fast = t1 if update_period(t1) < update_period(t2) else t2
    steps = t1 if variant == "c" else fast
    i1 = np.searchsorted(t1, steps, side="right") - 1  # latest value at each step (-1: none)
    i2 = np.searchsorted(t2, steps, side="right") - 1
    use1, use2 = i1 >= 0, i2 >= 0
    if variant == "c":
        prev = np.concatenate([[-np.inf], steps[:-1]])
        use2 &= t2[np.maximum(i2, 0)] > prev  # fresh: reported since the previous step
    a1, a2 = s1[np.maximum(i1, 0)], s2[np.maximum(i2, 0)]
    w1, w2 = a2, a1
    if variant == "b":
        w1, w2 = a2 * update_period(t2), a1 * update_period(t1)
    both = (use1 & use2)[:, None]
    c1 = np.where(both, w1 / (w1 + w2), use1[:, None] * 1.0)
    c2 = np.where(both, w2 / (w1 + w2), (use2 & ~use1)[:, None] * 1.0)
    y = c1 * y1[np.maximum(i1, 0)] + c2 * y2[np.maximum(i2, 0)]
    var = c1**2 * a1**2 + c2**2 * a2**2
    x, v, Pa = alpha_beta_steps(steps, y, var, k_max)
    # every plot: the last step at or before it, predicted to its time
    j = np.searchsorted(steps, meas.t, side="right") - 1
    dt = meas.t - steps[np.maximum(j, 0)]
    jj = np.maximum(j, 0)
    out = np.column_stack([x[jj] + v[jj] * dt[:, None], v[jj]])
    F = np.zeros((dt.size, 2, 2))
    F[:, 0, 0] = F[:, 1, 1] = 1.0
    F[:, 0, 1] = dt
    cov = np.zeros((dt.size, 4, 4))
    for axis in (0, 1):  # state (x, z, vx, vz): axis a at indices (a, a + 2)
        Pax = F @ Pa[jj, axis] @ np.transpose(F, (0, 2, 1))
        cov[np.ix_(np.arange(dt.size), [axis, axis + 2], [axis, axis + 2])] = Pax
    before = j < 0  # no step yet (the other source's plots before the clock's first)
    if before.any():
        out[before] = np.column_stack([meas.centre[before], np.zeros((before.sum(), 2))])
        cov[before] = 0.0
        cov[np.ix_(before, [0, 1], [0, 1])] = meas.cov[before]
        cov[before, 2, 2] = cov[before, 3, 3] = SIGMA_V0**2
    return estimate(name, meas.t, out, cov, accurate_sensor=float(acc),
                    steps=float(steps.size))


def run_fusion_a(meas: PolarPlots | SensorPlots, k_max: int | None = K_MAX) -> FilterEstimate:
    return run_fusion(meas, "a", k_max)


def run_fusion_b(meas: PolarPlots | SensorPlots, k_max: int | None = K_MAX) -> FilterEstimate:
    return run_fusion(meas, "b", k_max)


def run_fusion_c(meas: PolarPlots | SensorPlots, k_max: int | None = K_MAX) -> FilterEstimate:
    return run_fusion(meas, "c", k_max)
