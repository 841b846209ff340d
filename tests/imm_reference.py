"""The IMM smoother's passes in plain numpy, as they were before the steps moved to compiled
CasADi functions (``solver.estimation.imm_step``): the reference the tests compare those with
(and the future-mode likelihood's own tests run on). Equations in
``solver.estimation.imm_smoother``."""

import numpy as np

from solver.estimation.imm_smoother import N_MODES, ForwardPass, _prior, pair_terms
from solver.estimation.kalman import position_update

_POS = (0, 1)
_EYE4 = np.eye(4)


def imm_forward(meas, Phi, Q, Pi, mu0, measurement: str = "ekf") -> ForwardPass:
    """The forward IMM of ``imm_smoother.imm_forward``: one ``position_update`` per mode."""
    n = len(meas)
    x0, P0 = _prior(meas)
    xf = np.empty((n, N_MODES, 4))
    Pf = np.empty((n, N_MODES, 4, 4))
    mu = np.empty((n, N_MODES))
    W = np.empty((max(n - 1, 0), N_MODES, N_MODES))
    XP = np.empty((max(n - 1, 0), N_MODES, 4))
    PP = np.empty((max(n - 1, 0), N_MODES, 4, 4))
    xf[0], Pf[0], mu[0] = x0, P0, mu0
    PhiT = np.swapaxes(Phi, -1, -2)
    loglik = np.empty(N_MODES)
    m, x, P = mu[0], xf[0], Pf[0]
    for k in range(1, n):
        joint = Pi[k - 1] * m[:, None]
        c = joint.sum(0)
        if c.min() > 0:
            w = joint / c
        else:
            w = np.divide(joint, c, out=np.repeat(m[:, None], N_MODES, 1), where=c > 0)
        W[k - 1] = w
        wt = w.T
        xm = wt @ x  # (j, 4)
        d = x[None, :, :] - xm[:, None, :]  # (j, i, 4)
        Pm = (wt @ P.reshape(N_MODES, 16)).reshape(N_MODES, 4, 4) \
            + (d * wt[:, :, None]).transpose(0, 2, 1) @ d
        xp = (Phi[k - 1] @ xm[:, :, None])[:, :, 0]
        Pp = Phi[k - 1] @ Pm @ PhiT[k - 1] + Q[k - 1]
        XP[k - 1], PP[k - 1] = xp, Pp
        x, P = xf[k], Pf[k]
        for j in range(N_MODES):
            x[j], P[j], nis, logdet = position_update(xp[j], Pp[j], meas, k, _POS, measurement)
            loglik[j] = -0.5 * (nis + logdet)
        post = c * np.exp(loglik - loglik.max())
        total = post.sum()
        m = mu[k] = post / total if total > 0 and np.isfinite(total) else c
    return ForwardPass(xf, Pf, mu, W, XP, PP)


def imm_backward(fw: ForwardPass, Phi, Q, future_modes: bool = True):
    """The backward pass of ``imm_smoother.imm_backward``, one step of numpy calls at a time."""
    xf, Pf, mu, W = fw.x, fw.P, fw.mu, fw.W
    n = xf.shape[0]
    xs, Ps, mus = xf.copy(), Pf.copy(), mu.copy()
    if n < 2:
        return xs, Ps, mus
    xpair, Ppair, C, a, B = pair_terms(fw, Phi, Q)  # unchanged numpy, shared
    CT = np.swapaxes(C, -1, -2)
    if future_modes:
        # whitening by the forward prediction: Pp = U U^T, so the later plots' information is
        # compared with the prediction's in a metric that does not depend on units
        white = np.linalg.inv(np.linalg.cholesky(fw.Pp))
    uniform = np.full((N_MODES, N_MODES), 1.0 / N_MODES)
    for k in range(n - 2, -1, -1):
        b = W[k]
        if future_modes:
            b = future_weights(b, xs[k + 1], Ps[k + 1], fw.xp[k], white[k], xpair[k],
                                Ppair[k])
        joint = b * mus[k + 1]
        m = joint.sum(1)
        mus[k] = m / m.sum()
        if m.min() > 0:
            wgt = joint / m[:, None]
        else:
            wgt = np.divide(joint, m[:, None], out=uniform.copy(), where=m[:, None] > 0)
        xij = a[k] + (C[k] @ xs[k + 1][None, :, :, None])[..., 0]  # (i, j, 4)
        Pij = B[k] + C[k] @ Ps[k + 1][None] @ CT[k]
        wv = wgt[:, :, None]
        x = (wv * xij).sum(1)
        d = xij - x[:, None, :]
        xs[k] = x
        Ps[k] = (wv[..., None] * Pij).sum(1) + (d * wv).transpose(0, 2, 1) @ d
    Ps = 0.5 * (Ps + np.swapaxes(Ps, -1, -2))
    return xs, Ps, mus


def future_weights(W, xs, Ps, xp, white, xpair, Ppair):
    """``b_ij`` proportional to ``W_ij L_ij`` over ``i``, one step (``imm_step.backward_step``)."""
    Ws = white @ Ps @ np.swapaxes(white, -1, -2)
    if not np.isfinite(Ws).all():  # absurd sigmas: no usable information, keep Kim's weights
        return W
    s, V = np.linalg.eigh(Ws)  # ascending; reads one triangle
    lam = 1.0 / np.maximum(s, 1e-300) - 1.0
    keep = lam > 1e-9 * lam[:, :1]
    sq = np.sqrt(np.where(keep, lam, 0.0))
    VtU = np.swapaxes(V, -1, -2) @ white  # (j, 4, 4)
    y = np.where(keep, (VtU @ (xs - xp)[:, :, None])[:, :, 0] / np.where(keep, sq, 1.0), 0.0)
    T = sq[:, :, None] * VtU
    r = T[None] @ (xpair - xs[None])[..., None] - y[None, :, :, None]  # (i, j, 4, 1)
    M = T[None] @ Ppair @ np.swapaxes(T, -1, -2)[None] + _EYE4
    chol = np.linalg.cholesky(M)
    z = np.linalg.solve(chol, r)
    logL = -np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1) - 0.5 * (z * z).sum((-2, -1))
    b = W * np.exp(logL - logL.max(0))
    tot = b.sum(0)
    good = (tot > 0) & np.isfinite(tot)
    if good.all():
        return b / tot
    return np.where(good[None], b / np.where(good, tot, 1.0)[None], W)
