"""Continuous linear models ``x' = F x + G w`` (``w`` white, spectral density ``qc``) to discrete
``x_{k+1} = Phi x_k + noise`` with ``Q = cov(noise)``, for arrays of (irregular) time steps.

- :func:`van_loan`: exact ``Phi = e^{F T}`` and ``Q = int_0^T e^{F s} G qc G^T e^{F^T s} ds`` from
  one matrix exponential of ``[[-F, G qc G^T], [0, F^T]] T`` (Van Loan 1978): no cancellation for
  small ``T`` unlike expanded closed forms.
- :func:`taylor` : the second-order series ``Phi = I + F T + F^2 T^2 / 2`` and
  ``Gamma = (I T + F T^2 / 2 + F^2 T^3 / 6) G`` used by seed 001, with
  ``Q = Gamma (qc / T) Gamma^T`` (a white sequence of variance ``qc / T`` held over the step;
  ``Q = 0`` for ``T = 0``, its limit).

Steps are rounded to 1e-9 s and each distinct step is computed once (scans repeat the same
``T``; a missed plot gives a multiple of it); :func:`van_loan` also keeps the last 256 distinct
``(F, G, qc, steps)`` results, since a radar's scan period repeats from request to request.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.linalg import expm

from ..inputs import FloatArray


def _unique_steps(dt: FloatArray) -> tuple[FloatArray, np.ndarray]:
    dt = np.asarray(dt, dtype=float)
    keys, inverse = np.unique(np.round(dt, 9), return_inverse=True)
    return keys, inverse.reshape(dt.shape)


def van_loan(F: FloatArray, G: FloatArray, qc: float, dt: FloatArray
             ) -> tuple[FloatArray, FloatArray]:
    """Exact ``(Phi, Q)``, shape ``(len(dt), n, n)``, of ``x' = F x + G w``,
    ``E[w w^T] = qc delta``."""
    n = F.shape[0]
    G = np.asarray(G, dtype=float).reshape(n, -1)
    steps, inverse = _unique_steps(dt)
    Phi, Q = _van_loan_steps(np.ascontiguousarray(F, dtype=float).tobytes(), n,
                             np.ascontiguousarray(G).tobytes(), float(qc), steps.tobytes())
    return Phi[inverse], Q[inverse]


@lru_cache(maxsize=256)
def _van_loan_steps(F_bytes: bytes, n: int, G_bytes: bytes, qc: float, steps_bytes: bytes
                    ) -> tuple[FloatArray, FloatArray]:
    F = np.frombuffer(F_bytes).reshape(n, n)
    G = np.frombuffer(G_bytes).reshape(n, -1)
    steps = np.frombuffer(steps_bytes)
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -F
    M[:n, n:] = qc * (G @ G.T)
    M[n:, n:] = F.T
    # e^{-F T} grows like e^{|F| T}: exponentiate T / 2^s with |F| T / 2^s <= 1, then double
    # with Phi(2h) = Phi(h)^2, Q(2h) = Phi(h) Q(h) Phi(h)^T + Q(h) (no cancellation)
    big = float(np.max(steps, initial=0.0)) * float(np.linalg.norm(F, 1))
    s = max(0, int(np.ceil(np.log2(big)))) if big > 1 else 0
    E = expm((steps / 2**s)[:, None, None] * M[None])
    Phi = np.transpose(E[:, n:, n:], (0, 2, 1))
    Q = Phi @ E[:, :n, n:]
    for _ in range(s):
        Q = Phi @ Q @ np.transpose(Phi, (0, 2, 1)) + Q
        Phi = Phi @ Phi
    Q = 0.5 * (Q + np.transpose(Q, (0, 2, 1)))
    Phi.flags.writeable = Q.flags.writeable = False  # shared by the cache
    return Phi, Q


def taylor(F: FloatArray, G: FloatArray, qc: float, dt: FloatArray
           ) -> tuple[FloatArray, FloatArray]:
    """Seed 001's second-order Taylor ``(Phi, Q)``; ``Q = Gamma (qc / T) Gamma^T``."""
    n = F.shape[0]
    G = np.asarray(G, dtype=float).reshape(n, -1)
    T = np.asarray(dt, dtype=float)[:, None, None]
    I, F2 = np.eye(n), F @ F
    Phi = I + F * T + F2 * T**2 / 2
    Gamma = (I * T + F * T**2 / 2 + F2 * T**3 / 6) @ G
    # a zero step (plots of two sensors at one instant): Gamma = 0, so Q = 0 (its limit)
    Q = Gamma @ np.transpose(Gamma, (0, 2, 1)) * np.divide(qc, T, out=np.zeros_like(T),
                                                            where=T > 0)
    return Phi, Q
