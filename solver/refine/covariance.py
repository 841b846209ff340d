"""Uncertainty of the refined track: the Laplace approximation at the solution.

The L1 prior on control changes is replaced by a Gaussian of the same variance (a Laplace
density ``exp(-lambda |Delta| / 2)`` has variance ``8 / lambda^2``, scaled by
``covariance_scale``), the dynamics and the plots' residuals are linearised about the solution,
and the covariance recursions of the Kalman filter and Rauch-Tung-Striebel smoother over the
nodes (:mod:`solver.estimation.covariance_pass`) give the marginal covariance of the
Gauss-Newton posterior. The state is the node
solution ``(x, z, phi, v, u, w[, h, hd])`` followed by the estimated radar offsets, which are
constant states (so their smoothed covariance is their posterior covariance, and the track's
covariance includes their uncertainty). A residual down-weighted by the robust loss enters with
its IRLS weight ``rho'(q) = 1 / sqrt(1 + q / delta^2)``.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

import casadi as ca
import numpy as np

from .. import compiled
from ..config import RefineSettings
from ..estimation.covariance_pass import filtered_covariances, smoothed_covariances
from ..estimation.kalman import covariance_update
from ..inputs import Bounds, FloatArray
from ..motion import motion_function
from ..sensors import ALTITUDE_RANGE_M
from .layout import BIAS_TERMS, HD_MAX, Variant
from .nodes import NodeData, info_matrices

NH = 6  # horizontal node state: x, z, phi, v, u, w

CHECK_EVERY = 1024  # nodes between deadline checks (about 15 ms of the forward pass)


def check_every(nx: int) -> int:
    """Nodes between deadline checks for ``nx`` states: :data:`CHECK_EVERY` for the track's 8,
    fewer as a node's work grows with ``nx^3`` (at least 16: 48 radars' offsets, ``nx`` 150,
    about 0.3 s of the forward pass)."""
    return max(16, int(CHECK_EVERY * (NH + 2) ** 3 / max(nx, NH + 2) ** 3))


@cache
def motion_jacobian() -> ca.Function:
    """``J(s6, dt) -> d s6(dt) / d s6``: the motion map's Jacobian with ``u, w`` in the state."""
    s = ca.SX.sym("s", NH)
    dt = ca.SX.sym("dt")
    out = ca.vertcat(motion_function()(s[:4], s[4], s[5], dt), s[4], s[5])
    return compiled.function("motion_jac", [s, dt], [ca.jacobian(out, s)], ["s", "dt"], ["jac"])


def transitions(sol: np.ndarray, dt: FloatArray, variant: Variant) -> np.ndarray:
    """``(m, nx, nx)`` state transitions over steps ``dt`` from node states ``sol`` (the motion
    Jacobian; ``h += dt hd``; offsets constant)."""
    m = dt.size
    nx = state_size(variant)
    Phi = np.zeros((m, nx, nx))
    Phi[:, :NH, :NH] = compiled.columns(motion_jacobian(), sol[:, :NH].T, dt[None, :])[0]
    Phi[:, range(NH, nx), range(NH, nx)] = 1.0
    if variant.altitude:
        Phi[:, NH, NH + 1] = dt
    return Phi


def state_size(variant: Variant) -> int:
    return NH + 2 * variant.altitude + BIAS_TERMS * variant.biases


def node_covariance(t_nodes: FloatArray, sol: np.ndarray, biases: np.ndarray, data: NodeData,
                    variant: Variant, st: RefineSettings, delta: float, bounds: Bounds,
                    hd_info: FloatArray, bias_sigma: FloatArray,
                    consider_from: int | None = None, time_gauge: np.ndarray | None = None,
                    check: Callable[[], None] | None = None) -> np.ndarray:
    """Smoothed ``(n, nx, nx)`` covariance of the node states (and offsets).

    ``check`` is called every :func:`check_every` nodes of the forward and backward passes
    (a deadline: on a 15,000-node track the forward pass takes about 0.2 s, past a deadline the
    solves had met; with many offsets a node costs ``nx^3``).

    ``consider_from``: from this node on the offsets were held, not estimated (later blocks of
    a long track), so they are *consider* states there (Schmidt-Kalman: their gain is zero, the
    Joseph form keeps the covariance right): the plots after it carry the offsets' uncertainty
    into the track without pretending to have informed them."""
    n = t_nodes.size
    nx = state_size(variant)
    dt = np.append(np.diff(t_nodes), 0.0)
    Phi = transitions(sol, dt, variant)
    Q = np.zeros((n, nx, nx))
    qvar = st.covariance_scale * np.array([8 / st.switch_penalty_u**2,
                                           8 / st.switch_penalty_w**2])
    # the prior is on the ground's accelerations (as the bounds): the plane's are the plane's
    # scale times those (NodeData.scaled), so their variance is its square times qvar
    Q[:, 4, 4], Q[:, 5, 5] = (qvar[:, None] * data.plane_scale[None, :] ** 2)
    if variant.altitude:  # the change into node k + 1 has variance 1 / hd_info[k + 1]
        Q[:-1, NH + 1, NH + 1] = 1.0 / hd_info[1:]
    H, Rinv = _plot_jacobians(sol, biases, data, variant, delta)
    measured = (Rinv.any(axis=(1, 2))) & (data.weight > 0)
    R = np.zeros_like(Rinv)
    R[measured] = np.linalg.inv(Rinv[measured])
    # weak prior: uniform within the bounds for heading, speed and the controls
    span = data.plane_scale[0] * np.array([bounds.v[1] - bounds.v[0], bounds.u[1] - bounds.u[0],
                                           bounds.w[1] - bounds.w[0]])
    prior = [1e12, 1e12, np.pi**2 / 3, *(span**2 / 12)]
    if variant.altitude:
        prior += [(ALTITUDE_RANGE_M[1] - ALTITUDE_RANGE_M[0]) ** 2 / 12, HD_MAX**2 / 3]
    prior += list(np.asarray(bias_sigma, float) ** 2)
    P0 = np.diag(prior)
    if time_gauge is not None and np.any(time_gauge):  # the NLP's gauge g . b_t = 0
        g = np.zeros((1, nx))
        g[0, NH + 2 * variant.altitude + 2::BIAS_TERMS] = time_gauge
        P0 = covariance_update(P0, g, np.array([[1.0]]))
    informed = np.ones((n, nx))  # the states a measurement at each node may inform
    if consider_from is not None:  # the offsets' rows of every gain are zero from there on
        informed[consider_from:, NH + 2 * variant.altitude:] = 0.0
    updates = [(H, R, informed * measured[:, None])]  # R unused where the gain is zero
    if variant.altitude:
        on = data.alt_info > 0
        alt_H = np.zeros((n, 1, nx))
        alt_H[:, 0, NH] = 1.0
        alt_R = 1.0 / np.where(on, data.alt_info, 1.0)
        updates.append((alt_H, alt_R[:, None, None], informed * on[:, None]))
    ns = NH + 2 * variant.altitude  # the offsets after them are constant states
    Pp, Pf = filtered_covariances(P0, Phi, Q, tuple(updates), check, check_every(nx), ns)
    Ps = smoothed_covariances(Pf, Pp, Phi, check, check_every(nx), ns)
    return Ps


def plot_covariances(cov_nodes: np.ndarray, sol: np.ndarray, biases: np.ndarray,
                     data: NodeData, variant: Variant, delta: float, nodes: np.ndarray
                     ) -> np.ndarray:
    """``(m, 2, 2)`` covariance of the position the track predicts for the plots at
    ``nodes``: ``H P H^T`` with the plot's whole Jacobian (the state, the estimated height, its
    sensor's offsets), not the position block of ``P`` alone. With offsets estimated on a
    short track the track's position carries their common shift (116-147 m where it is 25 m
    without them, a tester's), which the plot's prediction does not: the leverages from the
    position block clipped at 1, and two radars' sigmas estimated from them read 97 m for
    50 m (300-s tracks; 50 m from this)."""
    H, _ = _plot_jacobians(sol, biases, data, variant, delta)
    H, P = H[nodes], cov_nodes[nodes]
    return np.einsum("nij,njk,nlk->nil", H, P, H)


def _plot_jacobians(sol: np.ndarray, biases: np.ndarray, data: NodeData, variant: Variant,
                    delta: float) -> tuple[np.ndarray, np.ndarray]:
    """Per node: the ``(2, nx)`` Jacobian of the plot's residual with respect to the state, and
    the residual's information ``M rho'(q)`` (zero where no plot)."""
    n = sol.shape[0]
    nx = state_size(variant)
    H = np.zeros((n, 2, nx))
    H[:, 0, 0] = H[:, 1, 1] = 1.0
    if variant.altitude:
        H[:, :, NH] = -data.dcentre_dh(sol[:, NH])
    if variant.biases:
        phi, v = sol[:, 2], sol[:, 3]
        e = np.column_stack([np.cos(phi), np.sin(phi)])
        b = data.sensor @ biases  # (n, 3) offsets of each node's radar
        H[:, :, 2] += -(b[:, 2] * v)[:, None] * np.column_stack([-np.sin(phi), np.cos(phi)])
        H[:, :, 3] += -b[:, 2:3] * e
        base = NH + 2 * variant.altitude
        for j in range(variant.biases):
            on = data.sensor[:, j][:, None]
            H[:, :, base + 3 * j] = on * data.d_range
            H[:, :, base + 3 * j + 1] = on * data.d_azimuth
            H[:, :, base + 3 * j + 2] = on * -(v[:, None] * e)
    q = data.quad(sol, biases, variant.altitude)
    irls = 1.0 / np.sqrt(1 + q / delta**2)
    Rinv = info_matrices(data.info) * (irls * data.weight)[:, None, None]
    return H, Rinv
