"""One window: the constant-control fit as a CasADi NLP (spec/reconstruction.md section 5).

Decision variables ``(u, w)``; parameters: the start state ``(x0, z0, phi0, v0)``, the ``m`` plot
times relative to the start, the ``m`` ellipse centres and the ``m`` weight entries ``(a, b, c)``.
Objective: the criterion ``sum a dx^2 + 2 b dx dz + c dz^2`` (R1 is ``a = c = 1, b = 0``).
The speed bound ``v_min <= v0 + w T <= v_max`` (``T`` the last plot time) is linear in ``w``, so
it is folded into the box on ``w`` at call time (:func:`w_box`): the NLP has box constraints only.

Three NLPs, each built once per ``(m, plugin)`` (SX graph, ``functools.cache``) and fed the data
as parameters, never rebuilt per window: the window (:func:`window_solver`), the trial window
with a free start time (:func:`switch_solver`) and the first window with a free start state
(:func:`free_start_solver`). All trial windows of a step are solved in one call of the solver
mapped over them (``Function.map``; measured 0.10 vs 0.15 ms CPU per solve against one Python
call each), and so are the switch-time refinements of a step. Convergence of a window solve is
judged independently of the solver's status, by the first-order condition of the
box-constrained problem: the projected gradient ``|x - clip(x - grad f, lbx, ubx)|_inf <=
KKT_TOL (1 + f)``.

Default plugin: ``sqpmethod`` with the ``qrqp`` active-set QP and the exact Hessian, made
positive definite by eigenvalue reflection (``convexify_strategy = eigen-reflect``; the 2x2 and
3x3 Hessians make that cheap). Measured on the seed-like track (benchmarks/seed_track.py and
its results file): half the SQP iterations of a Gauss-Newton Hessian ``2 J^T J`` of the
weighted residuals (11.3k vs 22.8k; Gauss-Newton converges linearly on large-residual windows
and some solves stall at the iteration limit) for the same CPU time per track; ``regularize``
convexification stalls (45% of solves at the limit). IPOPT gives the
same optima about twenty times slower (per-call overhead of an interior-point method on a
2-variable problem). Gauss-Newton (:func:`use_hessian`) and ``ipopt``
stay selectable.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cache

import casadi as ca
import numpy as np

from .config import NlpSolver
from .inputs import Bounds, FloatArray
from .motion import propagate, propagate_ca

N_START = 4  # x0, z0, phi0, v0
CONVERGED = frozenset({"Solve_Succeeded", "Solve_Succeeded_To_Acceptable_Level",
                       "Search_Direction_Becomes_Too_Small"})
"""Return statuses of a single (free-start) solve taken as converged. sqpmethod stops with
``Search_Direction_Becomes_Too_Small`` when its step is below ``min_step_size``: no further
progress is possible at that point (its projected gradients measure like converged ones)."""
KKT_TOL = 1e-6
"""Relative projected-gradient tolerance of a converged window solve (converged solves measure
below 1e-9, stalled ones above 1e-6)."""
def return_status(solver: ca.Function) -> str | None:
    """The last solve's ``return_status``; None when CasADi cannot tell (it raised "construction
    from null" on a window of junk plots)."""
    try:
        return solver.stats().get("return_status")
    except RuntimeError:
        return None


HESSIAN = "exact"  # sqpmethod Hessian of newly built solvers; see use_hessian


def n_params(m: int) -> int:
    """Length of the parameter vector of an ``m``-plot window."""
    return N_START + 6 * m


def pack_params(start: FloatArray, t: FloatArray, cx: FloatArray, cz: FloatArray,
                abc: FloatArray) -> FloatArray:
    """``(n, 4 + 6 m)`` parameter rows: start, times, centres x, centres z, a, b, c."""
    return np.hstack([start, t, cx, cz, abc[..., 0], abc[..., 1], abc[..., 2]])


def _residuals(start, u, w, t, data, m: int):
    """Weighted residuals ``r`` (``R = |r|^2``) of positions propagated from ``start`` over the
    relative times ``t[i]``; ``data`` holds centres x, z and weights a, b, c (``m`` each)."""
    res = []
    for i in range(m):
        cx, cz = data[i], data[m + i]
        a, b, c = data[2 * m + i], data[3 * m + i], data[4 * m + i]
        s = propagate_ca(start, u, w, t[i])
        dx, dz = s[0] - cx, s[1] - cz
        sa = ca.sqrt(a)
        # Cholesky of M = [[a, b], [b, c]]:
        # d^T M d = (sqrt(a) dx + b/sqrt(a) dz)^2 + (c - b^2/a) dz^2
        res += [sa * dx + b / sa * dz, ca.sqrt(ca.fmax(c - b * b / a, 0.0)) * dz]
    return ca.vertcat(*res)


def _nlpsol(name: str, x: ca.SX, p: ca.SX, r: ca.SX, g: ca.SX, plugin: NlpSolver,
            hessian: str) -> ca.Function:
    """``min |r(x, p)|^2`` s.t. box on ``x`` and ``lbg <= g(x, p) <= ubg``."""
    f = ca.dot(r, r)
    nlp = {"x": x, "p": p, "f": f, "g": g}
    if plugin == "sqpmethod":
        opts: dict = {
            "qpsol": "qrqp",
            "qpsol_options": {"print_iter": False, "print_header": False, "print_info": False,
                              "error_on_fail": False},
            "print_header": False, "print_iteration": False, "print_status": False,
            "print_time": False, "error_on_fail": False, "max_iter": 50,
            "tol_pr": 1e-9, "tol_du": 1e-9,
        }
        if hessian == "gauss-newton":
            # 2 J^T J of the residuals plus the exact Hessian of the (few, simple) constraints
            lam_f, lam_g = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", g.numel())
            jr = ca.jacobian(r, x)
            h = lam_f * 2 * ca.mtimes(jr.T, jr)
            if g.numel():
                h += ca.hessian(ca.dot(lam_g, g), x)[0]
            opts["hess_lag"] = ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [h],
                                           ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        else:
            opts["convexify_strategy"] = "eigen-reflect"
        return ca.nlpsol(f"{name}_sqp", "sqpmethod", nlp, opts)
    if plugin == "ipopt":
        opts = {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False,
                "ipopt.tol": 1e-10, "error_on_fail": False}
        return ca.nlpsol(f"{name}_ipopt", "ipopt", nlp, opts)
    raise ValueError(f"unknown NLP solver {plugin!r}")


@cache
def window_solver(m: int, plugin: NlpSolver = "sqpmethod", hessian: str | None = None
                  ) -> ca.Function:
    """The NLP solver of ``m``-plot windows: ``x = (u, w)``, ``p`` as :func:`pack_params`."""
    uw = ca.SX.sym("uw", 2)
    p = ca.SX.sym("p", n_params(m))
    t = [p[N_START + i] for i in range(m)]
    r = _residuals(p[0:N_START], uw[0], uw[1], t, p[N_START + m:], m)
    return _nlpsol(f"window{m}", uw, p, r, ca.SX(0, 1), plugin, hessian or HESSIAN)


@cache
def window_batch(m: int, plugin: NlpSolver, n: int) -> ca.Function:
    """:func:`window_solver` mapped over ``n`` windows (inputs and outputs as columns)."""
    return window_solver(m, plugin).map(n)


@cache
def _window_kkt(m: int) -> ca.Function:
    uw, p = ca.SX.sym("uw", 2), ca.SX.sym("p", n_params(m))
    lb, ub = ca.SX.sym("lb", 2), ca.SX.sym("ub", 2)
    t = [p[N_START + i] for i in range(m)]
    r = _residuals(p[0:N_START], uw[0], uw[1], t, p[N_START + m:], m)
    f = ca.dot(r, r)
    pg = uw - ca.fmin(ca.fmax(uw - ca.gradient(f, uw), lb), ub)
    return ca.Function("kkt", [uw, p, lb, ub], [ca.norm_inf(pg), f])


@cache
def window_kkt(m: int, n: int) -> ca.Function:
    """``(x, p, lbx, ubx) -> (|projected gradient|_inf, f)`` of ``n`` windows (columns)."""
    return _window_kkt(m).map(n)


@cache
def switch_solver(m: int, plugin: NlpSolver = "sqpmethod", hessian: str | None = None
                  ) -> ca.Function:
    """NLP of a trial window whose start time is free: ``x = (u, w, tau)``.

    Parameters: the current window's start state (4) and controls ``(u_c, w_c)``, then the
    trial window's data as in :func:`pack_params` with times relative to the current start.
    The trial starts at ``tau`` on the current trajectory, ``propagate(start, u_c, w_c, tau)``.
    Constraint ``g = v(tau) + w (t_m - tau)``: the speed at the window's last plot.
    """
    x = ca.SX.sym("uwt", 3)
    p = ca.SX.sym("p", n_params(m) + 2)
    u, w, tau = x[0], x[1], x[2]
    start = propagate_ca(p[0:N_START], p[N_START], p[N_START + 1], tau)
    off = N_START + 2
    t = [p[off + i] - tau for i in range(m)]
    r = _residuals(start, u, w, t, p[off + m:], m)
    g = start[3] + w * t[-1]
    return _nlpsol(f"switch{m}", x, p, r, g, plugin, hessian or HESSIAN)


def use_hessian(hessian: str) -> None:
    """Select the sqpmethod Hessian (``exact`` or ``gauss-newton``) for all window solvers from
    now on (drops the cached solvers; for benchmarks and comparisons)."""
    global HESSIAN
    if hessian not in ("exact", "gauss-newton"):
        raise ValueError(f"unknown Hessian {hessian!r}")
    HESSIAN = hessian
    for f in (window_solver, window_batch, switch_solver, switch_batch, free_start_solver):
        f.cache_clear()


FREE_START_SCALE = np.array([1000.0, 1000.0, 1.0, 100.0])
"""Scale of the free start's variables (km, km, rad, 100 m/s) for a well-conditioned NLP."""


@cache
def free_start_solver(m: int, plugin: NlpSolver = "sqpmethod", hessian: str | None = None
                      ) -> ca.Function:
    """NLP of a first window whose start state is free: ``x = (dx0, dz0, dphi0, v0, u, w)``
    scaled by :data:`FREE_START_SCALE`, the start being ``p[0:4] + scale * x[0:4]`` with
    ``p[0:4] = (x_ref, z_ref, phi_ref, 0)``; then ``m`` plots as in :func:`pack_params` (times
    relative to the start, the first plot at 0). Constraint ``g``: the speed at the last plot.
    """
    x = ca.SX.sym("sx", 6)
    p = ca.SX.sym("p", n_params(m))
    start = p[0:N_START] + ca.DM(FREE_START_SCALE) * x[0:4]
    t = [p[N_START + i] for i in range(m)]
    r = _residuals(start, x[4], x[5], t, p[N_START + m:], m)
    g = start[3] + x[5] * t[-1]
    return _nlpsol(f"free{m}", x, p, r, g, plugin, hessian or HESSIAN)


@dataclass
class FreeStartFit:
    """Solution of the free-start first window."""

    start: FloatArray  # (x0, z0, phi0, v0)
    u: float
    w: float
    value: float
    failed: bool
    solve_ms: float


def solve_free_start(ref: FloatArray, uw: FloatArray, t: FloatArray, cx: FloatArray,
                     cz: FloatArray, abc: FloatArray, bounds: Bounds,
                     plugin: NlpSolver = "sqpmethod") -> FreeStartFit:
    """Fit start state and controls to ``m`` plots (``t[0] = 0``: the start plot), from the
    reference start ``ref`` and controls ``uw`` (the seed's rule and its window fit). A
    non-finite or infeasible point comes back with ``value = inf`` and ``failed``."""
    m = t.shape[0]
    solver = free_start_solver(m, plugin)
    p = pack_params(np.array([[ref[0], ref[1], ref[2], 0.0]]), t[None], cx[None], cz[None],
                    abc[None])[0]
    big = np.inf
    lbx = [-big, -big, -big, bounds.v[0] / 100.0, bounds.u[0], bounds.w[0]]
    ubx = [big, big, big, bounds.v[1] / 100.0, bounds.u[1], bounds.w[1]]
    x0 = [0.0, 0.0, 0.0, ref[3] / 100.0, uw[0], uw[1]]
    t0 = time.perf_counter()
    sol = solver(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=bounds.v[0], ubg=bounds.v[1])
    ms = (time.perf_counter() - t0) * 1e3
    failed = return_status(solver) not in CONVERGED
    x = np.asarray(sol["x"]).ravel()
    start = np.array([ref[0], ref[1], ref[2], 0.0]) + FREE_START_SCALE * x[:4]
    u, w = float(np.clip(x[4], *bounds.u)), float(np.clip(x[5], *bounds.w))
    v_end = start[3] + w * t[-1]
    tol = 1e-9 * bounds.v[1]
    feasible = (np.all(np.isfinite(x)) and bounds.v[0] - tol <= start[3] <= bounds.v[1] + tol
                and bounds.v[0] - tol <= v_end <= bounds.v[1] + tol)
    if not feasible:
        return FreeStartFit(ref, float(uw[0]), float(uw[1]), np.inf, True, ms)
    start[3] = np.clip(start[3], *bounds.v)
    value = float(criterion(start, np.asarray(u), np.asarray(w), t, cx, cz, abc))
    return FreeStartFit(start, u, w, value, failed, ms)


def w_box(v0: FloatArray, t_end: FloatArray, bounds: Bounds
          ) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Box on ``w`` with the speed bound folded in: ``v_min <= v0 + w T <= v_max``.

    Returns ``(lbw, ubw, flagged)``. ``flagged`` marks starts whose own speed is outside the
    bounds (accepted states never are): the box then asks for the speed to be back in bounds by
    ``T``, or, where ``[w_min, w_max]`` cannot achieve that, shrinks to the single ``w`` that
    comes nearest.
    """
    (w_lo, w_hi), (v_lo, v_hi) = bounds.w, bounds.v
    lbw = np.maximum(w_lo, (v_lo - v0) / t_end)
    ubw = np.minimum(w_hi, (v_hi - v0) / t_end)
    empty = lbw > ubw
    pin = np.where(v0 < v_lo, w_hi, w_lo)
    flagged = (v0 < v_lo) | (v0 > v_hi)
    return np.where(empty, pin, lbw), np.where(empty, pin, ubw), flagged


def criterion(start: FloatArray, u: FloatArray, w: FloatArray, t: FloatArray, cx: FloatArray,
              cz: FloatArray, abc: FloatArray) -> FloatArray:
    """Window criterion in numpy. ``start (..., 4)``, ``u, w (...)``, data ``(..., m[, 3])``."""
    x, z, _, _ = propagate(start[..., 0:1], start[..., 1:2], start[..., 2:3], start[..., 3:4],
                           u[..., None], w[..., None], t)
    dx, dz = x - cx, z - cz
    return np.sum(abc[..., 0] * dx * dx + 2 * abc[..., 1] * dx * dz + abc[..., 2] * dz * dz,
                  axis=-1)


@dataclass
class WindowFits:
    """Solutions of ``n`` windows: controls, criterion values and what happened."""

    u: FloatArray
    w: FloatArray
    value: FloatArray
    failed: np.ndarray  # solver reported failure or returned a non-finite/out-of-box point
    fallback: np.ndarray  # the initial guess was kept (solver point unusable or no better)
    solve_ms: FloatArray


def solve_windows(start: FloatArray, t: FloatArray, cx: FloatArray, cz: FloatArray,
                  abc: FloatArray, guess: FloatArray, lbw: FloatArray, ubw: FloatArray,
                  bounds: Bounds, plugin: NlpSolver = "sqpmethod") -> WindowFits:
    """Solve ``n`` windows of ``m`` plots (arrays with a leading ``n``) in one mapped call.

    ``guess (n, 2)`` is clipped to the box. A solve is ``failed`` when its point is non-finite,
    outside the box (beyond rounding) or not first-order optimal (:data:`KKT_TOL`); the window
    keeps the better of the solver's point (if finite and in the box) and the guess, and is a
    ``fallback`` when that is the guess. ``solve_ms`` is the batch time split evenly.
    """
    n, m = t.shape
    params = pack_params(start, t, cx, cz, abc)
    lb = np.column_stack([np.full(n, bounds.u[0]), lbw])
    ub = np.column_stack([np.full(n, bounds.u[1]), ubw])
    g = np.clip(guess, lb, ub)
    t0 = time.perf_counter()
    sol = window_batch(m, plugin, n)(x0=g.T, p=params.T, lbx=lb.T, ubx=ub.T)
    ms = np.full(n, (time.perf_counter() - t0) * 1e3 / n)
    x = np.asarray(sol["x"]).T
    # active-set steps land on the bounds up to rounding: snap within 1e-6, else unusable
    snapped = np.clip(np.nan_to_num(x, nan=np.inf), lb, ub)
    in_box = np.all(np.abs(snapped - x) < 1e-6, axis=1)
    pg, f = (np.asarray(a).ravel() for a in window_kkt(m, n)(snapped.T, params.T, lb.T, ub.T))
    failed = ~(in_box & (pg <= KKT_TOL * (1 + np.abs(f))))
    both = np.stack([g, snapped])  # (2, n, 2): guess, solver point
    vals = criterion(np.broadcast_to(start, (2, *start.shape)), both[..., 0], both[..., 1],
                     t, cx, cz, abc)
    vals[1] = np.where(in_box & np.isfinite(vals[1]), vals[1], np.inf)
    fallback = ~(vals[1] <= vals[0])
    best = np.where(fallback[:, None], g, snapped)
    val = np.where(fallback, vals[0], vals[1])
    return WindowFits(best[:, 0], best[:, 1], val, failed, fallback, ms)


@dataclass
class SwitchFits:
    """Solutions of ``k`` free-start-time trial windows (see :func:`switch_solver`)."""

    u: FloatArray
    w: FloatArray
    tau: FloatArray  # start times relative to the current window's start
    value: FloatArray  # inf where the solver's point is unusable
    failed: np.ndarray
    solve_ms: FloatArray


@cache
def switch_batch(m: int, plugin: NlpSolver, k: int) -> ca.Function:
    """:func:`switch_solver` mapped over ``k`` trial windows."""
    return switch_solver(m, plugin).map(k)


def solve_switches(cur_start: FloatArray, cur_uw: FloatArray, t: FloatArray, cx: FloatArray,
                   cz: FloatArray, abc: FloatArray, guess: FloatArray, tau_box: FloatArray,
                   bounds: Bounds, plugin: NlpSolver = "sqpmethod") -> SwitchFits:
    """Refine ``k`` trial windows' start times ``tau`` (within ``tau_box (k, 2)``) together with
    their controls, in one mapped call.

    ``t (k, m)`` are plot times relative to the current start; ``guess (k, 3) = (u, w, tau)``
    are feasible grid candidates. A solve is ``failed`` (and its value ``inf``) when its point is
    non-finite, outside the box beyond rounding or breaks the speed bounds; any other point is
    usable, converged or not, since the caller only ever takes it when it beats a converged grid
    candidate.
    """
    k, m = t.shape
    params = np.hstack([np.broadcast_to(cur_start, (k, N_START)), np.broadcast_to(cur_uw, (k, 2)),
                        t, cx, cz, abc[..., 0], abc[..., 1], abc[..., 2]])
    lb = np.column_stack([np.full(k, bounds.u[0]), np.full(k, bounds.w[0]), tau_box[:, 0]])
    ub = np.column_stack([np.full(k, bounds.u[1]), np.full(k, bounds.w[1]), tau_box[:, 1]])
    t0 = time.perf_counter()
    sol = switch_batch(m, plugin, k)(x0=guess.T, p=params.T, lbx=lb.T, ubx=ub.T,
                                     lbg=bounds.v[0], ubg=bounds.v[1])
    ms = np.full(k, (time.perf_counter() - t0) * 1e3 / k)
    x = np.asarray(sol["x"]).T
    value = np.asarray(sol["f"]).ravel()
    clipped = np.clip(np.nan_to_num(x, nan=np.inf), lb, ub)
    # speeds at the switch and at the last plot: v is linear in time on both pieces
    v_tau = cur_start[3] + cur_uw[1] * clipped[:, 2]
    v_end = v_tau + clipped[:, 1] * (t[:, -1] - clipped[:, 2])
    tol = 1e-9 * bounds.v[1]
    usable = (np.all(np.abs(clipped - x) < 1e-6, axis=1) & np.isfinite(value)
              & (np.minimum(v_tau, v_end) >= bounds.v[0] - tol)
              & (np.maximum(v_tau, v_end) <= bounds.v[1] + tol))
    return SwitchFits(clipped[:, 0], clipped[:, 1], clipped[:, 2],
                      np.where(usable, value, np.inf), ~usable, ms)


