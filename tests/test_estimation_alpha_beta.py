"""Growing-memory alpha-beta(-gamma) equals least-squares polynomial fits to all past plots."""

import numpy as np
import pytest

from solver.estimation.alpha_beta import closed_form_gains, gain_sequence, run_alpha_beta
from solver.estimation.measurements import PolarPlots


def polar(t, x, z):
    return PolarPlots(t=t, d=np.hypot(x, z), sigma_d=np.full(t.size, 100.0),
                      psi=np.unwrap(np.arctan2(z, x)), sigma_psi=0.002)


@pytest.mark.parametrize("order", [2, 3])
def test_growing_memory_equals_least_squares_fit(order):
    rng = np.random.default_rng(4)
    n = 40
    t = np.cumsum(rng.choice([4.8, 4.8, 9.6, 14.4], n)) + rng.uniform(-0.3, 0.3, n)
    x = 50_000 + 90 * t + 0.02 * t**2 + rng.normal(0, 300, n)
    z = -30_000 + 40 * t + rng.normal(0, 300, n)
    meas = polar(t, x, z)
    est = run_alpha_beta(meas, order=order, k_max=None).states
    pts = meas.points()
    for k in range(order - 1, n):
        tau = t[: k + 1] - t[k]
        for axis, (pos, vel) in enumerate([(est.x, est.vx), (est.z, est.vz)]):
            c = np.polynomial.polynomial.polyfit(tau, pts[: k + 1, axis], order - 1)
            assert abs(pos[k] - c[0]) <= 1e-9 * abs(c[0]) + 1e-6
            assert abs(vel[k] - c[1]) <= 1e-9 * max(abs(c[1]), 1.0) + 1e-8


@pytest.mark.parametrize("order", [2, 3])
def test_constant_step_gains_equal_closed_forms(order):
    T = 4.8
    t = T * np.arange(30)
    K = gain_sequence(t, order, k_max=None)
    ks = np.arange(order - 1, 30)  # from the first exact fit on
    ref = closed_form_gains(ks, order)
    scale = np.array([1.0, T, T * T / 2][:order])
    np.testing.assert_allclose(K[ks] * scale, ref, rtol=1e-9)


def test_memory_cap_holds_the_gains():
    t = 10.0 * np.arange(20)
    K = gain_sequence(t, 2, k_max=6)
    np.testing.assert_allclose(K[6:] * [1, 10.0], np.tile(closed_form_gains(6), (14, 1)))
    np.testing.assert_allclose(K[5] * [1, 10.0], closed_form_gains(5), rtol=1e-9)
    # a capped filter follows a turn that the growing-memory one lags behind
    tt = 5.0 * np.arange(80)
    w = np.where(tt > 200, 0.03, 0.0)
    heading = np.cumsum(w * 5.0)
    x = 60_000 + np.cumsum(150 * np.cos(heading) * 5.0)
    z = 10_000 + np.cumsum(150 * np.sin(heading) * 5.0)
    meas = polar(tt, x, z)
    capped = run_alpha_beta(meas, k_max=6).states
    grown = run_alpha_beta(meas, k_max=None).states
    e_cap = np.hypot(capped.x - x, capped.z - z)[-20:].mean()
    e_grow = np.hypot(grown.x - x, grown.z - z)[-20:].mean()
    assert e_cap < 0.2 * e_grow


def test_bad_parameters():
    meas = polar(np.arange(5.0), 1e4 + np.arange(5.0), np.ones(5))
    with pytest.raises(ValueError):
        run_alpha_beta(meas, order=4)
    with pytest.raises(ValueError):
        run_alpha_beta(meas, order=3, k_max=2)
