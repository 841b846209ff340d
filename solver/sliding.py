"""Sliding extended windows (spec/reconstruction.md section 6): the seed's reconstruction.

An extended window is a start (time + state ``(x, z, phi, v)``) plus the ``m`` plots strictly
after it. The current window is fitted by constant controls (:mod:`solver.window`); candidate
starts are taken on its trajectory at its plot times and every ``trial_step_s`` from its first
plot; each candidate's trial window (the ``m`` plots strictly after it) is fitted, and the lowest
criterion wins. The current trajectory up to the winning candidate becomes a final segment (the
controls switch there) and the winner becomes the current window. When the current window holds
the last plot it is accepted whole.

Two refinements of the seed's rule, measured in benchmarks/seed_track.py (``seed_rule`` turns
both off):

- the best grid candidate of every trial plot set is refined by an NLP that frees its start
  time together with its controls (:func:`solver.window.solve_switches`), anywhere between the
  plot before that set and its first plot (for the set after the window's last plot this reaches
  past that plot: the current controls carried on into the gap). This places control switches
  exactly: noise-free seed-like track, m = 3, worst error 561 m -> 0.2 m. The price of the
  wider choice under noise is small: RMS 665 -> 678 m (10 noise seeds; raw plots 948 m);
- the first window frees its start state too (:func:`solver.window.solve_free_start`), fitted to
  the first ``max(m + 1, 6)`` plots, start plot included, and kept when it lowers the criterion
  there: the seed's start (first plot, chord velocity) plants the first plot's noise, and its
  chord heading is wrong when the track starts in a turn (578 m -> 0 noise-free on such a
  track); noisy RMS 678 -> 671 m.

Defined behaviours:

- Trial windows need ``m`` plots: a candidate with fewer than ``m`` plots after it is not tried
  (a 1-plot window is fitted exactly by the two controls, so any per-plot comparison would always
  pick it). While the current window does not hold the last plot, its first-plot candidate has
  ``m`` plots after it, so the slide always advances by at least one plot.
- Missed plots: a window simply takes the next ``m`` plots; candidates every ``trial_step_s``
  let the controls switch inside the gap.
- Near-duplicate times (strictly increasing but close): fitted like any others; the initial
  velocity uses the first plot at least ``max(1 s, median spacing / 2)`` after the first plot
  (:func:`initial_state`), so two nearly simultaneous plots never set it.
- Wild plots: the seed's windows have no defence, and one false plot spoils its windows'
  fits (1 % false plots within +-20 km and +-5 deg: 552 -> 1,034 m and 628 -> 1,687 m RMS on
  two seed001 dev tracks). The plots a gated constant-velocity Kalman filter and smoother leaves
  out (:mod:`solver.estimation.gating`) get no weight (warned; flagged in the residuals of
  a plot table's reconstruction);
  the states at them come from the track. ``refine.outlier_gate = None`` turns this off with
  the refinement's gate.
- Fewer than ``m + 1`` plots: one window with all plots after the first (warning).
  2 plots: one straight constant-speed segment between the two ellipse centres (speed clipped
  to the bounds, warning if clipped). 1 plot: no segments; the state at the plot is its ellipse
  centre with zero velocity (warning).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from .config import ReconstructionConfig
from .geometry import uncertainty_ellipses
from .guess import initial_guess
from .inputs import FloatArray, InputError, Plots, Radar
from .motion import propagate
from .plots import PlotTable
from .refine import DeadlineExceeded
from .results import Diagnostics, FilterEstimate, Reconstruction, Segment, StateSeries, listed
from .trajectory import evaluate, sample_times
from .window import SwitchFits, criterion, solve_free_start, solve_switches, solve_windows, w_box

MIN_BASELINE_S = 1.0  # shortest time between the two plots that set the initial velocity
FREE_START_PLOTS = 6  # fewest plots (start plot included) the free-start first window fits
SWITCH_GAP_S = 1e-3  # a refined switch stays this far before the trial window's first plot
# most candidate starts in one window: each is a window NLP (tens of microseconds in a mapped
# call) and a few arrays of its own, so 20000 cost about a second per step; a 1e-9-s trial step
# over a 19-s window would ask for 2e10 (memory exhaustion before the first solve)
MAX_CANDIDATES = 20_000


def criterion_data(plots: Plots, radar: Radar, criterion: str
                   ) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Ellipse centres ``cx, cz (n,)``, weight entries ``(n, 3)`` scaled for the solver, and the
    factor that turns a scaled criterion value back into the criterion's units.

    R2 weights are used as they are (values near the number of plots for a good fit); R1 is
    ``|d|^2`` in m^2, solved as ``|d|^2 / eps_r^2`` so that the solver's tolerances mean the same
    thing for both criteria.
    """
    ell = uncertainty_ellipses(plots, radar)
    if criterion == "R2":
        return ell.cx, ell.cz, ell.weights(), 1.0
    scale = float(radar.range_error_m) ** 2
    abc = np.tile([1.0 / scale, 0.0, 1.0 / scale], (len(plots), 1))
    return ell.cx, ell.cz, abc, scale


def initial_state(t: FloatArray, cx: FloatArray, cz: FloatArray, v_box: tuple[float, float]
                  ) -> tuple[FloatArray, bool]:
    """Start ``(x0, z0, phi0, v0)`` at the first ellipse centre, heading and speed towards the
    first plot at least ``max(MIN_BASELINE_S, median spacing / 2)`` later (else the last plot);
    the speed is clipped to ``v_box``. Returns the state and whether the speed was clipped."""
    baseline = max(MIN_BASELINE_S, 0.5 * float(np.median(np.diff(t))))
    j = int(np.searchsorted(t, t[0] + baseline, side="left"))
    j = min(max(j, 1), len(t) - 1)
    dx, dz = cx[j] - cx[0], cz[j] - cz[0]
    speed = np.hypot(dx, dz) / (t[j] - t[0])
    heading = float(np.mod(np.arctan2(dz, dx), 2 * np.pi))
    v0 = float(np.clip(speed, *v_box))
    return np.array([cx[0], cz[0], heading, v0]), bool(v0 != speed)


class _Fitter:
    """Fits batches of extended windows over one track's data and keeps the diagnostics."""

    def __init__(self, t: FloatArray, cx: FloatArray, cz: FloatArray, abc: FloatArray,
                 config: ReconstructionConfig, diag: Diagnostics):
        self.t, self.cx, self.cz, self.abc = t, cx, cz, abc
        self.config, self.diag = config, diag
        self.flagged = 0

    def fit(self, start: FloatArray, t_start: FloatArray, first: np.ndarray, m: int,
            extra: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
        """Fit ``n`` windows: starts ``(n, 4)`` at times ``t_start (n,)``, plots
        ``first[k] .. first[k] + m - 1``. Returns ``(u, w)`` as ``(n, 2)`` and the values."""
        idx = first[:, None] + np.arange(m)
        t_rel = self.t[idx] - t_start[:, None]
        cx, cz, abc = self.cx[idx], self.cz[idx], self.abc[idx]
        bounds = self.config.bounds
        lbw, ubw, flagged = w_box(start[:, 3], t_rel[:, -1], bounds)
        self.flagged += int(flagged.sum())
        guess, _ = initial_guess(start, t_rel, cx, cz, abc, bounds.u, lbw, ubw, extra)
        fits = solve_windows(start, t_rel, cx, cz, abc, guess, lbw, ubw, bounds,
                             self.config.nlp_solver)
        d = self.diag
        d.windows_solved += len(first)
        d.solver_failures += int(fits.failed.sum())
        d.fallbacks += int(fits.fallback.sum())
        d.nlp_solve_ms.extend(fits.solve_ms.tolist())
        return np.column_stack([fits.u, fits.w]), fits.value

    def fit_switches(self, cur_t: float, cur_s: FloatArray, cur_uw: FloatArray,
                     cand: FloatArray, first: np.ndarray, uw: FloatArray, val: FloatArray,
                     m: int) -> tuple[SwitchFits, np.ndarray] | None:
        """Free the start time of the best grid candidate of every trial plot set: within the
        plot before the set and (just before) its first plot, where the current trajectory's
        speed is in bounds. Returns the fits and the first plot of each one's set, or ``None``
        when no interval is long enough to matter."""
        v_lo, v_hi = self.config.bounds.v
        v0, w0 = cur_s[3], cur_uw[1]
        v_limit = np.inf if w0 == 0 else ((v_hi if w0 > 0 else v_lo) - v0) / w0
        sets = np.unique(first)
        best = np.array([g[np.argmin(val[g])] for g in (np.flatnonzero(first == f)
                                                        for f in sets)])
        lo = self.t[sets - 1] - cur_t
        hi = np.minimum(self.t[sets] - cur_t - SWITCH_GAP_S, v_limit)
        tau = cand[best] - cur_t
        ok = (hi - lo >= SWITCH_GAP_S) & (lo <= tau) & (tau <= hi)
        if not ok.any():
            return None
        sets, best, lo, hi, tau = sets[ok], best[ok], lo[ok], hi[ok], tau[ok]
        idx = sets[:, None] + np.arange(m)
        fits = solve_switches(cur_s, cur_uw, self.t[idx] - cur_t, self.cx[idx], self.cz[idx],
                              self.abc[idx], np.column_stack([uw[best], tau]),
                              np.column_stack([lo, hi]), self.config.bounds,
                              self.config.nlp_solver)
        d = self.diag
        d.windows_solved += len(sets)
        d.solver_failures += int(fits.failed.sum())
        d.nlp_solve_ms.extend(fits.solve_ms.tolist())
        return fits, sets

    def fit_free_start(self, start: FloatArray, uw: FloatArray, value: float, m: int
                       ) -> tuple[FloatArray, FloatArray, float]:
        """Free the first window's start state: fit ``(x0, z0, phi0, v0, u, w)`` to the first
        ``max(m + 1, FREE_START_PLOTS)`` plots (the start plot included; at least 4 plots must
        be available so the fit is overdetermined). Kept only when it lowers the criterion over
        those plots against the seed's start with its fitted controls; returns the (possibly
        unchanged) start, controls and window value (then over those plots)."""
        k = min(len(self.t), max(m + 1, FREE_START_PLOTS))
        if k < 4:  # 2 k residuals must outnumber the 6 unknowns
            return start, uw, value
        t, cx, cz, abc = self.t[:k] - self.t[0], self.cx[:k], self.cz[:k], self.abc[:k]
        fit = solve_free_start(start, uw, t, cx, cz, abc, self.config.bounds,
                               self.config.nlp_solver)
        d = self.diag
        d.windows_solved += 1
        d.solver_failures += int(fit.failed)
        d.nlp_solve_ms.append(fit.solve_ms)
        ref = float(criterion(start, np.asarray(uw[0]), np.asarray(uw[1]), t, cx, cz, abc))
        if not fit.value < ref:
            d.fallbacks += int(fit.failed)
            return start, uw, value
        d.extra["free_start_shift_m"] = float(np.hypot(*(fit.start[:2] - start[:2])))
        return fit.start, np.array([fit.u, fit.w]), fit.value


def _segment(t0: float, t1: float, state: FloatArray, uw: FloatArray) -> Segment:
    return Segment(float(t0), float(t1), float(state[0]), float(state[1]),
                   float(np.mod(state[2], 2 * np.pi)), float(state[3]), float(uw[0]),
                   float(uw[1]))


def candidate_times(t: FloatArray, k: int, m: int, step: float) -> FloatArray:
    """Candidate starts of the window of plots ``k .. k + m - 1``: its plot times and every
    ``step`` from its first plot up to its last plot."""
    last = k + m - 1
    count = (t[last] - t[k]) / step
    if not count <= MAX_CANDIDATES:
        raise InputError(("window", "trial_step_s"), (
            f"({step:g} s) gives {count:.3g} trial starts in the window of plots {k}-{last} "
            f"({t[last] - t[k]:g} s); at most {MAX_CANDIDATES} are allowed: raise it"))
    extra = t[k] + step * np.arange(1, int(np.ceil(count)))
    return np.union1d(t[k:last + 1], extra[extra < t[last]])


def slide(t: FloatArray, cx: FloatArray, cz: FloatArray, abc: FloatArray, start: FloatArray,
          m: int, config: ReconstructionConfig, diag: Diagnostics, value_scale: float = 1.0,
          seed_rule: bool = False, deadline: float | None = None) -> list[Segment]:
    """Segments of the sliding extended windows from ``start`` at ``t[0]`` (needs
    ``len(t) >= m + 1``). Appends each accepted window's criterion value to ``diag``.
    ``seed_rule`` follows the seed literally (see the module docstring for what it turns off).
    ``deadline`` (a :func:`time.monotonic` value): checked before every step, raises
    :class:`DeadlineExceeded` once passed (one step is one batch of window NLPs, milliseconds).
    """
    n = len(t)
    bounds = config.bounds
    fitter = _Fitter(t, cx, cz, abc, config, diag)
    cur_t, cur_s, cur_k = float(t[0]), start, 1
    uw, val = fitter.fit(cur_s[None, :], np.array([cur_t]), np.array([cur_k]), m)
    cur_uw, cur_val = uw[0], float(val[0])
    if not seed_rule:
        cur_s, cur_uw, cur_val = fitter.fit_free_start(cur_s, cur_uw, cur_val, m)
    segments: list[Segment] = []
    while cur_k + m - 1 < n - 1:
        if deadline is not None and time.monotonic() > deadline:
            raise DeadlineExceeded(f"deadline passed at plot {cur_k} of {n}")
        cand = candidate_times(t, cur_k, m, config.trial_step_s)
        first = np.searchsorted(t, cand, side="right")
        x, z, phi, v = propagate(cur_s[0], cur_s[1], cur_s[2], cur_s[3], cur_uw[0], cur_uw[1],
                                 cand - cur_t)
        slack = 1e-9 * bounds.v[1]  # rounding of v0 + w t at a bound
        keep = (first + m - 1 <= n - 1) & (v >= bounds.v[0] - slack) & (v <= bounds.v[1] + slack)
        keep[0] = True  # the window's first plot: m plots follow, speed between v0 and v(t_m)
        cand, first = cand[keep], first[keep]
        states = np.column_stack([x, z, phi, v])[keep]
        extra = np.broadcast_to(cur_uw, (len(cand), 1, 2))
        uw, val = fitter.fit(states, cand, first, m, extra)
        diag.trial_windows += len(cand)
        b = int(np.argmin(val))
        nxt_t, nxt_s, nxt_uw, nxt_val = float(cand[b]), states[b], uw[b], float(val[b])
        nxt_k = int(first[b])
        if not seed_rule:
            refined = fitter.fit_switches(cur_t, cur_s, cur_uw, cand, first, uw, val, m)
            if refined is not None and refined[0].value.min() < nxt_val:
                fits, sets = refined
                j = int(np.argmin(fits.value))
                nxt_t = cur_t + fits.tau[j]
                nxt_s = np.array(propagate(*cur_s, *cur_uw, fits.tau[j]))
                nxt_uw, nxt_val = np.array([fits.u[j], fits.w[j]]), float(fits.value[j])
                nxt_k = int(sets[j])
        segments.append(_segment(cur_t, nxt_t, cur_s, cur_uw))
        diag.criterion_values.append(cur_val * value_scale)
        cur_t, cur_s, cur_k, cur_uw, cur_val = nxt_t, nxt_s, nxt_k, nxt_uw, nxt_val
    segments.append(_segment(cur_t, t[n - 1], cur_s, cur_uw))
    diag.criterion_values.append(cur_val * value_scale)
    if fitter.flagged:
        diag.warnings.append(f"{fitter.flagged} window start(s) had a speed outside the bounds; "
                             "their fits bring it back by the window's last plot")
    return segments


def reconstruct_sliding(plots: Plots, radar: Radar, config: ReconstructionConfig,
                        deadline: float | None = None) -> Reconstruction:
    """Reconstruct by sliding extended windows (the seed's method; see the module docstring).
    ``deadline``: see :func:`slide`."""
    from .estimation import run_filter

    clock = time.perf_counter()
    diag = Diagnostics(method="sliding", criterion=config.criterion)
    cx, cz, abc, scale = criterion_data(plots, radar, config.criterion)
    keep = _not_wild(lambda: run_filter("cv_rts", plots, radar), len(plots.t), config, diag)
    rec = _slide_track(plots.t[keep], cx[keep], cz[keep], abc[keep], scale, config, diag,
                       deadline, at=plots.t)
    rec.no_weight = np.flatnonzero(~keep)
    diag.elapsed_ms = (time.perf_counter() - clock) * 1e3
    return rec


def _not_wild(smoother: Callable[[], FilterEstimate], n: int, config: ReconstructionConfig,
              diag: Diagnostics) -> np.ndarray:
    """``(n,)`` True for the plots the windows use: all but those the gated constant-velocity
    smoother ``smoother()`` (run only when needed) leaves out (module docstring), named in a
    warning; all when the refinement's gate is off, or when fewer than 3 plots would be left."""
    keep = np.ones(n, dtype=bool)
    if config.refine.outlier_gate is None or n < 4:
        return keep
    wild = np.flatnonzero(smoother().info.get("gated", ()))  # none from a numerical fallback
    if wild.size and n - wild.size >= 3:
        keep[wild] = False
        diag.warnings.append(
            f"{wild.size} plot(s) far from a gated constant-velocity smoother were given no "
            f"weight (wild plots): plots {listed(wild, 20)}")
    return keep


def reconstruct_sliding_table(table: PlotTable, config: ReconstructionConfig,
                              deadline: float | None = None) -> Reconstruction:
    """The sliding windows over any plot table: several sensors at their sites on the earth,
    position sensors (ADS-B) among them. Each plot is its fix in the table's plane
    (:meth:`solver.plots.PlotTable.fixes`: its position and one-sigma ellipse from its sensor),
    and the windows slide over the fixes of all sensors in time order, as over one radar's;
    plots of several sensors at one instant are one fix (information-weighted,
    :func:`solver.refine.nodes.fused_points`), so a window's plots are distinct instants.

    What the sliding windows do not estimate, the table's plots fix beforehand: radar plots
    without an altitude, where another sensor sees the aircraft, are placed at the refinement's
    starting height (:func:`solver.refine.nodes.altitude_guess`: the plots' altitudes
    interpolated, else the constant height whose fixes a constant-velocity smoother fits
    best), else at the radar's height (the seed's convention). Sensor offsets are not
    estimated (a warning names the sensors that ask for it). R1 weighs every plot alike in
    units of the median along-ray sigma. States at the plots come in table order, each plot
    against the track (:func:`solver.refine.output.plot_residuals`) with its sensor's
    statistics; no covariance (as the seed's method)."""
    from .refine import unreachable_in
    from .refine.layout import BIAS_TERMS, Variant
    from .refine.nodes import NodeData, altitude_guess, fused_points, info_matrices, node_grid
    from .refine.output import plot_residuals, sensor_reports

    clock = time.perf_counter()
    diag = Diagnostics(method="sliding", criterion=config.criterion)
    order = table.time_order()
    fixes = table.fixes()
    heights = None
    free = fixes.altitude_free  # radar plots without altitude whose height is estimated
    if free.any():
        t_nodes, node_of_sorted = node_grid(table.t[order], config.refine.max_node_step_s)
        plot_node = np.empty(len(table), dtype=int)
        plot_node[order] = node_of_sorted
        data = NodeData.assemble(table, fixes, t_nodes.size, plot_node,
                                 Variant(altitude=True), [])
        # the height guessed without the plots out of reach of the others (one 3-km range
        # put every plot at 0 m instead of 10 km: 643 m off in the median)
        data = data.without(plot_node[unreachable_in(table, data, plot_node, config.bounds)])
        _, h_nodes = altitude_guess(table, data, plot_node, t_nodes, config.bounds)
        heights = h_nodes[plot_node]
        centres = fixes.centre_at(heights)
        diag.warnings.append(
            f"{int(free.sum())} radar plot(s) without an altitude placed at "
            f"{float(np.median(heights[free])):.0f} m (median), the height the plots fit best; "
            "the sliding windows do not estimate it (the refined method does)")
    else:
        centres = np.column_stack([fixes.ellipses.cx, fixes.ellipses.cz])
    asked = [s.id for s in table.sensors if s.estimate_bias]
    if asked:
        diag.warnings.append(f"estimate_bias: the sliding windows do not estimate sensor "
                             f"offsets ({', '.join(asked)}); the refined method does")
    ell = fixes.ellipses
    if config.criterion == "R2":
        abc, scale = ell.weights(), 1.0
    else:
        scale = float(np.median(ell.B)) ** 2
        abc = np.tile([1.0 / scale, 0.0, 1.0 / scale], (len(table), 1))
    from .estimation import run_filter
    from .estimation.measurements import at_estimated_heights

    keep = _not_wild(lambda: run_filter("cv_rts", at_estimated_heights(table, heights)),
                     len(table), config, diag)
    # the criterion's sum of simultaneous plots' quadratic forms is the fused fix's + a constant
    times, fused, info = fused_points(table.t[keep], centres[keep], info_matrices(abc[keep]),
                                      min_gap_s=np.finfo(float).tiny)
    if times.size < keep.sum():
        diag.extra["fused_plots"] = int(keep.sum()) - times.size
    fused_abc = np.column_stack([info[:, 0, 0], info[:, 0, 1], info[:, 1, 1]])
    rec = _slide_track(times, fused[:, 0], fused[:, 1], fused_abc, scale, config, diag,
                       deadline, at=table.t)
    if heights is not None:
        rec.at_plots.h = heights
    none = np.zeros((0, BIAS_TERMS))  # no offsets estimated
    rec.no_weight = np.flatnonzero(~keep)
    rec.residuals = plot_residuals(table, rec.at_plots, rec.no_weight, none, [])
    rec.sensors = sensor_reports(table, rec.residuals, none, np.zeros((0, 0)), [])
    diag.elapsed_ms = (time.perf_counter() - clock) * 1e3
    return rec


def _straight_beyond(segments: list[Segment], t_lo: float, t_hi: float) -> list[Segment]:
    """``segments`` with a straight constant-speed segment (``u = w = 0``) before the first
    and after the last where the times asked for reach beyond them: a first or last plot left
    out as wild. The last segment's controls carried on past its end broke the bounds (a
    decelerating track's speed went below ``bounds.v``, found by the property test)."""
    first, last = segments[0], segments[-1]
    before, after = [], []
    if t_lo < first.t_start:
        x, z, phi, v = propagate(first.x, first.z, first.heading, first.speed, 0.0, 0.0,
                                 t_lo - first.t_start)
        before = [Segment(t_lo, first.t_start, float(x), float(z), float(phi), float(v),
                          0.0, 0.0)]
    if t_hi > last.t_end:
        x, z, phi, v = propagate(last.x, last.z, last.heading, last.speed, last.u, last.w,
                                 last.t_end - last.t_start)
        after = [Segment(last.t_end, t_hi, float(x), float(z), float(phi), float(v), 0.0, 0.0)]
    return [*before, *segments, *after]


def _slide_track(t: FloatArray, cx: FloatArray, cz: FloatArray, abc: FloatArray, scale: float,
                 config: ReconstructionConfig, diag: Diagnostics, deadline: float | None,
                 at: FloatArray | None = None) -> Reconstruction:
    """The sliding windows over time-ordered fixes (centres, R2 weight entries, the factor of
    the criterion's units); states at the times ``at`` (default ``t``)."""
    at = t if at is None else at
    n = len(t)
    if n == 1:
        diag.warnings.append("only one plot: no trajectory; the state at the plot is its "
                             "position with zero velocity")
        k = len(at)  # several sensors' plots of that one instant
        state = StateSeries(at.copy(), np.full(k, cx[0]), np.full(k, cz[0]), np.zeros(k),
                            np.zeros(k))
        samples = StateSeries(t.copy(), cx.copy(), cz.copy(), np.zeros(1), np.zeros(1))
        return Reconstruction([], state, samples, diag)
    start, clipped = initial_state(t, cx, cz, config.bounds.v)
    if n == 2:
        diag.warnings.append("only two plots: one straight constant-speed segment")
        if clipped:
            diag.warnings.append("the speed between the two plots is outside the speed bounds "
                                 "and was clipped")
        segments = [Segment(float(t[0]), float(t[1]), *map(float, start), 0.0, 0.0)]
    else:
        m = config.window_plots
        if n - 1 < m:
            diag.warnings.append(f"window of {m} plots is longer than the track; one window "
                                 f"with all {n - 1} plots after the first is used")
            m = n - 1
        if clipped:
            diag.warnings.append("initial speed from the first plots was outside the speed "
                                 "bounds and was clipped")
        segments = slide(t, cx, cz, abc, start, m, config, diag, scale, deadline=deadline)
    segments = _straight_beyond(segments, float(np.min(at)), float(np.max(at)))
    at_plots = evaluate(segments, at)
    samples = evaluate(segments, sample_times(segments[0].t_start, segments[-1].t_end,
                                              config.sample_step_s))
    diag.extra["accepted_windows"] = len(diag.criterion_values)
    return Reconstruction(segments, at_plots, samples, diag)
