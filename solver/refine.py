"""Full-track refinement: one bounded piecewise-constant-control NLP over all plots.

The sliding windows (spec section 6) look a few plots ahead and never revise what they
accepted; a reconstruction sees the whole recording. This solves, by multiple shooting on a
node grid (every plot time, plus extra nodes so no interval exceeds ``max_node_step_s``)::

    min  sum_i rho(d_i^T M_i d_i) + sum_k lambda_u |u_k - u_{k-1}| + lambda_w |w_k - w_{k-1}|
                                  + sum_k dt_k (mu_u |u_k| + mu_w |w_k|)
    s.t. s_{k+1} = F(s_k, u_k, w_k, t_{k+1} - t_k)   (closed-form motion, solver.motion)
         u in [u_min, u_max],  w in [w_min, w_max],  v_k in [v_min, v_max]

where ``s = (x, z, phi, v)``, ``d_i`` is plot i's position residual, ``M_i`` its statistical
weight (one-sigma ellipse, :func:`solver.geometry.statistical_ellipses`), ``rho`` the
pseudo-Huber loss ``2 delta^2 (sqrt(1 + q / delta^2) - 1)`` (``~q`` for small ``q``, linear in
the residual beyond ``delta`` sigmas) and the L1 term keeps the controls piecewise constant with
few switches; the level term (smoothed near 0) says aircraft fly mostly straight at constant
speed. The changes are split ``Delta = Delta+ - Delta-`` with ``Delta+-  >= 0``, so the NLP has
only bounds and the dynamics as constraints; IPOPT solves it with exact sparse second
derivatives. Since ``v`` is linear inside an interval, bounds at the nodes bound it everywhere.

A second, warm-started solve then holds every control change the first one did not select
(``<= switch_threshold``) at exactly zero, so the segments describe the trajectory exactly, and
gives no weight to plots further than ``outlier_gate`` sigmas from the first solution (unless
they are more than ``outlier_max_share`` of the plots, or the first solution's speed sits at a
bound for ``SPEED_MISFIT_SHARE`` of the track: then the bounds or the sigmas, not a few wild
plots, are what does not fit, and a warning says so).

Solvers are built once per block size of a fixed ladder and reused: a track is cut into
overlapping blocks of at most ``block_nodes`` nodes, each padded to the next ladder size with
zero-length, zero-weight intervals (``F(s, u, w, 0) = s``). A block after the first starts from
the previous block's state at the middle of their overlap (its controls there enter the first
L1 term), so the result is one continuous piecewise-constant-control trajectory.

Uncertainty (Laplace approximation at the solution): the L1 prior on control changes is
replaced by a Gaussian of the same variance (a Laplace density ``exp(-lambda |Delta| / 2)`` has
variance ``8 / lambda^2``), the dynamics are linearised about the solution, and a
Rauch-Tung-Striebel smoother over the nodes gives the marginal covariance of the Gauss-Newton
posterior; a residual down-weighted by the robust loss enters with its IRLS weight.
"""

from __future__ import annotations

import math
import time
from functools import cache
from typing import NamedTuple

import casadi as ca
import numpy as np

from . import compiled
from .config import ReconstructionConfig, RefineSettings
from .estimation.cv_rts import smoothed_means
from .geometry import statistical_ellipses
from .inputs import Bounds, FloatArray, Plots, Radar
from .motion import motion_function, propagate
from .results import Diagnostics, Reconstruction, Segment, StateSeries
from .trajectory import evaluate, sample_times

# Block sizes (nodes): ratio 2^(1/4), so padding wastes at most 19 %; one solver per size, built
# on first use (about 0.3 s each: the NLP stays an MX graph over the mapped SX motion function,
# which solves as fast as the expanded SX graph and builds 30 times faster).
LADDER = tuple(sorted({round(16 * 2 ** (k / 4)) for k in range(29)}))
INIT_SMOOTHER_Q = 30.0  # m^2/s^3: the CV smoother of the initial guess follows turns
NX = 6  # node variables: x, z, phi, v, u, w
ND = 4  # L1 split: du+, du-, dw+, dw-
# IPOPT works on the node variables divided by VAR_SCALE (positions in units of 30 m, speed in
# units of 10 m/s) and on the dynamics gaps divided likewise: 9 % and 7 % fewer iterations than
# unscaled on the 18 dev runs of seeds 100 and 101 (10 m or 100 m: 2-11 %), same solutions.
VAR_SCALE = np.array([30.0, 30.0, 1.0, 10.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
# The speed at a bound of bounds.v for this share of the track or more means the bounds do not
# fit the aircraft (warned; no plot is then taken for a wild one).
SPEED_MISFIT_SHARE = 0.1


@cache
def _jacobian_function() -> ca.Function:
    """``J(s6, dt) -> d s6(dt) / d s6``: the motion map's Jacobian with ``u, w`` in the state."""
    s = ca.SX.sym("s", NX)
    dt = ca.SX.sym("dt")
    out = ca.vertcat(motion_function()(s[:4], s[4], s[5], dt), s[4], s[5])
    return compiled.function("motion_jac", [s, dt], [ca.jacobian(out, s)], ["s", "dt"], ["jac"])


NPAR = 9  # per node: dt to the next node, centre (cx, cz), R2 entries (a, b, c), plot weight,
#           lambda_u, lambda_w
NEXTRA = 6  # per block: u_prev, w_prev, huber delta, level_u, level_w, level smoothing


@cache
def block_solver(n: int, warm: bool = False, tol: float = RefineSettings.ipopt_tol
                 ) -> ca.Function:
    """IPOPT solver for a block of ``n`` nodes (built once per ladder size and tolerance).

    Variables per node ``[x, z, phi, v, u, w, du+, du-, dw+, dw-] / VAR_SCALE``; parameters
    ``NPAR`` per node and ``NEXTRA`` per block. Exact sparse Hessian: a Gauss-Newton one
    (without the dynamics' curvature) is cheaper per iteration but stalled at IPOPT's iteration
    limit on tight turns (measured: 653 vs 139 iterations on one dev track).
    """
    X_scaled = ca.MX.sym("X", NX + ND, n)
    X = X_scaled * ca.repmat(ca.DM(VAR_SCALE), 1, n)
    P = ca.MX.sym("P", NPAR, n)
    E = ca.MX.sym("E", NEXTRA)
    s, u, w = X[:4, :], X[4, :], X[5, :]
    dup, dum, dwp, dwm = X[6, :], X[7, :], X[8, :], X[9, :]
    dt = P[0, :]
    f = motion_function().map(n - 1)
    nxt = f(s[:, : n - 1], u[: n - 1], w[: n - 1], dt[: n - 1])
    g_dyn = (s[:, 1:] - nxt) / ca.repmat(ca.DM(VAR_SCALE[:4]), 1, n - 1)
    g_ctl = ca.vertcat(u - ca.horzcat(E[0], u[: n - 1]) - dup + dum,
                       w - ca.horzcat(E[1], w[: n - 1]) - dwp + dwm)
    dx, dz = s[0, :] - P[1, :], s[1, :] - P[2, :]
    q = P[3, :] * dx * dx + 2 * P[4, :] * dx * dz + P[5, :] * dz * dz
    delta = E[2]
    data = ca.sum2(P[6, :] * 2 * delta**2 * (ca.sqrt(1 + q / delta**2) - 1))
    pen = ca.sum2(P[7, :] * (dup + dum) + P[8, :] * (dwp + dwm))
    eps = E[5]
    pen += ca.sum2(dt * (E[3] * ca.sqrt(u * u + eps**2) + E[4] * ca.sqrt(w * w + eps**2)))
    nlp = {
        "x": ca.vec(X_scaled),
        "p": ca.vertcat(ca.vec(P), E),
        "f": data + pen,
        "g": ca.vertcat(ca.vec(g_dyn), ca.vec(g_ctl)),
    }
    opts = {
        "print_time": False,
        "error_on_fail": False,
        "ipopt": {
            "print_level": 0,
            "sb": "yes",
            "tol": tol,  # chi-square units (RefineSettings.ipopt_tol)
            "acceptable_tol": tol,
            "max_iter": 300,
            "mu_strategy": "adaptive",
        },
    }
    if warm:  # the polish solve starts at the first solve's primal-dual solution
        opts["ipopt"].update({"warm_start_init_point": "yes", "warm_start_bound_push": 1e-6,
                              "warm_start_mult_bound_push": 1e-6, "mu_init": 1e-5})
    return ca.nlpsol(f"refine_{n}{'_warm' if warm else ''}", "ipopt", nlp, opts)


def build_solvers() -> None:
    """Build every block solver of the ladder (about 2 s in all), e.g. before serving."""
    for n in LADDER:
        block_solver(n)
        block_solver(n, warm=True)


def node_grid(t_plots: FloatArray, max_step: float) -> tuple[FloatArray, np.ndarray]:
    """Node times (every plot time plus equal subdivisions of long gaps) and each plot's node."""
    gaps = np.diff(t_plots)
    parts = np.maximum(np.ceil(gaps / max_step - 1e-9).astype(int), 1)
    starts = np.concatenate([[0], np.cumsum(parts)])
    frac = np.arange(starts[-1]) - np.repeat(starts[:-1], parts)
    t_nodes = np.repeat(t_plots[:-1], parts) + frac * np.repeat(gaps / parts, parts)
    return np.append(t_nodes, t_plots[-1]), starts


def _blocks(n: int, size: int, overlap: int) -> list[tuple[int, int, int]]:
    """``(start, stop, keep_until)`` node ranges; block j keeps ``[start, keep_until]``."""
    if n <= size:
        return [(0, n, n - 1)]
    out = []
    start = 0
    while True:
        stop = min(start + size, n)
        if stop == n:
            out.append((start, n, n - 1))
            return out
        cut = stop - overlap // 2
        out.append((start, stop, cut))
        start = cut


def refine(plots: Plots, radar: Radar, config: ReconstructionConfig,
           initial: Reconstruction | None = None) -> Reconstruction:
    """Reconstruct by the full-track NLP (at least 3 plots).

    The initial guess is the means of a constant-velocity smoother on the plots' ellipses
    (``config.refine.init == "smoother"``, default; :func:`solver.estimation.cv_rts.smoothed_means`)
    or the sliding-window result ``initial`` (``"sliding"``). The start decides the iteration
    count, not the answer: started at the true trajectory instead, the refinement reached the same
    solutions (pooled RMS equal to 1e-8 m over the six dev tracks, seeds 100 and 101, for each of
    seed000 and seed001; more iterations: 37 against 20 on one track).
    """
    t0 = time.perf_counter()
    st: RefineSettings = config.refine
    bounds = config.bounds
    t_nodes, plot_node = node_grid(plots.t, st.max_node_step_s)
    n = t_nodes.size
    meas = _node_measurements(plots, radar, t_nodes.size, plot_node)
    if st.init == "sliding":
        if initial is None or not initial.segments:
            raise ValueError('refine.init == "sliding" needs the sliding-window result')
        guess = nodes_from_segments(initial, t_nodes, bounds)
        diag = initial.diagnostics
    else:
        at = meas[plot_node]
        info = np.stack([at[:, [M_A, M_B]], at[:, [M_B, M_C]]], axis=1)
        smooth = smoothed_means(plots.t, at[:, [M_CX, M_CZ]], info, INIT_SMOOTHER_Q)
        guess = nodes_from_states(StateSeries(plots.t, *smooth.T), t_nodes, bounds)
        diag = Diagnostics(criterion="R2")
    delta = st.huber_delta if st.huber_delta is not None else 1e6
    diag.method = "refined"
    blocks = _blocks(n, st.block_nodes, st.overlap_nodes)

    duals: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(blocks)

    clock = {"ipopt": 0.0, "model": 0.0}  # s inside IPOPT calls / in its model evaluations

    def solve_blocks(start_guess: np.ndarray, meas: np.ndarray,
                     fixed: np.ndarray | None) -> tuple[np.ndarray, int, int]:
        out = np.empty((n, NX))
        prev: np.ndarray | None = None
        fails = its = 0
        for j, (start, stop, keep) in enumerate(blocks):
            t_call = time.perf_counter()
            blk = _solve_block(
                t_nodes[start:stop], meas[start:stop], start_guess[start:stop], prev, bounds, st,
                delta, None if fixed is None else fixed[:, start:stop], duals[j])
            clock["ipopt"] += time.perf_counter() - t_call
            clock["model"] += blk.model_s
            duals[j] = blk.duals
            fails += not blk.ok
            its += blk.iterations
            out[start: keep + 1] = blk.x[: keep + 1 - start]
            prev = blk.x[keep - start]
        return out, fails, its

    sol, failures, iters = solve_blocks(guess, meas, None)
    solves = len(blocks)
    # Second solve. Outlier gate: plots further than ``outlier_gate`` sigmas from the first
    # solution get no weight (reported). Polish (relaxed lasso): keep the switches the L1
    # solution selected, hold every other control change at exactly zero. Both are decided on
    # the stitched solution, so blocks and one block decide alike.
    rejected = np.array([], dtype=int)
    if st.outlier_gate is not None:
        far = np.flatnonzero(_quad(sol, meas)[plot_node] > st.outlier_gate**2)
        far_text = (f"{far.size} of {plot_node.size} plots are more than {st.outlier_gate:g} "
                    "sigma from the track")
        if far.size and max(_at_bounds(t_nodes, sol, bounds, "v")) >= SPEED_MISFIT_SHARE:
            diag.warnings.append(f"{far_text}, whose speed sits at a bound of bounds.v: the "
                                 "bounds, not wild plots, keep them far; none was given zero "
                                 "weight")
        elif far.size > st.outlier_max_share * plot_node.size:
            diag.warnings.append(f"{far_text}: too many to be wild plots (do the bounds and the "
                                 "radar's sigmas fit this aircraft?); none was given zero weight")
        else:
            rejected = far
    fixed = None
    if st.switch_threshold > 0 and n > 1:
        fixed = np.zeros((2, n), dtype=bool)
        fixed[:, 1:] = np.abs(np.diff(sol[:, 4:6], axis=0)).T <= st.switch_threshold
    if fixed is not None or rejected.size:
        meas = meas.copy()
        meas[plot_node[rejected], M_W] = 0.0
        sol, f2, it2 = solve_blocks(sol, meas, fixed)
        failures, iters, solves = failures + f2, iters + it2, solves + len(blocks)
    if rejected.size:
        diag.warnings.append(
            f"{rejected.size} plot(s) more than {st.outlier_gate:g} sigma from the track were "
            f"given no weight: plots {rejected.tolist()[:50]}")
    diag.extra["rejected_plots"] = int(rejected.size)
    diag.solver_failures += failures
    diag.extra.update(refine_blocks=len(blocks), refine_nodes=n, refine_iterations=iters)
    if failures:
        diag.warnings.append(f"refinement: IPOPT did not converge in {failures} of {solves} "
                             f"block solve(s) over {len(blocks)} block(s); the last iterate "
                             "was kept")
    _report_bounds(t_nodes, sol, bounds, diag)
    segments = _segments(t_nodes, sol, bounds)
    cov_nodes = _node_covariance(t_nodes, sol, meas, st, delta, bounds)
    at_plots = _series(t_nodes, sol, cov_nodes, plots.t)
    samples = _series(t_nodes, sol, cov_nodes,
                      sample_times(plots.t[0], plots.t[-1], config.sample_step_s))
    crit = meas[:, M_W] * _quad(sol, meas)
    diag.criterion_values = [float(crit.sum())]
    diag.extra["refine_ms"] = (time.perf_counter() - t0) * 1e3
    diag.extra["refine_ipopt_ms"] = clock["ipopt"] * 1e3
    diag.extra["refine_model_ms"] = clock["model"] * 1e3
    diag.extra["switches"] = len(segments) - 1
    return Reconstruction(segments, at_plots, samples, diag)


# columns of the node measurement array
M_CX, M_CZ, M_A, M_B, M_C, M_W = range(6)


def _node_measurements(plots: Plots, radar: Radar, n: int, plot_node: np.ndarray) -> np.ndarray:
    """``(n, 6)`` per node: the plot's one-sigma ellipse centre ``(cx, cz)`` and R2 entries
    ``(a, b, c)``, and its weight (1 at plot nodes, 0 elsewhere).

    The centre is the plot point at the ground range where the plot carries its altitude and at
    the slant range otherwise: a constant unknown altitude is not observable from 2-D plots
    (a straight pass at altitude ``h`` and ground distance ``d`` has the same slant ranges as one
    at altitude 0 and distance ``sqrt(d^2 + h^2)``), so it is not estimated.
    """
    ell = statistical_ellipses(plots, radar)
    meas = np.zeros((n, 6))
    meas[plot_node, M_CX], meas[plot_node, M_CZ] = ell.cx, ell.cz
    meas[plot_node, M_A:M_C + 1] = ell.weights()
    meas[plot_node, M_W] = 1.0
    return meas


def _quad(sol: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """R2 terms ``d^T M d`` of the node positions (0 where no plot)."""
    dx, dz = sol[:, 0] - meas[:, M_CX], sol[:, 1] - meas[:, M_CZ]
    return meas[:, M_A] * dx * dx + 2 * meas[:, M_B] * dx * dz + meas[:, M_C] * dz * dz


def nodes_from_segments(initial: Reconstruction, t_nodes: FloatArray,
                        bounds: Bounds) -> np.ndarray:
    """Node guess ``(x, z, phi, v, u, w)`` from the sliding-window segments."""
    series = evaluate(initial.segments, t_nodes)
    starts = np.array([s.t_start for s in initial.segments])
    idx = np.clip(np.searchsorted(starts, t_nodes, side="right") - 1, 0, len(starts) - 1)
    u = np.array([initial.segments[i].u for i in idx])
    w = np.array([initial.segments[i].w for i in idx])
    return _node_array(series, u, w, bounds)


def nodes_from_states(states: StateSeries, t_nodes: FloatArray, bounds: Bounds) -> np.ndarray:
    """Node guess from smoothed states at the plot times (e.g. a CV smoother):
    states interpolated linearly to the nodes, ``u = v dphi/dt``, ``w = dv/dt``."""
    cols = [np.interp(t_nodes, states.t, c) for c in (states.x, states.z, states.vx, states.vz)]
    series = StateSeries(t_nodes, *cols)
    phi = np.unwrap(series.heading)
    v = series.speed
    dt = np.maximum(np.diff(t_nodes), 1e-9)
    u = np.append(v[:-1] * np.diff(phi) / dt, 0.0)
    w = np.append(np.diff(v) / dt, 0.0)
    return _node_array(series, u, w, bounds)


def _node_array(series: StateSeries, u: FloatArray, w: FloatArray, bounds: Bounds) -> np.ndarray:
    out = np.empty((series.t.size, NX))
    out[:, 0], out[:, 1] = series.x, series.z
    out[:, 2] = np.unwrap(series.heading)
    out[:, 3] = np.clip(series.speed, *bounds.v)
    out[:, 4] = np.clip(u, *bounds.u)
    out[:, 5] = np.clip(w, *bounds.w)
    return out


def _ladder(n: int) -> int:
    for size in LADDER:
        if n <= size:
            return size
    raise ValueError(f"block of {n} nodes exceeds the largest ladder size {LADDER[-1]}")


class BlockResult(NamedTuple):
    """One block's solve: node states ``(m, 6)``, success, IPOPT iterations, the multipliers
    (to warm-start the next solve), and the seconds IPOPT spent evaluating the model."""

    x: np.ndarray
    ok: bool
    iterations: int
    duals: tuple[np.ndarray, np.ndarray] | None
    model_s: float


def _solve_block(t: FloatArray, meas: np.ndarray, guess: np.ndarray, prev: np.ndarray | None,
                 bounds: Bounds, st: RefineSettings, delta: float,
                 fixed: np.ndarray | None = None,
                 duals: tuple[np.ndarray, np.ndarray] | None = None) -> BlockResult:
    """Solve one block; ``prev`` (the previous block's node state, or None) fixes the start;
    ``fixed`` (``(2, m)`` bool) marks control changes held at exactly zero (polish step);
    ``duals`` (bound and constraint multipliers of an earlier solve) warm-start IPOPT.
    """
    m = t.size
    size = _ladder(m)
    solver = block_solver(size, duals is not None, st.ipopt_tol)
    par = np.zeros((NPAR, size))
    par[0, : m - 1] = np.diff(t)
    par[1:7, :m] = meas.T
    par[7, :] = st.switch_penalty_u
    par[8, :] = st.switch_penalty_w
    x0 = np.zeros((NX + ND, size))
    x0[:NX, :m] = guess.T
    x0[:NX, m:] = guess[-1][:, None]
    first = x0[4:6, 0] if prev is None else prev[4:6]
    d = np.diff(x0[4:6, :], prepend=first[:, None], axis=1)
    inf = np.inf
    du_max, dw_max = bounds.u[1] - bounds.u[0], bounds.w[1] - bounds.w[0]
    lo = np.array([-inf, -inf, -inf, bounds.v[0], bounds.u[0], bounds.w[0], 0, 0, 0, 0])
    hi = np.array([inf, inf, inf, bounds.v[1], bounds.u[1], bounds.w[1],
                   du_max, du_max, dw_max, dw_max])
    lbx = np.tile(lo[:, None], (1, size))
    ubx = np.tile(hi[:, None], (1, size))
    if prev is None:
        par[7:9, 0] = 0.0  # the first controls are free
    else:
        lbx[:4, 0] = ubx[:4, 0] = x0[:4, 0] = prev[:4]
    if fixed is not None:
        held = np.ones((2, size), dtype=bool)  # padding holds its controls too
        held[:, :m] = fixed
        if prev is None:
            held[:, 0] = False
        ubx[6:8, held[0]] = 0.0
        ubx[8:10, held[1]] = 0.0
        par[7:9] *= st.polish_penalty_scale
        d[:, held[0] & held[1]] = 0.0
    x0[6], x0[7] = np.maximum(d[0], 0), np.maximum(-d[0], 0)
    x0[8], x0[9] = np.maximum(d[1], 0), np.maximum(-d[1], 0)
    x0 = np.clip(x0, lbx, ubx)
    extra = [first[0], first[1], delta, st.level_penalty_u, st.level_penalty_w,
             st.level_smoothing]
    scale = VAR_SCALE[:, None]
    args = {"x0": (x0 / scale).T.ravel(), "p": np.concatenate([par.T.ravel(), extra]),
            "lbx": (lbx / scale).T.ravel(), "ubx": (ubx / scale).T.ravel(), "lbg": 0, "ubg": 0}
    if duals is not None:
        args["lam_x0"], args["lam_g0"] = duals
    res = solver(**args)
    stats = solver.stats()
    if stats.get("return_status") == "User_Requested_Stop":
        raise KeyboardInterrupt("IPOPT stopped by a signal")
    x = (np.array(res["x"]).reshape(size, NX + ND) * VAR_SCALE)[:m, :NX]
    its = int(stats.get("iter_count", 0))
    model_s = sum(v for k, v in stats.items() if k.startswith("t_wall_nlp_"))
    if not np.all(np.isfinite(x)):
        return BlockResult(guess.copy(), False, its, None, model_s)
    return BlockResult(x, bool(stats["success"]), its,
                       (np.array(res["lam_x"]), np.array(res["lam_g"])), model_s)


def _at_bounds(t_nodes: FloatArray, sol: np.ndarray, bounds: Bounds, name: str
               ) -> tuple[float, float]:
    """Shares of the track's time with ``name`` (``v``, ``u`` or ``w``) at its lower and at its
    upper bound (within 1e-4 of the bound range)."""
    dt = np.diff(t_nodes)  # at least 3 plots at increasing times: sum > 0
    lo, hi = getattr(bounds, name)
    tol = 1e-4 * (hi - lo)
    val = sol[:-1, 3 + "vuw".index(name)]
    return (float(dt[val <= lo + tol].sum() / dt.sum()),
            float(dt[val >= hi - tol].sum() / dt.sum()))


def _report_bounds(t_nodes: FloatArray, sol: np.ndarray, bounds: Bounds,
                   diag: Diagnostics) -> None:
    """Share of the track's time with ``v``, ``u``, ``w`` at a bound (``extra``), and a warning
    when the speed sits at one for ``SPEED_MISFIT_SHARE`` of it or more: the plots then ask for
    an aircraft the bounds do not allow (the turn and acceleration bounds are met in hard
    manoeuvres)."""
    shares = {name: _at_bounds(t_nodes, sol, bounds, name) for name in "vuw"}
    for name, (at_lo, at_hi) in shares.items():
        diag.extra[f"{name}_at_bound_share"] = at_lo + at_hi
    for share, side, value in zip(shares["v"], ("lower", "upper"), bounds.v, strict=True):
        if share >= SPEED_MISFIT_SHARE:
            diag.warnings.append(
                f"speed at its {side} bound ({value:g} m/s) for {100 * share:.0f} % of "
                "the track: the plots ask for an aircraft that bounds.v does not allow")


def _segments(t_nodes: FloatArray, sol: np.ndarray, bounds: Bounds) -> list[Segment]:
    """Merge node intervals whose controls agree (to 1e-6 of the bound range) into segments."""
    n = t_nodes.size
    ctl = sol[: n - 1, 4:6] if n > 1 else sol[:, 4:6]
    tol = 1e-6 * np.array([bounds.u[1] - bounds.u[0], bounds.w[1] - bounds.w[0]])
    change = np.any(np.abs(np.diff(ctl, axis=0)) > tol, axis=1)
    starts = np.concatenate([[0], np.flatnonzero(change) + 1])
    ends = np.append(starts[1:], n - 1)
    segs = []
    for a, b in zip(starts, ends, strict=True):
        sel = ctl[a:b] if b > a else ctl[a: a + 1]
        u, w = np.mean(sel, axis=0)
        segs.append(Segment(float(t_nodes[a]), float(t_nodes[b]), float(sol[a, 0]),
                            float(sol[a, 1]), float(np.mod(sol[a, 2], 2 * math.pi)),
                            float(sol[a, 3]), float(u), float(w)))
    return segs


def _node_covariance(t_nodes: FloatArray, sol: np.ndarray, meas: np.ndarray,
                     st: RefineSettings, delta: float, bounds: Bounds) -> np.ndarray:
    """Smoothed ``(n, 6, 6)`` covariance of ``(x, z, phi, v, u, w)`` at the nodes (Laplace)."""
    n = t_nodes.size
    dt = np.append(np.diff(t_nodes), 0.0)
    A = compiled.columns(_jacobian_function(), sol.T, dt[None, :])[0]
    # Objective = sum q + lambda |Delta| = 2 * neg-log-posterior: q = chi^2 and the Laplace
    # prior exp(-lambda |Delta| / 2) has variance 8 / lambda^2.
    qvar = st.covariance_scale * np.array([8 / st.switch_penalty_u**2, 8 / st.switch_penalty_w**2])
    q = _quad(sol, meas)
    irls = 1.0 / np.sqrt(1 + q / delta**2)  # rho'(q): weight of each residual at the solution
    Rinv = np.zeros((n, 2, 2))
    Rinv[:, 0, 0], Rinv[:, 0, 1], Rinv[:, 1, 0], Rinv[:, 1, 1] = (
        meas[:, M_A], meas[:, M_B], meas[:, M_B], meas[:, M_C])
    Rinv *= (irls * meas[:, M_W])[:, None, None]
    # weak prior, uniform within the bounds for heading and the controls
    span = np.array([bounds.v[1] - bounds.v[0], bounds.u[1] - bounds.u[0],
                     bounds.w[1] - bounds.w[0]])
    prior = np.concatenate([[1e12, 1e12, np.pi**2 / 3], span**2 / 12])
    return _rts_covariance(A, Rinv, qvar, prior)


def _rts_covariance(A: np.ndarray, Rinv: np.ndarray, qvar: np.ndarray,
                    prior_var: np.ndarray) -> np.ndarray:
    """Smoothed covariances of a linear-Gaussian chain (Kalman filter, Joseph form, then RTS).

    ``s_{k+1} = A_k s_k + [0, 0, 0, 0, e_u, e_w]``, ``e ~ N(0, diag(qvar))`` (a control change
    at each node); position measurements with information ``Rinv_k`` at node k (zero: none);
    prior ``N(s_0, diag(prior_var))``.
    """
    n = A.shape[0]
    Q = np.zeros((NX, NX))
    Q[4, 4], Q[5, 5] = qvar
    eye = np.eye(NX)
    Pf = np.empty((n, NX, NX))
    Pp = np.empty((n, NX, NX))
    measured = Rinv.any(axis=(1, 2))
    R = np.zeros_like(Rinv)
    R[measured] = np.linalg.inv(Rinv[measured])
    P = np.diag(prior_var)
    for k in range(n):  # H selects the position (x, z): H P = P[:2], K H = [K, 0]
        if k:
            P = A[k - 1] @ P @ A[k - 1].T + Q
        Pp[k] = P
        if measured[k]:
            K = np.linalg.solve(P[:2, :2] + R[k], P[:2]).T
            IKH = eye.copy()
            IKH[:, :2] -= K
            P = IKH @ P @ IKH.T + K @ R[k] @ K.T
        Pf[k] = P
    Ps = np.empty_like(Pf)
    Ps[-1] = Pf[-1]
    if n < 2:
        return Ps
    G = np.linalg.solve(Pp[1:], A[: n - 1] @ Pf[:-1]).transpose(0, 2, 1)  # batched: filter only
    for k in range(n - 2, -1, -1):
        P = Pf[k] + G[k] @ (Ps[k + 1] - Pp[k + 1]) @ G[k].T
        Ps[k] = (P + P.T) / 2
    return Ps


def _series(t_nodes: FloatArray, sol: np.ndarray, cov_nodes: np.ndarray,
            t: FloatArray) -> StateSeries:
    """States and ``(x, z, vx, vz)`` covariances at times ``t`` from the node solution.

    Between nodes the control is constant, so the state at ``tau`` is a deterministic function
    of the node state: ``P(tau) = A(tau) P_k A(tau)^T`` exactly for the linearised model.
    """
    k = np.clip(np.searchsorted(t_nodes, t, side="right") - 1, 0, t_nodes.size - 1)
    tau = t - t_nodes[k]
    s = sol[k]
    x, z, phi, v = propagate(s[:, 0], s[:, 1], s[:, 2], s[:, 3], s[:, 4], s[:, 5], tau)
    m = t.size
    A = compiled.columns(_jacobian_function(), s.T, tau[None, :])[0]
    P = A @ cov_nodes[k] @ A.transpose(0, 2, 1)
    T = np.zeros((m, 4, NX))
    T[:, 0, 0] = T[:, 1, 1] = 1.0
    c, sn = np.cos(phi), np.sin(phi)
    T[:, 2, 2], T[:, 2, 3] = -v * sn, c
    T[:, 3, 2], T[:, 3, 3] = v * c, sn
    cov = T @ P @ T.transpose(0, 2, 1)
    return StateSeries(t.copy(), x, z, v * c, v * sn, cov)
