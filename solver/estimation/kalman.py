"""Kalman predict / update / smooth (FilterPy-style explicit matrices, Joseph-form updates).

- :func:`predict`, :func:`update` : one step of a linear Gaussian filter;
  :func:`covariance_update` : its covariance alone.
- :func:`position_update` : update of a state whose position sits at indices ``pos`` from one
  polar plot, as a converted measurement or an EKF update (see ``measurements.py``), or from a
  linear position fix of another sensor.
- :func:`filter_track` : a linear-model filter over a whole track (``Phi``, ``Q`` per step).
- :func:`channel_filter` : many independent scalar-measurement filters at once (batch axis ``B``);
  used per radar coordinate; an optional gain rule replaces the Kalman gain.
- :func:`rts_smoother` : Rauch-Tung-Striebel fixed-interval smoother.

The filters leave out plots far from their predictions (the validation gate, :mod:`.gating`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..inputs import FloatArray
from .gating import GATE_SIGMA, gated_pass
from .measurements import (
    LINEARISATION_TOLERANCE,
    MAX_LINEARISATIONS,
    MEASUREMENT_MODES,
    PolarPlots,
    SensorPlots,
    converted_cov,
    polar_innovation,
)


def predict(x: FloatArray, P: FloatArray, Phi: FloatArray, Q: FloatArray
            ) -> tuple[FloatArray, FloatArray]:
    """``x = Phi x``, ``P = Phi P Phi^T + Q``."""
    return Phi @ x, Phi @ P @ Phi.T + Q


def update(x: FloatArray, P: FloatArray, nu: FloatArray, H: FloatArray, R: FloatArray
           ) -> tuple[FloatArray, FloatArray, float, float]:
    """Update with innovation ``nu``: ``K = P H^T S^-1``, Joseph form for ``P``; returns also the
    normalised innovation squared ``nu^T S^-1 nu`` and ``log det S`` (for likelihoods)."""
    PHt = P @ H.T
    S = H @ PHt + R
    Sinv = np.linalg.inv(S)
    K = PHt @ Sinv
    IKH = np.eye(P.shape[0]) - K @ H
    P = IKH @ P @ IKH.T + K @ R @ K.T
    return x + K @ nu, P, float(nu @ Sinv @ nu), float(np.log(np.linalg.det(S)))


def covariance_update(P: FloatArray, H: FloatArray, R: FloatArray) -> FloatArray:
    """The covariance of :func:`update` alone (Joseph form, the same equations); ``S^-1`` in
    closed form for one or two measured components: half its cost in a loop over nodes, where
    ``update``'s general inverse, determinant and mean went to waste."""
    PHt = P @ H.T
    S = H @ PHt + R
    if S.shape == (1, 1):
        Sinv = 1.0 / S
    elif S.shape == (2, 2):
        a, b, c, d = S[0, 0], S[0, 1], S[1, 0], S[1, 1]
        Sinv = np.array([[d, -b], [-c, a]]) / (a * d - b * c)
    else:
        Sinv = np.linalg.inv(S)
    K = PHt @ Sinv
    IKH = np.eye(P.shape[0]) - K @ H
    return IKH @ P @ IKH.T + K @ R @ K.T


def position_update(x: FloatArray, P: FloatArray, meas: PolarPlots | SensorPlots, k: int,
                    pos: tuple[int, int], mode: str) -> tuple[FloatArray, FloatArray, float, float]:
    """Update with plot ``k``; ``mode`` ``"converted"`` or ``"ekf"`` (polar plots). A linear
    position fix of :class:`SensorPlots` (``z = p + v``, ``v ~ N(0, R)``) is the same for both
    modes: ``H`` selects ``pos``, ``R = meas.cov[k]``."""
    if mode not in MEASUREMENT_MODES:
        raise ValueError(f"unknown measurement mode {mode!r} (use 'converted' or 'ekf')")
    H = np.zeros((2, x.shape[0]))
    H[0, pos[0]] = H[1, pos[1]] = 1.0
    p = x[list(pos)]
    if isinstance(meas, SensorPlots):
        if not meas.polar[k]:
            return update(x, P, meas.centre[k] - p, H, meas.cov[k])
        sigma_psi = float(meas.sigma_psi[k])
    else:
        sigma_psi = meas.sigma_psi
    d, psi, sigma_d = meas.d[k], meas.psi[k], meas.sigma_d[k]
    if mode == "converted":
        z = np.array([d * np.cos(psi), d * np.sin(psi)])
        R = converted_cov(np.hypot(p[0], p[1]), np.arctan2(p[1], p[0]), sigma_d, sigma_psi)
        return update(x, P, z - p, H, R)
    return _iterated_polar_update(x, P, H, p, pos, d, psi, float(sigma_d), float(sigma_psi))


def _iterated_polar_update(x: FloatArray, P: FloatArray, H: FloatArray, p: FloatArray,
                           pos: tuple[int, int], d: float, psi: float, sigma_d: float,
                           sigma_psi: float) -> tuple[FloatArray, FloatArray, float, float]:
    """The EKF update of ``(x, P)`` (position ``p = x[pos] = H x``) by the polar plot ``(d, psi)``,
    relinearised at the updated position (the iterated EKF, Gauss-Newton on the posterior
    mode: ``x_{i+1} = x + K_i (z - h(p_i) - J_i (p - p_i))``, ``K_i`` from ``J_i H``) while
    the linearisation error exceeds :data:`.measurements.LINEARISATION_TOLERANCE` sigma; at
    most :data:`.measurements.MAX_LINEARISATIONS` updates. The first is the EKF's update."""
    R = np.diag(np.square([sigma_d, sigma_psi]))  # numpy: inf, not OverflowError, if absurd
    tol_d, tol_psi = LINEARISATION_TOLERANCE * sigma_d, LINEARISATION_TOLERANCE * sigma_psi
    at = p
    nu, J = polar_innovation(at, d, psi)
    out = update(x, P, nu, J @ H, R)
    for _ in range(MAX_LINEARISATIONS - 1):
        ax, az = float(at[0]), float(at[1])
        nx, nz = float(out[0][pos[0]]), float(out[0][pos[1]])
        # a bound first (cheap, most updates stop here): along the step |h''| <= 1 / rho_min
        # in range and 1 / rho_min^2 in azimuth, so the error is at most step^2 / 2 of these
        # (products, not powers: a float's ** raises on overflow, absurd sigmas reach it)
        step = math.hypot(nx - ax, nz - az)
        rho_min = math.hypot(ax, az) - step
        if (rho_min > 0 and step * step <= 2 * rho_min * tol_d
                and step * step <= 2 * rho_min * rho_min * tol_psi):
            break
        new = np.array([nx, nz])
        nu_new, J_new = polar_innovation(new, d, psi)
        # h(new) - h(at) - J (new - at), from the innovations (z - h): wrapped in azimuth
        error = (nu - nu_new) - J @ (new - at)
        if (abs(error[0]) <= tol_d
                and abs((error[1] + math.pi) % (2 * math.pi) - math.pi) <= tol_psi):
            break
        at, nu, J = new, nu_new, J_new
        out = update(x, P, nu - J @ (p - at), J @ H, R)
    return out


def filter_track(x0: FloatArray, P0: FloatArray, Phi: FloatArray, Q: FloatArray,
                 meas: PolarPlots | SensorPlots, pos: tuple[int, int], mode: str,
                 gate: float | None = GATE_SIGMA
                 ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Filter plots ``1..n-1`` after the prior ``(x0, P0)`` at plot 0 (built from plot 0).

    Returns filtered ``xf (n, m)``, ``Pf (n, m, m)``, predicted ``xp``, ``Pp`` (index 0 = prior),
    the normalised innovations squared ``(n,)`` (0 at plot 0) and ``(n,)`` True where the plot
    was left out by the validation gate (:mod:`.gating`; ``gate=None``: none). Plots of several
    sensors at one instant are sequential updates after a zero-length step (``Phi = I``,
    ``Q = 0``).
    """
    n, m = len(meas), x0.shape[0]
    xf, Pf = np.empty((n, m)), np.empty((n, m, m))
    xp, Pp = np.empty((n, m)), np.empty((n, m, m))
    nis = np.zeros(n)
    xf[0] = xp[0] = x0
    Pf[0] = Pp[0] = P0
    out = np.zeros((2, 1))

    def step(k: int, lanes: np.ndarray, use: bool) -> np.ndarray:
        xp[k], Pp[k] = predict(xf[k - 1], Pf[k - 1], Phi[k - 1], Q[k - 1])
        if use:
            xf[k], Pf[k], nis[k], logdet = position_update(xp[k], Pp[k], meas, k, pos, mode)
            out[0, 0], out[1, 0] = nis[k], nis[k] + logdet
        else:
            xf[k], Pf[k] = xp[k], Pp[k]
        return out

    gated = gated_pass(n, 1, step, gate)[:, 0]
    return xf, Pf, xp, Pp, nis, gated


Gain = Callable[[int, "np.ndarray | slice", FloatArray, FloatArray], FloatArray]
"""A gain rule of :func:`channel_filter`: ``(k, lanes, nu / sqrt(S), K_kalman) -> K``
(``lanes`` an index array or ``slice(None)``)."""


def channel_filter(x0: FloatArray, P0: FloatArray, Phi: FloatArray, Q: FloatArray,
                   z: FloatArray, R: FloatArray, gain: Gain | None = None,
                   gate: float | None = GATE_SIGMA
                   ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``B`` independent filters with scalar measurements ``z[k, b]`` of the first state component.

    ``x0 (B, m)``, ``P0 (B, m, m)``, ``Phi``/``Q`` ``(n-1, B, m, m)``, ``z (n, B)``,
    ``R (n, B)``. ``gain(k, lanes, nu / sqrt(S), K_kalman) -> K`` may replace the Kalman gain
    ``(len(lanes), m)`` of the filters ``lanes`` (an index array, or ``slice(None)``: all); the
    covariance is then propagated for the gain actually used (Joseph form). The filters come in
    pairs ``(b, b + B/2)``, the two coordinates of one plot (range and azimuth, or the plane
    axes): a pair leaves the plot out when the sum of its two normalised innovations squared
    exceeds ``gate^2`` (:mod:`.gating`; None: never; gating one coordinate alone let a plot
    wild in range pull the azimuth channel off). Returns filtered ``xf (n, B, m)``,
    ``Pf (n, B, m, m)``, the normalised innovations ``(n, B)`` and ``(n, B)`` True where left out.
    """
    n, (B, m) = z.shape[0], x0.shape
    xf, Pf = np.empty((n, B, m)), np.empty((n, B, m, m))
    nus = np.zeros((n, B))
    xf[0], Pf[0] = x0, P0
    eye = np.eye(m)

    def step(k: int, lanes: np.ndarray, use: bool) -> np.ndarray:
        sel = slice(None) if lanes.size == B else lanes  # all lanes: views, not copies
        F = Phi[k - 1, sel]
        x = np.einsum("bij,bj->bi", F, xf[k - 1, sel])
        P = F @ Pf[k - 1, sel] @ np.transpose(F, (0, 2, 1)) + Q[k - 1, sel]
        if not use:
            xf[k, sel], Pf[k, sel] = x, P
            return np.zeros((2, x.shape[0]))  # not read
        r = R[k, sel]
        S = P[:, 0, 0] + r
        nu = z[k, sel] - x[:, 0]
        K = P[:, :, 0] / S[:, None]
        nus[k, sel] = nu / np.sqrt(S)
        if gain is not None:
            K = gain(k, sel, nus[k, sel], K)
        IKH = eye - K[:, :, None] * eye[0][None, None, :]
        xf[k, sel] = x + K * nu[:, None]
        Pf[k, sel] = IKH @ P @ np.transpose(IKH, (0, 2, 1)) + r[:, None, None] * (
            K[:, :, None] * K[:, None, :])
        out = full if isinstance(sel, slice) else np.empty((2, S.size))
        np.square(nus[k, sel], out=out[0])
        np.log(S, out=out[1])
        out[1] += out[0]
        return out

    half = B // 2
    every = np.arange(B)
    full, pair_full = np.empty((2, B)), np.empty((2, half))  # the all-lanes step's outputs

    def pair_step(k: int, pairs: np.ndarray, use: bool) -> np.ndarray:
        if pairs.size == half:
            v = step(k, every, use)
            return np.add(v[:, :half], v[:, half:], out=pair_full)
        v = step(k, np.concatenate([pairs, pairs + half]), use)
        return v[:, :pairs.size] + v[:, pairs.size:]

    gated = gated_pass(n, half, pair_step, gate)
    return xf, Pf, nus, np.concatenate([gated, gated], axis=1)


def rts_smoother(xf: FloatArray, Pf: FloatArray, xp: FloatArray, Pp: FloatArray,
                 Phi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``C_k = Pf_k Phi_k^T Pp_{k+1}^-1``; ``xs_k = xf_k + C_k (xs_{k+1} - xp_{k+1})``;
    ``Ps_k = Pf_k + C_k (Ps_{k+1} - Pp_{k+1}) C_k^T``."""
    xs, Ps = xf.copy(), Pf.copy()
    n = xf.shape[0]
    if n < 2:
        return xs, Ps
    # the gains need only the filter's output: one batched solve, then the recursion proper
    C = np.linalg.solve(Pp[1:], Phi[: n - 1] @ Pf[:-1]).transpose(0, 2, 1)
    for k in range(n - 2, -1, -1):
        xs[k] = xf[k] + C[k] @ (xs[k + 1] - xp[k + 1])
        P = Pf[k] + C[k] @ (Ps[k + 1] - Pp[k + 1]) @ C[k].T
        Ps[k] = 0.5 * (P + P.T)
    return xs, Ps
