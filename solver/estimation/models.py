"""Motion models (one per function): continuous matrices, exact transitions and process noise.

Per-axis states are ``[p, p', ...]``; two horizontal axes stack as blocks ``[x-axis, z-axis]``
(:func:`two_axes`). All functions take an array of time steps ``dt`` (irregular allowed).
"""

from __future__ import annotations

import numpy as np

from ..inputs import FloatArray
from .discretize import taylor, van_loan


def two_axes(M: FloatArray) -> FloatArray:
    """Block-diagonal ``(..., 2m, 2m)`` of the same per-axis ``(..., m, m)`` matrices."""
    m = M.shape[-1]
    out = np.zeros((*M.shape[:-2], 2 * m, 2 * m))
    out[..., :m, :m] = M
    out[..., m:, m:] = M
    return out


# --- constant velocity (white-noise acceleration) -------------------------------------------

def cv(dt: FloatArray, q: float) -> tuple[FloatArray, FloatArray]:
    """Per axis ``[p, v]``: ``Phi = [[1, T], [0, 1]]``, ``Q = q [[T^3/3, T^2/2], [T^2/2, T]]``
    (``q`` = spectral density of the white acceleration, m^2/s^3)."""
    T = np.asarray(dt, dtype=float)
    Phi = np.zeros((T.size, 2, 2))
    Phi[:, 0, 0] = Phi[:, 1, 1] = 1.0
    Phi[:, 0, 1] = T
    Q = q * np.stack([np.stack([T**3 / 3, T**2 / 2], -1), np.stack([T**2 / 2, T], -1)], -2)
    return Phi, Q


# --- Singer ----------------------------------------------------------------------------------

def singer_F(alpha: float) -> FloatArray:
    """``p''' = -alpha p'' + w``: ``F = [[0, 1, 0], [0, 0, 1], [0, 0, -alpha]]``."""
    return np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -alpha]])


def singer_transition(dt: FloatArray, alpha: float) -> FloatArray:
    """Closed-form ``Phi(T)`` (spec filters.md section 1); ``expm1`` keeps small ``alpha T`` exact
    to rounding in the (1, 2) and (2, 3) entries; the (1, 3) entry uses its series below 1e-3."""
    T = np.asarray(dt, dtype=float)
    aT = alpha * T
    e = np.exp(-aT)
    em1 = -np.expm1(-aT)  # 1 - e^{-aT}
    small = aT < 1e-3
    safe = np.where(small, 1.0, aT)
    p13 = np.where(small, T**2 * (0.5 - aT / 6 + aT**2 / 24), (safe - em1) / alpha**2 if alpha
                   else T**2 / 2)
    p23 = np.where(small, T * (1 - aT / 2 + aT**2 / 6), em1 / alpha if alpha else T)
    Phi = np.zeros((T.size, 3, 3))
    Phi[:, 0, 0] = Phi[:, 1, 1] = 1.0
    Phi[:, 0, 1] = T
    Phi[:, 0, 2] = p13
    Phi[:, 1, 2] = p23
    Phi[:, 2, 2] = e
    return Phi


def singer(dt: FloatArray, alpha: float, sigma_m: float) -> tuple[FloatArray, FloatArray]:
    """Singer ``(Phi, Q)``: exact transition, ``Q = 2 alpha sigma_m^2 q(T)`` by Van Loan."""
    _, Q = van_loan(singer_F(alpha), np.array([0.0, 0.0, 1.0]), 2 * alpha * sigma_m**2, dt)
    return singer_transition(dt, alpha), Q


# --- quasi-optimal control-law model (seed 001) ----------------------------------------------

def quasi_optimal_F(lam: float, alpha: float) -> FloatArray:
    """State ``[q, q', r]``: ``q'' = -sqrt(Lambda) q' + Lambda r``, ``r' = -alpha r + w``."""
    return np.array([[0.0, 1.0, 0.0], [0.0, -np.sqrt(lam), lam], [0.0, 0.0, -alpha]])


def quasi_optimal(dt: FloatArray, lam: float, alpha: float, sigma_m: float,
                  method: str = "exact") -> tuple[FloatArray, FloatArray]:
    """``(Phi, Q)`` of the quasi-optimal model; ``w`` has spectral density ``2 alpha sigma_m^2``
    (so ``r`` is stationary with RMS ``sigma_m``). ``method``: ``"exact"`` (Van Loan) or
    ``"taylor"`` (the paper's second-order series, ``Q = 2 alpha sigma_m^2 / T`` through Gamma)."""
    F, G = quasi_optimal_F(lam, alpha), np.array([0.0, 0.0, 1.0])
    if method == "exact":
        return van_loan(F, G, 2 * alpha * sigma_m**2, dt)
    if method == "taylor":
        return taylor(F, G, 2 * alpha * sigma_m**2, dt)
    raise ValueError(f"unknown discretisation {method!r} (use 'exact' or 'taylor')")


# --- coordinated turn with unknown rate (state x, z, vx, vz, omega) --------------------------

TURN_SERIES_WT = 1e-3
"""Below this ``|omega T|`` the turn terms are their series (the exact forms divide by ``w``)."""


def _turn_terms(w: float, T: float) -> tuple[float, float, float, float]:
    """``s = sin(wT)/w``, ``c = (1 - cos wT)/w`` and their derivatives in ``w`` (series near 0)."""
    wT = w * T
    if abs(wT) < TURN_SERIES_WT:
        s = T * (1 - wT**2 / 6)
        c = T * (wT / 2 - wT**3 / 24)
        ds = -T**2 * (wT / 3 - wT**3 / 30)
        dc = T**2 * (0.5 - wT**2 / 8)
        return s, c, ds, dc
    sn, cs = np.sin(wT), np.cos(wT)
    s, c = sn / w, (1 - cs) / w
    ds = (wT * cs - sn) / w**2
    dc = (wT * sn - (1 - cs)) / w**2
    return s, c, ds, dc


def ct_predict(x: FloatArray, T: float) -> tuple[FloatArray, FloatArray]:
    """Coordinated turn (``v' = omega J v``, turning right for ``omega > 0`` in the x-north,
    z-east frame): returns ``f(x)`` and its Jacobian."""
    px, pz, vx, vz, w = x
    s, c, ds, dc = _turn_terms(w, T)
    cw, sw = np.cos(w * T), np.sin(w * T)
    fx = np.array([px + s * vx - c * vz, pz + c * vx + s * vz,
                   cw * vx - sw * vz, sw * vx + cw * vz, w])
    J = np.eye(5)
    J[0, 2], J[0, 3], J[0, 4] = s, -c, ds * vx - dc * vz
    J[1, 2], J[1, 3], J[1, 4] = c, s, dc * vx + ds * vz
    J[2, 2], J[2, 3], J[2, 4] = cw, -sw, T * (-sw * vx - cw * vz)
    J[3, 2], J[3, 3], J[3, 4] = sw, cw, T * (cw * vx - sw * vz)
    return fx, J
