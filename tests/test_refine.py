"""Full-track refinement (solver.refine): noise-free recovery, switch count, block seams,
robustness to a wild plot, and calibration of the returned covariance."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from tracks import SEED_RADAR, make_track, truth

from solver.config import (
    MAX_BLOCK_NODES,
    MIN_BLOCK_NODES,
    ReconstructionConfig,
    RefineSettings,
)
from solver.inputs import InputError, Plots, Radar
from solver.reconstruct import reconstruct
from solver.refine import LADDER, node_grid, refine

# Switches on the 10-s scan grid, so the node grid can represent the truth exactly: straight
# legs, a deceleration, a right turn of about 210 deg, an acceleration, a left turn of about
# 185 deg. 8 switches.
SCAN = 10.0
LEGS = [
    (300.0, 0.0, 0.0),
    (40.0, 0.0, -1.5),   # 190 -> 130 m/s
    (200.0, 0.0, 0.0),
    (80.0, 6.0, 0.0),    # ~211 deg right at 130 m/s
    (200.0, 0.0, 0.0),
    (40.0, 0.0, 1.0),    # 130 -> 170 m/s
    (200.0, 0.0, 0.0),
    (110.0, -5.0, 0.0),  # ~185 deg left at 170 m/s
    (300.0, 0.0, 0.0),
]
START = (40_000.0, -60_000.0, np.deg2rad(30.0), 190.0)
TRUE_SWITCHES = len(LEGS) - 1


def _plots(t, radar_sigma_r=0.0, radar_sigma_psi=0.0, seed=0, altitude=None):
    x, z, phi, v = truth(LEGS, START, t)
    rng = np.random.default_rng(seed)
    h = 0.0 if altitude is None else altitude
    r = np.sqrt(x * x + z * z + h * h) + radar_sigma_r * rng.standard_normal(t.size)
    psi = np.arctan2(z, x) + radar_sigma_psi * rng.standard_normal(t.size)
    alt = None if altitude is None else np.full(t.size, altitude)
    return Plots.from_arrays(t, r, psi, alt), (x, z, phi, v)


def _scan_times(drop_in_turns: bool = True) -> np.ndarray:
    total = sum(d for d, _, _ in LEGS)
    t = np.arange(0.0, total + 1e-9, SCAN)
    if drop_in_turns:  # every second plot missing in the turns
        edges = np.cumsum([0.0] + [d for d, _, _ in LEGS])
        k = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(LEGS) - 1)
        turning = np.array([LEGS[i][1] != 0 for i in k])
        t = t[~(turning & (np.cumsum(turning) % 2 == 0))]
    return t


@pytest.mark.parametrize("wild", [3, 0, 7])
def test_a_plot_out_of_reach_at_the_speed_bound_is_left_out_from_the_start(wild):
    """Eight exact plots of a straight flight, 10 s apart, one with a range of 1 m (inside,
    first or last): the start's smoother and the first solve were pulled 50 km towards it and
    IPOPT ended 1e16 m away (600 iterations, answered 200). It is out of reach of its
    neighbours at bounds.v (330 m/s): no weight, said, and the rest of the track exact."""
    x = -50_000.0 + 2_000.0 * np.arange(8)
    z = np.full(8, 30_000.0)
    r = np.hypot(x, z)
    r[wild] = 1.0
    plots = Plots.from_arrays(10.0 * np.arange(8), r, np.arctan2(z, x))
    rec = refine(plots, Radar(500.0, np.deg2rad(1.5)), ReconstructionConfig())
    keep = np.arange(8) != wild
    err = np.hypot(rec.at_plots.x - x, rec.at_plots.z - z)[keep]
    assert err.max() < 1.0, err
    assert any(f"plots [{wild}]" in w and "out of reach at bounds.v" in w
               for w in rec.diagnostics.warnings), rec.diagnostics.warnings
    assert rec.diagnostics.solver_failures == 0


def test_unreachable_plots_against_brute_force():
    """On random tracks with wild plots put in (30-90 km off, never two in a row), exactly
    those are found, the kept plots are within reach of each other in turn, and a direct
    check of each removed one finds it out of reach of the kept plots before and after it;
    a clean line keeps every plot."""
    from solver.refine.gate import UNREACHABLE_SLACK_M, unreachable_plots

    rng = np.random.default_rng(5)
    v = 300.0
    for _ in range(40):
        n = int(rng.integers(5, 40))
        t = np.cumsum(rng.uniform(1.0, 12.0, n))
        c = np.column_stack([250.0 * t, 20.0 * t]) + rng.normal(0, 50.0, (n, 2))
        sigma, spread = np.full(n, 60.0), np.zeros(n)
        # wild plots never next to each other (two near each other would look like a track)
        wild = rng.choice(np.arange(0, n, 2), size=int(rng.integers(0, n // 5 + 1)),
                          replace=False)
        c[wild] += rng.uniform(3e4, 9e4, (wild.size, 2)) * rng.choice([-1, 1], (wild.size, 2))
        out = unreachable_plots(t, c, sigma, spread, v)
        assert set(out.tolist()) == set(wild.tolist())

        def far(i, j, c=c, t=t):
            return np.hypot(*(c[j] - c[i])) > (v * abs(t[j] - t[i]) + 20 * 60.0
                                                + UNREACHABLE_SLACK_M)

        kept = np.setdiff1d(np.arange(n), out)
        assert not any(far(i, j) for i, j in itertools.pairwise(kept))
        for k in out:
            before, after = kept[kept < k], kept[kept > k]
            assert (before.size == 0 or far(before[-1], k)) and (after.size == 0
                                                                  or far(k, after[0]))
    t = np.arange(10.0)
    line = np.column_stack([200.0 * t, 0.0 * t])
    assert unreachable_plots(t, line, np.full(10, 50.0), np.zeros(10), v).size == 0
    # a burst of plots in reach of each other (clutter at the radar, 1 m away: sigmas of
    # 1 m), off the track's chain, up to CHAIN_SKIP - 1 in a row
    t = np.arange(60.0) * 4.0
    c = np.column_stack([-50_000.0 + 220.0 * t, 30_000.0 + 0.0 * t])
    sigma = np.full(60, 150.0)
    for start, size in ((20, 3), (40, 7), (0, 4)):
        wild = np.arange(start, start + size)
        cc, ss = c.copy(), sigma.copy()
        cc[wild], ss[wild] = 0.0, 1.0
        assert unreachable_plots(t, cc, ss, np.zeros(60), v).tolist() == wild.tolist()


def test_node_grid_keeps_plot_times_and_bounds_steps():
    t = np.array([0.0, 4.0, 30.0, 31.0, 55.0])
    nodes, idx = node_grid(t, 10.0)
    np.testing.assert_array_equal(nodes[idx], t)
    assert np.all(np.diff(nodes) <= 10.0 + 1e-12)
    assert np.all(np.diff(nodes) > 0)


def test_noise_free_truth_recovered_with_its_switch_count():
    """Exact plots (weights from 1-m sigmas): positions within 5 m at every plot and sample,
    and the L1 penalty picks the sparse control history: switch count within +-2."""
    t = _scan_times()
    plots, (x, z, _, v) = _plots(t)
    radar = Radar(range_error_m=3.0, azimuth_error_rad=3e-5)  # sigma 1 m, 1e-5 rad
    cfg = ReconstructionConfig(refine=RefineSettings(max_node_step_s=SCAN))
    rec = reconstruct(plots, radar, cfg)
    err = np.hypot(rec.at_plots.x - x, rec.at_plots.z - z)
    assert err.max() < 5.0, err.max()
    xs, zs, _, _ = truth(LEGS, START, rec.samples.t)
    assert np.hypot(rec.samples.x - xs, rec.samples.z - zs).max() < 5.0
    switches = len(rec.segments) - 1
    assert abs(switches - TRUE_SWITCHES) <= 2, [(s.t_start, s.u, s.w) for s in rec.segments]
    bounds = cfg.bounds
    for seg in rec.segments:
        assert bounds.u[0] - 1e-6 <= seg.u <= bounds.u[1] + 1e-6
        assert bounds.w[0] - 1e-6 <= seg.w <= bounds.w[1] + 1e-6
    assert np.all(rec.samples.speed >= bounds.v[0] - 1e-6)
    assert np.all(rec.samples.speed <= bounds.v[1] + 1e-6)
    assert np.abs(rec.at_plots.speed - v).max() < 1.0


def _noisy(seed: int = 1, drop: bool = True):
    radar = Radar(range_error_m=500.0, azimuth_error_rad=np.deg2rad(1.5))
    plots, tr = _plots(_scan_times(drop), radar.sigma_r, radar.sigma_psi, seed)
    return plots, radar, tr


def test_blocked_and_unblocked_solutions_agree():
    """The seed-like 5057-s track (1065 nodes) in blocks of 512 nodes whose cuts leave 256 nodes
    of look-ahead agrees with the one-block solution to 1 m everywhere."""
    radar = SEED_RADAR
    plots = make_track(sigma_r=radar.sigma_r, sigma_psi=radar.sigma_psi, seed=3).plots
    base = RefineSettings(max_node_step_s=5.0)
    one = refine(plots, radar, ReconstructionConfig(refine=base))
    assert one.diagnostics.extra["refine_blocks"] == 1
    cut = dataclasses.replace(base, block_nodes=512, overlap_nodes=512)
    many = refine(plots, radar, ReconstructionConfig(refine=cut))
    assert many.diagnostics.extra["refine_blocks"] >= 4
    diff = np.hypot(many.samples.x - one.samples.x, many.samples.z - one.samples.z)
    assert diff.max() < 1.0, diff.max()
    # one continuous piecewise-constant-control trajectory: the segments chain exactly
    for a, b in zip(many.segments, many.segments[1:], strict=False):
        assert a.t_end == pytest.approx(b.t_start)


def test_level_relief_weights_follow_the_pilot_turn_rate():
    """``1 / (1 + (u0 / c)^2)`` per node on ``|u|``, ``|w|`` untouched; 0 leaves the weights."""
    from solver.refine.nodes import NodeData

    data = NodeData(**{f.name: None for f in dataclasses.fields(NodeData)})
    data = dataclasses.replace(data, level=np.ones((5, 2)))
    u0 = np.array([0.0, 1.0, -2.0, 4.0, 20.0])
    got = data.relieved(u0, 2.0).level
    np.testing.assert_allclose(got[:, 0], [1.0, 0.8, 0.5, 0.2, 1 / 101])
    np.testing.assert_array_equal(got[:, 1], 1.0)
    assert data.relieved(u0, 0.0).level is data.level


def test_level_relief_keeps_turns_on_noisy_plots():
    """The seed radar's noise (eps 500 m, 1.5 deg) on the two-turn track, seeds 0-5: relieving
    the level penalty where the start turns brings the plots in the turns closer to the truth
    and the whole track no further (pooled RMS when measured: turns 285 -> 251 m, whole track
    241 -> 233 m)."""
    t = _scan_times()
    edges = np.cumsum([0.0] + [d for d, _, _ in LEGS])
    leg = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(LEGS) - 1)
    turning = np.array([LEGS[i][1] != 0 for i in leg])
    err: dict[float, list[np.ndarray]] = {0.0: [], RefineSettings.level_relief_u: []}
    for seed in range(6):
        plots, (x, z, _, _) = _plots(t, 500.0 / 3, np.deg2rad(0.5), seed=seed)
        for relief in err:
            cfg = ReconstructionConfig(refine=RefineSettings(level_relief_u=relief))
            rec = reconstruct(plots, SEED_RADAR, cfg)
            err[relief].append(np.hypot(rec.at_plots.x - x, rec.at_plots.z - z))
    flat, relieved = (np.concatenate(e) for e in err.values())
    turns = np.tile(turning, 6)

    def rms(e: np.ndarray) -> float:
        return float(np.sqrt(np.mean(e**2)))

    assert rms(relieved[turns]) < 0.95 * rms(flat[turns])
    assert rms(relieved) <= rms(flat)


def test_wild_plot_moves_track_less_than_200_m():
    plots, radar, _ = _noisy(seed=2)
    clean = reconstruct(plots, radar)
    i = len(plots) // 2
    rng = plots.range_m.copy()
    rng[i] += 20_000.0
    wild = Plots.from_arrays(plots.t, rng, plots.azimuth_rad)
    rec = reconstruct(wild, radar)
    moved = np.hypot(rec.samples.x - clean.samples.x, rec.samples.z - clean.samples.z)
    assert moved.max() < 200.0, moved.max()


def test_covariance_calibrated_on_the_models_own_noise():
    """Share of truth positions inside the 95 % ellipse between 93 % and 98 % and their mean
    squared Mahalanobis distance between 0.9 and 1.8 (8 noise seeds; measured 97.9 % and 1.27:
    the covariance scale is set a little wide on purpose, `RefineSettings.covariance_scale`).
    An audit's mutations: the plots' information x2 (overconfident) gave 92.1 %, which the
    former lower bound of 90 % let through; x0.6 was caught."""
    m2 = []
    for seed in range(8):
        plots, radar, (x, z, _, _) = _noisy(seed=10 + seed)
        rec = reconstruct(plots, radar)
        d = np.stack([rec.at_plots.x - x, rec.at_plots.z - z], axis=1)
        cov = rec.at_plots.cov[:, :2, :2]
        m2.append(np.einsum("ni,nij,nj->n", d, np.linalg.inv(cov), d))
    all_m2 = np.concatenate(m2)
    share = float(np.mean(all_m2 <= 5.991))  # chi-square 2 dof, 95 %
    assert 0.93 <= share <= 0.98, share
    assert 0.9 <= all_m2.mean() <= 1.8, all_m2.mean()


def test_refined_beats_raw_plots_and_sliding():
    plots, radar, (x, z, _, _) = _noisy(seed=5)
    px, pz = plots.range_m * np.cos(plots.azimuth_rad), plots.range_m * np.sin(plots.azimuth_rad)
    raw = np.sqrt(np.mean((px - x) ** 2 + (pz - z) ** 2))
    refined = reconstruct(plots, radar)
    rms = np.sqrt(np.mean((refined.at_plots.x - x) ** 2 + (refined.at_plots.z - z) ** 2))
    sliding = reconstruct(plots, radar, ReconstructionConfig(method="sliding")).at_plots
    rms_sliding = np.sqrt(np.mean((sliding.x - x) ** 2 + (sliding.z - z) ** 2))
    # measured 213 m against 917 m raw (0.23) and 635 m sliding (0.34); with circles for the
    # plots' ellipses (an audit's mutation) 245 m, 0.27 of raw, which the former 0.6 let through
    assert rms < 0.26 * raw, (rms, raw)
    assert rms < 0.4 * rms_sliding, (rms, rms_sliding)
    assert refined.diagnostics.method == "refined"
    assert refined.at_plots.cov is not None and refined.samples.cov is not None
    assert np.all(np.linalg.eigvalsh(refined.samples.cov) > 0)
    ex = refined.diagnostics.extra  # where the time went, for operators and benchmarks
    assert 0 < ex["refine_model_ms"] < ex["refine_ipopt_ms"] < ex["refine_ms"]


def test_known_altitude_is_used():
    """Plots at 9 km altitude: with altitude_m the ground range is exact; without it the slant
    range puts the track h^2 / 2r further out."""
    t = _scan_times(False)[:80]
    plots, (x, z, _, _) = _plots(t, altitude=9000.0)
    radar = Radar(range_error_m=3.0, azimuth_error_rad=3e-5)  # exact plots, 1-m sigmas
    with_alt = reconstruct(plots, radar)
    err = np.hypot(with_alt.at_plots.x - x, with_alt.at_plots.z - z)
    assert err.max() < 5.0
    blind = reconstruct(dataclasses.replace(plots, altitude_m=None), radar)
    err_blind = np.hypot(blind.at_plots.x - x, blind.at_plots.z - z)
    assert err_blind.mean() > 100.0


def test_solver_failure_is_reported_not_raised(monkeypatch):
    """If IPOPT fails in a block, the last iterate is kept and the failures are counted per
    solve."""
    import solver.refine as refine_module
    from solver.refine import nlp
    from solver.refine.layout import Variant

    real = nlp.block_solver

    def crippled(n, variant=Variant(), warm=False, tol=RefineSettings.ipopt_tol):  # noqa: B008
        solver = real(n, variant, warm, tol)

        class OneIteration:
            def __call__(self, **kw):
                return solver(**kw)

            def stats(self):
                st = dict(solver.stats())
                st["success"] = False
                return st

        return OneIteration()

    monkeypatch.setattr(nlp, "block_solver", crippled)
    plots, radar, _ = _noisy(seed=7)
    rec = refine_module.refine(plots, radar, ReconstructionConfig())
    # every solve "fails": one block, solved twice (switch selection, then polish)
    assert rec.diagnostics.solver_failures == 2
    assert any("did not converge in 2 of 2 block solve(s) over 1 block(s)" in w
               for w in rec.diagnostics.warnings), rec.diagnostics.warnings
    assert np.all(np.isfinite(rec.at_plots.x))


def test_refinement_exception_falls_back_to_sliding(monkeypatch):
    """A refinement that raises degrades to the sliding-window result, flagged."""
    import solver.refine as refine_module

    def broken(*args, **kwargs):
        raise np.linalg.LinAlgError("singular matrix")

    monkeypatch.setattr(refine_module, "refine", broken)
    plots, radar, _ = _noisy(seed=8)
    rec = reconstruct(plots, radar)
    assert rec.diagnostics.method == "sliding"
    assert rec.diagnostics.fallbacks >= 1 and rec.diagnostics.solver_failures >= 1
    assert any("refinement failed" in w for w in rec.diagnostics.warnings)
    assert len(rec.at_plots) == len(plots)


def test_plots_overhead_keep_finite_weights():
    """Altitude a hair below the slant range (aircraft over the radar): the ground-range sigma
    is bounded by its second-order value, so the refinement stays finite."""
    from solver.geometry import ground_range_error, statistical_ellipses

    r = np.array([10_000.0, 10_000.0])
    d = np.array([0.0, 5_000.0])
    e = ground_range_error(50.0, r, d)
    assert e[0] == pytest.approx(50.0 * 10_000.0 / np.sqrt(2 * 10_000.0 * 50.0))
    assert e[1] == pytest.approx(100.0)
    t = _scan_times(False)[:30]
    plots, _ = _plots(t, altitude=9000.0)
    overhead = Plots.from_arrays(plots.t, plots.range_m, plots.azimuth_rad,
                                 plots.range_m * (1 - 1e-15))
    radar = Radar(range_error_m=150.0, azimuth_error_rad=np.deg2rad(0.24))
    assert np.all(np.isfinite(statistical_ellipses(overhead, radar).weights()))
    rec = reconstruct(overhead, radar)
    assert np.all(np.isfinite(rec.samples.states)) and np.all(np.isfinite(rec.samples.cov))


def _straight(speed: float, wild: tuple[int, ...] = (), seed: int = 3) -> tuple[Plots, Radar]:
    """63 plots of a straight pass at ``speed`` (SSR-like noise), ``wild`` ones 20 km long."""
    radar = Radar(range_error_m=150.0, azimuth_error_rad=np.deg2rad(0.24), range_sigma_m=50.0,
                  azimuth_sigma_rad=np.deg2rad(0.08))
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 300.0, 4.8)
    x, z = 30_000.0 + speed * t, np.full(t.size, 5_000.0)
    r = np.hypot(x, z) + rng.normal(0.0, 50.0, t.size)
    r[list(wild)] += 20_000.0
    return Plots.from_arrays(t, r, np.arctan2(z, x) + rng.normal(0.0, 0.0014, t.size)), radar


def test_a_minority_of_wild_plots_is_rejected_and_listed():
    plots, radar = _straight(200.0, wild=(10, 30, 50))
    diag = reconstruct(plots, radar).diagnostics
    assert diag.extra["rejected_plots"] == 3
    assert any("plots [10, 30, 50]" in w for w in diag.warnings), diag.warnings
    assert diag.extra["v_at_bound_share"] == 0.0


@pytest.mark.parametrize(("offset_m", "rejected"), [(200.0, 0), (350.0, 1)])
def test_the_wild_plot_gate_sits_at_five_sigma(offset_m, rejected):
    """One plot 4 or 7 range sigmas (50 m) off a straight pass: the 5-sigma gate keeps the one
    and gives the other no weight (measured: 250 m kept, 300 m not). The other tests' wild plots
    are kilometres off: a gate at 10 sigma (an audit's mutation) passed them all."""
    plots, radar = _straight(200.0)
    r = plots.range_m.copy()
    r[20] += offset_m
    diag = reconstruct(Plots.from_arrays(plots.t, r, plots.azimuth_rad), radar).diagnostics
    assert diag.extra["rejected_plots"] == rejected
    assert any("plots [20]" in w for w in diag.warnings) == bool(rejected), diag.warnings


@pytest.mark.parametrize(("speed", "side"), [(700.0, "upper bound (330 m/s)"),
                                             (20.0, "lower bound (30 m/s)")])
def test_a_track_the_bounds_do_not_fit_rejects_no_plot_and_says_why(speed, side):
    """700 m/s against bounds.v up to 330 m/s (62 of 63 plots far from the best bounded track),
    or a slow 20 m/s against bounds.v from 30 m/s (4 of 63 far, few enough to pass for wild
    plots): the speed sits at a bound, so the bounds, not wild plots, keep them far; nothing
    gets zero weight (the slow target lost its 4 far plots before)."""
    plots, radar = _straight(speed)
    diag = reconstruct(plots, radar).diagnostics
    assert diag.extra["rejected_plots"] == 0
    assert diag.extra["v_at_bound_share"] == pytest.approx(1.0)
    assert any("the bounds, not wild plots, keep them far" in w for w in diag.warnings), \
        diag.warnings
    assert any(f"{side} for 100 %" in w for w in diag.warnings), diag.warnings
    # with bounds that allow it, the same plots fit: no warning, no speed at a bound
    fits = ReconstructionConfig(bounds=dataclasses.replace(ReconstructionConfig().bounds,
                                                           v=(1.0, 800.0)))
    diag = reconstruct(plots, radar, fits).diagnostics
    assert diag.warnings == [] and diag.extra["v_at_bound_share"] == 0.0


@pytest.mark.parametrize("threshold", [RefineSettings.switch_threshold, 0.0])
def test_only_a_solve_the_polish_follows_is_loose(monkeypatch, threshold):
    """The cold first solve runs to ``first_solve_tol`` only when the polish solve follows it;
    every solve whose answer can be the result (the polish, or the only solve when there is no
    polish) runs to ``ipopt_tol``."""
    import solver.refine as refine_pkg

    calls = []
    real = refine_pkg.solve_block

    def spy(*args, **kwargs):
        calls.append((args[7] is not None, kwargs["tol"]))
        return real(*args, **kwargs)

    monkeypatch.setattr(refine_pkg, "solve_block", spy)
    plots, radar = _straight(200.0)
    st = RefineSettings(switch_threshold=threshold)
    rec = reconstruct(plots, radar, ReconstructionConfig(refine=st))
    assert rec.diagnostics.extra["rejected_plots"] == 0
    if threshold > 0:
        assert calls == [(False, st.first_solve_tol), (True, st.ipopt_tol)]
        assert st.first_solve_tol > st.ipopt_tol
    else:  # no wild plot and no switch to hold: the first solve is the answer
        assert calls == [(False, st.ipopt_tol)]


def test_sigmas_far_too_small_reject_no_plot_and_say_why():
    """Radar sigmas declared 10 times too small: 36 of 63 plots of a straight pass are more than
    5 (declared) sigma from the track, too many to be wild plots; nothing gets zero weight."""
    plots, radar = _straight(200.0)
    tight = dataclasses.replace(radar, range_sigma_m=5.0, azimuth_sigma_rad=np.deg2rad(0.008))
    diag = reconstruct(plots, tight).diagnostics
    assert diag.extra["rejected_plots"] == 0 and diag.extra["v_at_bound_share"] == 0.0
    assert any("too many to be wild plots" in w for w in diag.warnings), diag.warnings


@pytest.mark.parametrize(("field", "value", "message"), [
    ("switch_penalty_u", 0.0, "must be positive"),  # the covariance divides by it
    ("level_smoothing", 0.0, "must be positive"),
    ("ipopt_tol", float("nan"), "must be positive"),
    ("first_solve_tol", 0.0, "must be positive"),
    ("level_penalty_w", -0.1, "must be zero or positive"),
    ("level_relief_u", -1.0, "must be zero or positive"),
    ("huber_delta", 0.0, "must be positive or None"),
    ("outlier_max_share", 1.5, "must be between 0 and 1"),
    ("block_nodes", 4096, "must be between 16 and 2048"),
    ("block_nodes", 8, "must be between 16 and 2048"),
    ("overlap_nodes", 1, "must be at least 2"),
    ("overlap_nodes", 64, "less than 2 * block_nodes"),  # block_nodes 32
    ("init", "truth", "must be sliding or smoother"),
])
def test_unusable_refine_settings_are_named(field, value, message):
    plots, radar = _straight(200.0)
    settings = dataclasses.replace(RefineSettings(block_nodes=32, overlap_nodes=16),
                                   **{field: value})
    with pytest.raises(InputError) as err:
        reconstruct(plots, radar, ReconstructionConfig(refine=settings))
    assert err.value.loc == ("refine", field)
    assert message in str(err.value), str(err.value)


def test_smallest_blocks_the_settings_allow_still_chain():
    """Blocks of the smallest solver, cut 1 node before their end (overlap 2): the 63-plot pass
    is solved in 5 blocks into one continuous trajectory. (Such a short look-ahead costs
    accuracy, see ``RefineSettings``.) The accepted block sizes are the ladder's."""
    assert (LADDER[0], LADDER[-1]) == (MIN_BLOCK_NODES, MAX_BLOCK_NODES)
    plots, radar = _straight(200.0)
    rec = reconstruct(plots, radar, ReconstructionConfig(
        refine=RefineSettings(block_nodes=MIN_BLOCK_NODES, overlap_nodes=2)))
    assert rec.diagnostics.extra["refine_blocks"] == 5
    assert rec.segments[0].t_start == plots.t[0] and rec.segments[-1].t_end == plots.t[-1]
    for a, b in zip(rec.segments, rec.segments[1:], strict=False):
        assert a.t_end == pytest.approx(b.t_start)
    assert np.all(np.isfinite(rec.at_plots.states))


def test_noise_free_seed_like_track_keeps_its_manoeuvres():
    """Issue 17: the seed-like track (19-s scans, turns of 220 and 180 deg, plots missing in
    the turns) with exact plots and Mode C, the seed000 radar's declared sigmas and the
    defaults: within 50 m at every plot (the penalties alone cut the turns by 267 m, taking the
    exact plots for noisy ones; the plots' scatter, far below the sigmas, rescales them)."""
    from benchmarks.profiles import PROFILES
    from benchmarks.simulate import simulate
    from benchmarks.truth import SYNTHETIC, load_truth

    prof = PROFILES["seed000"]
    truth = load_truth(SYNTHETIC)
    t = simulate(truth, prof, seed=0, drop_in_turns=True).plots.t
    st, h = truth.at(t), truth.altitude_at(t)
    plots = Plots.from_arrays(t, np.sqrt(st.x**2 + st.z**2 + h**2), np.arctan2(st.z, st.x), h)
    radar = Radar(prof.eps_r, prof.eps_psi, range_sigma_m=prof.sigma_r,
                  azimuth_sigma_rad=prof.sigma_psi, max_altitude_m=prof.h_max,
                  max_elevation_rad=prof.alpha_max)
    rec = reconstruct(plots, radar)
    err = np.hypot(rec.at_plots.x - st.x, rec.at_plots.z - st.z)
    assert err.max() < 50.0, err.max()
    assert rec.diagnostics.extra["sigma_scale_radar"] < 0.1
    assert any("declared sigmas" in w for w in rec.diagnostics.warnings)
