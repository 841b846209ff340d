"""Closed-form aircraft motion for constant controls, in numpy and as a CasADi expression.

Model (spec/reconstruction.md section 2)::

    x' = v cos(phi),  z' = v sin(phi),  phi' = u / v,  v' = w.

For constant ``(u, w)`` from ``(0, 0, 0, v0)``, with ``zeta = x + i z``::

    v(t) = v0 + w t,   L = ln(v / v0) = log1p(w t / v0),   mu = L / w = (t / v0) g(w t / v0),
    phi(t) = u mu,     zeta(t) = v0^2 mu E(2 L + i phi),

where ``g(a) = log1p(a) / a`` and ``E(y) = (e^y - 1) / y`` (both equal 1 at 0). This equals the
seed's ``[u v^2 sin phi + 2 w (v^2 cos phi - v0^2)] / (u^2 + 4 w^2)`` (multiply out
``(v^2 e^{i phi} - v0^2) / (2 w + i u)``) but divides by nothing that vanishes: ``g`` and ``E``
switch to their Taylor series near 0, so ``w = 0``, ``u = 0`` and ``u = w = 0`` are exact.
A general start rotates ``zeta`` by ``phi0`` and shifts it by ``(x0, z0)``.

The model needs ``v(t) > 0``; the log argument is clamped at ``-1 + 1e-9`` so an infeasible
iterate of an optimiser yields a large finite value rather than NaN.
"""

from __future__ import annotations

from functools import cache

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import compiled

FloatArray = NDArray[np.float64]

_A_SERIES = 1e-4  # |w t / v0| below this: g by its series (error < 1e-20)
_Y_SERIES = 1e-2  # |y| below this: E by its series (error < 3e-17)
_A_FLOOR = -1.0 + 1e-9


def _g_np(a: FloatArray) -> FloatArray:
    """``log1p(a) / a`` with its series ``1 - a/2 + a^2/3 - a^3/4`` near 0."""
    small = np.abs(a) < _A_SERIES
    safe = np.where(small, 1.0, a)
    series = 1.0 - a / 2 + a * a / 3 - a * a * a / 4
    return np.where(small, series, np.log1p(safe) / safe)


def _e_np(re: FloatArray, im: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(e^y - 1) / y`` for ``y = re + i im``, as (real, imaginary) parts."""
    y = re + 1j * im
    small = np.abs(y) < _Y_SERIES
    safe = np.where(small, 1.0, y)
    # expm1 of a complex number without cancellation: e^a cos b - 1 = expm1(a) cos b - 2 sin^2(b/2)
    sre, sim = safe.real, safe.imag
    em1 = np.expm1(sre) * np.cos(sim) - 2 * np.sin(sim / 2) ** 2 + 1j * np.exp(sre) * np.sin(sim)
    series = 1 + y / 2 * (1 + y / 3 * (1 + y / 4 * (1 + y / 5 * (1 + y / 6))))
    out = np.where(small, series, em1 / safe)
    return out.real, out.imag


def propagate(
    x0: ArrayLike, z0: ArrayLike, phi0: ArrayLike, v0: ArrayLike,
    u: ArrayLike, w: ArrayLike, t: ArrayLike,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """State ``(x, z, phi, v)`` after time ``t`` under constant ``(u, w)``; numpy, broadcasting."""
    x0, z0, phi0, v0, u, w, t = (np.asarray(a, dtype=float) for a in (x0, z0, phi0, v0, u, w, t))
    a = np.maximum(w * t / v0, _A_FLOOR)
    mu = t / v0 * _g_np(a)
    big_l = np.log1p(a)
    phi = u * mu
    e_re, e_im = _e_np(2 * big_l, phi)
    scale = v0 * v0 * mu
    dx, dz = scale * e_re, scale * e_im
    c0, s0 = np.cos(phi0), np.sin(phi0)
    return x0 + c0 * dx - s0 * dz, z0 + s0 * dx + c0 * dz, phi0 + phi, v0 * (1 + a)


def velocity(phi: ArrayLike, v: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """``(vx, vz) = v (cos phi, sin phi)``."""
    return v * np.cos(phi), v * np.sin(phi)


def _g_ca(a: ca.SX) -> ca.SX:
    small = ca.fabs(a) < _A_SERIES
    safe = ca.if_else(small, 1.0, a)
    series = 1.0 - a / 2 + a * a / 3 - a * a * a / 4
    return ca.if_else(small, series, ca.log1p(safe) / safe)


def _e_ca(re: ca.SX, im: ca.SX) -> tuple[ca.SX, ca.SX]:
    small = re * re + im * im < _Y_SERIES**2
    sre = ca.if_else(small, 1.0, re)
    sim = ca.if_else(small, 0.0, im)
    n_re = ca.expm1(sre) * ca.cos(sim) - 2 * ca.sin(sim / 2) ** 2
    n_im = ca.exp(sre) * ca.sin(sim)
    den = sre * sre + sim * sim
    d_re = (n_re * sre + n_im * sim) / den
    d_im = (n_im * sre - n_re * sim) / den
    # series 1 + y/2 + y^2/6 + y^3/24 + y^4/120 + y^5/720 in real arithmetic (Horner, complex)
    p_re, p_im = 1.0 + re / 6, im / 6
    for k in (5, 4, 3, 2):
        q_re = (re * p_re - im * p_im) / k
        q_im = (re * p_im + im * p_re) / k
        p_re, p_im = 1.0 + q_re, q_im
    return ca.if_else(small, p_re, d_re), ca.if_else(small, p_im, d_im)


def propagate_ca(state: ca.SX | ca.MX, u, w, t):
    """CasADi expression of :func:`propagate`: ``state = (x, z, phi, v)`` -> state at ``t``."""
    x0, z0, phi0, v0 = state[0], state[1], state[2], state[3]
    a = ca.fmax(w * t / v0, _A_FLOOR)
    mu = t / v0 * _g_ca(a)
    phi = u * mu
    e_re, e_im = _e_ca(2 * ca.log1p(a), phi)
    scale = v0 * v0 * mu
    dx, dz = scale * e_re, scale * e_im
    c0, s0 = ca.cos(phi0), ca.sin(phi0)
    return ca.vertcat(x0 + c0 * dx - s0 * dz, z0 + s0 * dx + c0 * dz, phi0 + phi, v0 * (1 + a))


@cache
def motion_function(compile: bool = True) -> ca.Function:
    """``F(state[4], u, w, t) -> state[4]``, built once; compiled when a C compiler is at hand
    (:mod:`solver.compiled`) unless ``compile`` is False."""
    s = ca.SX.sym("s", 4)
    u, w, t = ca.SX.sym("u"), ca.SX.sym("w"), ca.SX.sym("t")
    args = ([s, u, w, t], [propagate_ca(s, u, w, t)], ["state", "u", "w", "t"], ["state_t"])
    return compiled.function("motion", *args) if compile else ca.Function("motion_vm", *args)
