"""Growing-memory alpha-beta(-gamma) equals least-squares polynomial fits to all past plots."""

import numpy as np
import pytest

from solver.estimation.alpha_beta import (
    closed_form_gains,
    gain_sequence,
    memory_starts,
    run_alpha_beta,
)
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


@pytest.mark.parametrize("order", [2, 3])
def test_a_long_gap_starts_the_memory_afresh(order):
    """An aircraft flying 150 m/s north holds for 900 s between plots 15 and 16 (10-s scans;
    plots resume where they stopped). With the frozen gains the prediction ran 135 km ahead
    and only alpha of it was corrected (the seed track: 26, 79 and 314 km off after 300, 900
    and 3,600 s); now the memory starts at the plot after the gap: its state is the plot, the
    next is the line through the two, and then the fit of the plots since the gap, as from the
    first plot. A step within ``k_max - 1/2`` median steps keeps the memory."""
    t = 10.0 * np.arange(30)
    t[16:] += 900.0
    y = 60_000 + 150.0 * np.minimum(np.arange(30), 15) * 10.0
    meas = polar(t, y, np.full(30, 20_000.0))
    starts = memory_starts(t, 4)
    assert starts.nonzero()[0].tolist() == [0, 16]
    est = run_alpha_beta(meas, order=order).states
    pts = meas.points()
    np.testing.assert_allclose([est.x[16], est.z[16]], pts[16], atol=1e-6)
    np.testing.assert_allclose(est.vx[17], (pts[17, 0] - pts[16, 0]) / 10.0, atol=1e-9)
    restarted = run_alpha_beta(polar(t[16:] - t[16], y[16:], np.full(14, 20_000.0)),
                               order=order).states
    np.testing.assert_allclose(est.x[16:], restarted.x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(est.vx[16:], restarted.vx, rtol=0, atol=1e-9)
    # a memory of 4 plots (35 s at 10-s scans) keeps 2 missed scans (a 30-s step), not 3
    tt = np.array([0.0, 10, 20, 50, 60, 70, 110, 120])
    assert memory_starts(tt, 4).nonzero()[0].tolist() == [0, 6]
    assert not memory_starts(t, None)[1:].any()  # growing memory: every plot kept


def test_a_split_plot_does_not_become_a_velocity():
    """A noise-free straight track (150 m/s, 10-s scans) with a second plot 19 us before plot
    15, 300 m off: with the frozen gains' ``beta / T`` it became 4e6 m/s and the state went
    20,000 km away; the gains' step is at least half the median step, so the velocity moves by
    at most ``beta / 5 s * 300 m`` = 12 m/s."""
    t = 10.0 * np.arange(30)
    x, z = 60_000 + 150.0 * t, np.full(30, 20_000.0)
    t, x, z = np.insert(t, 15, t[15] - 19e-6), np.insert(x, 15, x[15]), np.insert(z, 15, z[15])
    x[15] += 300.0
    est = run_alpha_beta(polar(t, x, z)).states
    assert np.abs(np.hypot(est.vx, est.vz)[1:] - 150.0).max() < 13.0  # plot 0: unknown
    assert np.hypot(est.x - x, est.z - z).max() < 300.0


def test_bad_parameters():
    meas = polar(np.arange(5.0), 1e4 + np.arange(5.0), np.ones(5))
    with pytest.raises(ValueError):
        run_alpha_beta(meas, order=4)
    with pytest.raises(ValueError):
        run_alpha_beta(meas, order=3, k_max=2)
