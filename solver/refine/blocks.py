"""Long tracks in blocks: a fixed ladder of block sizes (one cached solver each), the cut into
overlapping blocks, and one block's solve.

A track is cut into overlapping blocks of at most ``block_nodes`` nodes, each padded to the next
ladder size with zero-length, zero-weight intervals (``F(s, u, w, 0) = s``). A block after the
first starts from the previous block's state at the middle of their overlap (its controls there
enter the first L1 term), so the result is one continuous piecewise-constant-control
trajectory. Estimated radar offsets are free in the first block and held at its estimate in
the others (one block holds up to 2048 nodes: hours of plots).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from ..config import RefineSettings
from ..inputs import Bounds, FloatArray
from . import nlp
from .layout import (
    HD_MAX,
    Variant,
    block_parameters,
    global_scale,
    global_variables,
    node_parameters,
    node_scale,
    node_variables,
    solution_columns,
)
from .nodes import NodeData

# Block sizes (nodes): ratio 2^(1/4), so padding wastes at most 19 %.
LADDER = tuple(sorted({round(16 * 2 ** (k / 4)) for k in range(29)}))


class DeadlineExceeded(RuntimeError):
    """The refinement passed its deadline (IPOPT stopped by the iteration callback, or a check
    between the stages after it)."""


def check_deadline(deadline: float | None) -> None:
    """Raise :class:`DeadlineExceeded` once ``time.monotonic()`` is past ``deadline``."""
    if deadline is not None and time.monotonic() > deadline:
        raise DeadlineExceeded("the refinement passed its deadline")


def ladder(n: int) -> int:
    """The smallest ladder size that holds ``n`` nodes."""
    for size in LADDER:
        if n <= size:
            return size
    raise ValueError(f"block of {n} nodes exceeds the largest ladder size {LADDER[-1]}")


def build_solvers(variants: tuple[Variant, ...] = (Variant(),)) -> None:
    """Build every block solver the default settings use (the cold first solve at
    ``first_solve_tol``, the warm ones at ``ipopt_tol``) over the ladder (about 2 s per
    variant), e.g. before serving."""
    st = RefineSettings()
    for v in variants:
        for n in LADDER:
            nlp.block_solver(n, v, tol=st.first_solve_tol)
            nlp.block_solver(n, v, warm=True, tol=st.ipopt_tol)


def cut(n: int, size: int, overlap: int) -> list[tuple[int, int, int]]:
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
        c = stop - overlap // 2
        out.append((start, stop, c))
        start = c


class BlockResult(NamedTuple):
    """One block's solve: node solution ``(m, nv)``, the radars' offsets ``(biases, 3)``,
    success, IPOPT iterations, the multipliers (to warm-start the next solve), and the seconds
    IPOPT spent evaluating the model."""

    x: np.ndarray
    biases: np.ndarray
    ok: bool
    iterations: int
    duals: tuple[np.ndarray, np.ndarray] | None
    model_s: float


class Problem(NamedTuple):
    """What every block of one track shares."""

    t_nodes: FloatArray
    hd_info: FloatArray
    variant: Variant
    bounds: Bounds
    settings: RefineSettings
    delta: float  # pseudo-Huber threshold (sigmas)
    bias_info: FloatArray  # (biases * 3,) prior information of the offsets
    time_gauge: FloatArray | None = None  # (biases,) weights g of g . b_t = 0 (time_reference)


def solve_block(pb: Problem, start: int, stop: int, data: NodeData, guess: np.ndarray,
                biases: np.ndarray, prev: np.ndarray | None, fixed: np.ndarray | None,
                duals: tuple[np.ndarray, np.ndarray] | None, hold_biases: bool,
                tol: float) -> BlockResult:
    """Solve nodes ``[start, stop)`` to IPOPT's tolerance ``tol``; ``prev`` (the previous
    block's node solution, or None) fixes the start; ``fixed`` (``(2, m)`` bool) marks control
    changes held at exactly zero (polish step); ``duals`` warm-start IPOPT; ``hold_biases`` fixes
    the offsets at ``biases``.
    """
    st, bounds, v = pb.settings, pb.bounds, pb.variant
    V, G, P, E = (node_variables(v), global_variables(v), node_parameters(v),
                  block_parameters(v))
    t = pb.t_nodes[start:stop]
    m = t.size
    size = ladder(m)
    solver = nlp.block_solver(size, v, duals is not None, tol)
    sl = slice(start, stop)
    par = np.zeros((P.size, size))
    par[P["dt"], : m - 1] = np.diff(t)
    par[P["centre"], :m] = data.centre[sl].T
    par[P["info"], :m] = data.info[sl].T
    par[P["weight"], :m] = data.weight[sl]
    par[P["switch"]] = np.array([[st.switch_penalty_u], [st.switch_penalty_w]])
    par[P["level"], :m] = data.level[sl].T
    cols = solution_columns(v)
    rows = [V.row(name) for name in cols]  # solution column j lives in variable row rows[j]
    x0 = np.zeros((V.size, size))
    x0[rows, :m] = guess[sl].T
    x0[rows, m:] = guess[stop - 1][:, None]
    uw = V["u"].start
    first = x0[uw: uw + 2, 0] if prev is None else prev[[cols.index("u"), cols.index("w")]]
    d = np.diff(x0[uw: uw + 2, :], prepend=first[:, None], axis=1)
    inf = np.inf
    du_max, dw_max = bounds.u[1] - bounds.u[0], bounds.w[1] - bounds.w[0]
    lo = np.full(V.size, -inf)
    hi = np.full(V.size, inf)
    lo[V["v"]], hi[V["v"]] = bounds.v
    lo[V["u"]], hi[V["u"]] = bounds.u
    lo[V["w"]], hi[V["w"]] = bounds.w
    lo[V["du"]], hi[V["du"]] = 0.0, du_max
    lo[V["dw"]], hi[V["dw"]] = 0.0, dw_max
    lbx = np.tile(lo[:, None], (1, size))
    ubx = np.tile(hi[:, None], (1, size))
    # speed and accelerations bounded on the ground: the plane's are its scale times those
    k = np.append(data.plane_scale[sl], np.full(size - m, data.plane_scale[stop - 1]))
    for name in ("v", "u", "w", "du", "dw"):
        lbx[V[name]] *= k
        ubx[V[name]] *= k
    extra = np.zeros(E.size)
    extra[E["u_prev"]], extra[E["w_prev"]] = first
    extra[E["huber"]] = pb.delta
    extra[E["level_u"]], extra[E["level_w"]] = st.level_penalty_u, st.level_penalty_w
    extra[E["level_eps"]] = st.level_smoothing
    if v.altitude:
        for name in ("ray", "slant", "site_h", "h_mid", "h_half", "alt", "alt_info"):
            par[P[name], :m] = getattr(data, name)[sl].T
        par[P["h_half"], m:] = 1.0
        par[P["slant"], m:] = 1e7
        par[P["centre_h"], :m] = data.centre_h[sl].transpose(1, 2, 0).reshape(-1, m)
        par[P["hd_info"], :m] = pb.hd_info[sl]
        h_row, hd_row = V.row("h"), V.row("hd")
        lbx[h_row, :m], ubx[h_row, :m] = data.h_lo[sl], data.h_hi[sl]
        lbx[h_row, m:], ubx[h_row, m:] = data.h_lo[stop - 1], data.h_hi[stop - 1]
        lbx[hd_row], ubx[hd_row] = -HD_MAX, HD_MAX
        extra[E["hd_prev"]] = 0.0 if prev is None else prev[cols.index("hd")]
        if prev is None:
            par[P["hd_info"], 0] = 0.0
    if v.biases:
        par[P["d_range"], :m] = data.d_range[sl].T
        par[P["d_azimuth"], :m] = data.d_azimuth[sl].T
        par[P["sensor"], :m] = data.sensor[sl].T
        extra[E["bias_info"]] = pb.bias_info
        extra[E["time_gauge"]] = 0.0 if pb.time_gauge is None else pb.time_gauge
    if prev is None:
        par[P["switch"], 0] = 0.0  # the first controls are free
    else:
        names = ("x", "z", "phi", "v") + (("h",) if v.altitude else ())
        fix = [V.row(name) for name in names]
        lbx[fix, 0] = ubx[fix, 0] = x0[fix, 0] = prev[[cols.index(name) for name in names]]
    if fixed is not None:
        held = np.ones((2, size), dtype=bool)  # padding holds its controls too
        held[:, :m] = fixed
        if prev is None:
            held[:, 0] = False
        ubx[V["du"], held[0]] = 0.0
        ubx[V["dw"], held[1]] = 0.0
        par[P["switch"]] *= st.polish_penalty_scale
        d[:, held[0] & held[1]] = 0.0
    du, dw = V["du"].start, V["dw"].start
    x0[du], x0[du + 1] = np.maximum(d[0], 0), np.maximum(-d[0], 0)
    x0[dw], x0[dw + 1] = np.maximum(d[1], 0), np.maximum(-d[1], 0)
    x0 = np.clip(x0, lbx, ubx)
    scale = node_scale(v)[:, None]
    gscale = global_scale(v)
    g0 = biases.ravel() / gscale
    glo = np.full(G.size, -inf)
    ghi = np.full(G.size, inf)
    if hold_biases:
        glo = ghi = g0
    args = {"x0": np.concatenate([(x0 / scale).T.ravel(), g0]),
            "p": np.concatenate([par.T.ravel(), extra]),
            "lbx": np.concatenate([(lbx / scale).T.ravel(), glo]),
            "ubx": np.concatenate([(ubx / scale).T.ravel(), ghi]), "lbg": 0, "ubg": 0}
    if duals is not None:
        args["lam_x0"], args["lam_g0"] = duals
    res = solver(**args)
    try:
        stats = solver.stats()
    except RuntimeError:  # CasADi could not tell (see solver.window.return_status)
        stats = {}
    status = stats.get("return_status")
    if status == "User_Requested_Stop":
        if time.monotonic() > nlp._deadline[0]:
            raise DeadlineExceeded("the refinement passed its deadline")
        raise KeyboardInterrupt("IPOPT stopped by a signal")
    xall = np.array(res["x"]).ravel()
    nodes_x = xall[: V.size * size].reshape(size, V.size) * node_scale(v)
    x = nodes_x[:m, rows]
    b = (xall[V.size * size:] * gscale).reshape(-1, 3)
    its = int(stats.get("iter_count", 0))
    model_s = sum(val for k, val in stats.items() if k.startswith("t_wall_nlp_"))
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(b))):
        return BlockResult(guess[sl].copy(), biases.copy(), False, its, None, model_s)
    return BlockResult(x, b, bool(stats["success"]), its,
                       (np.array(res["lam_x"]), np.array(res["lam_g"])), model_s)
