"""The IMM smoother's passes in plain numpy, as they were before the steps moved to compiled
CasADi functions (``solver.estimation.imm_step``): the reference the tests compare those with
(and the future-mode likelihood's own tests run on). Equations in
``solver.estimation.imm_smoother``."""

import numpy as np

from solver.estimation.imm_smoother import N_MODES, ForwardPass, _prior
from solver.estimation.kalman import position_update

_POS = (0, 1)
_EYE4 = np.eye(4)


def imm_forward(meas, Phi, Q, Pi, mu0, measurement: str = "ekf") -> ForwardPass:
    """The forward IMM (Blom and Bar-Shalom 1988). Per step ``k`` (``T = t_k - t_{k-1}``):

    - predicted mode probabilities ``c_j = sum_i Pi_ij mu_i``, mixing weights
      ``W_ij = P(m_{k-1} = i | m_k = j, Z^{k-1}) = Pi_ij mu_i / c_j``;
    - mixed ``x0_j = sum_i W_ij x_i``, ``P0_j = sum_i W_ij (P_i + (x_i - x0_j)(x_i - x0_j)^T)``;
    - model ``j``: ``x_j = Phi_j x0_j``, ``P_j = Phi_j P0_j Phi_j^T + Q_j``, then the position
      update with plot ``k`` (``kalman.position_update``, Joseph form), likelihood
      ``L_j = exp(-(nu^T S^-1 nu + log det S) / 2)``;
    - ``mu_j = c_j L_j / sum_l c_l L_l``.

    A mode with ``c_j = 0`` (absorbing chain) is mixed with ``mu`` and keeps probability 0.
    """
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
    """Backward pass per mode pair (Kim 1994), ``i`` the mode at ``k``, ``j`` at ``k + 1``. With the
    forward mode-conditioned ``x_k^i``, ``P_k^i``:

    - states: ``x^{ij} = Phi_j x_k^i``, ``P^{ij} = Phi_j P_k^i Phi_j^T + Q_j``,
      ``C^{ij} = P_k^i Phi_j^T (P^{ij})^-1``; ``xs_k^{ij} = x_k^i + C^{ij} (xs_{k+1}^j - x^{ij})``,
      ``Ps_k^{ij} = P_k^i + C^{ij} (Ps_{k+1}^j - P^{ij}) C^{ij T}`` (exact RTS steps: the models
      are linear);
    - modes: ``P(m_k = i, m_{k+1} = j | Z^N) = b_ij mus_{k+1}(j)``, ``mus_k(i) = sum_j`` of it,
      ``b_ij = P(m_k = i | m_{k+1} = j, Z^N)``;
    - ``xs_k^i = sum_j w_ij xs_k^{ij}``, ``Ps_k^i = sum_j w_ij (Ps_k^{ij} + dd^T)``,
      ``w_ij = b_ij mus_{k+1}(j) / mus_k(i)``, ``d = xs_k^{ij} - xs_k^i``.

    Kim's ``b_ij`` is the forward ``W_ij = P(m_k = i | m_{k+1} = j, Z^k)``: it ignores what the
    plots after ``k`` say about ``m_k``, so a turn the filter noticed late starts late in the
    smoothed modes too, and a stiff CV model then carries the turned heading backwards
    (measured: on tracks drawn from the model itself with ``q_cv = 0.5``, twice the forward
    filter's error). With ``future_modes`` (default) ``b_ij`` is ``W_ij L_ij`` normalised over
    ``i``, ``L_ij`` the likelihood of the later plots given the pair:

        L_ij = int N(x; xs_{k+1}^j, Ps_{k+1}^j) / N(x; xp_{k+1}^j, Pp_{k+1}^j)
                   N(x; x^{ij}, P^{ij}) dx

    (the later plots' information about ``x_{k+1}``: the smoothed over the forward mixed
    prediction ``xp``, ``Pp``, kept where it is positive; closed form in
    :func:`_future_weights`).

    The pair gains depend on the forward pass only and are computed for all steps at once.
    Returns the smoothed mode-conditioned states, covariances and mode probabilities.
    """
    xf, Pf, mu, W = fw.x, fw.P, fw.mu, fw.W
    n = xf.shape[0]
    xs, Ps, mus = xf.copy(), Pf.copy(), mu.copy()
    if n < 2:
        return xs, Ps, mus
    # pairs (k, i, j): model j applied to the filtered x_k^i
    Phj = Phi[:, None]  # (n-1, 1, j, 4, 4)
    Pk = Pf[:-1, :, None]  # (n-1, i, 1, 4, 4)
    PhiP = Phj @ Pk  # Phi_j P_k^i
    xpair = (Phj @ xf[:-1, :, None, :, None])[..., 0]  # (n-1, i, j, 4)
    Ppair = PhiP @ np.swapaxes(Phj, -1, -2) + Q[:, None]
    Ppair = 0.5 * (Ppair + np.swapaxes(Ppair, -1, -2))
    C = np.swapaxes(np.linalg.solve(Ppair, PhiP), -1, -2)  # P_k^i Phi_j^T (P^{ij})^-1
    CT = np.swapaxes(C, -1, -2)
    # the parts of the pair recursion known before the backward pass:
    # xs^{ij} = a^{ij} + C^{ij} xs_{k+1}^j, Ps^{ij} = B^{ij} + C^{ij} Ps_{k+1}^j C^{ij T}
    a = xf[:-1, :, None, :] - (C @ xpair[..., None])[..., 0]
    B = Pk - C @ Ppair @ CT
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
    """``b_ij`` proportional to ``W_ij L_ij`` over ``i`` (see :func:`imm_backward`) for one step:
    ``xs (j, 4)``, ``Ps (j, 4, 4)`` smoothed at ``k + 1``; ``xp`` the forward mixed prediction
    and ``white = U^-1`` with ``Pp = U U^T`` its covariance; ``xpair (i, j, 4)``,
    ``Ppair (i, j, 4, 4)`` the pair predictions.

    The later plots' information about ``x_{k+1}`` is ``L = Ps^-1 - Pp^-1`` with the vector
    ``e = Pp^-1 (xs - xp)``: a pseudo-measurement ``y = L^+ e`` of weight ``L``. In whitened
    coordinates ``w = U^-1 x`` it is ``U^-1 Ps U^-T = V diag(s) V^T``, information
    ``l = 1/s - 1`` along ``V``; directions with ``l <= 0`` (the mixture approximations can make
    the smoothed spread exceed the prediction's) carry none and are dropped: negative
    information would reward pair predictions for being far away. Whitening makes the split
    independent of units (m against m/s). With ``T = diag(sqrt l) V^T U^-1``,
    ``r = T (x^{ij} - xs) - diag(1/sqrt l) V^T U^-1 (xs - xp)`` and
    ``M = I + T P^{ij} T^T`` (positive definite):
    ``log L_ij = -(log det M + r^T M^-1 r) / 2`` up to a constant per ``j``."""
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
