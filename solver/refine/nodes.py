"""The node grid of the refinement and what each node knows: its plot's fix, the initial guess.

Nodes: every plot time in time order (plots of different sensors at one instant get nodes
joined by zero-length intervals, ``F(s, u, w, 0) = s``), plus equal subdivisions of gaps longer
than ``max_node_step_s``. One plot per node at most, so every plot keeps its own weight.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..estimation.cv_rts import smoothed_means
from ..frames import LocalFrame
from ..inputs import Bounds, FloatArray
from ..plots import PlotTable
from ..results import Reconstruction, StateSeries
from ..sensors import (
    ALTITUDE_FIT_DEGREE,
    PlaneFixes,
    beyond_reach,
    reach,
    reach_slope,
)
from ..trajectory import evaluate
from .layout import HD_MAX, Variant

INIT_SMOOTHER_Q = 30.0  # m^2/s^3: the CV smoother of the initial guess follows turns
Q_VERTICAL = 0.5
"""m^2/s^3: spectral density of vertical-rate changes (integrated random walk of the height):
a level-off from 10 m/s within 30 s costs about 7 chi-square units."""
MIN_NODE_DT = 1.0  # s: the vertical-rate change across a zero-length interval is weighted as 1 s
ALTITUDE_GUESSES = np.arange(0.0, 19_001.0, 1000.0)  # m: constant heights tried for the start


def node_grid(t_plots: FloatArray, max_step: float) -> tuple[FloatArray, np.ndarray]:
    """Node times (every plot time, non-decreasing, plus equal subdivisions of long gaps) and
    each (time-ordered) plot's node."""
    gaps = np.diff(t_plots)
    parts = np.maximum(np.ceil(gaps / max_step - 1e-9).astype(int), 1)
    starts = np.concatenate([[0], np.cumsum(parts)])
    frac = np.arange(starts[-1]) - np.repeat(starts[:-1], parts)
    t_nodes = np.repeat(t_plots[:-1], parts) + frac * np.repeat(gaps / parts, parts)
    return np.append(t_nodes, t_plots[-1]), starts


@dataclass
class NodeData:
    """Per node (``n`` rows; zero where the node has no plot): the plot's fix (centre, R2
    entries ``(a, b, c)`` of its one-sigma ellipse, weight), and for the variants the centre's
    altitude dependence and height bounds, measured altitudes, and bias derivatives."""

    centre: FloatArray  # (n, 2)
    info: FloatArray  # (n, 3)
    weight: FloatArray  # (n,)
    centre_h: FloatArray  # (n, 2, DEG): coefficients of s^1..s^DEG
    ray: FloatArray  # (n, 2)
    slant: FloatArray  # (n,)
    site_h: FloatArray
    h_mid: FloatArray
    h_half: FloatArray
    h_lo: FloatArray
    h_hi: FloatArray
    alt: FloatArray
    alt_info: FloatArray
    d_range: FloatArray  # (n, 2)
    d_azimuth: FloatArray  # (n, 2)
    sensor: FloatArray  # (n, biases) one-hot
    free: np.ndarray  # (n,) bool: the centre depends on the height
    level: FloatArray  # (n, 2) scale of the level penalties on |u|, |w| (1: the full weight)
    plane_scale: FloatArray  # (n,) the plane's scale at the node (speeds there are this x)

    @classmethod
    def assemble(cls, table: PlotTable, fixes: PlaneFixes, n: int, plot_node: np.ndarray,
                 variant: Variant, bias_sensors: list[int]) -> NodeData:
        """Scatter the plots' fixes (table rows) to their nodes."""
        def scatter(values: np.ndarray, fill: float = 0.0) -> np.ndarray:
            out = np.full((n, *values.shape[1:]), fill, dtype=float)
            out[plot_node] = values
            return out

        e = fixes.ellipses
        free = np.zeros(n, bool)
        free[plot_node] = fixes.altitude_free
        # heights each node may take: the track's (a free centre follows the height within
        # its plot's reach, solver.sensors.reach, bounded by the same)
        lo, hi = table.heights()
        h_lo, h_hi = np.full(n, lo), np.full(n, hi)
        known = np.isfinite(table.altitude_m)
        alt_sigma = table.altitude_sigmas()
        onehot = np.zeros((len(table), variant.biases))
        for j, k in enumerate(bias_sensors):
            onehot[table.sensor == k, j] = 1.0
        return cls(
            # a free centre is the fit's constant term plus its height terms
            centre=scatter(np.where(fixes.altitude_free[:, None], fixes.poly[:, :, 0],
                                    np.column_stack([e.cx, e.cz]))),
            info=scatter(e.weights()),
            weight=scatter(np.ones(len(table))),
            centre_h=scatter(fixes.poly[:, :, 1:]),
            ray=scatter(fixes.ray),
            # far beyond any height where no free plot is (nodes without a plot too: a slant
            # of 0 there made the NLP's sqrt(slant^2 - h^2) NaN, every block failing at a gap)
            slant=scatter(np.where(fixes.altitude_free, fixes.slant, 1e7), 1e7),
            site_h=scatter(fixes.site_h),
            h_mid=scatter(fixes.h_mid),
            h_half=scatter(fixes.h_half, 1.0),
            h_lo=h_lo,
            h_hi=h_hi,
            alt=scatter(np.where(known, table.altitude_m, 0.0)),
            alt_info=scatter(np.where(known, 1.0 / alt_sigma**2, 0.0)),
            d_range=scatter(fixes.d_range),
            d_azimuth=scatter(fixes.d_azimuth),
            sensor=scatter(onehot),
            free=free,
            level=np.ones((n, 2)),
            plane_scale=np.ones(n),
        )

    def weighed_info(self) -> FloatArray:
        """``info`` times ``weight``: zero for the plots given no weight."""
        return self.info * self.weight[:, None]

    def without(self, nodes: np.ndarray) -> NodeData:
        """A copy with no weight on the plots at ``nodes`` (gated as wild)."""
        weight = self.weight.copy()
        weight[nodes] = 0.0
        return replace(self, weight=weight)

    def scaled(self, frame: LocalFrame | None, x: FloatArray, z: FloatArray) -> NodeData:
        """A copy with the plane's scale at the nodes' positions ``(x, z)`` (a pilot's): the
        bounds on speed and accelerations hold on the ground, so the plane's are this many times
        theirs. A track 2600 km from the reference (scale 1.076) at 320 m/s moved at 344 m/s
        in the plane: held at 330 m/s, it came out 16 km off (1 without a frame)."""
        if frame is None:
            return self
        return replace(self, plane_scale=np.asarray(frame.scale(x, z), float))

    def on_ground(self, sol: np.ndarray) -> np.ndarray:
        """The node solution with speed and accelerations (columns 3-5) over the plane's scale:
        what the bounds hold."""
        out = sol.copy()
        out[:, 3:6] /= self.plane_scale[:, None]
        return out

    def relieved(self, u0: FloatArray, relief: float) -> NodeData:
        """A copy whose ``|u|`` level weight is ``1 / (1 + (u0 / relief)^2)`` per node (``u0``:
        a pilot estimate of the lateral acceleration, m/s^2; ``relief`` 0: unchanged)."""
        if relief <= 0:
            return self
        level = self.level.copy()
        level[:, 0] = 1.0 / (1.0 + (np.asarray(u0, dtype=float) / relief) ** 2)
        return replace(self, level=level)

    def reweighted(self, plot_node: np.ndarray, factor: FloatArray) -> NodeData:
        """A copy whose plots' ellipse weights are multiplied by ``factor`` (per plot)."""
        info = self.info.copy()
        info[plot_node] *= factor[:, None]
        return replace(self, info=info)

    def relinearised(self, table: PlotTable, plot_node: np.ndarray, variant: Variant,
                     bias_sensors: list[int], biases: FloatArray, sensor_scale: FloatArray
                     ) -> NodeData:
        """A copy whose radar plots' centres and derivatives are taken at the offsets
        ``biases`` (``(radars, 3)``, range and azimuth; the time offset's term is exact):
        ``c(r - b0, psi - b0) + J b0`` as the centre, so the NLP's ``p + J b - centre`` is the
        residual linearised at ``b0`` instead of at zero (a Gauss-Newton step on the radar
        model). At zero, a 2-deg azimuth offset at 280 km leaves ``r b^2 / 2 = 170 m`` along the
        ray, which the range offset took up. Weights, gating, level relief and the sensors'
        weight scales ``sensor_scale`` (per table sensor) carry over."""
        offsets = {k: (float(biases[j, 0]), float(biases[j, 1]))
                   for j, k in enumerate(bias_sensors)}
        new = NodeData.assemble(table, table.corrected(offsets).fixes(), len(self.weight),
                                plot_node, variant, bias_sensors)
        b = new.sensor @ biases
        centre = new.centre + new.d_range * b[:, 0:1] + new.d_azimuth * b[:, 1:2]
        new = new.reweighted(plot_node, sensor_scale[table.sensor])
        return replace(new, centre=centre, weight=self.weight, level=self.level,
                       plane_scale=self.plane_scale)

    def beyond_reach(self, h: FloatArray) -> np.ndarray:
        """``(n,)`` bool: nodes whose plot's centre follows the height (no altitude) but not to
        ``h``, the node's height: beyond its reach (:func:`solver.sensors.reach`) by more than
        the reach's smooth ends (an aircraft above 74 deg elevation, a wild range)."""
        return self.free & beyond_reach(h, self.h_mid, self.h_half)

    def centre_at(self, h: FloatArray | None) -> FloatArray:
        """``(n, 2)`` plot centres at node heights ``h`` (None: the fixed centres)."""
        if h is None:
            return self.centre
        h = reach(h, self.h_mid, self.h_half)
        sh = (h - self.h_mid) / self.h_half
        c = self.centre.copy()
        for j in range(ALTITUDE_FIT_DEGREE):
            c += self.centre_h[:, :, j] * sh[:, None] ** (j + 1)
        ground = np.sqrt(np.maximum(self.slant**2 - (h - self.site_h) ** 2, 0.0))
        return c + self.ray * ground[:, None]

    def dcentre_dh(self, h: FloatArray) -> FloatArray:
        """``(n, 2)`` derivative of the centres with respect to the height."""
        slope = reach_slope(h, self.h_mid, self.h_half)
        h = reach(h, self.h_mid, self.h_half)
        sh = (h - self.h_mid) / self.h_half
        d = np.zeros_like(self.centre)
        for j in range(ALTITUDE_FIT_DEGREE):
            d += self.centre_h[:, :, j] * (j + 1) * sh[:, None] ** j / self.h_half[:, None]
        dh = h - self.site_h
        ground = np.sqrt(np.maximum(self.slant**2 - dh**2, 1e-6))
        return (d - self.ray * (dh / ground)[:, None]) * slope[:, None]

    def residuals(self, sol: np.ndarray, biases: FloatArray | None, altitude: bool
                  ) -> FloatArray:
        """``(n, 2)`` plane residuals ``d = p - c(h)`` of the node solution (0 where no plot)."""
        p = sol[:, :2].copy()
        if biases is not None and biases.size:
            b = self.sensor @ biases  # (n, 3) offsets of each node's radar
            vel = sol[:, 3:4] * np.column_stack([np.cos(sol[:, 2]), np.sin(sol[:, 2])])
            p += -b[:, 2:3] * vel + self.d_range * b[:, 0:1] + self.d_azimuth * b[:, 1:2]
        c = self.centre_at(sol[:, 6] if altitude else None)
        return np.where((self.info[:, 0] != 0)[:, None], p - c, 0.0)

    def quad(self, sol: np.ndarray, biases: FloatArray | None, altitude: bool) -> FloatArray:
        """R2 terms ``d^T M d`` of the node solution (0 where no plot)."""
        d = self.residuals(sol, biases, altitude)
        a, b, c = self.info.T
        return a * d[:, 0] ** 2 + 2 * b * d[:, 0] * d[:, 1] + c * d[:, 1] ** 2


def hd_information(t_nodes: FloatArray) -> FloatArray:
    """Information ``1 / (q_h max(dt, 1 s))`` of the vertical-rate change into each node (node 0:
    0, set per block)."""
    dt = np.maximum(np.diff(t_nodes), MIN_NODE_DT)
    return np.concatenate([[0.0], 1.0 / (Q_VERTICAL * dt)])


# ------------------------------------------------------------------------- initial guess


GUESS_MIN_GAP_S = 1.0
"""Plots closer in time than this are fused into one point for the initial guess only: the CV
smoother's ``Q^-1 ~ 12 / (q T^3)`` loses positive definiteness in float64 for steps of
hundredths of a second (seen with two radars' asynchronous scans); the merged point is off by at
most half a second of flight, which the NLP removes."""


def fused_points(t: FloatArray, centre: FloatArray, info: FloatArray,
                 min_gap_s: float = GUESS_MIN_GAP_S
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Plots within ``min_gap_s`` of each other (e.g. several sensors at one instant) fused
    into one point (information-weighted, at the group's mean time): times, centres ``(m, 2)``
    and information ``(m, 2, 2)``. The sum of the plots' quadratic forms ``d^T I d`` is the
    fused point's plus a constant, for any position at that time.

    A run of plots each within ``min_gap_s`` of the next that spans ``min_gap_s`` or more (many
    sensors: 16 radars' 2,000 plots over 618 s left no gap of 1 s, and the whole track became 2
    points, a start 7 km from the truth in the median, on which IPOPT with the radars' offsets
    ran out of its 300 iterations twice) is cut into bins of ``min_gap_s`` from its first plot,
    each bin's time held within its middle half, so fused points stay ``min_gap_s / 2`` apart
    and each is off by at most ``3 min_gap_s / 4`` of flight."""
    order = np.argsort(t, kind="stable")
    ts = t[order]
    run = np.concatenate([[0], np.cumsum(np.diff(ts) >= min_gap_s)])
    first = ts[np.flatnonzero(np.diff(run, prepend=-1))][run]  # each run's first time
    span = np.zeros(run[-1] + 1)
    np.maximum.at(span, run, ts - first)
    long = (span >= min_gap_s)[run]
    part = np.where(long, np.floor((ts - first) / min_gap_s), 0.0)
    group_sorted = np.concatenate([[0], np.cumsum((np.diff(run) > 0) | (np.diff(part) != 0))])
    inverse = np.empty(t.size, dtype=int)
    inverse[order] = group_sorted
    m = int(group_sorted[-1]) + 1
    times = np.bincount(inverse, weights=t, minlength=m) / np.bincount(inverse, minlength=m)
    cut = np.zeros(m, bool)
    cut[group_sorted[long]] = True
    if cut.any():  # a bin's time within the middle half of the bin
        start = np.zeros(m)
        start[group_sorted] = first + part * min_gap_s
        times[cut] = np.clip(times[cut], start[cut] + min_gap_s / 4,
                             start[cut] + 3 * min_gap_s / 4)
    I = np.zeros((times.size, 2, 2))
    np.add.at(I, inverse, info)
    b = np.zeros((times.size, 2))
    np.add.at(b, inverse, np.einsum("kij,kj->ki", info, centre))
    return times, np.linalg.solve(I, b[:, :, None])[:, :, 0], I


def info_matrices(info3: FloatArray) -> FloatArray:
    """``(n, 2, 2)`` from R2 entries ``(a, b, c)``."""
    return np.stack([info3[:, [0, 1]], info3[:, [1, 2]]], axis=1)


GUESS_HUBER_SIGMA = 3.0
"""The start's smoother down-weights plots further than this many sigmas from it (Huber weights
``min(1, delta / r)``, iterated: :func:`smoother_guess`)."""
GUESS_ROUNDS = 4  # at most this many reweighted smoother solves


def smoother_guess(t_plot: FloatArray, centre: FloatArray, info3: FloatArray, t_nodes: FloatArray,
                   bounds: Bounds, huber: float | None = GUESS_HUBER_SIGMA
                   ) -> tuple[np.ndarray, float]:
    """Node guess from the constant-velocity smoother's means at the plots (one banded solve),
    and the smoother's weighted residual sum (to compare altitude hypotheses).

    Robust (iteratively reweighted): each plot's information is scaled by ``min(1, huber / r)``,
    ``r`` its distance in sigmas from the previous smooth, and the smoother solved again, while
    the weights move. A wild plot within reach of its neighbours (the farther ones never get
    here: :func:`.gate.unreachable_plots`) pulled the plain smoother's start off by kilometres,
    and in a turn the refinement stayed in that wrong solution: with 1 % false plots within
    +-20 km and +-5 deg (``benchmarks/gating.py``), two of 14 dev runs of the ssr profile ended
    187 and 229 m RMS from the truth instead of 54 and 87 m."""
    used = info3[:, 0] + info3[:, 2] > 0  # plots given no weight are no part of it
    t_u, c_u, I_u = t_plot[used], centre[used], info_matrices(info3[used])
    weight = np.ones(t_u.size)
    for _ in range(GUESS_ROUNDS if huber is not None else 1):
        times, c, I = fused_points(t_u, c_u, I_u * weight[:, None, None])
        if times.size < 2:  # every plot at one instant: a point at rest
            s = np.zeros((2, 4))
            s[:, :2] = c[0]
            times = np.array([times[0], times[0] + 1.0])
            return nodes_from_states(StateSeries(times, *s.T), t_nodes, bounds), 0.0
        smooth = smoothed_means(times, c, I, INIT_SMOOTHER_Q)
        if huber is None:
            break
        at = np.column_stack([np.interp(t_u, times, smooth[:, 0]),
                              np.interp(t_u, times, smooth[:, 1])])
        d = at - c_u
        r = np.sqrt(np.maximum(np.einsum("ki,kij,kj->k", d, I_u, d), 0.0))
        new = np.minimum(1.0, huber / np.maximum(r, 1e-300))
        if np.max(np.abs(new - weight)) < 0.05:
            break
        weight = new
    d = smooth[:, :2] - c
    cost = float(np.einsum("ki,kij,kj->", d, I, d))
    return nodes_from_states(StateSeries(times, *smooth.T), t_nodes, bounds), cost


def altitude_guess(table: PlotTable, data: NodeData, plot_node: np.ndarray, t_nodes: FloatArray,
                   bounds: Bounds) -> tuple[np.ndarray, FloatArray]:
    """Start of the altitude variant: heights interpolated from the plots' altitudes where any
    carry one, else the constant height (of 0, 1, ..., 14 km) whose plot centres the CV smoother
    fits best; the horizontal guess from the smoother at those heights."""
    known = np.isfinite(table.altitude_m)
    order = np.argsort(table.t[known], kind="stable")
    if known.any():
        h = np.interp(t_nodes, table.t[known][order], table.altitude_m[known][order])
        candidates = [h]
    else:
        candidates = [np.full(t_nodes.size, h0) for h0 in ALTITUDE_GUESSES]
    best: tuple[float, np.ndarray, FloatArray] | None = None
    for h in candidates:
        h = np.clip(h, data.h_lo, data.h_hi)
        c = data.centre_at(h)[plot_node]
        guess, cost = smoother_guess(table.t, c, data.weighed_info()[plot_node], t_nodes,
                                     bounds)
        if best is None or cost < best[0]:
            best = (cost, guess, h)
    assert best is not None
    return best[1], best[2]


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
    dt = np.diff(t_nodes)
    ok = dt > 1e-9
    u = np.zeros(t_nodes.size)
    w = np.zeros(t_nodes.size)
    u[:-1][ok] = v[:-1][ok] * np.diff(phi)[ok] / dt[ok]
    w[:-1][ok] = np.diff(v)[ok] / dt[ok]
    return _node_array(series, u, w, bounds)


def _node_array(series: StateSeries, u: FloatArray, w: FloatArray, bounds: Bounds) -> np.ndarray:
    out = np.empty((series.t.size, 6))
    out[:, 0], out[:, 1] = series.x, series.z
    out[:, 2] = np.unwrap(series.heading)
    out[:, 3] = np.clip(series.speed, *bounds.v)
    out[:, 4] = np.clip(u, *bounds.u)
    out[:, 5] = np.clip(w, *bounds.w)
    return out


def with_altitude(guess: np.ndarray, h: FloatArray, t_nodes: FloatArray) -> np.ndarray:
    """Append the height and vertical-rate columns to a horizontal node guess."""
    dt = np.diff(t_nodes)
    hd = np.zeros(t_nodes.size)
    ok = dt > 1e-9
    hd[:-1][ok] = np.diff(h)[ok] / dt[ok]
    return np.column_stack([guess, h, np.clip(hd, -HD_MAX, HD_MAX)])


OFFSET_GUESS_ROUNDS = 3
"""Huber-reweighted least-squares rounds of :func:`offset_guess`."""


def offset_guess(data: NodeData, guess: np.ndarray, altitude: bool, bias_info: FloatArray,
                 time_gauge: FloatArray | None, huber: float = GUESS_HUBER_SIGMA
                 ) -> np.ndarray:
    """Start ``(biases, 3)`` of the estimated offsets: the least-squares offsets of the plots
    against the start's track, ``min_b sum_i w_i |J_i b - d_i|^2_{M_i} + sum b^2 / s_b^2 +
    (g . b_t)^2`` with ``d_i = c_i - p_i`` and ``J_i = [dc/dr, dc/dpsi, -v_i e_i]`` (the NLP's
    linearised plot model, :mod:`.nlp`), Huber weights ``w_i = min(1, huber / r_i)`` of each
    plot's distance in sigmas after the previous round (zero offsets where that is not
    finite). Started at zero, 16 radars' 48 offsets took 93 IPOPT iterations of the first
    solve (2,004 plots, about 0.13 s each: 12 s of 17), at the true offsets 19, here 17; the
    same solution (offsets and sigmas of the tests' two-radar cases to the printed digits)."""
    nb = data.sensor.shape[1]
    m = 3 * nb
    plotted = (data.weight > 0) & (data.info[:, 0] + data.info[:, 2] > 0) & data.sensor.any(1)
    if nb == 0 or not plotted.any():
        return np.zeros((nb, 3))
    k = np.flatnonzero(plotted)
    phi, v = guess[k, 2], guess[k, 3]
    J = np.stack([data.d_range[k], data.d_azimuth[k],
                  -v[:, None] * np.column_stack([np.cos(phi), np.sin(phi)])], axis=2)
    d = -data.residuals(guess, None, altitude)[k]
    M = info_matrices(data.weighed_info()[k])
    onehot = data.sensor[k]
    prior = np.diag(np.asarray(bias_info, float))
    if time_gauge is not None and np.any(time_gauge):
        g = np.zeros(m)
        g[2::3] = time_gauge
        prior += np.outer(g, g)
    w = np.ones(k.size)
    b = np.zeros(m)
    for _ in range(OFFSET_GUESS_ROUNDS):
        JtM = np.einsum("nki,nkl->nil", J, M * w[:, None, None])
        A = prior.copy()
        blocks = np.einsum("ns,nij->sij", onehot, JtM @ J)
        rhs = np.einsum("ns,ni->si", onehot, np.einsum("nil,nl->ni", JtM, d))
        for j in range(nb):
            A[3 * j: 3 * j + 3, 3 * j: 3 * j + 3] += blocks[j]
        b = np.linalg.solve(A, rhs.ravel())
        e = np.einsum("nij,nj->ni", J, (onehot @ b.reshape(nb, 3))) - d
        r = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", e, M, e), 0.0))
        w = np.minimum(1.0, huber / np.maximum(r, 1e-300))
    return b.reshape(nb, 3) if np.all(np.isfinite(b)) else np.zeros((nb, 3))
