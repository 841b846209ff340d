"""solver.estimation.covariance_pass: the chained CasADi covariance recursions against numpy
loops of the same equations, against the batch least-squares posterior (independent of any
Kalman code), across chain-size boundaries, with consider states and deadline checks."""

from __future__ import annotations

import numpy as np
import pytest

from solver.estimation.covariance_pass import (
    CHUNK_SIZES,
    filtered_covariances,
    smoothed_covariances,
)
from solver.estimation.kalman import rts_smoother, update


def _spd(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return scale * (a @ a.T + n * np.eye(n))


def _problem(rng: np.random.Generator, n: int, nx: int, m: int = 2, share: float = 0.7):
    Phi = np.eye(nx) + 0.2 * rng.normal(size=(n, nx, nx))
    Q = np.stack([_spd(rng, nx, 0.05) for _ in range(n)])
    H = rng.normal(size=(n, m, nx))
    R = np.stack([_spd(rng, m, 0.5) for _ in range(n)])
    measured = rng.random(n) < share
    return _spd(rng, nx, 3.0), Phi, Q, H, R, measured


def _loop(P0, Phi, Q, updates):
    """Reference: a Python loop, Joseph form with the masked gain written out."""
    n, nx = Phi.shape[0], P0.shape[0]
    Pp, Pf = np.empty((n, nx, nx)), np.empty((n, nx, nx))
    P = P0
    for k in range(n):
        if k:
            P = Phi[k - 1] @ P @ Phi[k - 1].T + Q[k - 1]
        Pp[k] = P
        for H, R, gain in updates:
            if not gain[k].any():
                continue
            S = H[k] @ P @ H[k].T + R[k]
            K = gain[k][:, None] * (P @ H[k].T @ np.linalg.inv(S))
            IKH = np.eye(nx) - K @ H[k]
            P = IKH @ P @ IKH.T + K @ R[k] @ K.T
        Pf[k] = P
    return Pp, Pf



class _Stop(Exception):
    pass


def _stop_at(k: int, calls: list[int]):
    """A ``check`` that counts its calls in ``calls`` and raises :class:`_Stop` at the k-th."""
    def check() -> None:
        calls.append(1)
        if len(calls) == k:
            raise _Stop
    return check

@pytest.mark.parametrize("n", [1, 2, 15, 16, 17, 300, 1100])
def test_filter_matches_the_loop_across_chain_sizes(n):
    rng = np.random.default_rng(n)
    nx = 6
    P0, Phi, Q, H, R, measured = _problem(rng, n, nx)
    gain = np.where(measured[:, None], 1.0, 0.0) * np.ones(nx)
    gain[n // 2:, 4:] *= 0.0  # consider states in the second half
    h2 = np.zeros((n, 1, nx))
    h2[:, 0, 3] = 1.0
    r2 = rng.uniform(0.5, 2.0, size=(n, 1, 1))
    g2 = (rng.random(n) < 0.3)[:, None] * np.ones(nx)
    updates = ((H, R, gain), (h2, r2, g2))
    Pp, Pf = filtered_covariances(P0, Phi, Q, updates, check_every=256)
    Pp_ref, Pf_ref = _loop(P0, Phi, Q, updates)
    np.testing.assert_allclose(Pp, Pp_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(Pf, Pf_ref, rtol=1e-9, atol=1e-9)


def test_one_update_equals_the_full_kalman_update():
    rng = np.random.default_rng(7)
    n, nx = 40, 4
    P0, Phi, Q, H, R, measured = _problem(rng, n, nx)
    gain = measured[:, None] * np.ones(nx)
    _, Pf = filtered_covariances(P0, Phi, Q, ((H, R, gain),))
    P = P0
    for k in range(n):
        if k:
            P = Phi[k - 1] @ P @ Phi[k - 1].T + Q[k - 1]
        if measured[k]:
            _, P, _, _ = update(np.zeros(nx), P, np.zeros(2), H[k], R[k])
        np.testing.assert_allclose(Pf[k], P, rtol=1e-10, atol=1e-10)


def test_a_step_without_measurement_leaves_the_covariance_exactly():
    rng = np.random.default_rng(3)
    n, nx = 20, 6
    P0, Phi, Q, H, R, measured = _problem(rng, n, nx, share=0.5)
    H[~measured] = np.nan  # never read where there is no measurement
    R[~measured] = np.nan
    gain = measured[:, None] * np.ones(nx)
    Pp, Pf = filtered_covariances(P0, Phi, Q, ((H, R, gain),))
    assert np.all(np.isfinite(Pf))
    assert np.array_equal(Pf[~measured], Pp[~measured])


def test_smoother_matches_rts_smoother():
    rng = np.random.default_rng(11)
    for n in (1, 2, 17, 700):
        nx = 6
        P0, Phi, Q, H, R, measured = _problem(rng, n, nx)
        Pp, Pf = filtered_covariances(P0, Phi, Q, ((H, R, measured[:, None] * np.ones(nx)),))
        Ps = smoothed_covariances(Pf, Pp, Phi)
        _, Ps_ref = rts_smoother(np.zeros((n, nx)), Pf, np.zeros((n, nx)), Pp, Phi)
        np.testing.assert_allclose(Ps, Ps_ref, rtol=1e-9, atol=1e-9)


def test_smoothed_covariance_is_the_batch_posterior():
    """Linear Gaussian chain: the smoothed covariances are the diagonal blocks of the inverse of
    the joint information matrix of all states (prior, process and measurement terms)."""
    rng = np.random.default_rng(5)
    n, nx = 9, 3
    P0, Phi, Q, H, R, measured = _problem(rng, n, nx, share=0.6)
    J = np.zeros((n * nx, n * nx))
    J[:nx, :nx] += np.linalg.inv(P0)
    for k in range(n - 1):  # x_{k+1} - Phi_k x_k ~ N(0, Q_k)
        D = np.zeros((nx, n * nx))
        D[:, k * nx:(k + 1) * nx] = -Phi[k]
        D[:, (k + 1) * nx:(k + 2) * nx] = np.eye(nx)
        J += D.T @ np.linalg.inv(Q[k]) @ D
    for k in np.flatnonzero(measured):
        sl = slice(k * nx, (k + 1) * nx)
        J[sl, sl] += H[k].T @ np.linalg.inv(R[k]) @ H[k]
    cov = np.linalg.inv(J)
    Pp, Pf = filtered_covariances(P0, Phi, Q, ((H, R, measured[:, None] * np.ones(nx)),))
    Ps = smoothed_covariances(Pf, Pp, Phi)
    for k in range(n):
        np.testing.assert_allclose(Ps[k], cov[k * nx:(k + 1) * nx, k * nx:(k + 1) * nx],
                                   rtol=1e-8, atol=1e-10)
    # and the filtered covariance at the last step is the posterior there too
    np.testing.assert_allclose(Pf[-1], cov[-nx:, -nx:], rtol=1e-8, atol=1e-10)


def test_check_is_called_before_every_block_of_steps():
    rng = np.random.default_rng(2)
    n, nx = 1100, 4
    P0, Phi, Q, H, R, measured = _problem(rng, n, nx)
    calls: list[int] = []
    filtered_covariances(P0, Phi, Q, ((H, R, measured[:, None] * np.ones(nx)),),
                         check=lambda: calls.append(1), check_every=256)
    assert len(calls) == 5  # before steps 0, 256, 512, 768, 1024

    calls.clear()
    stop_second = _stop_at(2, calls)
    with pytest.raises(_Stop):
        filtered_covariances(P0, Phi, Q, ((H, R, measured[:, None] * np.ones(nx)),),
                             check=stop_second, check_every=CHUNK_SIZES[0])


def test_smoother_checks_before_every_block_of_steps_and_many_states_match():
    """The backward pass calls ``check`` as the forward pass does (its gains were one batched
    solve without a check: seconds with 48 radars' offsets); with 54 states (16 radars'
    offsets: chains of at most 64 steps) both passes still match the reference loops."""
    rng = np.random.default_rng(4)
    n, nx = 300, 54
    P0, Phi, Q, H, R, measured = _problem(rng, n, nx)
    Phi = np.eye(nx) + 0.02 * rng.normal(size=(n, nx, nx))
    updates = ((H, R, measured[:, None] * np.ones(nx)),)
    Pp, Pf = filtered_covariances(P0, Phi, Q, updates)
    _, Pf_ref = _loop(P0, Phi, Q, updates)
    np.testing.assert_allclose(Pf, Pf_ref, rtol=1e-8, atol=1e-8)
    calls: list[int] = []
    Ps = smoothed_covariances(Pf, Pp, Phi, check=lambda: calls.append(1), check_every=64)
    assert len(calls) == 5  # before steps 0, 64, 128, 192, 256 of the 299
    _, Ps_ref = rts_smoother(np.zeros((n, nx)), Pf, np.zeros((n, nx)), Pp, Phi)
    np.testing.assert_allclose(Ps, Ps_ref, rtol=1e-8, atol=1e-8)

    calls.clear()
    stop_second = _stop_at(2, calls)
    with pytest.raises(_Stop):
        smoothed_covariances(Pf, Pp, Phi, check=stop_second, check_every=CHUNK_SIZES[0])


@pytest.mark.parametrize(("n", "ns", "m"), [(1, 6, 3), (40, 6, 3), (300, 8, 48)])
def test_constant_states_by_blocks_match_the_loops(n, ns, m):
    """States after the first ``ns`` constant (sensor offsets: transition I, no noise): the
    block steps (``ns`` given, ``O(ns nx^2)``) against the reference loops of the dense
    equations, with two updates, measurements on both blocks and consider offsets (gain
    zero) in the second half."""
    rng = np.random.default_rng(n + m)
    nx = ns + m
    P0, Phi, Q, H, R, measured = _problem(rng, n, nx)
    Phi[:, ns:, :] = 0.0
    Phi[:, :ns, ns:] = 0.0
    Phi[:, ns:, ns:] = np.eye(m)
    Phi[:, :ns, :ns] = np.eye(ns) + 0.05 * rng.normal(size=(n, ns, ns))
    Q[:, ns:, :] = Q[:, :, ns:] = 0.0
    gain = measured[:, None] * np.ones(nx)
    gain[n // 2:, ns:] = 0.0
    h2 = rng.normal(size=(n, 1, nx))
    on2 = (rng.random(n) < 0.5)[:, None] * np.ones(nx)
    updates = ((H, R, gain), (h2, np.full((n, 1, 1), 2.0), on2))
    Pp, Pf = filtered_covariances(P0, Phi, Q, updates, ns=ns)
    Pp_ref, Pf_ref = _loop(P0, Phi, Q, updates)
    # entries near zero differ by rounding at the matrices' scale (2.7e-8 of 330 at 56 states)
    tol = 1e-9 * np.abs(P0).max()
    np.testing.assert_allclose(Pp, Pp_ref, rtol=1e-8, atol=tol)
    np.testing.assert_allclose(Pf, Pf_ref, rtol=1e-8, atol=tol)
    Ps = smoothed_covariances(Pf, Pp, Phi, ns=ns)
    _, Ps_ref = rts_smoother(np.zeros((n, nx)), Pf, np.zeros((n, nx)), Pp, Phi)
    np.testing.assert_allclose(Ps, Ps_ref, rtol=1e-8, atol=tol)
