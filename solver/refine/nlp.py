"""The refinement NLP of one block of nodes, built once per (size, variant) and reused.

::

    min  sum_i w_i rho(d_i^T M_i d_i) + sum_k lambda_u |u_k - u_{k-1}| + lambda_w |w_k - w_{k-1}|
         + sum_k dt_k (mu_u a_k |u_k| + mu_w |w_k|)
         [+ sum_i (h_i - a_i)^2 / s_a^2 + sum_k (hd_k - hd_{k-1})^2 / (q_h dt_k)]   (altitude)
         [+ sum_j b_j^2 / s_b^2 (+ g (sum_j b_t,j)^2 without a time reference)]        (biases)
    s.t. s_{k+1} = F(s_k, u_k, w_k, t_{k+1} - t_k)   (closed-form motion, solver.motion)
         [h_{k+1} = h_k + dt_k hd_k]
         u in [u_min, u_max],  w in [w_min, w_max],  v_k in [v_min, v_max]

``a_k`` scales the level penalty at node k (:meth:`solver.refine.nodes.NodeData.relieved`);
``d_i = p_i - c_i(h_i)`` is plot i's residual in the plane: ``p_i`` the node position (with
biases: ``p_i - b_t v_i + (dc/dr) b_r + (dc/dpsi) b_psi``, the plot's centre as the radar's
offsets would move it), ``c_i(h)`` the plot's centre at the node's height (as far as the
plot's reach goes, :func:`solver.sensors.reach`; fixed where the altitude is known or not
estimated), ``M_i`` its one-sigma ellipse's weight, ``rho`` the
pseudo-Huber loss ``2 delta^2 (sqrt(1 + q / delta^2) - 1)``. Changes are split ``Delta =
Delta+ - Delta-`` with ``Delta+- >= 0``, so the NLP has only bounds and the dynamics as
constraints; IPOPT solves it with exact sparse second derivatives (a Gauss-Newton Hessian is
cheaper per iteration but stalled at the iteration limit on tight turns: 653 vs 139 iterations
on one dev track). The NLP stays an MX graph over the mapped SX motion function: as fast to
solve as the expanded SX graph and 30 times faster to build (about 0.3 s per size).
"""

from __future__ import annotations

import logging
import time
from functools import cache

import casadi as ca

from .. import compiled
from ..config import RefineSettings
from ..motion import motion_function
from ..sensors import ALTITUDE_FIT_DEGREE, reach
from .layout import (
    BIAS_TERMS,
    Variant,
    block_parameters,
    global_scale,
    global_variables,
    node_parameters,
    node_scale,
    node_variables,
)

LOG = logging.getLogger(__name__)
_deadline = [float("inf")]  # time.monotonic() at which a running solve stops (set per solve)


class _DeadlineCallback(ca.Callback):
    """IPOPT's iteration callback: stops the solve once ``time.monotonic()`` passes the current
    deadline (IPOPT then returns ``User_Requested_Stop`` with its last iterate). Used instead
    of ``max_wall_time``, which is fixed when the solver is built."""

    def __init__(self, name: str, nx: int, ng: int, np_: int):
        ca.Callback.__init__(self)
        self.nx, self.ng, self.np_ = nx, ng, np_
        self.construct(name, {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "ret"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        n = ca.nlpsol_out(i)
        if n == "f":
            return ca.Sparsity.scalar()
        if n in ("x", "lam_x"):
            return ca.Sparsity.dense(self.nx)
        if n in ("g", "lam_g"):
            return ca.Sparsity.dense(self.ng)
        return ca.Sparsity(0, 0)

    def eval(self, arg: list) -> list:
        return [1 if time.monotonic() > _deadline[0] else 0]


_callbacks: list[_DeadlineCallback] = []  # kept alive as long as their solvers


def set_deadline(deadline: float | None) -> None:
    """The ``time.monotonic()`` deadline of the next solves (None: none)."""
    _deadline[0] = float("inf") if deadline is None else deadline


@cache
def block_solver(n: int, variant: Variant = Variant(), warm: bool = False,  # noqa: B008
                 tol: float = RefineSettings.ipopt_tol) -> ca.Function:
    """IPOPT solver for a block of ``n`` nodes: variables ``vec(X / node_scale)`` then the
    global offsets ``/ global_scale``; parameters ``vec(P)`` then the block's ``E`` (layouts in
    :mod:`solver.refine.layout`).

    IPOPT's derivatives of the compiled motion model are compiled as the solver is built. Where
    that fails (no compiler, and a cache that holds the model but not these derivatives: seen
    when another process filled it with the model alone), the solver is built on the
    interpreted model instead, with a warning, rather than the refinement failing."""
    motion = motion_function()
    if not compiled.is_compiled("motion"):
        return _block_solver(n, variant, warm, tol, motion)
    if not _interpreted_derivatives:
        try:
            return _block_solver(n, variant, warm, tol, motion)
        except RuntimeError as e:
            LOG.warning("compiling the motion model's derivatives failed, interpreting them in "
                        "this process's solvers: %s", str(e).strip().splitlines()[-1])
            _interpreted_derivatives.append(True)  # later sizes do not try again
    return _block_solver(n, variant, warm, tol, motion_function(compile=False))


_interpreted_derivatives: list[bool] = []  # non-empty once compiling them failed


def _block_solver(n: int, variant: Variant, warm: bool, tol: float,
                  motion: ca.Function) -> ca.Function:
    nlp = block_nlp(n, variant, motion)
    nx, ng = nlp["x"].shape[0], nlp["g"].shape[0]
    callback = _DeadlineCallback(f"deadline_{n}_{len(_callbacks)}", nx, ng, nlp["p"].shape[0])
    _callbacks.append(callback)
    opts = {
        "print_time": False,
        "error_on_fail": False,
        "iteration_callback": callback,
        "ipopt": {
            "print_level": 0,
            "sb": "yes",
            "tol": tol,  # chi-square units (RefineSettings.ipopt_tol)
            "acceptable_tol": tol,
            "max_iter": 300,
            # adaptive, also in the cold first solve: the monotone barrier from 0.01 there took
            # 11 / 14 / 1 % less CPU on dev seeds 100-107 (seed000 / seed001 / ssr; its
            # quality-function oracle is work in every iteration), but on the blocked seed-like
            # track of tests/test_refine.py it chose other switches: 12.4 m from the one-block
            # solution, against the test's 1 m
            "mu_strategy": "adaptive",
            # refine a linear solve only when its residual asks for it (IPOPT still checks
            # residual_ratio_max after every solve); IPOPT's default of at least one step costs
            # a back-substitution per solve: MUMPS's solves were 17 % of a reconstruction.
            "min_refinement_steps": 0,
            # MUMPS without its scaling and permutation (ICNTL 6 and 8): the NLP is scaled
            # already (layout.node_scale); 4.7 % fewer instructions a seed000 pass, the same
            # iterations (915 on the 42 dev runs) and positions (< 0.05 mm)
            "mumps_permuting_scaling": 0,
            "mumps_scaling": 0,
        },
    }
    if warm:  # the polish solve starts at the first solve's primal-dual solution
        opts["ipopt"].update({"warm_start_init_point": "yes", "warm_start_bound_push": 1e-6,
                              "warm_start_mult_bound_push": 1e-6, "mu_init": 1e-5})
    if variant.biases:
        opts["hess_lag"] = hessian_by_parts(nlp)
    name = f"refine_{n}_{int(variant.altitude)}{variant.biases}{'_warm' if warm else ''}"
    return ca.nlpsol(name, "ipopt", nlp, opts)


def block_nlp(n: int, variant: Variant, motion: ca.Function) -> dict[str, ca.MX]:
    """The NLP of a block of ``n`` nodes (module docstring): ``x`` is ``vec(X)`` then the
    offsets ``B``, two symbols (``x.primitives()``)."""
    V, G = node_variables(variant), global_variables(variant)
    P, E = node_parameters(variant), block_parameters(variant)
    Xs = ca.MX.sym("X", V.size, n)
    X = Xs * ca.repmat(ca.DM(node_scale(variant)), 1, n)
    Bs = ca.MX.sym("B", G.size)
    Pm = ca.MX.sym("P", P.size, n)
    Em = ca.MX.sym("E", E.size)

    def row(M: ca.MX, layout: object, name: str, k: int = 0) -> ca.MX:
        return M[layout[name].start + k, :]  # type: ignore[index]

    x, z, phi, v = (row(X, V, name) for name in ("x", "z", "phi", "v"))
    u, w = row(X, V, "u"), row(X, V, "w")
    dup, dum, dwp, dwm = row(X, V, "du"), row(X, V, "du", 1), row(X, V, "dw"), row(X, V, "dw", 1)
    dt = row(Pm, P, "dt")
    s = ca.vertcat(x, z, phi, v)
    f = motion.map(n - 1)
    nxt = f(s[:, : n - 1], u[: n - 1], w[: n - 1], dt[: n - 1])
    g_dyn = (s[:, 1:] - nxt) / ca.repmat(ca.DM(node_scale(variant)[:4]), 1, n - 1)
    g_ctl = ca.vertcat(u - ca.horzcat(Em[E["u_prev"]], u[: n - 1]) - dup + dum,
                       w - ca.horzcat(Em[E["w_prev"]], w[: n - 1]) - dwp + dwm)
    px, pz = x, z
    if variant.biases:
        B = Bs * ca.DM(global_scale(variant))
        b = ca.reshape(B, BIAS_TERMS, variant.biases)  # column j: radar j's offsets
        sel = Pm[P["sensor"], :]
        b_r, b_psi, b_t = (ca.mtimes(b[i, :], sel) for i in range(BIAS_TERMS))
        vx, vz = v * ca.cos(phi), v * ca.sin(phi)
        px = px - b_t * vx + row(Pm, P, "d_range") * b_r + row(Pm, P, "d_azimuth") * b_psi
        pz = pz - b_t * vz + row(Pm, P, "d_range", 1) * b_r + row(Pm, P, "d_azimuth", 1) * b_psi
    cx, cz = row(Pm, P, "centre"), row(Pm, P, "centre", 1)
    g_alt = []
    alt_pen = 0
    if variant.altitude:
        h, hd = row(X, V, "h"), row(X, V, "hd")
        h_mid, h_half = row(Pm, P, "h_mid"), row(Pm, P, "h_half")
        hc = reach(h, h_mid, h_half, ca)  # the height the plot's centre follows
        sh = (hc - h_mid) / h_half
        ground = ca.sqrt(row(Pm, P, "slant") ** 2 - (hc - row(Pm, P, "site_h")) ** 2)
        cx = cx + row(Pm, P, "ray") * ground
        cz = cz + row(Pm, P, "ray", 1) * ground
        for j in range(ALTITUDE_FIT_DEGREE):
            cx = cx + row(Pm, P, "centre_h", j) * sh ** (j + 1)
            cz = cz + row(Pm, P, "centre_h", ALTITUDE_FIT_DEGREE + j) * sh ** (j + 1)
        g_alt = [(h[1:] - h[: n - 1] - dt[: n - 1] * hd[: n - 1]) / node_scale(variant)[-2]]
        dhd = hd - ca.horzcat(Em[E["hd_prev"]], hd[: n - 1])
        alt_pen = ca.sum2(row(Pm, P, "alt_info") * (h - row(Pm, P, "alt")) ** 2
                          + row(Pm, P, "hd_info") * dhd**2)
    dx, dz = px - cx, pz - cz
    info_a, info_b, info_c = row(Pm, P, "info"), row(Pm, P, "info", 1), row(Pm, P, "info", 2)
    q = info_a * dx * dx + 2 * info_b * dx * dz + info_c * dz * dz
    delta = Em[E["huber"]]
    data = ca.sum2(row(Pm, P, "weight") * 2 * delta**2 * (ca.sqrt(1 + q / delta**2) - 1))
    pen = ca.sum2(row(Pm, P, "switch") * (dup + dum) + row(Pm, P, "switch", 1) * (dwp + dwm))
    eps = Em[E["level_eps"]]
    pen += ca.sum2(dt * (Em[E["level_u"]] * row(Pm, P, "level") * ca.sqrt(u * u + eps**2)
                         + Em[E["level_w"]] * row(Pm, P, "level", 1) * ca.sqrt(w * w + eps**2)))
    pen += alt_pen
    if variant.biases:
        B = Bs * ca.DM(global_scale(variant))
        pen += ca.sum1(Em[E["bias_info"]] * B**2)
        pen += ca.dot(Em[E["time_gauge"]], B[2::BIAS_TERMS]) ** 2
    nlp = {
        "x": ca.vertcat(ca.vec(Xs), Bs),
        "p": ca.vertcat(ca.vec(Pm), Em),
        "f": data + pen,
        "g": ca.vertcat(ca.vec(g_dyn), ca.vec(g_ctl), *(ca.vec(g) for g in g_alt)),
    }
    return nlp


def hessian_by_parts(nlp: dict[str, ca.MX]) -> ca.Function:
    """The Lagrangian's Hessian (upper triangle, IPOPT's ``hess_lag``) in blocks: nodes-nodes,
    nodes-offsets, offsets-offsets. The offsets couple every node, so the whole Hessian has
    dense rows, and CasADi's star colouring of it is quadratic in the nodes: building one solver
    of 1024 nodes with three radars' offsets took 6.3 s, 20 s at 1750 nodes (a 47-s first
    request). In blocks: 0.3 s, the same sparsity and values (tested)."""
    Xs, Bs = nlp["x"].primitives()
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", nlp["g"].shape[0])
    lagrangian = lam_f * nlp["f"] + ca.dot(lam_g, nlp["g"])
    h_xx = ca.hessian(lagrangian, Xs)[0]
    h_xb = ca.jacobian(ca.gradient(lagrangian, Xs), Bs)
    h_bb = ca.hessian(lagrangian, Bs)[0]
    h = ca.triu(ca.blockcat([[h_xx, h_xb], [h_xb.T, h_bb]]))
    return ca.Function("hess_lag_parts", [nlp["x"], nlp["p"], lam_f, lam_g], [h])
