"""Fuzzy gain inference against a hand-worked Mamdani example; monotone gain in the innovation."""

from fractions import Fraction

import numpy as np
import pytest

from solver.estimation.fuzzy import FuzzyGain, _memberships


def test_hand_worked_three_terms_triangular():
    """Input terms at 0, 1.5, 3 (crossover 0.5: unit-slope triangles of half-width 1.5); input
    0.375 fires Small 0.75, Medium 0.25, Large 0. Output terms at 0, 0.5, 1 (half-width 0.5).
    The clipped-and-maxed set is 0.75 on [0, 1/8], 1 - 2y on [1/8, 3/8], 1/4 on [3/8, 7/8],
    2 - 2y on [7/8, 1]: area 23/64, first moment 65/512, centroid 65/184."""
    kb = FuzzyGain(3, "triangular", 0.5, u_max=3.0)
    np.testing.assert_allclose(_memberships(np.array(0.375), kb.in_centres, "triangular", 0.5),
                               [0.75, 0.25, 0.0])
    area = Fraction(3, 4) / 8 + Fraction(1, 8) + Fraction(1, 8) + Fraction(1, 64)
    assert area == Fraction(23, 64)
    assert float(kb.centroid(np.array(0.375))) == pytest.approx(65 / 184, abs=1e-12)
    lo, hi = kb.centroid(np.array([0.0, 3.0]))
    assert float(kb(np.array(0.375))) == pytest.approx((65 / 184 - lo) / (hi - lo), abs=1e-12)


def test_hand_worked_crossover_and_gaussian():
    kb = FuzzyGain(5, "gaussian", 0.3, u_max=3.0)
    mu = _memberships(np.array([0.375]), kb.in_centres, "gaussian", 0.3)  # centres 0, .75, ...
    assert mu[0, 0] == pytest.approx(0.3)  # midway between two centres: the crossover level
    assert mu[0, 1] == pytest.approx(0.3)
    # input exactly at the top term saturates: only the largest terms fire, gain near the top
    assert kb(np.array(10.0)) == kb(np.array(3.0))
    assert kb(np.array(3.0)) == 1.0 and kb(np.array(0.0)) == 0.0
    raw = kb.centroid(np.array([0.0, 3.0]))
    assert 0 < raw[0] < 0.2 and 0.8 < raw[1] < 1


@pytest.mark.parametrize("n_terms", [3, 5, 7])
@pytest.mark.parametrize("shape", ["triangular", "gaussian"])
@pytest.mark.parametrize("crossover", [0.3, 0.5, 0.7])
def test_gain_is_monotone_in_innovation(n_terms, shape, crossover):
    kb = FuzzyGain(n_terms, shape, crossover)
    u = np.linspace(0, 4, 801)
    g = kb(u)
    # kinks of the clipped set fall between grid nodes: centroid error up to ~5e-6 on the
    # 401-point grid, so "monotone" is checked to 1e-5 (a wrong rule base fails by O(0.1))
    assert np.all(np.diff(g) >= -1e-5)
    assert np.all(np.diff(kb.centroid(u)) >= -1e-5)
    assert g[0] == 0.0 and g[-1] == 1.0
    assert np.all(np.diff(g[u < 3]) > 0) or shape == "triangular"  # strictly rising (Gaussian)


def test_bad_configuration():
    with pytest.raises(ValueError):
        FuzzyGain(4)
    with pytest.raises(ValueError):
        FuzzyGain(3, "trapezoid")(np.array(1.0))
    with pytest.raises(ValueError):
        FuzzyGain(3, crossover=1.0)


def test_steady_gain_doubling_matches_scipy_dare():
    from scipy.linalg import solve_discrete_are

    from solver.estimation.fuzzy import steady_gain
    from solver.estimation.models import singer

    steps = np.array([0.5, 4.8, 10.0, 19.0, 57.0])
    for sigma in (0.01, 0.3, 5.0):
        Phi, Q = singer(steps, 1 / 20, sigma)
        for R in (50.0**2, 1000.0**2):
            K = steady_gain(Phi, Q, np.full(steps.size, R))
            for i in range(steps.size):
                H = np.array([[1.0, 0.0, 0.0]])
                P = solve_discrete_are(Phi[i].T, H.T, Q[i], np.array([[R]]))
                ref = (P @ H.T / (H @ P @ H.T + R)).ravel()
                np.testing.assert_allclose(K[i], ref, rtol=1e-7, atol=1e-12)
