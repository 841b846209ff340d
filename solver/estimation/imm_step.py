"""The IMM smoother's steps (:mod:`.imm_smoother`) as compiled CasADi functions.

In numpy each step is a few dozen calls on 4x4 arrays (3 modes, 9 mode pairs), and their
overhead was the smoother's cost. Here one step is one function (:func:`solver.compiled.function`:
compiled when a C compiler or the compiled-object cache is at hand), called through its buffer
on numpy memory. Measured on a 1,458-plot dev track of the ssr profile (3 alternated runs, least
CPU time of 5 each): the forward pass 320-369 -> 7-13 us a plot, the backward pass 215-272 ->
59-70 us (numpy's ``eigh`` of three 4x4 matrices, about 30 us, is half of it), the whole smoother
1,670-1,920 -> 13,300-14,100 plots per CPU-second. Compiling the three functions takes about 4 s,
once per machine.

Forward (:func:`forward_step`): mixing ``c = Pi^T mu``, ``W_ij = Pi_ij mu_i / c_j`` (``mu`` where
``c_j = 0``), mixed moments, prediction ``Phi_j``, ``Q_j``, the position update of
:func:`.kalman.position_update` per mode (EKF or converted for a polar plot, linear for a fix,
Joseph form) and ``mu_j`` proportional to ``c_j L_j``. Backward (:func:`backward_step`): the
mode-pair recursion of :func:`.imm_smoother.imm_backward` with the later plots' mode
likelihoods, given the eigen-decomposition numpy's ``eigh`` computes between the calls. The
numpy passes they replaced are the tests' reference (``tests/imm_reference.py``): the same
results to 1e-10 m on the dev tracks.

The functions take and give flat vectors; their layouts (:data:`STATE`, :data:`STEP`,
:data:`EXTRA`, :data:`EIGEN`, :data:`BACK`: named slices, each part in numpy's row-major order)
are the one source for both the functions and the passes that fill them (:func:`pack`).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

import casadi as ca
import numpy as np

from .. import compiled
from .gating import gated_pass
from .measurements import (
    LINEARISATION_TOLERANCE,
    MAX_LINEARISATIONS,
    PolarPlots,
    SensorPlots,
)

N_MODES = 3
"""CV, right turn, left turn."""


def _blocks(**sizes: int) -> dict[str, slice]:
    """Consecutive slices of a flat vector, in the order given."""
    out, start = {}, 0
    for name, size in sizes.items():
        out[name] = slice(start, start + size)
        start += size
    return out


_M, _PAIRS = N_MODES, N_MODES * N_MODES
STATE = _blocks(x=_M * 4, P=_M * 16, mu=_M)
"""A pass's state at one plot (forward: filtered; backward: smoothed)."""
STEP = _blocks(Phi=_M * 16, Q=_M * 16, Pi=_M * _M, plot=11, lin=_M * 2, relin=_M, use=1)
"""The forward step's inputs; ``plot`` as :func:`plot_rows`; ``lin``, ``relin`` where each mode's
EKF update is linearised (:func:`update_terms`; 0: at the prediction); ``use`` 0: the plot is
left out (the validation gate, :mod:`.gating`: the state is the prediction)."""
EXTRA = _blocks(W=_M * _M, xp=_M * 4, Pp=_M * 16)
"""The forward step's outputs for the backward pass."""
EIGEN = _blocks(s=_M * 4, V=_M * 16)
"""``eigh`` of the whitened smoothed covariances ``Ws = U^-1 Ps_{k+1} U^-T`` (ascending)."""
BACK = _blocks(W=_M * _M, xp=_M * 4, white=_M * 16, xpair=_PAIRS * 4, Ppair=_PAIRS * 16,
               a=_PAIRS * 4, B=_PAIRS * 16, C=_PAIRS * 16, white_prev=_M * 16, future=1)
"""The backward step's inputs: the forward ``W``, ``xp``, the whitening ``U^-1`` of the
forward prediction, the pair terms (:func:`.imm_smoother.pair_terms`, pairs ``(i, j)`` in
row-major order), the previous step's whitening, the future-modes flag (0: Kim's weights)."""


def size(layout: dict[str, slice]) -> int:
    """Length of a flat vector laid out as ``layout``."""
    return max(s.stop for s in layout.values())


def pack(layout: dict[str, slice], rows: int, **parts: np.ndarray | float) -> np.ndarray:
    """``(rows, size)`` array of ``layout``, each named part reshaped to ``(rows, -1)`` (row-major)
    or broadcast (a number)."""
    out = np.empty((rows, size(layout)))
    for name, v in parts.items():
        out[:, layout[name]] = np.reshape(v, (rows, -1)) if np.ndim(v) else v
    return out


def _modes(v: ca.SX, width: int) -> list[ca.SX]:
    """A flat block of consecutive parts of ``width`` (one per mode or pair); 16 wide: 4x4
    matrices."""
    parts = [v[width * j: width * (j + 1)] for j in range(v.shape[0] // width)]
    return [_mat(p, 4, 4) for p in parts] if width == 16 else parts


def plot_rows(meas: PolarPlots | SensorPlots) -> np.ndarray:
    """``(n, 11)`` per plot ``(polar, d, psi, sigma_d, sigma_psi, centre, cov)`` for the
    steps; the unused part of a row is finite (``d = 1``, unit covariance)."""
    n = len(meas)
    rows = np.zeros((n, 11))
    rows[:, 7] = rows[:, 10] = 1.0
    if isinstance(meas, SensorPlots):
        polar = meas.polar.astype(bool)
        rows[:, 0] = polar
        for col, v in ((1, meas.d), (2, meas.psi), (3, meas.sigma_d), (4, meas.sigma_psi)):
            rows[:, col] = np.where(polar, v, 1.0)
        rows[~polar, 5:7] = meas.centre[~polar]
        rows[~polar, 7:11] = meas.cov[~polar].reshape(-1, 4)
    else:
        rows[:, 0] = 1.0
        rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4] = meas.d, meas.psi, meas.sigma_d, \
            meas.sigma_psi
    return rows


def _mat(v: ca.SX, rows: int, cols: int) -> ca.SX:
    """A row-major flat block as a matrix."""
    return ca.reshape(v, cols, rows).T


def _flat(m: ca.SX) -> ca.SX:
    """A matrix as a row-major flat block."""
    return ca.vec(m.T)


def _wrap(a: ca.SX) -> ca.SX:
    """numpy's ``mod(a + pi, 2 pi) - pi``: an angle in ``[-pi, pi)``."""
    a = ca.fmod(a + ca.pi, 2 * ca.pi)
    return ca.if_else(a < 0, a + 2 * ca.pi, a) - ca.pi


def _polar(at: ca.SX, d: ca.SX, psi: ca.SX) -> tuple[ca.SX, ca.SX]:
    """:func:`.measurements.polar_innovation` at position ``at``: ``z - h(at)`` and ``J``."""
    ax, az = at[0], at[1]
    rho2 = ax * ax + az * az
    rho = ca.sqrt(rho2)
    nu = ca.vertcat(d - rho, _wrap(psi - ca.atan2(az, ax)))
    J = ca.vertcat(ca.horzcat(ax / rho, az / rho), ca.horzcat(-az / rho2, ax / rho2))
    return nu, J


def update_terms(xp: ca.SX, Pp: ca.SX, plot: ca.SX, measurement: str, lin: ca.SX | None = None,
                 relin: ca.SX | None = None, use: ca.SX | None = None
                 ) -> tuple[ca.SX, ca.SX, ca.SX, ca.SX, ca.SX]:
    """Position update of one mode's ``(m,)``, ``(m, m)`` prediction (the position first):
    updated state, covariance, ``-(nu^T S^-1 nu + log det S) / 2``, whether to update again and
    ``nu^T S^-1 nu``; where ``use`` is 0 the prediction itself, log-likelihood 0, no update again
    (a plot the validation gate left out).

    The EKF update of a polar plot is linearised at the position ``lin`` where ``relin`` is
    nonzero, else at the prediction's; it is :func:`.kalman.position_update`'s iterated update
    when the caller repeats the step, relinearised at the updated position, while the last
    output (1: the linearisation error at the updated position exceeds
    :data:`.measurements.LINEARISATION_TOLERANCE` sigma; always 0 for the converted
    measurement and for fixes) asks for it (:func:`relinearise`)."""
    polar, d, psi, sigma_d, sigma_psi = (plot[i] for i in range(5))
    centre, cov = plot[5:7], _mat(plot[7:11], 2, 2)
    px, pz = xp[0], xp[1]
    rho2 = px * px + pz * pz
    rho = ca.sqrt(rho2)
    eye2 = ca.SX.eye(2)
    if measurement == "ekf":
        at = xp[:2] if lin is None else ca.if_else(relin, lin, xp[:2])
        nu_at, H_polar = _polar(at, d, psi)
        nu_polar = nu_at - ca.mtimes(H_polar, xp[:2] - at)
        R_polar = ca.diag(ca.vertcat(sigma_d**2, sigma_psi**2))
    else:  # converted: the plot point, the covariance's Jacobian at the prediction
        nu_polar = ca.vertcat(d * ca.cos(psi), d * ca.sin(psi)) - xp[:2]
        H_polar = eye2
        c, s = px / rho, pz / rho
        vr, vc = sigma_d**2, (rho * sigma_psi) ** 2
        R_polar = ca.vertcat(ca.horzcat(c * c * vr + s * s * vc, s * c * (vr - vc)),
                             ca.horzcat(s * c * (vr - vc), s * s * vr + c * c * vc))
    nu = ca.if_else(polar, nu_polar, centre - xp[:2])
    Hp = ca.if_else(polar, H_polar, eye2)
    R = ca.if_else(polar, R_polar, cov)
    PHt = ca.mtimes(Pp[:, :2], Hp.T)
    S = ca.mtimes(Hp, PHt[:2, :]) + R
    det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
    Sinv = ca.vertcat(ca.horzcat(S[1, 1], -S[0, 1]), ca.horzcat(-S[1, 0], S[0, 0])) / det
    K = ca.mtimes(PHt, Sinv)
    m = xp.shape[0]
    IKH = ca.SX.eye(m) - ca.horzcat(ca.mtimes(K, Hp), ca.SX.zeros(m, m - 2))
    P = ca.mtimes([IKH, Pp, IKH.T]) + ca.mtimes([K, R, K.T])
    nis = ca.mtimes([nu.T, Sinv, nu])
    x = xp + ca.mtimes(K, nu)
    again = ca.SX(0)
    if measurement == "ekf":
        nu_new, _ = _polar(x[:2], d, psi)
        error = (nu_at - nu_new) - ca.mtimes(H_polar, x[:2] - at)  # h(new) - h(at) - J (new - at)
        tol = LINEARISATION_TOLERANCE
        again = ca.logic_and(polar, ca.logic_or(ca.fabs(error[0]) > tol * sigma_d,
                                                ca.fabs(_wrap(error[1])) > tol * sigma_psi))
    loglik = -0.5 * (nis + ca.log(det))
    if use is not None:
        x, P = ca.if_else(use, x, xp), ca.if_else(use, P, Pp)
        loglik, again = ca.if_else(use, loglik, 0.0), ca.logic_and(use, again)
    return x, P, loglik, again, nis


def relinearise(evaluate: Callable[[], None], a: np.ndarray, s_next: np.ndarray,
                again: np.ndarray, step: dict[str, slice], state: dict[str, slice],
                n_x: int) -> None:
    """Repeat a step whose ``again`` output (``[any, per mode]``) asks for it: each mode that
    asks is linearised at its updated position (inputs ``lin``, ``relin`` of the step's row
    ``a``, changed in place), the others where they were, until none asks or
    :data:`.measurements.MAX_LINEARISATIONS` updates were made; ``s_next`` holds the result."""
    lin = a[step["lin"]].reshape(-1, 2)
    relin = a[step["relin"]]
    x = s_next[state["x"]].reshape(-1, n_x)
    for _ in range(MAX_LINEARISATIONS - 1):
        redo = again[1:] > 0
        lin[redo] = x[redo, :2]
        relin[redo] = 1.0
        evaluate()
        if not again[0]:
            return


def gated_steps(fn: ca.Function, S: np.ndarray, A: np.ndarray, extra: np.ndarray | None,
                step: dict[str, slice], state: dict[str, slice], n_x: int,
                gate: float | None) -> np.ndarray:
    """Run a compiled IMM's forward steps ``1 .. n-1`` (inputs row ``k - 1`` of ``A``, the state
    after plot ``k - 1`` in row ``k - 1`` of ``S`` -> row ``k``; ``fn``'s ``extra`` output, if any,
    to row ``k - 1`` of ``extra``), each repeated while it asks (:func:`relinearise`), with the
    validation gate on the modes' least normalised innovation and the plot's predictive
    likelihood (:func:`.gating.gated_pass`: a plot no mode expects, ``use`` 0). Returns
    ``(n,)`` True where left out."""
    n_modes = state["mu"].stop - state["mu"].start
    again, nis = np.zeros(n_modes + 1), np.zeros(n_modes + 2)
    buf, evaluate = fn.buffer()
    buf.set_res(fn.index_out("again"), memoryview(again))
    buf.set_res(fn.index_out("nis"), memoryview(nis))
    i_extra = fn.index_out("extra") if extra is not None else -1
    relin, use = step["relin"], step["use"]
    head = nis[:2].reshape(2, 1)  # a view: [least NIS, deviance]

    def one(k: int, lanes: np.ndarray, use_plot: bool) -> np.ndarray:
        a = A[k - 1]  # a view; its relin and use are 0 and 1 between steps
        if not use_plot:
            a[use] = 0.0
        buf.set_arg(0, memoryview(S[k - 1]))
        buf.set_arg(1, memoryview(a))
        buf.set_res(0, memoryview(S[k]))
        if extra is not None:
            buf.set_res(i_extra, memoryview(extra[k - 1]))
        evaluate()
        if again[0]:  # the iterated EKF update (a plot far from the prediction)
            relinearise(evaluate, a, S[k], again, step, state, n_x)
            a[relin] = 0.0
        if not use_plot:
            a[use] = 1.0
        return head

    return gated_pass(S.shape[0], 1, one, gate)[:, 0]


def _step(measurement: str) -> ca.Function:
    s, a = ca.SX.sym("s", size(STATE)), ca.SX.sym("a", size(STEP))
    x, P, mu = _modes(s[STATE["x"]], 4), _modes(s[STATE["P"]], 16), s[STATE["mu"]]
    Phi, Q = _modes(a[STEP["Phi"]], 16), _modes(a[STEP["Q"]], 16)
    Pi = _mat(a[STEP["Pi"]], N_MODES, N_MODES)
    plot, lin, relin = a[STEP["plot"]], _modes(a[STEP["lin"]], 2), a[STEP["relin"]]
    use = a[STEP["use"]]
    joint = Pi * ca.repmat(mu, 1, N_MODES)  # joint[i, j] = Pi_ij mu_i
    c = ca.sum1(joint).T
    W = ca.horzcat(*(ca.if_else(c[j] > 0, joint[:, j] / c[j], mu) for j in range(N_MODES)))
    xn, Pn, XP, PP, loglik, again, nis = [], [], [], [], [], [], []
    for j in range(N_MODES):
        xm = sum(W[i, j] * x[i] for i in range(N_MODES))
        Pm = sum(W[i, j] * (P[i] + ca.mtimes(x[i] - xm, (x[i] - xm).T)) for i in range(N_MODES))
        xp = ca.mtimes(Phi[j], xm)
        Pp = ca.mtimes([Phi[j], Pm, Phi[j].T]) + Q[j]
        xj, Pj, lj, aj, nj = update_terms(xp, Pp, plot, measurement, lin[j], relin[j], use)
        again.append(aj)
        nis.append(nj)
        xn.append(xj)
        Pn.append(Pj)
        XP.append(xp)
        PP.append(_flat(Pp))
        loglik.append(lj)
    ll = ca.vertcat(*loglik)
    post = c * ca.exp(ll - ca.mmax(ll))
    total = ca.sum1(post)
    ok = ca.logic_and(total > 0, total < ca.inf)
    mun = ca.if_else(ok, post / total, c)
    out = ca.vertcat(*xn, *(_flat(p) for p in Pn), mun)
    extra = ca.vertcat(_flat(W), *XP, *PP)
    flags = ca.vertcat(ca.mmax(ca.vertcat(*again)), *again)
    deviance = -2 * (ca.mmax(ll) + ca.log(total))  # -2 log sum_j c_j L_j
    nis_out = ca.vertcat(ca.mmin(ca.vertcat(*nis)), deviance, *nis)
    return compiled.function(f"imm_forward_{measurement}", [s, a],
                             [out, extra, flags, nis_out], ["s", "a"],
                             ["s_next", "extra", "again", "nis"], derivatives=False)


@cache
def forward_step(measurement: str) -> ca.Function:
    """One forward step: ``(s_{k-1}, inputs_k) -> (s_k, extras_k, again_k, nis_k)``; ``again``
    ``[any, per mode]`` asks for the step to be repeated (:func:`relinearise`); ``nis``
    ``[least, deviance, per mode]``: the modes' normalised innovations squared and the plot's
    ``-2 log`` predictive likelihood ``-2 log sum_j c_j L_j``, for the validation gate
    (:func:`gated_steps`)."""
    return _step(measurement)


# ---- backward pass (imm_smoother.imm_backward), one step per call around numpy's eigh ----

def _backward_step() -> ca.Function:
    st = ca.SX.sym("s", size(STATE))
    eig, a = ca.SX.sym("e", size(EIGEN)), ca.SX.sym("a", size(BACK))
    xs, Ps, mus = _modes(st[STATE["x"]], 4), _modes(st[STATE["P"]], 16), st[STATE["mu"]]
    ev, V = _modes(eig[EIGEN["s"]], 4), _modes(eig[EIGEN["V"]], 16)
    W = _mat(a[BACK["W"]], N_MODES, N_MODES)
    xp, white = _modes(a[BACK["xp"]], 4), _modes(a[BACK["white"]], 16)

    def pair(name: str, width: int) -> list[list[ca.SX]]:  # [i][j]
        flat = _modes(a[BACK[name]], width)
        return [flat[N_MODES * i: N_MODES * (i + 1)] for i in range(N_MODES)]

    xpair, Ppair, apair = pair("xpair", 4), pair("Ppair", 16), pair("a", 4)
    Bpair, Cpair = pair("B", 16), pair("C", 16)
    white_prev = _modes(a[BACK["white_prev"]], 16)
    future = a[BACK["future"]]
    # b_ij: Kim's W_ij times the later plots' likelihood of the pair (see backward_step)
    cols = []
    for j in range(N_MODES):
        lam = 1.0 / ca.fmax(ev[j], 1e-300) - 1.0
        keep = lam > 1e-9 * lam[0]
        sq = ca.sqrt(ca.if_else(keep, lam, 0.0))
        VtU = ca.mtimes(V[j].T, white[j])
        y = ca.if_else(keep, ca.mtimes(VtU, xs[j] - xp[j]) / ca.if_else(keep, sq, 1.0), 0.0)
        T = ca.repmat(sq, 1, 4) * VtU
        logL = []
        for i in range(N_MODES):
            r = ca.mtimes(T, xpair[i][j] - xs[j]) - y
            R = ca.chol(ca.mtimes([T, Ppair[i][j], T.T]) + ca.SX.eye(4))  # M = R^T R
            z = ca.solve(R.T, r)  # lower triangular
            logL.append(-ca.sum1(ca.log(ca.diag(R))) - 0.5 * ca.sumsqr(z))
        ll = ca.vertcat(*logL)
        b = W[:, j] * ca.exp(ll - ca.mmax(ll))
        tot = ca.sum1(b)
        good = ca.logic_and(future, ca.logic_and(tot > 0, tot < ca.inf))
        cols.append(ca.if_else(good, b / tot, W[:, j]))
    joint = ca.horzcat(*(cols[j] * mus[j] for j in range(N_MODES)))  # joint[i, j]
    m = ca.sum2(joint)
    mus_k = m / ca.sum1(m)
    xn, Pn, Wn = [], [], []
    for i in range(N_MODES):
        wgt = [ca.if_else(m[i] > 0, joint[i, j] / m[i], 1.0 / N_MODES) for j in range(N_MODES)]
        xij = [apair[i][j] + ca.mtimes(Cpair[i][j], xs[j]) for j in range(N_MODES)]
        Pij = [Bpair[i][j] + ca.mtimes([Cpair[i][j], Ps[j], Cpair[i][j].T])
               for j in range(N_MODES)]
        x = sum(wgt[j] * xij[j] for j in range(N_MODES))
        P = sum(wgt[j] * (Pij[j] + ca.mtimes(xij[j] - x, (xij[j] - x).T))
                for j in range(N_MODES))
        xn.append(x)
        Pn.append(P)
        Wn.append(_flat(ca.mtimes([white_prev[i], P, white_prev[i].T])))
    out = ca.vertcat(*xn, *(_flat(p) for p in Pn), mus_k)
    return compiled.function("imm_backward", [st, eig, a], [out, ca.vertcat(*Wn)],
                             ["s", "eigen", "a"], ["s_prev", "Ws_prev"], derivatives=False)


@cache
def backward_step() -> ca.Function:
    """One backward step: ``(s_{k+1}, eigen of Ws_k, inputs_k) -> (s_k, Ws_{k-1} (3, 4, 4))``,
    ``Ws_{k-1} = white_{k-1} Ps_k white_{k-1}^T`` for the next step's ``eigh``.

    The mode weights ``b_ij`` of :func:`.imm_smoother.imm_backward` are proportional over ``i``
    to ``W_ij L_ij``; ``xs``, ``Ps`` smoothed at ``k + 1``, ``xp`` the forward mixed prediction
    and ``white = U^-1`` with ``Pp = U U^T`` its covariance, ``x^{ij}``, ``P^{ij}`` the pair
    predictions. The later plots' information about ``x_{k+1}`` is ``L = Ps^-1 - Pp^-1`` with
    the vector ``e = Pp^-1 (xs - xp)``: a pseudo-measurement ``y = L^+ e`` of weight ``L``. In
    whitened coordinates ``w = U^-1 x`` it is ``U^-1 Ps U^-T = V diag(s) V^T`` (the ``eigen``
    input), information ``l = 1/s - 1`` along ``V``; directions with ``l <= 0`` (the mixture
    approximations can make the smoothed spread exceed the prediction's) carry none and are
    dropped: negative information would reward pair predictions for being far away. Whitening
    makes the split independent of units (m against m/s). With ``T = diag(sqrt l) V^T U^-1``,
    ``r = T (x^{ij} - xs) - diag(1/sqrt l) V^T U^-1 (xs - xp)`` and ``M = I + T P^{ij} T^T``
    (positive definite): ``log L_ij = -(log det M + r^T M^-1 r) / 2`` up to a constant per
    ``j``. Where a column's weights are not finite (absurd sigmas) or the ``future`` input is
    0, Kim's ``W_ij`` are kept."""
    return _backward_step()


def build() -> None:
    """Build (compile, or load from the cache) every step function: a warm-up's work."""
    for measurement in ("ekf", "converted"):
        forward_step(measurement)
    backward_step()
