"""Closed-form motion (numpy and CasADi) against a high-accuracy ODE integration."""

from __future__ import annotations

import itertools

import casadi as ca
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from solver.motion import motion_function, propagate, propagate_ca

U_GRID = [0.0, 1e-9, -1e-9, 1e-4, -1e-4, 7.0, -7.0]
W_GRID = [0.0, 1e-9, -1e-9, 1e-4, -1e-4, 3.0, -2.0]
# (x0, z0, phi0, v0): origin, a shifted start with nonzero heading, a slow start
STARTS = [(0.0, 0.0, 0.0, 200.0), (-35_000.0, 120_000.0, 2.4, 330.0),
          (5_000.0, -8_000.0, -1.1, 150.0)]
T_END = 60.0
TIMES = np.array([0.5, 7.0, 19.0, 38.0, T_END])


def _grid() -> np.ndarray:
    """Rows ``(x0, z0, phi0, v0, u, w)``; the speed stays >= 30 m/s over 60 s."""
    rows = [(*s, u, w) for s, u, w in itertools.product(STARTS, U_GRID, W_GRID)]
    return np.array([r for r in rows if r[3] + r[5] * T_END >= 30.0])


def _reference(grid: np.ndarray) -> np.ndarray:
    """All cases integrated as one ODE system by DOP853 at rtol 1e-12: ``(len(TIMES), n, 4)``."""
    n = grid.shape[0]
    u, w = grid[:, 4], grid[:, 5]

    def rhs(_t, y):
        _, _, phi, v = y.reshape(4, n)
        return np.concatenate([v * np.cos(phi), v * np.sin(phi), u / v, w])

    y0 = grid[:, :4].T.ravel()
    sol = solve_ivp(rhs, (0.0, T_END), y0, method="DOP853", t_eval=TIMES, rtol=1e-12,
                    atol=1e-9)
    assert sol.success
    return sol.y.reshape(4, n, len(TIMES)).transpose(2, 1, 0)


@pytest.fixture(scope="module")
def cases() -> tuple[np.ndarray, np.ndarray]:
    grid = _grid()
    return grid, _reference(grid)


def test_grid_covers_degenerate_cases(cases):
    grid, _ = cases
    for u, w in [(0.0, 0.0), (1e-9, -1e-9), (0.0, 1e-4), (-1e-4, 0.0), (7.0, 3.0), (-7.0, -2.0)]:
        assert np.any((grid[:, 4] == u) & (grid[:, 5] == w))


def test_numpy_closed_form_matches_ode(cases):
    grid, ref = cases
    for k, t in enumerate(TIMES):
        x, z, phi, v = propagate(*grid[:, :4].T, grid[:, 4], grid[:, 5], t)
        pos_err = np.hypot(x - ref[k, :, 0], z - ref[k, :, 1])
        assert pos_err.max() < 1e-3, grid[np.argmax(pos_err)]
        assert np.abs(phi - ref[k, :, 2]).max() < 1e-9
        assert np.abs(v - ref[k, :, 3]).max() < 1e-9


def test_casadi_closed_form_matches_ode(cases):
    grid, ref = cases
    f = motion_function().map(grid.shape[0])
    for k, t in enumerate(TIMES):
        out = np.asarray(f(grid[:, :4].T, grid[:, 4], grid[:, 5], t)).T
        pos_err = np.hypot(out[:, 0] - ref[k, :, 0], out[:, 1] - ref[k, :, 1])
        assert pos_err.max() < 1e-3, grid[np.argmax(pos_err)]
        assert np.abs(out[:, 2:] - ref[k, :, 2:]).max() < 1e-9


def test_casadi_gradient_is_finite_and_right_at_degenerate_points():
    """The window NLP differentiates through the series branches: compare the CasADi Jacobian in
    ``(u, w)`` with central differences of the numpy closed form."""
    s, uw, t = ca.SX.sym("s", 4), ca.SX.sym("uw", 2), ca.SX.sym("t")
    pos = propagate_ca(s, uw[0], uw[1], t)[:2]
    jac = ca.Function("j", [s, uw, t], [ca.jacobian(pos, uw)])
    start = np.array([1000.0, -2000.0, 0.7, 180.0])
    for u, w in [(0.0, 0.0), (1e-9, 0.0), (0.0, -1e-9), (1e-4, 1e-4), (-3.0, 0.0), (0.0, 2.0)]:
        j = np.asarray(jac(start, [u, w], 40.0))
        assert np.all(np.isfinite(j))
        h = 1e-3
        for col, (du, dw) in enumerate([(h, 0.0), (0.0, h)]):
            xp, zp, _, _ = propagate(*start, u + du, w + dw, 40.0)
            xm, zm, _, _ = propagate(*start, u - du, w - dw, 40.0)
            fd = np.array([xp - xm, zp - zm]) / (2 * h)
            assert np.allclose(j[:, col], fd, rtol=1e-5, atol=1e-4), (u, w, col)


def test_zero_controls_fly_straight():
    x, z, phi, v = propagate(100.0, 200.0, np.pi / 2, 250.0, 0.0, 0.0, 10.0)
    assert np.allclose([x, z, phi, v], [100.0, 2700.0, np.pi / 2, 250.0], atol=1e-9)


def test_identities_of_the_closed_form():
    """Spec section 2: ``u x + 2 w z = v^2 sin phi`` and ``2 w x - u z + v0^2 = v^2 cos phi``."""
    rng = np.random.default_rng(3)
    u, w = rng.uniform(-7, 7, 50), rng.uniform(-2, 3, 50)
    v0, t = rng.uniform(150, 300, 50), rng.uniform(1, 60, 50)
    x, z, phi, v = propagate(0.0, 0.0, 0.0, v0, u, w, t)
    assert np.allclose(u * x + 2 * w * z, v**2 * np.sin(phi), rtol=1e-9, atol=1e-3)
    assert np.allclose(2 * w * x - u * z + v0**2, v**2 * np.cos(phi), rtol=1e-9, atol=1e-3)
