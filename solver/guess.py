"""Analytic initial guess of a window's controls: the seed's point transfer (spec section 5).

For a target point ``(x, z)`` reached at time ``t`` from ``(0, 0, heading 0, v0)``:

1. ``w`` from the circle approximation ``(x - v0 t/4)^2 + z^2 = (3/4 v0 t + 1/2 w t^2)^2``;
2. ``u`` from ``(x^2+z^2) u^2 - 2 v0^2 z u + 4 (x^2+z^2) w^2 + 4 v0^2 x w - (v^4 - v0^4) = 0``,
   ``v = v0 + w t`` (the squared sum of the identities ``u x + 2 w z = v^2 sin phi`` and
   ``2 w x - u z + v0^2 = v^2 cos phi``), keeping the root whose trajectory lands nearer;
3. optionally one Newton step on the end position with the 2x2 Jacobian in ``(u, w)``.

Every pair is clipped to the window's box. Each plot of a window gives one pair (plus any extra
pairs the caller supplies, e.g. the previous window's controls); the pair with the lowest
criterion is the NLP's starting point. Everything is vectorised over windows and plots.
"""

from __future__ import annotations

import numpy as np

from .inputs import FloatArray
from .motion import propagate
from .window import criterion


def to_start_frame(start: FloatArray, cx: FloatArray, cz: FloatArray
                   ) -> tuple[FloatArray, FloatArray]:
    """Points ``(cx, cz) (n, m)`` in the frame of ``start (n, 4)``: origin at ``(x0, z0)``, x axis
    along the heading ``phi0``."""
    dx, dz = cx - start[:, 0:1], cz - start[:, 1:2]
    c, s = np.cos(start[:, 2:3]), np.sin(start[:, 2:3])
    return c * dx + s * dz, -s * dx + c * dz


def _end(v0: FloatArray, u: FloatArray, w: FloatArray, t: FloatArray
         ) -> tuple[FloatArray, FloatArray]:
    x, z, _, _ = propagate(0.0, 0.0, 0.0, v0, u, w, t)
    return x, z


def point_transfer(x: FloatArray, z: FloatArray, t: FloatArray, v0: FloatArray,
                   u_box: tuple[float, float], lbw: FloatArray, ubw: FloatArray,
                   newton: bool = True) -> tuple[FloatArray, FloatArray]:
    """Controls ``(u, w)`` that carry ``(0, 0, 0, v0)`` to ``(x, z)`` at ``t`` (broadcasting),
    clipped to ``u_box`` and ``[lbw, ubw]``."""
    r = np.hypot(x - v0 * t / 4, z)
    w = np.clip(2 * (r - 0.75 * v0 * t) / (t * t), lbw, ubw)
    v = v0 + w * t
    q2 = x * x + z * z
    c0 = 4 * q2 * w * w + 4 * v0 * v0 * x * w - (v**4 - v0**4)
    half_b = v0 * v0 * z
    root = np.sqrt(np.maximum(half_b * half_b - q2 * c0, 0.0))
    q2s = np.where(q2 > 0, q2, 1.0)
    u1 = np.clip((half_b + root) / q2s, *u_box)
    u2 = np.clip((half_b - root) / q2s, *u_box)
    e1 = np.hypot(*(np.subtract(_end(v0, u1, w, t), (x, z))))
    e2 = np.hypot(*(np.subtract(_end(v0, u2, w, t), (x, z))))
    u = np.where(e1 <= e2, u1, u2)
    if newton:
        u, w = _newton_step(x, z, t, v0, u, w, u_box, lbw, ubw)
    return u, w


def _newton_step(x, z, t, v0, u, w, u_box, lbw, ubw):
    """One Newton step on ``end(u, w) = (x, z)``, Jacobian by central differences, clipped;
    kept only where it brings the end point nearer."""
    hu, hw = 1e-4, 1e-5
    ex, ez = _end(v0, u, w, t)
    xup, zup = _end(v0, u + hu, w, t)
    xum, zum = _end(v0, u - hu, w, t)
    xwp, zwp = _end(v0, u, w + hw, t)
    xwm, zwm = _end(v0, u, w - hw, t)
    j11, j21 = (xup - xum) / (2 * hu), (zup - zum) / (2 * hu)
    j12, j22 = (xwp - xwm) / (2 * hw), (zwp - zwm) / (2 * hw)
    det = j11 * j22 - j12 * j21
    ok = np.abs(det) > 1e-12 * (np.abs(j11 * j22) + np.abs(j12 * j21) + 1e-300)
    dets = np.where(ok, det, 1.0)
    rx, rz = x - ex, z - ez
    du = np.where(ok, (j22 * rx - j12 * rz) / dets, 0.0)
    dw = np.where(ok, (-j21 * rx + j11 * rz) / dets, 0.0)
    un, wn = np.clip(u + du, *u_box), np.clip(w + dw, lbw, ubw)
    nx, nz = _end(v0, un, wn, t)
    better = np.hypot(nx - x, nz - z) < np.hypot(rx, rz)
    return np.where(better, un, u), np.where(better, wn, w)


def initial_guess(start: FloatArray, t: FloatArray, cx: FloatArray, cz: FloatArray,
                  abc: FloatArray, u_box: tuple[float, float], lbw: FloatArray,
                  ubw: FloatArray, extra: FloatArray | None = None,
                  newton: bool = False) -> tuple[FloatArray, FloatArray]:
    """Best starting ``(u, w) (n, 2)`` of ``n`` windows and its criterion value ``(n,)``.

    Candidates: the point transfer to each of the ``m`` plots, plus ``extra (n, k, 2)`` pairs
    (clipped to the box); the one with the lowest criterion wins. The Newton step is off by
    default: measured on the seed-like and a 4.8-s-scan track it leaves the optima and the
    solver's work unchanged and costs 10% of the run time.
    """
    lb, ub = lbw[:, None], ubw[:, None]
    xs, zs = to_start_frame(start, cx, cz)
    u, w = point_transfer(xs, zs, t, start[:, 3:4], u_box, lb, ub, newton)
    cand = np.stack([u, w], axis=-1)  # (n, m, 2)
    if extra is not None:
        ex = np.stack([np.clip(extra[..., 0], *u_box), np.clip(extra[..., 1], lb, ub)], axis=-1)
        cand = np.concatenate([cand, ex], axis=1)
    k = cand.shape[1]
    vals = criterion(np.repeat(start[:, None, :], k, axis=1), cand[..., 0], cand[..., 1],
                     t[:, None, :], cx[:, None, :], cz[:, None, :], abc[:, None, :, :])
    vals = np.where(np.isfinite(vals), vals, np.inf)
    best = np.argmin(vals, axis=1)
    rows = np.arange(start.shape[0])
    return cand[rows, best], vals[rows, best]
