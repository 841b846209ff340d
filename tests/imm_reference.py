"""The IMM smoother's passes and the causal IMM in plain numpy, as they were before their steps
moved to compiled CasADi functions (``solver.estimation.imm_step``, ``imm_ct_step``): the
reference the tests compare those with (and the future-mode likelihood's own tests run on).
Equations in ``solver.estimation.imm_smoother`` and ``imm_ct_step``."""

import numpy as np

from solver.estimation.common import estimate
from solver.estimation.gating import GATE_SIGMA, gated_pass
from solver.estimation.imm import OMEGA_MAX, Q_CT, Q_CV, Q_OMEGA, TAU_CT, TAU_CV, prior
from solver.estimation.imm_smoother import N_MODES, ForwardPass, _prior, pair_terms
from solver.estimation.kalman import position_update
from solver.estimation.models import ct_predict

_POS = (0, 1)
_EYE4 = np.eye(4)


def imm_forward(meas, Phi, Q, Pi, mu0, measurement: str = "ekf",
                gate: float | None = GATE_SIGMA) -> ForwardPass:
    """The forward IMM of ``imm_smoother.imm_forward``: one ``position_update`` per mode; a plot
    whose least NIS over the modes exceeds ``gate^2`` left out as ``gating.gated_pass`` says."""
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
    loglik, nis = np.empty(N_MODES), np.empty(N_MODES)

    def step(k: int, lanes, use: bool):
        m, x, P = mu[k - 1], xf[k - 1], Pf[k - 1]
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
        if not use:
            xf[k], Pf[k], mu[k] = xp, Pp, c
            return np.zeros((2, 1))
        x, P = xf[k], Pf[k]
        for j in range(N_MODES):
            x[j], P[j], nis[j], logdet = position_update(xp[j], Pp[j], meas, k, _POS, measurement)
            loglik[j] = -0.5 * (nis[j] + logdet)
        post = c * np.exp(loglik - loglik.max())
        total = post.sum()
        mu[k] = post / total if total > 0 and np.isfinite(total) else c
        return np.array([[nis.min()], [-2 * (loglik.max() + np.log(total))]])

    gated = gated_pass(n, 1, step, gate)[:, 0]
    return ForwardPass(xf, Pf, mu, W, XP, PP, gated)


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


# ---- the causal IMM (solver.estimation.imm) as it was before its step was compiled ----


def switching_matrix(T: float, tau_cv: float, tau_ct: float):
    """``Pi(T) = expm(G T)`` of the two-state chain with leaving rates ``1/tau``."""
    a, b = 1 / tau_cv, 1 / tau_ct
    s = a + b
    e = np.exp(-s * T)
    return np.array([[(b + a * e) / s, a * (1 - e) / s], [b * (1 - e) / s, (a + b * e) / s]])


def _cv_noise(T: float, q: float):
    Q = np.zeros((5, 5))
    for p, v in ((0, 2), (1, 3)):
        Q[p, p], Q[p, v], Q[v, p], Q[v, v] = q * T**3 / 3, q * T**2 / 2, q * T**2 / 2, q * T
    return Q


def run_imm(meas, q_cv=Q_CV, q_ct=Q_CT, q_omega=Q_OMEGA, tau_cv=TAU_CV, tau_ct=TAU_CT,
            omega_max=OMEGA_MAX, measurement: str = "ekf", gate: float | None = GATE_SIGMA):
    """``solver.estimation.imm.run_imm`` in numpy: one ``position_update`` per mode; the gate
    on the modes' least NIS (``gating.gated_pass``)."""
    n = len(meas)
    t = meas.t
    x0, P0 = prior(meas)
    XS = np.empty((n, 2, 5))
    PS = np.empty((n, 2, 5, 5))
    MU = np.empty((n, 2))
    XS[0] = np.stack([x0, x0])
    PS[0] = np.stack([P0, P0])
    PS[0, 0, 4, 4] = 1e-12  # the CV model's omega is 0
    XS[0, 0, 4] = 0.0
    MU[0] = np.array([tau_cv, tau_ct]) / (tau_cv + tau_ct)
    F_cv = np.eye(5)
    F_cv[4, 4] = 0.0
    nis = np.empty(2)

    def step(k: int, lanes, use: bool):
        xs, Ps, mu = XS[k - 1], PS[k - 1], MU[k - 1]
        T = t[k] - t[k - 1]
        Pi = switching_matrix(T, tau_cv, tau_ct)
        c = mu @ Pi  # predicted model probabilities
        w = Pi * mu[:, None] / c[None, :]  # w[i, j] = P(was i | now j)
        xm = w.T @ xs
        Pm = np.empty_like(Ps)
        for j in range(2):
            d = xs - xm[j]
            Pm[j] = np.einsum("i,ijk->jk", w[:, j], Ps + d[:, :, None] * d[:, None, :])
        loglik = np.zeros(2)
        F_cv[0, 2] = F_cv[1, 3] = T
        Q_cv = _cv_noise(T, q_cv)
        Q_cv[4, 4] = 1e-12
        preds = [(F_cv @ xm[0], F_cv @ Pm[0] @ F_cv.T + Q_cv)]
        fx, J = ct_predict(xm[1], T)
        Q_ct = _cv_noise(T, q_ct)
        Q_ct[4, 4] = q_omega * T
        preds.append((fx, J @ Pm[1] @ J.T + Q_ct))
        for j, (xp, Pp) in enumerate(preds):
            if use:
                XS[k, j], PS[k, j], nis[j], logdet = position_update(xp, Pp, meas, k, (0, 1),
                                                                     measurement)
                loglik[j] = -0.5 * (nis[j] + logdet)
            else:
                XS[k, j], PS[k, j] = xp, Pp
        XS[k, 1, 4] = np.clip(XS[k, 1, 4], -omega_max, omega_max)  # projection on the bound
        lik = np.exp(loglik - loglik.max())
        m = c * lik
        deviance = -2 * (loglik.max() + np.log(m.sum()))
        m = np.maximum(m / m.sum(), 1e-12)
        MU[k] = m / m.sum()
        return np.array([[nis.min()], [deviance]])

    gated = gated_pass(n, 1, step, gate)[:, 0]
    x = np.einsum("ni,nij->nj", MU, XS)
    d = XS - x[:, None, :]
    P = np.einsum("ni,nijk->njk", MU, PS + d[..., :, None] * d[..., None, :])
    return estimate("imm", t, x[:, :4], P[:, :4, :4], model_probabilities=MU,
                    turn_rate=x[:, 4], gated=gated)
