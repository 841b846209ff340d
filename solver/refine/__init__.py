"""Full-track refinement: one bounded piecewise-constant-control NLP over all plots of all
sensors.

The sliding windows (spec section 6) look a few plots ahead and never revise what they
accepted; a reconstruction sees the whole recording. The NLP (:mod:`.nlp`) is solved by
multiple shooting on a node grid (:mod:`.nodes`: every plot, gaps subdivided), in blocks for
long tracks (:mod:`.blocks`), twice: a second, warm-started solve holds every control change the
first one did not select (``<= switch_threshold``) at exactly zero, so the segments describe the
trajectory exactly, and gives no weight to wild plots (:mod:`.gate`). The covariance is the
Laplace approximation at the solution (:mod:`.covariance`); :mod:`.output` turns the nodes into
segments, states and per-sensor statistics.

Every plot is weighted by its own sensor's model at its own time (no "aging"). Where radar plots
without altitude meet another sensor, the height becomes observable and is estimated per node
(an integrated random walk); radars with ``estimate_bias`` have their range, azimuth and time
offsets estimated with the track under their priors, position sensors (ADS-B) their time
offset.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from ..config import ReconstructionConfig, RefineSettings
from ..inputs import Bounds, Plots, Radar
from ..plots import PlotTable
from ..results import Diagnostics, Reconstruction, listed
from ..sensors import MAX_ELEVATION_DEG, Sensor
from ..trajectory import sample_times
from . import nlp
from .blocks import (
    LADDER,
    DeadlineExceeded,
    Problem,
    build_solvers,
    check_deadline,
    cut,
    solve_block,
)
from .covariance import node_covariance, plot_covariances, state_size
from .gate import (
    RESCALE_ROUNDS,
    misfit_stretches,
    overstated_sigmas,
    report_bounds,
    report_scales,
    turn_warning,
    unreachable_plots,
    wild_plots,
)
from .layout import BIAS_TERMS, Variant, solution_columns
from .nodes import (
    NodeData,
    altitude_guess,
    hd_information,
    node_grid,
    nodes_from_segments,
    offset_guess,
    smoother_guess,
    with_altitude,
)
from .output import leverages, plot_residuals, segments, sensor_reports, series

TIME_GAUGE_INFO = 1e6  # 1/s^2: the reference's time offsets held at zero to a millisecond

__all__ = ["LADDER", "DeadlineExceeded", "build_solvers", "node_grid", "refine", "refine_table",
           "time_reference", "unreachable_in"]


def time_reference(sensors: Sequence[Sensor], bias_sensors: list[int]) -> np.ndarray:
    """Weights ``g`` (one per offset-estimating sensor) of the time gauge ``g . b_t = 0``:
    zero when some sensor keeps absolute time (estimates no offset). When every sensor
    estimates its time offset a shift common to all of them is a shift of the whole track in
    time and cannot be observed (left free it drifted 7-10 s, 800 m, in the benchmark): the
    radars' mean offset is then held at zero, their time stamps the reference (else the sum
    over the position sensors). The sum over every sensor, as before, split the common part
    by the priors: a 1-s ADS-B latency came out as ADS-B +0.69 s and the radars -0.32 and
    -0.36 s (a walkthrough helper); now ADS-B +1.0 s and the radars 0."""
    g = np.zeros(len(bias_sensors))
    if not bias_sensors or len(bias_sensors) < len(sensors):
        return g
    radar = np.array([sensors[k].kind == "radar" for k in bias_sensors])
    g[radar if radar.any() else slice(None)] = np.sqrt(TIME_GAUGE_INFO)
    return g


BULK_SHARE = 0.2
"""A sensor with this share of its plots in a track given no weight is named as likely offset
(:func:`_by_sensor`)."""


def _by_sensor(table: PlotTable, rejected: np.ndarray) -> str:
    """With several sensors, how many plots of each were given no weight, and a hint when one
    lost a share of its plots in bulk: with ADS-B 0.8 s late the fused track sat 180-212 m
    behind and 44 % and 51 % of two radars' plots were given no weight, the warning naming
    none (a tester's recording); a sensor's offset, not wild plots, does that."""
    if len(table.sensors) < 2:
        return ""
    lost = np.bincount(table.sensor[rejected], minlength=len(table.sensors))
    total = np.bincount(table.sensor, minlength=len(table.sensors))
    parts = [f"{s.id} {lost[k]} of {total[k]}" for k, s in enumerate(table.sensors) if lost[k]]
    bulk = [s.id for k, s in enumerate(table.sensors)
            if total[k] and lost[k] >= BULK_SHARE * total[k]]
    hint = (f"; so many of {', '.join(bulk)} suggest an offset between the sensors (a range, "
            "azimuth or time offset, e.g. a late ADS-B: estimate_bias or the known offsets), "
            "not wild plots") if bulk else ""
    return f" ({', '.join(parts)}{hint})"


def unreachable_in(table: PlotTable, data: NodeData, plot_node: np.ndarray, bounds: Bounds,
                 bias_sensors: list[int] | None = None) -> np.ndarray:
    """:func:`solver.refine.gate.unreachable_plots` of the table's plots: their centres (at the
    middle of their reach where the height is free), largest sigma, and the centre's move over
    the heights each may take; each sensor whose offsets are estimated apart."""
    a, b, c = data.info[plot_node].T
    lam_min = (a + c) / 2 - np.sqrt(((a - c) / 2) ** 2 + b**2)
    sigma = 1.0 / np.sqrt(np.maximum(lam_min, 1e-18))
    low, high = table.heights()
    lo = data.centre_at(np.full(data.centre.shape[0], low))[plot_node]
    hi = data.centre_at(np.full(data.centre.shape[0], high))[plot_node]
    spread = np.where(data.free[plot_node], np.hypot(*(hi - lo).T), 0.0)
    centre = data.centre_at(data.h_mid)[plot_node]
    # a sensor whose offsets are estimated is judged by its own plots alone: until they are
    # estimated, its plots may lie kilometres off the others' (2 deg at 280 km: every plot of
    # a radar next to 1-Hz ADS-B left out, the offset then the prior's)
    alone = list(bias_sensors or [])
    groups = [np.flatnonzero(table.sensor == k) for k in alone]
    groups.append(np.flatnonzero(~np.isin(table.sensor, alone)))
    # plane distances: the fastest ground speed times the plane's largest scale at the plots
    v_max = bounds.v[1] * (float(np.max(table.frame.scale(*centre.T)))
                           if table.frame is not None else 1.0)
    out = [g[unreachable_plots(table.t[g], centre[g], sigma[g], spread[g], v_max)]
           for g in groups if g.size]
    return np.sort(np.concatenate(out)) if out else np.zeros(0, dtype=int)


def refine(plots: Plots, radar: Radar, config: ReconstructionConfig,
           initial: Reconstruction | None = None, deadline: float | None = None
           ) -> Reconstruction:
    """Refine the seed's single radar at the origin of a flat plane (see :func:`refine_table`)."""
    return refine_table(PlotTable.from_plots(plots, radar), config, initial, deadline)


def refine_table(table: PlotTable, config: ReconstructionConfig,
                 initial: Reconstruction | None = None, deadline: float | None = None
                 ) -> Reconstruction:
    """Reconstruct by the full-track NLP (at least 3 plots).

    The initial guess is the means of a constant-velocity smoother on the plots' ellipses
    (``config.refine.init == "smoother"``, default; with the altitude estimated, at the constant
    height the smoother fits best) or the sliding-window result ``initial`` (``"sliding"``). The
    start as such decides the iteration count, not the answer: started at the true trajectory
    with the same level-relief weights, the refinement reached the same solutions (positions
    0.39 m RMS apart over the seven dev tracks of seed000, seeds 100 and 101; 267 against 272
    iterations). But the relief weights come from the start's lateral acceleration, and there a
    better pilot pays: relieved by the true ``u`` instead, the pooled RMS falls from 363.0 to
    351.6 m (seed000), 317.0 to 306.6 m (seed001) and 75.0 to 74.6 m (ssr). Pilots tried
    without gain on every profile: the same smoother at q 10-300 m^2/s^3, the first solve's
    ``u`` (under 0.4 % better, 50 % more polish iterations), the IMM smoother's turn rate times
    speed (its per-profile tuning; dev seeds 100 and 101: 366.9 / 320.5 / 74.7 m against 363.0 /
    317.0 / 75.0 m) and the larger of that and the start's (363.7 / 317.3 / 74.9 m).

    ``deadline`` (``time.monotonic()``): IPOPT stops at its next iteration after it and
    :class:`DeadlineExceeded` is raised; the covariance and sampling after the solves check it
    too (on 15,000 nodes they take about 1.7 s, which a deadline met by the solves was
    overshot by).
    """
    t0 = time.perf_counter()
    st: RefineSettings = config.refine
    bounds = config.bounds
    order = table.time_order()
    t_nodes, node_of_sorted = node_grid(table.t[order], st.max_node_step_s)
    n = t_nodes.size
    plot_node = np.empty(len(table), dtype=int)
    plot_node[order] = node_of_sorted
    # a position sensor's range and azimuth terms have no plot behind them (zero derivatives):
    # their priors hold them at zero, and only its time offset is reported
    bias_sensors = [k for k, s in enumerate(table.sensors) if s.estimate_bias]
    lone = bool(bias_sensors) and len(table.sensors) < 2
    if lone:  # nothing to register against: the penalties, not the plots, would set them
        bias_sensors = []
    time_gauge = time_reference(table.sensors, bias_sensors)
    variant = Variant(altitude=table.estimate_altitude(), biases=len(bias_sensors))
    fixes = table.fixes()
    data = NodeData.assemble(table, fixes, n, plot_node, variant, bias_sensors)
    impossible = unreachable_in(table, data, plot_node, bounds, bias_sensors)
    data = data.without(plot_node[impossible])  # from the start (the guess too) to the end
    bias_sigma = np.concatenate([table.sensors[k].bias_prior.sigmas  # type: ignore[union-attr]
                                 for k in bias_sensors]) if bias_sensors else np.zeros(0)
    if st.init == "sliding":
        if initial is None or not initial.segments:
            raise ValueError('refine.init == "sliding" needs the sliding-window result')
        guess = nodes_from_segments(initial, t_nodes, bounds)
        diag = initial.diagnostics
    else:
        diag = Diagnostics(criterion="R2")
        if lone:
            kind = "radar" if table.sensors[0].kind == "radar" else "position sensor"
            diag.warnings.append(f"estimate_bias: a lone {kind}'s offsets are not observable "
                                 "(nothing to register it against); not estimated")
        if variant.altitude:
            guess, h0 = altitude_guess(table, data, plot_node, t_nodes, bounds)
        else:
            guess, _ = smoother_guess(table.t, data.centre[plot_node],
                                      data.weighed_info()[plot_node], t_nodes, bounds)
    if variant.altitude:
        if st.init == "sliding":
            _, h0 = altitude_guess(table, data, plot_node, t_nodes, bounds)
        guess = with_altitude(guess, h0, t_nodes)
    # the level penalty relieved where the start turns (RefineSettings.level_relief_u)
    data = data.relieved(guess[:, solution_columns(variant).index("u")], st.level_relief_u)
    data = data.scaled(table.frame, guess[:, 0], guess[:, 1])
    delta = st.huber_delta if st.huber_delta is not None else 1e6
    diag.method = "refined"
    pb = Problem(t_nodes, hd_information(t_nodes), variant, bounds, st, delta,
                 1.0 / bias_sigma**2 if bias_sigma.size else bias_sigma, time_gauge)
    blocks = cut(n, st.block_nodes, st.overlap_nodes)
    duals: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(blocks)
    clock = {"ipopt": 0.0, "model": 0.0}  # s inside IPOPT calls / in its model evaluations
    nlp.set_deadline(deadline)

    # the polish solve holds the switches the first one did not select; when it follows, the
    # cold first solve only chooses what it holds and weighs, to a looser tolerance
    polish = st.switch_threshold > 0 and n > 1
    first_tol = max(st.first_solve_tol, st.ipopt_tol) if polish else st.ipopt_tol

    def solve_all(start_guess: np.ndarray, data: NodeData, biases: np.ndarray,
                  fixed: np.ndarray | None, tol: float = st.ipopt_tol
                  ) -> tuple[np.ndarray, np.ndarray, int, int]:
        out = np.empty((n, len(solution_columns(variant))))
        prev: np.ndarray | None = None
        fails = its = 0
        for j, (start, stop, keep) in enumerate(blocks):
            check_deadline(deadline)
            t_call = time.perf_counter()
            blk = solve_block(pb, start, stop, data, start_guess, biases, prev,
                              None if fixed is None else fixed[:, start:stop], duals[j],
                              hold_biases=j > 0, tol=tol)
            clock["ipopt"] += time.perf_counter() - t_call
            clock["model"] += blk.model_s
            duals[j] = blk.duals
            fails += not blk.ok
            its += blk.iterations
            if j == 0:
                biases = blk.biases
            out[start: keep + 1] = blk.x[: keep + 1 - start]
            prev = blk.x[keep - start]
        return out, biases, fails, its

    kept = np.array([], dtype=int)  # far plots kept as a turn harder than the bounds
    try:
        biases0 = offset_guess(data, guess, variant.altitude, pb.bias_info, time_gauge)
        sol, biases, failures, iters = solve_all(guess, data, biases0, None, first_tol)
        solves = len(blocks)
        # Sensors whose plots lie far closer to the track than their declared sigmas: weight
        # them by the scatter they show (re-solved from the solution, at most a few rounds).
        weight_scale = np.ones(len(table.sensors))
        for _ in range(RESCALE_ROUNDS):
            quad = data.quad(sol, biases, variant.altitude)
            factor = overstated_sigmas(quad[plot_node], table.sensor, len(table.sensors),
                                       weight_scale)
            if np.all(factor == 1.0):
                break
            weight_scale *= factor
            data = data.reweighted(plot_node, factor[table.sensor])
            sol, biases, f1, it1 = solve_all(sol, data, biases, None)
            failures, iters, solves = failures + f1, iters + it1, solves + len(blocks)
        report_scales(weight_scale, table, diag)
        # Second solve, decided on the stitched solution so blocks and one block decide alike.
        overhead = np.array([], dtype=int)
        if variant.altitude:
            # plots beyond their reach at the track's height (above 74 deg without altitude):
            # left out and solved again, before they are taken for a turn or wild plots
            h = sol[:, solution_columns(variant).index("h")]
            overhead = np.flatnonzero(data.beyond_reach(h)[plot_node]
                                      & (data.weight[plot_node] > 0))
            if overhead.size:
                data = data.without(plot_node[overhead])
                sol, biases, f1, it1 = solve_all(sol, data, biases, None)
                failures, iters, solves = failures + f1, iters + it1, solves + len(blocks)
        quad = data.quad(sol, biases, variant.altitude)
        rejected, kept = wild_plots(quad[plot_node], t_nodes, data.on_ground(sol), bounds,
                                    st, diag, plot_node)
        fixed = None
        if polish:
            fixed = np.zeros((2, n), dtype=bool)
            fixed[:, 1:] = np.abs(np.diff(sol[:, 4:6], axis=0)).T <= st.switch_threshold
        if variant.biases:  # the radar model linearised at the offsets found, not at zero
            data = data.relinearised(table, plot_node, variant, bias_sensors, biases,
                                     weight_scale)
        if fixed is not None or rejected.size or variant.biases:
            data = data.without(plot_node[rejected])
            sol, biases, f2, it2 = solve_all(sol, data, biases, fixed)
            failures, iters, solves = failures + f2, iters + it2, solves + len(blocks)
    finally:
        nlp.set_deadline(None)
    if impossible.size:
        diag.warnings.append(
            f"{impossible.size} plot(s) out of reach at bounds.v of the track's other plots "
            f"(off their longest chain in time, each in reach of the one before: a wild range "
            f"or azimuth, or another aircraft's plots under the same key, e.g. a radar track "
            f"number or Mode 3/A code used again) were given no weight and are left out of the "
            f"sensors' statistics: plots {listed(impossible)}")
    if overhead.size:
        diag.warnings.append(
            f"{overhead.size} plot(s) without altitude whose slant range cannot place them at "
            f"the track's height (above {MAX_ELEVATION_DEG:.0f} deg elevation there, or a range "
            f"shorter than the height: solver.sensors.MAX_ELEVATION_FRACTION) were given no "
            f"weight: plots {listed(overhead)}")
    rejected = np.setdiff1d(rejected, np.union1d(impossible, overhead))
    if rejected.size:
        diag.warnings.append(
            f"{rejected.size} plot(s) more than {st.outlier_gate:g} sigma from the track were "
            f"given no weight{_by_sensor(table, rejected)}: plots {listed(rejected)}")
    rejected = np.union1d(np.union1d(rejected, impossible), overhead).astype(int)
    diag.extra["rejected_plots"] = int(rejected.size)
    diag.solver_failures += failures
    diag.extra.update(refine_blocks=len(blocks), refine_nodes=n, refine_iterations=iters)
    if failures:
        diag.warnings.append(f"refinement: IPOPT did not converge in {failures} of {solves} "
                             f"block solve(s) over {len(blocks)} block(s); the last iterate "
                             "was kept")
    report_bounds(t_nodes, data.on_ground(sol), bounds, diag)
    segs = segments(t_nodes, sol, bounds)
    # offsets estimated in the first block only are consider states after it
    consider = blocks[0][2] + 1 if variant.biases and len(blocks) > 1 else None
    check_deadline(deadline)  # the stages below have no solver to stop: checked between them
    cov_nodes = node_covariance(t_nodes, sol, biases, data, variant, st, delta, bounds,
                                pb.hd_info, bias_sigma, consider, time_gauge,
                                check=lambda: check_deadline(deadline))
    check_deadline(deadline)
    # each plot's own node (plots of several sensors may share an instant)
    at_plots_own = series(t_nodes, sol, cov_nodes, table.t, variant, nodes=plot_node)
    samples = series(t_nodes, sol, cov_nodes,
                     sample_times(float(table.t.min()), float(table.t.max()),
                                  config.sample_step_s), variant)
    check_deadline(deadline)
    # a plot given no weight adds nothing, also where its residual is infinite (0 * inf)
    quad_end = data.quad(sol, biases, variant.altitude)
    turned = turn_warning(kept, quad_end[plot_node], table.t, st.outlier_gate)
    if turned is not None:
        diag.warnings.append(turned)
    crit = np.where(data.weight > 0, data.weight * quad_end, 0.0)
    diag.criterion_values = [float(crit.sum())]
    nb = state_size(variant) - BIAS_TERMS * variant.biases
    bias_cov = cov_nodes[-1][nb:, nb:]
    rec = Reconstruction(segs, at_plots_own, samples, diag, no_weight=rejected)
    if table.frame is not None or len(table.sensors) > 1:
        # no reference for the sensors: plots out of reach, stretches the bounds bend off
        misfit = misfit_stretches(np.where(data.weight > 0, quad_end, 0.0)[plot_node],
                                  table.t, sol, bounds, st.outlier_gate, plot_node)
        lever = None if at_plots_own.cov is None else leverages(
            data.weighed_info()[plot_node], data.d_range[plot_node],
            plot_covariances(cov_nodes, sol, biases, data, variant, delta, plot_node))
        rec.residuals = plot_residuals(table, at_plots_own, rejected, biases, bias_sensors,
                                       misfit, lever, unreachable=impossible)
        rec.sensors = sensor_reports(table, rec.residuals, biases, bias_cov, bias_sensors)
    if variant.altitude:
        w = np.gradient(t_nodes) if n > 1 else np.ones(1)
        w = w / w.sum() if w.sum() > 0 else np.full(n, 1.0 / n)
        rec.altitude_m = float(w @ sol[:, 6])
        rec.altitude_sigma_m = float(np.sqrt(w @ cov_nodes[:, 6, 6]))
        diag.extra["altitude_estimated"] = 1
    diag.extra["refine_ms"] = (time.perf_counter() - t0) * 1e3
    diag.extra["refine_ipopt_ms"] = clock["ipopt"] * 1e3
    diag.extra["refine_model_ms"] = clock["model"] * 1e3
    diag.extra["switches"] = len(segs) - 1
    return rec
