"""The window NLP, its analytic initial guess and the free-start-time (switch) NLP."""

from __future__ import annotations

import numpy as np
import pytest

import solver.window as window
from solver.geometry import weight_entries
from solver.guess import initial_guess, point_transfer
from solver.inputs import Bounds
from solver.motion import propagate
from solver.window import criterion, solve_free_start, solve_switches, solve_windows, w_box

BOUNDS = Bounds()


def _random_windows(n: int, m: int, noise: float, seed: int):
    """``n`` windows of ``m`` plots flown with random in-bounds controls, centres with Gaussian
    noise, R2 weights of a 500 m / 1.5 deg radar."""
    rng = np.random.default_rng(seed)
    start = np.column_stack([rng.uniform(-1e5, 1e5, n), rng.uniform(-1e5, 1e5, n),
                             rng.uniform(0, 2 * np.pi, n), rng.uniform(120, 300, n)])
    t = np.cumsum(rng.uniform(5, 25, (n, m)), axis=1)
    u = rng.uniform(-7, 7, n)
    w = np.clip(rng.uniform(-2, 3, n), (40 - start[:, 3]) / t[:, -1],
                (320 - start[:, 3]) / t[:, -1])
    x, z, _, _ = propagate(start[:, 0:1], start[:, 1:2], start[:, 2:3], start[:, 3:4],
                           u[:, None], w[:, None], t)
    cx, cz = x + noise * rng.standard_normal(x.shape), z + noise * rng.standard_normal(x.shape)
    psi = np.arctan2(cz, cx)
    abc = weight_entries(psi.ravel(), np.deg2rad(1.5) * np.hypot(cx, cz).ravel(),
                         np.full(n * m, 500.0)).reshape(n, m, 3)
    return start, t, cx, cz, abc, u, w


def _solve(start, t, cx, cz, abc, plugin="sqpmethod"):
    lbw, ubw, _ = w_box(start[:, 3], t[:, -1], BOUNDS)
    guess, _ = initial_guess(start, t, cx, cz, abc, BOUNDS.u, lbw, ubw)
    return solve_windows(start, t, cx, cz, abc, guess, lbw, ubw, BOUNDS, plugin), lbw, ubw


def test_noise_free_window_recovers_controls():
    start, t, cx, cz, abc, u, w = _random_windows(40, 3, 0.0, seed=1)
    fits, _, _ = _solve(start, t, cx, cz, abc)
    assert not fits.failed.any()
    assert np.abs(fits.u - u).max() < 1e-5
    assert np.abs(fits.w - w).max() < 1e-5
    assert fits.value.max() < 1e-10


@pytest.mark.parametrize("m", [3, 5])
def test_nlp_matches_brute_force_grid(m):
    """On noisy windows the NLP value is never above the minimum over a fine (u, w) grid of the
    feasible box (plus the grid's own resolution), and the point is feasible."""
    start, t, cx, cz, abc, _, _ = _random_windows(12, m, 400.0, seed=m)
    fits, lbw, ubw = _solve(start, t, cx, cz, abc)
    gu = np.linspace(BOUNDS.u[0], BOUNDS.u[1], 281)
    for k in range(len(t)):
        gw = np.linspace(lbw[k], ubw[k], 201)
        uu, ww = np.meshgrid(gu, gw)
        vals = criterion(np.broadcast_to(start[k], (*uu.shape, 4)), uu, ww, t[k], cx[k], cz[k],
                         abc[k])
        assert fits.value[k] <= vals.min() * (1 + 1e-9) + 1e-12, k
        assert BOUNDS.u[0] <= fits.u[k] <= BOUNDS.u[1]
        assert lbw[k] <= fits.w[k] <= ubw[k]
        v_end = start[k, 3] + fits.w[k] * t[k, -1]
        assert BOUNDS.v[0] - 1e-9 <= v_end <= BOUNDS.v[1] + 1e-9


def test_ipopt_agrees_with_sqpmethod():
    start, t, cx, cz, abc, _, _ = _random_windows(10, 4, 400.0, seed=7)
    sqp, _, _ = _solve(start, t, cx, cz, abc, "sqpmethod")
    ipo, _, _ = _solve(start, t, cx, cz, abc, "ipopt")
    assert np.allclose(sqp.value, ipo.value, rtol=1e-7, atol=1e-12)


def test_speed_bound_folded_into_w_box():
    v0 = np.array([35.0, 200.0, 325.0, 20.0, 400.0, 20.0])
    t_end = np.array([50.0, 50.0, 50.0, 50.0, 50.0, 2.0])
    lbw, ubw, flagged = w_box(v0, t_end, BOUNDS)
    assert np.allclose(lbw, [-0.1, -2.0, -2.0, 0.2, -2.0, 3.0])
    assert np.allclose(ubw, [3.0, 2.6, 0.1, 3.0, -1.4, 3.0])
    # starts outside the speed bounds are flagged; an unreachable bound pins w to its limit
    assert list(flagged) == [False, False, False, True, True, True]


def test_speed_bound_is_active_when_data_ask_for_more():
    """Plots that run away faster than v_max: the fit sits on the folded speed bound."""
    start = np.array([[0.0, 0.0, 0.0, 300.0]])
    t = np.array([[19.0, 38.0, 57.0]])
    cx, cz = 400.0 * t, np.zeros_like(t)
    abc = np.tile([1e-6, 0.0, 1e-6], (1, 3, 1))
    fits, _, ubw = _solve(start, t, cx, cz, abc)
    assert fits.w[0] == pytest.approx(ubw[0], abs=1e-9)
    assert start[0, 3] + fits.w[0] * t[0, -1] == pytest.approx(BOUNDS.v[1], abs=1e-6)


def test_point_transfer_lands_on_reachable_points():
    """Moderate manoeuvres (heading change below 90 deg): after the Newton step the guessed
    controls carry the start to within 1% of the distance of the target."""
    rng = np.random.default_rng(5)
    n = 500
    v0, t = rng.uniform(100, 300, n), rng.uniform(5, 60, n)
    u, w = rng.uniform(-7, 7, n), rng.uniform(-2, 3, n)
    keep = (np.abs(u) * t / v0 < np.pi / 2) & (v0 + w * t > 40)
    v0, t, u, w = v0[keep], t[keep], u[keep], w[keep]
    x, z, _, _ = propagate(0.0, 0.0, 0.0, v0, u, w, t)
    gu, gw = point_transfer(x, z, t, v0, BOUNDS.u, np.full(x.shape, -2.0), np.full(x.shape, 3.0))
    ex, ez, _, _ = propagate(0.0, 0.0, 0.0, v0, gu, gw, t)
    assert np.all(np.hypot(ex - x, ez - z) <= 0.01 * np.hypot(x, z))
    assert np.all((gu >= -7) & (gu <= 7) & (gw >= -2) & (gw <= 3))


class _FailingBatch:
    """Stands in for a mapped CasADi solver that returns garbage."""

    def __call__(self, **kwargs):
        return {"x": np.full(np.shape(kwargs["x0"]), np.nan)}


def test_solver_failure_falls_back_to_the_guess(monkeypatch):
    start, t, cx, cz, abc, _, _ = _random_windows(5, 3, 300.0, seed=3)
    lbw, ubw, _ = w_box(start[:, 3], t[:, -1], BOUNDS)
    guess, gval = initial_guess(start, t, cx, cz, abc, BOUNDS.u, lbw, ubw)
    monkeypatch.setattr(window, "window_batch", lambda m, plugin, n: _FailingBatch())
    fits = solve_windows(start, t, cx, cz, abc, guess, lbw, ubw, BOUNDS)
    assert fits.failed.all() and fits.fallback.all()
    assert np.allclose(np.column_stack([fits.u, fits.w]), guess)
    assert np.allclose(fits.value, gval)


def test_non_stationary_point_counts_as_failure(monkeypatch):
    """A solver that stops early (here: returns its starting point) is caught by the
    projected-gradient check even though its point is usable; the guess is kept."""

    class Idle:
        def __call__(self, **kwargs):
            return {"x": np.asarray(kwargs["x0"])}

    start, t, cx, cz, abc, _, _ = _random_windows(6, 3, 300.0, seed=4)
    lbw, ubw, _ = w_box(start[:, 3], t[:, -1], BOUNDS)
    guess, _ = initial_guess(start, t, cx, cz, abc, BOUNDS.u, lbw, ubw)
    monkeypatch.setattr(window, "window_batch", lambda m, plugin, n: Idle())
    fits = solve_windows(start, t, cx, cz, abc, guess, lbw, ubw, BOUNDS)
    assert fits.failed.all()
    assert np.allclose(np.column_stack([fits.u, fits.w]), guess)


def test_switch_nlp_finds_the_switch_time():
    """Straight flight until t = 23.4 s, then a turn: starting the trial at 19 s (a plot time),
    the free start time moves to the switch and the fit becomes exact."""
    cur = np.array([10_000.0, 50_000.0, 0.3, 200.0])
    cur_uw = np.array([0.0, 0.0])
    switch = 23.4
    s = np.array(propagate(*cur, 0.0, 0.0, switch))
    t = np.array([38.0, 57.0, 76.0])  # relative to the current start
    x, z, _, _ = propagate(*s, 4.0, -0.5, t - switch)
    abc = weight_entries(np.arctan2(z, x), np.full(3, 1500.0), np.full(3, 500.0))
    fits = solve_switches(cur, cur_uw, t[None], x[None], z[None], abc[None],
                          np.array([[3.0, 0.0, 19.0]]), np.array([[19.0, 37.999]]), BOUNDS)
    assert not fits.failed[0]
    assert fits.tau[0] == pytest.approx(switch, abs=1e-4)
    assert fits.u[0] == pytest.approx(4.0, abs=1e-4) and fits.w[0] == pytest.approx(-0.5, abs=1e-4)
    assert fits.value[0] < 1e-12


def test_free_start_nlp_recovers_the_start_state():
    """Six noise-free plots of a turning, accelerating flight; the reference start is 800 m and
    0.2 rad off with a wrong speed: the free-start NLP recovers state and controls."""
    true = np.array([40_000.0, -70_000.0, 2.0, 180.0])
    t = 19.0 * np.arange(6)
    x, z, _, _ = propagate(*true, 2.5, 0.4, t)
    abc = weight_entries(np.arctan2(z, x), np.full(6, 1500.0), np.full(6, 500.0))
    ref = true + np.array([600.0, -530.0, 0.2, -40.0])
    fit = solve_free_start(ref, np.array([0.0, 0.0]), t, x, z, abc, BOUNDS)
    assert not fit.failed and fit.value < 1e-12
    assert np.allclose(fit.start, true, rtol=0, atol=[1e-3, 1e-3, 1e-8, 1e-6])
    assert fit.u == pytest.approx(2.5, abs=1e-6) and fit.w == pytest.approx(0.4, abs=1e-6)
