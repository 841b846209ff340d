"""The covariance recursions of a Kalman filter and RTS smoother over many steps, in CasADi.

The refinement's Laplace covariance (:mod:`solver.refine.covariance`) runs a covariance-only
filter and smoother over every node of a track. As a Python loop of numpy calls a node cost
about 40 us, and the pass was a tenth of a whole reconstruction. Here one step is a small CasADi
matrix function and the steps are chained by ``mapaccum``, which evaluates the whole chain in
CasADi's virtual machine without returning to Python. The equations are those of
:func:`solver.estimation.kalman.covariance_update` and
:func:`solver.estimation.kalman.rts_smoother`:

- predict ``Pp_k = Phi_{k-1} P_{k-1} Phi_{k-1}^T + Q_{k-1}`` (``Pp_0 = P_0``);
- two sequential updates per step (e.g. a plot's position, then its altitude), each in Joseph
  form with a masked gain ``K = diag(g) P H^T S^-1``, ``S = H P H^T + R``,
  ``P = (I - K H) P (I - K H)^T + K R K^T``: ``g`` is 1 for the states the measurement informs,
  0 for *consider* states (Schmidt-Kalman), all 0 where there is no measurement;
- smooth ``Ps_k = Pf_k + C_k (Ps_{k+1} - Pp_{k+1}) C_k^T`` (symmetrised), with the gains
  ``C_k = Pf_k Phi_k^T Pp_{k+1}^-1`` from one batched numpy solve.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

import casadi as ca
import numpy as np

from .. import compiled

CHUNK_SIZES = tuple(2**k for k in range(4, 13))  # steps of the cached chains (16..4096)
CHAIN_ENTRIES = 2**18
"""A chain holds at most this many steps times ``nx^2``: 4096 steps of the track's 8 states,
64 of 56 (16 radars' offsets). Building ``mapaccum`` grows faster than its steps, and with the
states: 1024 steps of 54 states took 15.7 s to build (47 s of a 91-s reconstruction of 16
radars' offsets), 64 steps 0.03 s; a chain's evaluation costs the same in any chunks."""


def largest_chain(nx: int) -> int:
    """The longest cached chain for ``nx`` states (:data:`CHAIN_ENTRIES`)."""
    return max([s for s in CHUNK_SIZES if s * nx * nx <= CHAIN_ENTRIES], default=CHUNK_SIZES[0])


def _inverse(S: ca.MX) -> ca.MX:
    """``S^-1`` in closed form for one or two measured components."""
    if S.shape == (1, 1):
        return 1.0 / S
    a, b, c, d = S[0, 0], S[0, 1], S[1, 0], S[1, 1]
    return ca.vertcat(ca.horzcat(d, -b), ca.horzcat(-c, a)) / (a * d - b * c)


def _update(P: ca.MX, H: ca.MX, R: ca.MX, gain: ca.MX) -> ca.MX:
    """Joseph-form update with the gain masked row by row (``S^-1`` by :func:`_inverse`)."""
    PHt = ca.mtimes(P, H.T)
    K = ca.mtimes(ca.diag(gain), ca.mtimes(PHt, _inverse(ca.mtimes(H, PHt) + R)))
    IKH = ca.MX.eye(P.shape[0]) - ca.mtimes(K, H)
    return ca.mtimes(ca.mtimes(IKH, P), IKH.T) + ca.mtimes(ca.mtimes(K, R), K.T)


@cache
def _filter_step(nx: int, m1: int, m2: int) -> ca.Function:
    """``(P, Phi, Q, H1, R1, g1, H2, R2, g2) -> (Pf, Pp)``: one predict and two updates."""
    P, Phi, Q = ca.MX.sym("P", nx, nx), ca.MX.sym("Phi", nx, nx), ca.MX.sym("Q", nx, nx)
    H1, R1, g1 = ca.MX.sym("H1", m1, nx), ca.MX.sym("R1", m1, m1), ca.MX.sym("g1", nx)
    H2, R2, g2 = ca.MX.sym("H2", m2, nx), ca.MX.sym("R2", m2, m2), ca.MX.sym("g2", nx)
    Pp = ca.mtimes(ca.mtimes(Phi, P), Phi.T) + Q
    Pf = _update(_update(Pp, H1, R1, g1), H2, R2, g2)
    return ca.Function(f"cov_filter_step_{nx}_{m1}_{m2}", [P, Phi, Q, H1, R1, g1, H2, R2, g2],
                       [Pf, Pp])


@cache
def _smoother_step(nx: int) -> ca.Function:
    """``(Ps_next, Pf, C, Pp_next) -> Ps``: one RTS covariance step."""
    Ps1, Pf, C, Pp1 = (ca.MX.sym(name, nx, nx) for name in ("Ps1", "Pf", "C", "Pp1"))
    P = Pf + ca.mtimes(ca.mtimes(C, Ps1 - Pp1), C.T)
    return ca.Function(f"cov_smoother_step_{nx}", [Ps1, Pf, C, Pp1], [0.5 * (P + P.T)])


def _update_rank(P: ca.MX, H: ca.MX, R: ca.MX, gain: ca.MX) -> ca.MX:
    """:func:`_update`'s Joseph form ``(I - K H) P (I - K H)^T + K R K^T`` with each product
    by ``I - K H`` as a rank-``m`` correction, ``W = P - K (H P)``, ``W - (W H^T) K^T``:
    ``m nx^2`` work instead of ``nx^3``, the same products as :func:`_update`'s. Expanded to
    ``P - K U^T - U K^T + K S K^T`` it lost the track's covariance to cancellation against the
    1e12 m^2 prior (3e69 m^2 at the end of a test's 250 nodes); with ``(P H^T)^T`` for ``H P``
    (P is symmetric only to rounding) x's sigma ended 238 m for 27 m."""
    U = ca.mtimes(P, H.T)
    K = ca.repmat(gain, 1, H.shape[0]) * ca.mtimes(U, _inverse(ca.mtimes(H, U) + R))
    W = P - ca.mtimes(K, ca.mtimes(H, P))
    return W - ca.mtimes(ca.mtimes(W, H.T), K.T) + ca.mtimes(ca.mtimes(K, R), K.T)


@cache
def _filter_step_blocks(nx: int, ns: int, m1: int, m2: int) -> ca.Function:
    """:func:`_filter_step` for states whose last ``nx - ns`` are constant (transition ``I``,
    no noise: sensor offsets): ``(P, F, Qs, H1, R1, g1, H2, R2, g2) -> (Pf, Pp)`` with the
    ``ns x ns`` transition ``F`` and noise ``Qs`` of the others; ``O(ns nx^2)`` work."""
    P, F, Qs = ca.MX.sym("P", nx, nx), ca.MX.sym("F", ns, ns), ca.MX.sym("Qs", ns, ns)
    H1, R1, g1 = ca.MX.sym("H1", m1, nx), ca.MX.sym("R1", m1, m1), ca.MX.sym("g1", nx)
    H2, R2, g2 = ca.MX.sym("H2", m2, nx), ca.MX.sym("R2", m2, m2), ca.MX.sym("g2", nx)
    FB = ca.mtimes(F, P[:ns, ns:])
    Pp = ca.blockcat([[ca.mtimes(ca.mtimes(F, P[:ns, :ns]), F.T) + Qs, FB],
                      [FB.T, P[ns:, ns:]]])
    Pf = _update_rank(_update_rank(Pp, H1, R1, g1), H2, R2, g2)
    return ca.Function(f"cov_filter_blocks_{nx}_{ns}_{m1}_{m2}",
                       [P, F, Qs, H1, R1, g1, H2, R2, g2], [Pf, Pp])


@cache
def _smoother_step_blocks(nx: int, ns: int) -> ca.Function:
    """:func:`_smoother_step` when the last ``nx - ns`` states are constant: the gain is
    ``C = [[Ct], [0, I]]`` (``Ct``: its first ``ns`` rows), so ``C D C^T`` (``D = Ps1 - Pp1``)
    is ``[[Ct D Ct^T, (Ct D)_b], [., D_bb]]``: ``(Ps_next, Pf, Ct, Pp_next) -> Ps`` in
    ``O(ns nx^2)``."""
    Ps1, Pf, Pp1 = (ca.MX.sym(name, nx, nx) for name in ("Ps1", "Pf", "Pp1"))
    Ct = ca.MX.sym("Ct", ns, nx)
    D = Ps1 - Pp1
    top = ca.mtimes(Ct, D)
    P = Pf + ca.blockcat([[ca.mtimes(top, Ct.T), top[:, ns:]], [top[:, ns:].T, D[ns:, ns:]]])
    return ca.Function(f"cov_smoother_blocks_{nx}_{ns}", [Ps1, Pf, Ct, Pp1], [0.5 * (P + P.T)])


@cache
def _chain(step: ca.Function, size: int) -> ca.Function:
    """``step.mapaccum(size)``: the first input carried from step to step, built once."""
    return step.mapaccum(size)


def _run_chain(step: ca.Function, size: int, carry: np.ndarray, per_step: list[np.ndarray]
               ) -> list[np.ndarray]:
    """Evaluate ``size`` chained steps from ``carry``; ``per_step[i]`` is ``(size, *shape_i)``.
    Returns each output as ``(size, *shape)`` (output 0 is the carry after each step)."""
    f = _chain(step, size)
    # column-major data of a horizontal concatenation = each block's column-major data
    ins = [np.ascontiguousarray(carry.T, dtype=float).ravel()]
    ins += [np.ascontiguousarray(np.swapaxes(a, 1, 2), dtype=float).ravel() for a in per_step]
    outs = [np.empty(f.nnz_out(j)) for j in range(f.n_out())]
    compiled.evaluate_into(f, ins, outs)
    return [np.swapaxes(r.reshape(size, step.size2_out(j), step.size1_out(j)), 1, 2)
            for j, r in enumerate(outs)]


def _chunks(n: int, every: int, largest: int = CHUNK_SIZES[-1]) -> list[tuple[int, int, int]]:
    """``(start, stop, size)``: runs of cached chain sizes, the largest that fit (at most
    ``largest``), none crossing a multiple of ``every``; a run shorter than the smallest size
    (the end of a segment) is padded to it."""
    out = []
    for first in range(0, n, every):
        start, end = first, min(first + every, n)
        while start < end:
            size = max((s for s in CHUNK_SIZES if s <= min(end - start, largest)),
                       default=CHUNK_SIZES[0])
            out.append((start, min(start + size, end), size))
            start += size
    return out


def _padded(a: np.ndarray, start: int, stop: int, size: int) -> np.ndarray:
    """Rows ``start:stop`` of ``a``, padded to ``size`` rows by repeating the last (the padded
    steps' results are dropped)."""
    return a[np.r_[start:stop, np.full(size - (stop - start), stop - 1)]]


def filtered_covariances(P0: np.ndarray, Phi: np.ndarray, Q: np.ndarray,
                         updates: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...],
                         check: Callable[[], None] | None = None, check_every: int = 1024,
                         ns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Predicted and filtered covariances ``(Pp, Pf)``, each ``(n, nx, nx)``, of a filter
    started at ``P0`` at step 0 (``Pp_0 = P0``) with transitions ``Phi[k], Q[k]`` from step
    ``k`` to ``k + 1``.

    ``updates``: one or two ``(H, R, gain)`` per step in the order applied, ``H (n, m, nx)``,
    ``R (n, m, m)``, ``gain (n, nx)`` (the mask above; a step whose mask is all zero has no such
    measurement, and its ``H``, ``R`` are not used). ``check`` is called before every
    ``check_every`` steps (a deadline).

    ``ns``: only the first ``ns`` states move; the others are constant (``Phi`` the identity
    and ``Q`` zero there and across: sensor offsets), and the steps exploit it
    (:func:`_filter_step_blocks`: 48 radars' offsets, 150 states, cost 82 s of 2,000 steps as
    dense ``nx^3`` steps)."""
    n, nx = Phi.shape[0], P0.shape[0]
    ns = nx if ns is None else ns
    if not 1 <= len(updates) <= 2:
        raise ValueError("one or two updates per step")
    if len(updates) == 1:  # a second update that never acts
        updates = (*updates, (np.zeros((n, 1, nx)), np.ones((n, 1, 1)), np.zeros((n, nx))))
    per_step = []
    for H, R, gain in updates:
        none = ~gain.any(axis=1)
        H, R = H.copy(), R.copy()  # no measurement: S = R = I, K = 0, P unchanged
        H[none], R[none] = 0.0, np.eye(R.shape[1])
        per_step += [H, R, gain[:, :, None]]
    m1, m2 = updates[0][0].shape[1], updates[1][0].shape[1]
    step = _filter_step(nx, m1, m2) if ns == nx else _filter_step_blocks(nx, ns, m1, m2)
    # step k predicts over the transition k - 1 (none before step 0)
    Phi_in = np.concatenate([np.eye(ns)[None], Phi[: n - 1, :ns, :ns]])
    Q_in = np.concatenate([np.zeros((1, ns, ns)), Q[: n - 1, :ns, :ns]])
    Pf, Pp = np.empty((n, nx, nx)), np.empty((n, nx, nx))
    P = P0
    for start, stop, size in _chunks(n, check_every, largest_chain(nx)):
        if check is not None and start % check_every == 0:
            check()
        ins = [_padded(a, start, stop, size) for a in (Phi_in, Q_in, *per_step)]
        f, p = _run_chain(step, size, P, ins)
        Pf[start:stop], Pp[start:stop] = f[: stop - start], p[: stop - start]
        P = Pf[stop - 1]
    return Pp, Pf


def smoothed_covariances(Pf: np.ndarray, Pp: np.ndarray, Phi: np.ndarray,
                         check: Callable[[], None] | None = None, check_every: int = 1024,
                         ns: int | None = None) -> np.ndarray:
    """RTS-smoothed covariances ``(n, nx, nx)`` from :func:`filtered_covariances`' output;
    ``check`` is called before every ``check_every`` steps (a deadline), the gains of each
    run of steps solved just before it (their ``n nx^3`` work was one batched solve, no check
    in it: 48 radars' offsets, ``nx`` 150, cost seconds there). ``ns``: as in
    :func:`filtered_covariances`; only the first ``ns`` rows of each gain are solved for
    (:func:`_smoother_step_blocks`)."""
    n, nx = Pf.shape[0], Pf.shape[1]
    ns = nx if ns is None else ns
    Ps = Pf.copy()
    if n < 2:
        return Ps
    step = _smoother_step(nx) if ns == nx else _smoother_step_blocks(nx, ns)
    P = Pf[n - 1]
    # backwards: step j smooths k = n - 2 - j
    for start, stop, size in _chunks(n - 1, min(check_every, CHUNK_SIZES[-1]),
                                     largest_chain(nx)):
        if check is not None and start % check_every == 0:
            check()
        k = n - 2 - np.arange(start, stop)
        C = np.linalg.solve(Pp[k + 1], Phi[k] @ Pf[k][:, :, :ns]).transpose(0, 2, 1)
        (out,) = _run_chain(step, size, P, [_padded(a, 0, stop - start, size)
                                            for a in (Pf[k], C, Pp[k + 1])])
        Ps[k] = out[: stop - start]
        P = out[stop - start - 1]
    return Ps
