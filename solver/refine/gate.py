"""The outlier gate and the bound diagnostics of the refinement.

Plots further than ``outlier_gate`` sigmas from the first solution get no weight in the
second, unless they are more than ``outlier_max_share`` of the plots or the first solution's
speed sits at a bound of ``bounds.v`` for ``SPEED_MISFIT_SHARE`` of the track: then the bounds
or the sigmas, not a few wild plots, are what does not fit, and a warning says so.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..config import RefineSettings
from ..inputs import Bounds, FloatArray
from ..results import Diagnostics

SPEED_MISFIT_SHARE = 0.1
"""The speed at a bound of ``bounds.v`` for this share of the track or more means the bounds do
not fit the aircraft (warned; no plot is then taken for a wild one)."""
COLUMN = {"v": 3, "u": 4, "w": 5}  # columns of a node solution


def wild_plots(quad_at_plots: FloatArray, t_nodes: FloatArray, sol: np.ndarray, bounds: Bounds,
               st: RefineSettings, diag: Diagnostics,
               plot_node: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Indexes (into ``quad_at_plots``) of the plots to give no weight, with the warning when
    far plots are not taken for wild ones, and those of the far plots kept as a turn. Far
    plots where the lateral acceleration sits at a bound of ``bounds.u`` (on either side of
    their node: ``plot_node``) keep their weight (:func:`turn_warning` says so once the track
    is final): a turn harder than the bounds allow leaves its plots far, and gating them cut
    the turn further (a 3 deg/s turn at 230 m/s with u within 7 m/s^2: 25 plots 'wild', 1.4 km
    off); but not at the track's first or last node."""
    none = np.array([], dtype=int)
    if st.outlier_gate is None:
        return none, none
    far = np.flatnonzero(quad_at_plots > st.outlier_gate**2)
    n = quad_at_plots.size
    if far.size and plot_node is not None:
        node = plot_node[far]
        # not at the track's first or last node: a turn there has no later (earlier) plot to
        # say it is one, and a lone wild plot there bent the track's end to it (a tester's
        # lone-radar tracks: the next plot 250-500 m off, 13-14 good plots then left out)
        inner = (node != plot_node.min()) & (node != plot_node.max())
        turning = held_at_bound(sol, bounds, "u", node) & inner
        kept = far[turning]
        far = far[~turning]
    else:
        kept = none
    text = f"{far.size} of {n} plots are more than {st.outlier_gate:g} sigma from the track"
    if far.size and max(at_bounds(t_nodes, sol, bounds, "v")) >= SPEED_MISFIT_SHARE:
        diag.warnings.append(f"{text}, whose speed sits at a bound of bounds.v: the bounds, not "
                             "wild plots, keep them far; none of them was given zero weight for it")
        return none, kept
    if far.size > st.outlier_max_share * n:
        diag.warnings.append(f"{text}: too many to be wild plots (do the bounds and the "
                             "sensors' sigmas fit this aircraft?); none of them was given zero "
                             "weight for it")
        return none, kept
    return far, kept


def turn_warning(kept: np.ndarray, quad_at_plots: FloatArray, t_plots: FloatArray,
                 gate: float | None) -> str | None:
    """The warning of the far plots kept as a turn harder than the bounds (``kept``, from
    :func:`wild_plots`) that are still far from the final track: said of those plots the
    next solve brought back (a wild end plot's neighbour, bent towards it before the end plot
    was left out: a tester's), it named a turn that was not there."""
    if gate is None or not kept.size:
        return None
    still = kept[quad_at_plots[kept] > gate**2]
    if not still.size:
        return None
    t = t_plots[still]
    return (f"{still.size} plot(s) more than {gate:g} sigma from the track where the lateral "
            f"acceleration sits at a bound of bounds.u (t {t.min():g}-{t.max():g} s): a turn "
            "harder than the bounds allow, not wild plots; they keep their weight")


RESCALE_BELOW = 0.25
"""A sensor whose plots' median R2 term is below this fraction of chi-square's (2 dof) median
states sigmas at least twice too large; its weights are then scaled to the scatter shown (a
noise-free seed-like track: 267 m off in a turn with the declared 167 m / 0.5 deg, the
penalties outweighing plots they take for noisy; noisy plots with right sigmas give 0.6-1)."""
RESCALE_ROUNDS = 3
MAX_WEIGHT_SCALE = 1e4  # sigmas taken at most 100 times smaller than declared
CHI2_2DOF_MEDIAN = 2 * np.log(2)


def overstated_sigmas(quad_at_plots: FloatArray, sensor: np.ndarray, n_sensors: int,
                      applied: FloatArray) -> FloatArray:
    """Per sensor, the factor to multiply its plots' weights by: ``1 / s^2`` with ``s^2`` the
    median R2 term over chi-square's median, where ``s^2 < RESCALE_BELOW`` (at least 5 plots;
    the product with the factors ``applied`` before capped at ``MAX_WEIGHT_SCALE``), else 1."""
    factor = np.ones(n_sensors)
    for k in range(n_sensors):
        q = quad_at_plots[sensor == k]
        if q.size < 5 or applied[k] >= MAX_WEIGHT_SCALE:
            continue
        s2 = float(np.median(q)) / CHI2_2DOF_MEDIAN
        if s2 < RESCALE_BELOW:
            factor[k] = min(1.0 / max(s2, 1e-300), MAX_WEIGHT_SCALE / applied[k])
    return factor


def report_scales(weight_scale: FloatArray, table: object, diag: Diagnostics) -> None:
    """Say which sensors' sigmas were taken smaller than declared, and by how much."""
    for k, scale in enumerate(weight_scale):
        if scale == 1.0:
            continue
        sid = table.sensors[k].id  # type: ignore[attr-defined]
        diag.extra[f"sigma_scale_{sid}"] = float(1 / np.sqrt(scale))
        diag.warnings.append(
            f"the plots of {sid!r} lie much closer to the track than its declared sigmas "
            f"allow: weighted as if its sigmas were {1 / np.sqrt(scale):.3g} of the declared")


def held_at_bound(sol: np.ndarray, bounds: Bounds, name: str, node: np.ndarray) -> np.ndarray:
    """Whether ``name`` (``v``, ``u``, ``w``) sits at a bound (within 1e-4 of the bound range)
    on either side of each of the nodes ``node`` (node k's control holds over [t_k, t_k+1])."""
    lo, hi = getattr(bounds, name)
    tol = 1e-4 * (hi - lo)
    val = sol[:, COLUMN[name]]
    held = (val <= lo + tol) | (val >= hi - tol)
    return held[node] | held[np.maximum(node - 1, 0)]


MISFIT_MARGIN_S = 60.0
"""Plots within this time of a far plot at a bound (:func:`misfit_stretches`) are no reference
for the sensors' statistics either (the track is bent off around it)."""


def misfit_stretches(quad_at_plots: FloatArray, t: FloatArray, sol: np.ndarray,
                     bounds: Bounds, gate: float | None, plot_node: np.ndarray) -> np.ndarray:
    """Plots (indexes) where the track cannot follow its plots: within
    :data:`MISFIT_MARGIN_S` of a plot more than ``gate`` sigma from it where the lateral
    acceleration or the speed sits at a bound. The track there is the bounds', not the
    aircraft's: a 300-m/s jet turning at 2.5 g under the default u bound left its track 1.3
    km off and spread a second radar's range residuals to 228-277 m (its sigma 40 m, a
    tester's recording); such stretches are left out of the sensors' statistics."""
    if gate is None or not t.size:
        return np.zeros(0, dtype=int)
    far = np.flatnonzero(quad_at_plots > gate**2)
    node = plot_node[far]
    bad = far[held_at_bound(sol, bounds, "u", node) | held_at_bound(sol, bounds, "v", node)]
    if not bad.size:
        return np.zeros(0, dtype=int)
    tb = np.sort(t[bad])
    k = np.searchsorted(tb, t)
    near = np.minimum(np.abs(t - tb[np.clip(k - 1, 0, tb.size - 1)]),
                      np.abs(t - tb[np.clip(k, 0, tb.size - 1)]))
    return np.flatnonzero(near <= MISFIT_MARGIN_S)


def at_bounds(t_nodes: FloatArray, sol: np.ndarray, bounds: Bounds, name: str
              ) -> tuple[float, float]:
    """Shares of the track's time with ``name`` (``v``, ``u`` or ``w``) at its lower and at its
    upper bound (within 1e-4 of the bound range)."""
    dt = np.diff(t_nodes)
    total = dt.sum()
    if total <= 0:  # every plot at one instant
        return 0.0, 0.0
    lo, hi = getattr(bounds, name)
    tol = 1e-4 * (hi - lo)
    val = sol[:-1, COLUMN[name]]
    return float(dt[val <= lo + tol].sum() / total), float(dt[val >= hi - tol].sum() / total)


def report_bounds(t_nodes: FloatArray, sol: np.ndarray, bounds: Bounds,
                  diag: Diagnostics) -> None:
    """Share of the track's time with ``v``, ``u``, ``w`` at a bound (``extra``), and a warning
    when the speed sits at one for ``SPEED_MISFIT_SHARE`` of it or more: the plots then ask for
    an aircraft the bounds do not allow (the turn and acceleration bounds are met in hard
    manoeuvres)."""
    shares = {name: at_bounds(t_nodes, sol, bounds, name) for name in "vuw"}
    for name, (at_lo, at_hi) in shares.items():
        diag.extra[f"{name}_at_bound_share"] = at_lo + at_hi
    for share, side, value in zip(shares["v"], ("lower", "upper"), bounds.v, strict=True):
        if share >= SPEED_MISFIT_SHARE:
            diag.warnings.append(
                f"speed at its {side} bound ({value:g} m/s) for {100 * share:.0f} % of "
                "the track: the plots ask for an aircraft that bounds.v does not allow")


UNREACHABLE_SLACK_M = 2_000.0
"""Metres beyond ``v_max dt`` and ten sigmas both ways before a plot counts as out of reach of
its neighbours (:func:`unreachable_plots`): the wild plots it is for are tens of km off."""


def reach_m(dt: Any, sigmas: Any, spreads: Any, v_max: float) -> Any:
    """How far apart two plots ``dt`` s apart may lie and be of one aircraft under ``v_max``:
    ``v_max |dt| + 10 (sigma_i + sigma_j) + spread_i + spread_j + UNREACHABLE_SLACK_M``."""
    return v_max * abs(dt) + 10 * sigmas + spreads + UNREACHABLE_SLACK_M


MAX_OPEN_PIECES = 32
""":func:`aircraft_apart` follows at most this many pieces at a time (a key's scattered wild
plots would each start one: quadratic); a plot within reach of none beyond joins the first."""


def aircraft_apart(t: FloatArray, sensor: np.ndarray, centre: FloatArray, sigma: FloatArray,
                   spread: FloatArray, v_max: float, gap_s: float = np.inf) -> np.ndarray:
    """Plots of one key told apart into aircraft: a piece label per plot (in the order
    given). In time order each plot joins, of the pieces it is within reach of (as
    :func:`unreachable_plots` judges reach, from the piece's last plot of the same sensor:
    another sensor's plots may be offset from it; or its last plot when the piece has none of
    that sensor), the one whose course it lies nearest: the piece's plots of that sensor over
    the last :data:`COURSE_S` carried on to the plot's time, up to :data:`PREDICTION_S` (two
    aircraft crossing at 90 deg swapped halves when judged by the last plot alone, a
    reviewer's); a plot within reach of no piece starts one
    (pieces whose last plot is more than ``gap_s`` back are not followed, nor more than
    :data:`MAX_OPEN_PIECES`). Pieces are numbered by their first plot."""
    order = np.argsort(t, kind="stable")
    label = np.zeros(t.size, dtype=int)
    tt, sg, sp = t.tolist(), sigma.tolist(), spread.tolist()
    cx, cz, sensors = centre[:, 0].tolist(), centre[:, 1].tolist(), sensor.tolist()
    # per piece: sensor -> its recent plots (the last PREDICTION_S, oldest first); None -> the
    # piece's last plot
    ends: list[dict[object, list[int]]] = []
    pieces = 0
    for i in order.tolist():
        best, best_miss = -1, np.inf
        ends = [e for e in ends if tt[i] - tt[e[None][-1]] <= gap_s]
        for e in ends:
            recent = e.get(sensors[i], e[None])
            j, k = recent[-1], recent[0]
            dt = tt[i] - tt[j]
            reach = reach_m(dt, sg[i] + sg[j], sp[i] + sp[j], v_max)
            if math.hypot(cx[i] - cx[j], cz[i] - cz[j]) > reach:
                continue
            px, pz = cx[j], cz[j]
            if tt[j] - tt[k] > 0 and dt <= PREDICTION_S:  # the course over the recent plots
                f = dt / (tt[j] - tt[k])
                px, pz = px + f * (cx[j] - cx[k]), pz + f * (cz[j] - cz[k])
            miss = math.hypot(cx[i] - px, cz[i] - pz) / reach
            if miss < best_miss:
                best, best_miss, chosen = label[e[None][-1]], miss, e
        if best < 0 and len(ends) >= MAX_OPEN_PIECES:
            chosen = ends[0]
            best = label[chosen[None][-1]]
        if best < 0:
            best, chosen = pieces, {}
            pieces += 1
            ends.append(chosen)
        recent = [j for j in chosen.get(sensors[i], []) if tt[i] - tt[j] <= COURSE_S] + [i]
        chosen[sensors[i]], chosen[None] = recent, [i]
        label[i] = best
    return label


PREDICTION_S = 60.0
""":func:`aircraft_apart` carries a piece's course on over at most this time."""
COURSE_S = 30.0
"""... measured over its plots of the last this many seconds (two plots 4.8 s apart gave a
course too noisy to keep two aircraft crossing at 30 deg apart)."""


CHAIN_SKIP = 8
"""The longest run of plots the chain of :func:`unreachable_plots` may step over."""


def unreachable_plots(t: FloatArray, centre: FloatArray, sigma: FloatArray, spread: FloatArray,
                      v_max: float) -> np.ndarray:
    """Indexes of plots no aircraft under ``v_max`` could have made together with the others:
    those off the longest chain of plots in time order, each within reach of the one before
    it (stepping over at most :data:`CHAIN_SKIP` - 1 plots at a time). Within reach: ``|c_i -
    c_j| <= v_max |t_i - t_j| + 10 (sigma_i + sigma_j) + spread_i + spread_j +
    UNREACHABLE_SLACK_M`` (``sigma``: the largest one-sigma axis; ``spread``: how far the
    centre moves over the heights it may take). A burst of wild plots near each other (three
    at the radar, 1 m away: each in reach of the next) is a shorter chain than the track's,
    which steps over it. Such plots, with their tiny sigmas, would otherwise pull the start
    and the first solve towards them: 8-12 km, and IPOPT to 1e16 m for one plot on one radar,
    before the gate of the first solution sees them. Nothing is left out when the chain is
    not most of the plots (no track to judge by)."""
    n = t.size
    if n < 3:
        return np.zeros(0, dtype=int)
    order = np.argsort(t, kind="stable")
    ts, cs, ss, ps = t[order], centre[order], sigma[order], spread[order]
    near = np.zeros((CHAIN_SKIP + 1, n), dtype=bool)  # near[d, i]: i within reach of i - d
    for d in range(1, min(CHAIN_SKIP, n - 1) + 1):
        i, j = np.arange(d, n), np.arange(n - d)
        near[d, i] = np.hypot(*(cs[i] - cs[j]).T) <= reach_m(
            ts[i] - ts[j], ss[i] + ss[j], ps[i] + ps[j], v_max)
    if near[1, 1:].all():  # every plot in reach of the one before: the whole is the chain
        return np.zeros(0, dtype=int)
    length = np.ones(n, dtype=int)  # the longest chain ending at each plot
    back = np.full(n, -1)
    for i in range(1, n):  # sequential by nature (each length from earlier ones), n steps
        ds = np.arange(1, min(CHAIN_SKIP, i) + 1)
        ok = near[ds, i]
        if ok.any():
            cand = np.where(ok, length[i - ds], 0)
            k = int(np.argmax(cand))  # the nearest of the longest: ds ascending
            length[i], back[i] = cand[k] + 1, i - int(ds[k])
    end = int(np.argmax(length))
    if 2 * length[end] <= n:
        return np.zeros(0, dtype=int)
    on = np.zeros(n, dtype=bool)
    while end >= 0:
        on[end] = True
        end = back[end]
    return np.sort(order[~on])
