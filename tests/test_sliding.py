"""Sliding extended windows end to end: recovery, noise, bounds, edge cases, diagnostics."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from tracks import CLOSE_SWITCH_LEGS, SEED_RADAR, make_track

import solver.window as window
from solver.config import ReconstructionConfig
from solver.geometry import plot_points
from solver.inputs import Bounds, Plots, Radar
from solver.motion import propagate
from solver.sliding import reconstruct_sliding
from solver.trajectory import evaluate, sample_times

SIGMA_R, SIGMA_PSI = 500.0 / 3, np.deg2rad(0.5)  # one third of the seed's eps_r, eps_psi


def _config(**kw) -> ReconstructionConfig:
    return ReconstructionConfig(method="sliding", **kw)


def _check_bounds_and_continuity(rec, bounds: Bounds, tol: float = 1e-6) -> None:
    """Every segment's controls and its speed at both ends are within bounds; each segment ends
    where the next one starts; segments tile the time axis."""
    segs = rec.segments
    for s in segs:
        assert bounds.u[0] - tol <= s.u <= bounds.u[1] + tol
        assert bounds.w[0] - tol <= s.w <= bounds.w[1] + tol
        v_end = s.speed + s.w * (s.t_end - s.t_start)
        assert bounds.v[0] - tol <= s.speed <= bounds.v[1] + tol
        assert bounds.v[0] - tol <= v_end <= bounds.v[1] + tol
        assert s.t_end > s.t_start
    for a, b in itertools.pairwise(segs):
        assert a.t_end == b.t_start
        x, z, phi, v = propagate(a.x, a.z, a.heading, a.speed, a.u, a.w, a.t_end - a.t_start)
        assert np.hypot(x - b.x, z - b.z) < 1e-6 * max(1.0, np.hypot(b.x, b.z))
        assert abs(np.angle(np.exp(1j * (phi - b.heading)))) < 1e-9
        assert v == pytest.approx(b.speed, abs=1e-9)


@pytest.fixture(scope="module")
def clean_track():
    return make_track()


@pytest.fixture(scope="module")
def noisy_track():
    return make_track(sigma_r=SIGMA_R, sigma_psi=SIGMA_PSI, seed=11)


def test_noise_free_recovery(clean_track):
    """Seed-like track (straight legs, ~220 and ~180 deg turns, speed changes, 19-s scans, every
    second plot missing in turns): every plot-time position within 50 m, controls in bounds."""
    tr = clean_track
    assert np.diff(tr.t).max() == pytest.approx(38.0)  # the turns do have missing plots
    cfg = _config(window_plots=3)
    rec = reconstruct_sliding(tr.plots, SEED_RADAR, cfg)
    err = np.hypot(rec.at_plots.x - tr.x, rec.at_plots.z - tr.z)
    assert err.max() < 50.0
    _check_bounds_and_continuity(rec, cfg.bounds)
    speed_err = np.abs(rec.at_plots.speed - tr.v)
    assert speed_err.max() < 1.0
    # the turns are found: some segment turns right hard, some left hard
    assert max(s.u for s in rec.segments) > 5.5 and min(s.u for s in rec.segments) < -4.5


@pytest.mark.parametrize(("m", "share"), [(3, 0.67), (4, 0.65), (5, 0.61)])
def test_noisy_track_beats_raw_plots(noisy_track, m, share):
    """RMS error at most ``share`` of the raw plots' (measured 0.648 / 0.623 / 0.574 for
    m = 3 / 4 / 5; with circles instead of the plots' ellipses, an audit's mutation, 0.68 /
    0.64 / 0.68, which the former bound, the raw plots' error itself, let through)."""
    tr = noisy_track
    rec = reconstruct_sliding(tr.plots, SEED_RADAR, _config(window_plots=m))
    px, pz = plot_points(tr.plots)
    raw = np.sqrt(np.mean((px - tr.x) ** 2 + (pz - tr.z) ** 2))
    ours = np.sqrt(np.mean((rec.at_plots.x - tr.x) ** 2 + (rec.at_plots.z - tr.z) ** 2))
    assert ours < share * raw, ours / raw
    _check_bounds_and_continuity(rec, Bounds())


def test_close_switches_are_bounded_not_exact():
    """A 40-s deceleration right after a turn puts two switches inside one 3-plot window, which
    constant-control windows cannot fit exactly; the reconstruction stays continuous, in bounds
    and close (documented: some hundred metres at most on this track)."""
    tr = make_track(legs=CLOSE_SWITCH_LEGS, start=(-20_000.0, -90_000.0, 0.5, 235.0))
    rec = reconstruct_sliding(tr.plots, SEED_RADAR, _config())
    err = np.hypot(rec.at_plots.x - tr.x, rec.at_plots.z - tr.z)
    assert err.max() < 500.0
    _check_bounds_and_continuity(rec, Bounds())


def test_track_starting_in_a_turn():
    """The seed's start (velocity along the chord of the first two plots) is off by hundreds of
    metres when the track starts in a turn; the free-start first window fits it exactly."""
    legs = [(120.0, 5.0, 0.0), (600.0, 0.0, 0.0), (100.0, -4.0, 0.5), (600.0, 0.0, 0.0)]
    tr = make_track(legs=legs, start=(60_000.0, 40_000.0, 1.0, 200.0), drop_in_turns=False)
    rec = reconstruct_sliding(tr.plots, SEED_RADAR, _config())
    assert np.hypot(rec.at_plots.x - tr.x, rec.at_plots.z - tr.z).max() < 50.0
    assert rec.diagnostics.extra["free_start_shift_m"] < 50.0


def test_seed_rule_runs_and_respects_bounds(noisy_track):
    """The literal seed rule (no switch-time refinement, no free start) stays available
    through :func:`solver.sliding.slide`; it is coarser but must still be feasible."""
    from solver.results import Diagnostics
    from solver.sliding import criterion_data, initial_state, slide

    tr = noisy_track
    cfg = _config()
    cx, cz, abc, scale = criterion_data(tr.plots, SEED_RADAR, "R2")
    start, _ = initial_state(tr.t, cx, cz, cfg.bounds.v)
    diag = Diagnostics()
    segs = slide(tr.t, cx, cz, abc, start, 3, cfg, diag, scale, seed_rule=True)

    class _Rec:
        segments = segs

    _check_bounds_and_continuity(_Rec, cfg.bounds)
    assert segs[0].t_start == tr.t[0] and segs[-1].t_end == tr.t[-1]


def test_outputs_and_diagnostics(noisy_track):
    tr = noisy_track
    cfg = _config(sample_step_s=7.0)
    rec = reconstruct_sliding(tr.plots, SEED_RADAR, cfg)
    d = rec.diagnostics
    assert len(rec.at_plots) == len(tr.plots)
    assert np.array_equal(rec.at_plots.t, tr.t)
    assert rec.samples.t[0] == tr.t[0] and rec.samples.t[-1] == tr.t[-1]
    assert np.allclose(np.diff(rec.samples.t)[:-1], 7.0)
    assert len(d.criterion_values) == len(rec.segments) == d.extra["accepted_windows"]
    assert len(d.nlp_solve_ms) == d.windows_solved > d.trial_windows > 0
    assert d.elapsed_ms > 0 and d.method == "sliding" and d.criterion == "R2"
    assert np.all(np.isfinite(d.criterion_values))
    # at_plots agree with evaluating the segments independently
    again = evaluate(rec.segments, tr.t)
    assert np.allclose(again.x, rec.at_plots.x) and np.allclose(again.vz, rec.at_plots.vz)


def test_r1_criterion(noisy_track):
    """R1 (plain least squares) beats the raw plots, and R2's ellipse weights beat it with
    3-plot windows (measured 690 m against 649 m; 0.69 and 0.65 of the raw plots' error)."""
    tr = noisy_track
    rec = reconstruct_sliding(tr.plots, SEED_RADAR, _config(criterion="R1"))
    px, pz = plot_points(tr.plots)
    raw = np.sqrt(np.mean((px - tr.x) ** 2 + (pz - tr.z) ** 2))
    ours = np.sqrt(np.mean((rec.at_plots.x - tr.x) ** 2 + (rec.at_plots.z - tr.z) ** 2))
    assert ours < 0.72 * raw, ours / raw
    r2 = reconstruct_sliding(tr.plots, SEED_RADAR, _config(criterion="R2")).at_plots
    assert np.sqrt(np.mean((r2.x - tr.x) ** 2 + (r2.z - tr.z) ** 2)) < ours / 1.04
    # R1 values are reported in m^2: a good 3-plot fit leaves residuals of order sigma
    assert 1e2 < np.median(rec.diagnostics.criterion_values) < 3 * (3 * 500.0**2)


def test_solver_failures_degrade_gracefully(monkeypatch, noisy_track):
    """Every NLP fails: the reconstruction still completes from the analytic guesses, in bounds,
    and says so."""

    class Failing:
        def __call__(self, **kw):
            return {"x": np.full(np.shape(kw["x0"]), np.nan), "f": np.nan}

        def stats(self):
            return {"return_status": "Restoration_Failed", "success": False}

    monkeypatch.setattr(window, "window_batch", lambda m, plugin, n: Failing())
    monkeypatch.setattr(window, "switch_batch", lambda m, plugin, k: Failing())
    monkeypatch.setattr(window, "free_start_solver", lambda m, plugin: Failing())
    tr = noisy_track
    rec = reconstruct_sliding(tr.plots, SEED_RADAR, _config())
    d = rec.diagnostics
    assert d.solver_failures == d.windows_solved > 0
    assert d.fallbacks > 0
    _check_bounds_and_continuity(rec, Bounds())


# ---- edge cases -------------------------------------------------------------------------------


def _plots_from_xy(t, x, z) -> Plots:
    return Plots.from_arrays(t, np.hypot(x, z), np.arctan2(z, x))


def test_one_plot():
    plots = _plots_from_xy([5.0], [30_000.0], [40_000.0])
    rec = reconstruct_sliding(plots, SEED_RADAR, _config())
    assert rec.segments == []
    assert rec.at_plots.x[0] == pytest.approx(30_000.0) and rec.at_plots.z[0] == pytest.approx(
        40_000.0)
    assert rec.at_plots.speed[0] == 0.0 and len(rec.samples) == 1
    assert any("one plot" in w for w in rec.diagnostics.warnings)


@pytest.mark.parametrize(("dx", "clipped"), [(3_800.0, False), (100.0, True), (30_000.0, True)])
def test_two_plots(dx, clipped):
    plots = _plots_from_xy([0.0, 19.0], [50_000.0, 50_000.0 + dx], [10_000.0, 10_000.0])
    cfg = _config()
    rec = reconstruct_sliding(plots, SEED_RADAR, cfg)
    (seg,) = rec.segments
    assert seg.u == 0.0 and seg.w == 0.0 and seg.heading == pytest.approx(0.0)
    assert seg.speed == pytest.approx(np.clip(dx / 19.0, *cfg.bounds.v))
    assert any("clipped" in w for w in rec.diagnostics.warnings) == clipped
    assert rec.at_plots.x[0] == pytest.approx(50_000.0)


def test_window_longer_than_track():
    t = np.array([0.0, 19.0, 38.0])
    x, z, _, _ = propagate(60_000.0, 0.0, 1.0, 200.0, 1.0, 0.0, t)
    rec = reconstruct_sliding(_plots_from_xy(t, x, z), SEED_RADAR, _config(window_plots=5))
    assert len(rec.segments) == 1
    assert any("longer than the track" in w for w in rec.diagnostics.warnings)
    assert np.hypot(rec.at_plots.x - x, rec.at_plots.z - z).max() < 200.0


def test_near_duplicate_first_plots_do_not_set_the_velocity():
    """The first two plots 0.01 s apart and 300 m apart (noise) would give 30 km/s; the initial
    velocity comes from a plot at least max(1 s, half the median spacing) later instead."""
    t = np.concatenate([[0.0, 0.01], 19.0 * np.arange(1, 12)])
    x, z, _, _ = propagate(80_000.0, 20_000.0, 2.0, 220.0, 0.0, 0.0, t)
    x = x.copy()
    x[1] += 300.0
    rec = reconstruct_sliding(_plots_from_xy(t, x, z), SEED_RADAR, _config())
    first = rec.segments[0]
    assert first.speed == pytest.approx(220.0, rel=0.05)
    assert not any("clipped" in w for w in rec.diagnostics.warnings)
    assert np.hypot(rec.at_plots.x - x, rec.at_plots.z - z)[2:].max() < 100.0


def test_long_gap_of_missed_plots():
    """Eight scans missing in the middle of a turn: windows take the next plots across the gap
    (one constant control spans it, so the fit stays exact)."""
    legs = [(400.0, 0.0, 0.0), (300.0, 1.5, 0.0), (400.0, 0.0, 0.0)]
    tr = make_track(legs=legs, start=(-50_000.0, -60_000.0, 0.8, 200.0), drop_in_turns=False)
    keep = (tr.t < 470.0) | (tr.t > 640.0)
    assert np.diff(tr.t[keep]).max() > 8 * 19.0
    plots = Plots.from_arrays(tr.t[keep], tr.plots.range_m[keep], tr.plots.azimuth_rad[keep])
    rec = reconstruct_sliding(plots, SEED_RADAR, _config())
    err = np.hypot(rec.at_plots.x - tr.x[keep], rec.at_plots.z - tr.z[keep])
    assert err.max() < 50.0
    _check_bounds_and_continuity(rec, Bounds())


# ---- property test: bounds hold for random noisy inputs ---------------------------------------


@st.composite
def _scenarios(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    u_max = draw(st.floats(0.5, 7.0))
    w_lo, w_hi = -draw(st.floats(0.2, 2.0)), draw(st.floats(0.2, 3.0))
    v_lo = draw(st.floats(30.0, 150.0))
    v_hi = v_lo + draw(st.floats(20.0, 200.0))
    bounds = Bounds((-u_max, u_max), (w_lo, w_hi), (v_lo, v_hi))
    legs = [(float(rng.uniform(20, 200)), float(rng.uniform(-7, 7)), float(rng.uniform(-1, 1)))
            for _ in range(draw(st.integers(1, 4)))]
    start = (float(rng.uniform(-9e4, 9e4)), float(rng.uniform(-9e4, 9e4)),
             float(rng.uniform(0, 2 * np.pi)), float(rng.uniform(150, 250)))
    scan = draw(st.sampled_from([4.8, 10.0, 19.0]))
    m = draw(st.integers(2, 5))
    return bounds, legs, start, scan, m, seed


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_scenarios())
# a 20-s turn seen by a 19-s radar that loses every second plot in turns: one plot (found by
# Hypothesis in CI)
@example((Bounds(), [(20.0, 2.0, 0.0)], (1e4, 2e4, 0.5, 200.0), 19.0, 3, 1))
def test_bounds_hold_for_random_noisy_inputs(scenario):
    bounds, legs, start, scan, m, seed = scenario
    tr = make_track(legs=legs, start=start, scan_s=scan, sigma_r=SIGMA_R, sigma_psi=SIGMA_PSI,
                    drop_in_turns=bool(seed % 2), seed=seed)
    radar = Radar(range_error_m=500.0, azimuth_error_rad=np.deg2rad(1.5),
                  max_altitude_m=15_000.0, max_elevation_rad=np.deg2rad(60.0))
    cfg = _config(bounds=bounds, window_plots=m, criterion="R2" if seed % 3 else "R1")
    rec = reconstruct_sliding(tr.plots, radar, cfg)
    if len(tr.plots.t) == 1:  # no trajectory to bound: the documented answer, with its warning
        assert rec.segments == [] and np.all(rec.at_plots.speed == 0.0)
        assert any("only one plot" in w for w in rec.diagnostics.warnings)
        return
    _check_bounds_and_continuity(rec, bounds)
    assert np.all(np.isfinite(rec.at_plots.states))
    assert np.all(rec.at_plots.speed >= bounds.v[0] - 1e-6)
    assert np.all(rec.at_plots.speed <= bounds.v[1] + 1e-6)


def test_a_wild_last_plot_is_covered_within_the_bounds():
    """The first or last plot left out as wild (20 km off): the windows end before it, and the
    state there came from carrying the nearest segment's controls on: a track decelerating to
    34 m/s at its last plot was put at 24.1 m/s, under bounds.v's 30 (found by the property
    test). Now a straight constant-speed segment covers it, and the samples span every plot."""
    tr = make_track(legs=[(150.0, 0.0, 0.0), (130.0, 0.0, -0.35)],
                    start=(2e4, 6e4, 0.3, 75.0), scan_s=19.0, sigma_r=50.0,
                    sigma_psi=np.deg2rad(0.08), drop_in_turns=False, seed=4)
    p = tr.plots
    r = p.range_m.copy()
    r[-1] += 20_000.0
    bounds = Bounds(v=(30.0, 250.0))
    rec = reconstruct_sliding(Plots.from_arrays(p.t, r, p.azimuth_rad),
                              Radar(range_error_m=150.0, azimuth_error_rad=np.deg2rad(0.24)),
                              _config(bounds=bounds))
    assert rec.no_weight.tolist() == [len(p.t) - 1]
    _check_bounds_and_continuity(rec, bounds)
    assert np.all(rec.at_plots.speed >= 30.0 - 1e-6), rec.at_plots.speed
    edge = rec.segments[-1]
    assert (edge.u, edge.w, edge.t_start, edge.t_end) == (0.0, 0.0, p.t[-2], p.t[-1])
    assert rec.samples.t[0] == p.t[0] and rec.samples.t[-1] == p.t[-1]
    assert abs(rec.at_plots.speed[-1] - tr.v[-1]) < 5.0


def test_straight_segments_cover_times_before_and_after():
    """The cover at both ends (the gate never leaves a first plot out: its filter starts
    there; the code does not rely on that): straight, constant speed, continuous."""
    from solver.results import Segment
    from solver.sliding import _straight_beyond

    seg = Segment(10.0, 20.0, 1000.0, 2000.0, 0.4, 100.0, 2.0, -1.0)
    out = _straight_beyond([seg], 0.0, 30.0)
    assert [(s.t_start, s.t_end, s.u, s.w) for s in out] == [
        (0.0, 10.0, 0.0, 0.0), (10.0, 20.0, 2.0, -1.0), (20.0, 30.0, 0.0, 0.0)]
    assert out[0].speed == 100.0 and out[0].heading == 0.4
    x, z, _, _ = propagate(out[0].x, out[0].z, 0.4, 100.0, 0.0, 0.0, 10.0)
    assert (float(x), float(z)) == pytest.approx((1000.0, 2000.0), abs=1e-9)
    end = propagate(1000.0, 2000.0, 0.4, 100.0, 2.0, -1.0, 10.0)
    assert (out[2].x, out[2].z, out[2].heading, out[2].speed) == pytest.approx(
        tuple(map(float, end)), abs=1e-9)
    assert _straight_beyond([seg], 10.0, 20.0) == [seg]


def test_sample_times():
    assert np.allclose(sample_times(0.0, 10.0, 3.0), [0, 3, 6, 9, 10])
    assert np.allclose(sample_times(0.0, 9.0, 3.0), [0, 3, 6, 9])
    assert np.allclose(sample_times(2.0, 2.0, 1.0), [2.0])
