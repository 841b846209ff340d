"""Motion models and Kalman pieces against independent references (matrix exponential, quadrature,
discrete ARE, ODE integration, finite differences)."""

import numpy as np
import pytest
from scipy.integrate import quad_vec, solve_ivp
from scipy.linalg import expm, solve_discrete_are

from solver.estimation.discretize import taylor, van_loan
from solver.estimation.kalman import predict, update
from solver.estimation.models import (
    ct_predict,
    cv,
    quasi_optimal,
    quasi_optimal_F,
    singer,
    singer_F,
    singer_transition,
)

STEPS = np.array([1e-6, 1e-3, 0.1, 1.0, 4.8, 10.0, 19.0, 60.0])


def brute_noise(F, G, qc, T):
    """``int_0^T e^{Fs} G qc G^T e^{F^T s} ds`` by adaptive quadrature."""
    G = G.reshape(-1, 1)

    def f(s):
        E = expm(F * s)
        return E @ G @ G.T @ E.T * qc

    return quad_vec(f, 0.0, T, epsabs=0, epsrel=1e-12)[0]


@pytest.mark.parametrize("alpha", [1e-6, 1 / 60, 1 / 20, 1.0, 5.0])
def test_singer_transition_equals_matrix_exponential(alpha):
    Phi = singer_transition(STEPS, alpha)
    for T, P in zip(STEPS, Phi, strict=True):
        ref = expm(singer_F(alpha) * T)
        np.testing.assert_allclose(P, ref, rtol=1e-12, atol=1e-15 * max(1.0, T * T))


@pytest.mark.parametrize("alpha", [1e-4, 1 / 20, 1.0])
def test_singer_noise_equals_quadrature(alpha):
    sigma_m = 2.0
    _, Q = singer(STEPS, alpha, sigma_m)
    for T, Qk in zip(STEPS, Q, strict=True):
        ref = brute_noise(singer_F(alpha), np.array([0.0, 0.0, 1.0]), 2 * alpha * sigma_m**2, T)
        scale = np.sqrt(np.outer(np.diag(ref), np.diag(ref)))
        assert np.all(np.abs(Qk - ref) <= 1e-9 * scale + 1e-300)
        assert np.all(np.linalg.eigvalsh(Qk) >= -1e-12 * np.max(np.abs(Qk)))


def test_singer_noise_small_step_series():
    """For ``alpha T -> 0`` Q tends to the white-jerk closed form ``q [T^5/20, T^4/8, T^3/6; ...]``;
    the expanded Singer closed form loses every digit there, Van Loan must not."""
    alpha, sigma_m, T = 1e-3, 1.0, np.array([1e-2])
    q = 2 * alpha * sigma_m**2
    _, Q = singer(T, alpha, sigma_m)
    t = T[0]
    ref = q * np.array([[t**5 / 20, t**4 / 8, t**3 / 6], [t**4 / 8, t**3 / 3, t**2 / 2],
                        [t**3 / 6, t**2 / 2, t]])
    np.testing.assert_allclose(Q[0], ref, rtol=1e-4)


def test_quasi_optimal_exact_and_taylor():
    lam, alpha, sm = 0.01, 0.01, 2000.0
    F = quasi_optimal_F(lam, alpha)
    Phi, Q = quasi_optimal(STEPS, lam, alpha, sm, "exact")
    for T, P, Qk in zip(STEPS, Phi, Q, strict=True):
        np.testing.assert_allclose(P, expm(F * T), rtol=1e-11, atol=1e-11)
        ref = brute_noise(F, np.array([0.0, 0.0, 1.0]), 2 * alpha * sm**2, T)
        np.testing.assert_allclose(Qk, ref, rtol=1e-8, atol=1e-12 * np.max(np.abs(ref)))
    # the paper's Taylor transition is second order: error ~ T^3
    Pt, Qt = quasi_optimal(np.array([0.1, 0.2]), lam, alpha, sm, "taylor")
    Pe, Qe = quasi_optimal(np.array([0.1, 0.2]), lam, alpha, sm, "exact")
    e = [np.max(np.abs(Pt[i] - Pe[i])) for i in range(2)]
    assert 6 < e[1] / e[0] < 10
    # ... and its noise agrees with the exact one to leading order
    np.testing.assert_allclose(Qt[0][2, 2], Qe[0][2, 2], rtol=0.05)
    with pytest.raises(ValueError):
        quasi_optimal(STEPS, lam, alpha, sm, "euler")


def test_cv_equals_van_loan():
    F = np.array([[0.0, 1.0], [0.0, 0.0]])
    P1, Q1 = cv(STEPS, 3.0)
    P2, Q2 = van_loan(F, np.array([0.0, 1.0]), 3.0, STEPS)
    np.testing.assert_allclose(P1, P2, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(Q1, Q2, rtol=1e-9, atol=1e-20)
    Pt, _ = taylor(F, np.array([0.0, 1.0]), 3.0, STEPS)
    np.testing.assert_allclose(Pt, P1, atol=1e-12)  # exact for a nilpotent F


@pytest.mark.parametrize("T", [1.0, 10.0])
def test_singer_steady_state_gain_matches_dare(T):
    alpha, sigma_m, R = 1 / 20, 2.0, 400.0**2
    Phi, Q = singer(np.array([T]), alpha, sigma_m)
    Phi, Q = Phi[0], Q[0]
    H = np.array([[1.0, 0.0, 0.0]])
    x, P = np.zeros(3), np.diag([R, 300.0**2, sigma_m**2])
    for _ in range(2000):
        x, P = predict(x, P, Phi, Q)
        K = P @ H.T / (H @ P @ H.T + R)
        x, P, _, _ = update(x, P, np.zeros(1), H, np.array([[R]]))
    Pss = solve_discrete_are(Phi.T, H.T, Q, np.array([[R]]))
    Kss = Pss @ H.T / (H @ Pss @ H.T + R)
    np.testing.assert_allclose(K, Kss, rtol=1e-8)


@pytest.mark.parametrize("omega", [0.0, 1e-9, 1e-5, 0.02, -0.05])
def test_coordinated_turn_against_ode_and_finite_differences(omega):
    x0 = np.array([1000.0, -2000.0, 120.0, -40.0, omega])
    T = 12.0

    def rhs(_, s):
        return [s[2], s[3], -s[4] * s[3], s[4] * s[2], 0.0]

    ref = solve_ivp(rhs, (0, T), x0, rtol=1e-12, atol=1e-10, method="DOP853").y[:, -1]
    fx, J = ct_predict(x0, T)
    np.testing.assert_allclose(fx, ref, rtol=1e-10, atol=1e-7)
    num = np.empty((5, 5))
    for j in range(5):
        h = 1e-6 * max(1.0, abs(x0[j])) if j < 4 else 1e-7
        e = np.zeros(5)
        e[j] = h
        num[:, j] = (ct_predict(x0 + e, T)[0] - ct_predict(x0 - e, T)[0]) / (2 * h)
    np.testing.assert_allclose(J, num, rtol=1e-6, atol=1e-6)


def test_cv_smoothed_means_equal_the_recursive_rts_smoother():
    """The banded batch solve (flat prior) against a dense least-squares solve of the whitened
    residuals and against the Kalman filter + RTS recursion with a nearly flat prior (1e7 m
    standard deviation: its first updates lose millimetres to rounding), on irregular steps and
    rotated, elongated measurement ellipses."""
    from solver.estimation.cv_rts import smoothed_means
    from solver.estimation.kalman import rts_smoother
    from solver.estimation.models import two_axes

    rng = np.random.default_rng(11)
    n, q = 60, 30.0
    t = np.cumsum(np.concatenate([[0.0], rng.choice([4.8, 9.6, 19.0, 0.5], n - 1)]))
    centre = np.column_stack([np.linspace(4e4, 9e4, n), np.linspace(-2e4, 3e4, n)])
    centre += rng.normal(0, 300, (n, 2))
    ang = rng.uniform(0, np.pi, n)
    rot = np.stack([np.stack([np.cos(ang), -np.sin(ang)], -1),
                    np.stack([np.sin(ang), np.cos(ang)], -1)], -2)
    R = rot @ (np.eye(2) * np.array([[100.0**2], [900.0**2]])) @ rot.transpose(0, 2, 1)
    got = smoothed_means(t, centre, np.linalg.inv(R), q)

    Phi, Q = cv(np.diff(t), q)
    Phi, Q = two_axes(Phi), two_axes(Q)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    x, P = np.zeros(4), np.eye(4) * 1e14
    xf, Pf, xp, Pp = np.empty((n, 4)), np.empty((n, 4, 4)), np.empty((n, 4)), np.empty((n, 4, 4))
    for k in range(n):
        if k:
            x, P = predict(x, P, Phi[k - 1], Q[k - 1])
        xp[k], Pp[k] = x, P
        x, P, _, _ = update(x, P, centre[k] - H @ x, H, R[k])
        xf[k], Pf[k] = x, P
    xs, _ = rts_smoother(xf, Pf, xp, Pp, Phi)
    np.testing.assert_allclose(got, xs[:, [0, 2, 1, 3]], rtol=0, atol=0.02)

    rows, rhs = [], []
    for k in range(n):
        Lm = np.linalg.cholesky(np.linalg.inv(R[k])).T  # Lm^T Lm = R^-1
        A = np.zeros((2, 4 * n))
        A[:, 4 * k: 4 * k + 4] = Lm @ H
        rows.append(A)
        rhs.append(Lm @ centre[k])
    for k in range(n - 1):
        Lq = np.linalg.cholesky(np.linalg.inv(Q[k])).T
        A = np.zeros((4, 4 * n))
        A[:, 4 * k: 4 * k + 4] = -Lq @ Phi[k]
        A[:, 4 * k + 4: 4 * k + 8] = Lq
        rows.append(A)
        rhs.append(np.zeros(4))
    ls = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0].reshape(n, 4)
    np.testing.assert_allclose(got, ls[:, [0, 2, 1, 3]], rtol=0, atol=1e-6)


@pytest.mark.parametrize("m", [1, 2, 3])
def test_covariance_update_equals_the_full_update_and_the_information_form(m):
    """The covariance-only Joseph update against :func:`update` and against the information
    form ``(P^-1 + H^T R^-1 H)^-1``, for one, two (closed-form ``S^-1``) and three measured
    components."""
    from solver.estimation.kalman import covariance_update

    rng = np.random.default_rng(m)
    A = rng.normal(size=(6, 6))
    P = A @ A.T + np.eye(6)
    H = rng.normal(size=(m, 6))
    B = rng.normal(size=(m, m))
    R = B @ B.T + 0.5 * np.eye(m)
    got = covariance_update(P, H, R)
    np.testing.assert_allclose(got, update(np.zeros(6), P, np.zeros(m), H, R)[1], rtol=1e-12,
                               atol=1e-12)
    info = np.linalg.inv(np.linalg.inv(P) + H.T @ np.linalg.solve(R, H))
    np.testing.assert_allclose(got, info, rtol=1e-9, atol=1e-10)
