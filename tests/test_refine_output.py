"""solver.refine.output.series: covariances propagated between nodes, against finite
differences of the numpy motion model and the full-state propagation ``A P A^T``."""

from __future__ import annotations

import numpy as np

from solver import compiled
from solver.motion import propagate
from solver.refine.covariance import transitions
from solver.refine.layout import Variant
from solver.refine.output import series, velocity_covariance


def _states(rng: np.random.Generator, m: int) -> np.ndarray:
    s = np.column_stack([rng.normal(0, 5e4, m), rng.normal(0, 5e4, m),
                         rng.uniform(-np.pi, np.pi, m), rng.uniform(60, 260, m),
                         rng.normal(0, 2, m), rng.normal(0, 0.5, m)])
    s[:3, 4:] = 0.0  # straight and level too
    return s


def _observed(s: np.ndarray, tau: float) -> np.ndarray:
    x, z, phi, v = propagate(*s[:6], tau)
    return np.array([x, z, v * np.cos(phi), v * np.sin(phi)])


def test_velocity_covariance_is_the_propagated_covariance_by_finite_differences():
    rng = np.random.default_rng(4)
    m = 40
    s = _states(rng, m)
    tau = rng.uniform(0, 30, m)
    tau[:2] = 0.0
    a = rng.normal(size=(m, 6, 6))
    P = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(6)
    (C,) = compiled.columns(velocity_covariance(), s.T, tau[None, :],
                            P.transpose(0, 2, 1).reshape(m, 36).T)
    steps = np.array([1e-3, 1e-3, 1e-7, 1e-4, 1e-6, 1e-6])
    for i in range(m):
        M = np.empty((4, 6))
        for j in range(6):
            d = np.zeros(6)
            d[j] = steps[j]
            M[:, j] = (_observed(s[i] + d, tau[i]) - _observed(s[i] - d, tau[i])) / (2 * steps[j])
        ref = M @ P[i] @ M.T
        np.testing.assert_allclose(C[i], ref, rtol=1e-5, atol=1e-6 * np.abs(ref).max())


def test_series_equals_the_full_state_propagation_with_altitude_and_offsets():
    """``A P A^T`` over the whole state (motion, height, one radar's offsets), then the map to
    ``(x, z, vx, vz)``: the block-wise computation of :func:`series` gives the same."""
    rng = np.random.default_rng(9)
    variant = Variant(altitude=True, biases=1)
    n, nx = 12, 11
    t_nodes = np.cumsum(rng.uniform(1, 10, n))
    sol = np.column_stack([_states(rng, n), rng.uniform(3e3, 1e4, n), rng.normal(0, 5, n)])
    a = rng.normal(size=(n, nx, nx))
    cov_nodes = a @ a.transpose(0, 2, 1) + np.eye(nx)
    t = np.sort(rng.uniform(t_nodes[0], t_nodes[-1] + 5, 50))
    out = series(t_nodes, sol, cov_nodes, t, variant)
    k = np.clip(np.searchsorted(t_nodes, t, side="right") - 1, 0, n - 1)
    tau = t - t_nodes[k]
    A = transitions(sol[k], tau, variant)
    P = A @ cov_nodes[k] @ A.transpose(0, 2, 1)
    x, z, phi, v = propagate(*sol[k, :6].T, tau)
    np.testing.assert_allclose(out.z, z, rtol=0, atol=0)
    T = np.zeros((t.size, 4, nx))
    T[:, 0, 0] = T[:, 1, 1] = 1.0
    T[:, 2, 2], T[:, 2, 3] = -v * np.sin(phi), np.cos(phi)
    T[:, 3, 2], T[:, 3, 3] = v * np.cos(phi), np.sin(phi)
    ref = T @ P @ T.transpose(0, 2, 1)
    np.testing.assert_allclose(out.cov, ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out.h_sigma, np.sqrt(P[:, 6, 6]), rtol=1e-12)
    np.testing.assert_allclose(out.x, x, rtol=0, atol=0)
    np.testing.assert_allclose(out.vz, v * np.sin(phi), rtol=0, atol=0)
