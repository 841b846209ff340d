"""Benchmark truth and radar simulation: interpolation, determinism, noise statistics, Pd."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from benchmarks.profiles import PROFILES
from benchmarks.simulate import simulate
from benchmarks.truth import (
    DATA_DIR,
    SEED_LIKE_CONTROLS,
    Truth,
    load_truth,
    synthetic_seed_track,
    truth_names,
)


def test_truth_names_cover_the_csv_files_and_the_synthetic_track():
    names = truth_names()
    assert len(names) == 7
    assert "synthetic__seed_like" in names
    assert all((DATA_DIR / f"{n}.csv").exists() for n in names[:-1])


def test_truth_interpolation_reproduces_the_csv_samples_and_is_smooth_between():
    raw = np.loadtxt(DATA_DIR / "calibration__vienna.csv", delimiter=",", skiprows=1)
    tr = load_truth("calibration__vienna")
    s = tr.at(raw[:, 0])
    np.testing.assert_allclose(s.x, raw[:, 1], atol=1e-6)
    np.testing.assert_allclose(s.z, raw[:, 2], atol=1e-6)
    np.testing.assert_allclose(tr.altitude_at(raw[:, 0]), raw[:, 3], atol=1e-6)
    np.testing.assert_allclose(s.vx, raw[:, 4], atol=1e-6)
    # half-way between samples: close to the mean of the neighbours and of the trapezoid
    # x(t+2.5) ~ x(t) + 2.5 (vx(t) + vx(t+5)) / 2, within a few metres for an airliner
    mid = tr.at(raw[:-1, 0] + 2.5)
    trap = raw[:-1, 1] + 2.5 * (0.75 * raw[:-1, 4] + 0.25 * raw[1:, 4])
    assert np.max(np.abs(mid.x - trap)) < 15.0
    assert np.max(np.abs(mid.x - (raw[:-1, 1] + raw[1:, 1]) / 2)) < 50.0


def test_turn_rate_of_a_circle_is_speed_over_radius():
    t = np.arange(0.0, 600.0, 5.0)
    v, radius = 150.0, 6000.0
    om = v / radius
    tr = Truth("circle", t, radius * np.sin(om * t), radius * (1 - np.cos(om * t)),
               np.full(t.size, 1000.0), v * np.cos(om * t), v * np.sin(om * t))
    np.testing.assert_allclose(tr.turn_rate_at(t[5:-5]), om, rtol=1e-4)
    np.testing.assert_allclose(tr.at(t[5:-5] + 1.3).speed, v, rtol=1e-5)


def test_synthetic_track_turns_about_220_and_180_degrees():
    tr = synthetic_seed_track()
    assert 4900 <= tr.duration <= 5100
    t = np.arange(0.0, tr.duration, 0.5)
    rate = tr.turn_rate_at(t)
    right = np.degrees(np.sum(rate[rate > 0.005]) * 0.5)
    left = np.degrees(np.sum(rate[rate < -0.005]) * 0.5)
    assert right == pytest.approx(220, abs=3)
    assert left == pytest.approx(-180, abs=3)
    speeds = tr.at(t).speed
    assert speeds.min() == pytest.approx(150, abs=1) and speeds.max() == pytest.approx(220, abs=1)
    assert sum(d for d, _, _ in SEED_LIKE_CONTROLS) == pytest.approx(tr.duration)
    r = np.hypot(tr.x, tr.z)
    assert 20e3 < r.min() and r.max() < 200e3


def test_simulation_is_deterministic_per_seed_and_differs_between_seeds():
    tr, prof = load_truth("calibration__vienna"), PROFILES["seed000"]
    a, b, c = simulate(tr, prof, 3), simulate(tr, prof, 3), simulate(tr, prof, 4)
    np.testing.assert_array_equal(a.plots.t, b.plots.t)
    np.testing.assert_array_equal(a.plots.range_m, b.plots.range_m)
    np.testing.assert_array_equal(a.plots.azimuth_rad, b.plots.azimuth_rad)
    assert len(a.plots) != len(c.plots) or not np.array_equal(a.plots.range_m, c.plots.range_m)


def test_scan_times_are_a_phase_plus_multiples_of_the_scan_period():
    prof = PROFILES["seed001"]  # Pd = 1: every scan present
    sim = simulate(load_truth("calibration__bornholm"), prof, 7)
    d = np.diff(sim.plots.t)
    np.testing.assert_allclose(d, prof.scan_s, atol=1e-9)
    assert 0 <= sim.plots.t[0] < prof.scan_s
    np.testing.assert_array_equal(sim.truth.t, sim.plots.t)


def test_noise_sigmas_and_detection_probability_are_recovered():
    prof = PROFILES["seed000"]
    tr = load_truth("featured__belevingsvlucht")
    dr, dpsi, kept, scans = [], [], 0, 0
    for seed in range(12):
        sim = simulate(tr, prof, seed)
        x, z, h = sim.truth.x, sim.truth.z, sim.altitude
        dr.append(sim.plots.range_m - np.sqrt(x**2 + z**2 + h**2))
        dpsi.append(np.angle(np.exp(1j * (sim.plots.azimuth_rad - np.arctan2(z, x)))))
        first = sim.plots.t[0] - prof.scan_s * np.floor(sim.plots.t[0] / prof.scan_s)
        scans += np.arange(first, tr.t[-1], prof.scan_s).size
        kept += len(sim.plots)
    dr, dpsi = np.concatenate(dr), np.concatenate(dpsi)
    n = dr.size  # ~ 4000 plots: sigma to ~1.1 %, Pd to ~0.5 %
    assert n > 3000
    assert abs(dr.mean()) < 4 * prof.sigma_r / np.sqrt(n)
    assert np.std(dr) == pytest.approx(prof.sigma_r, rel=0.04)
    assert np.std(dpsi) == pytest.approx(prof.sigma_psi, rel=0.04)
    assert kept / scans == pytest.approx(prof.pd, abs=0.02)


def test_drop_in_turns_thins_plots_only_in_manoeuvres():
    tr, prof = synthetic_seed_track(), PROFILES["ssr"]
    full = [simulate(tr, prof, s) for s in range(4)]
    thin = [simulate(tr, prof, s, drop_in_turns=True, keep_in_turns=0.3) for s in range(4)]
    man_full = sum(int(s.manoeuvre.sum()) for s in full)
    man_thin = sum(int(s.manoeuvre.sum()) for s in thin)
    straight_full = sum(int((~s.manoeuvre).sum()) for s in full)
    straight_thin = sum(int((~s.manoeuvre).sum()) for s in thin)
    assert straight_thin == straight_full
    assert man_thin / man_full == pytest.approx(0.3, abs=0.08)


def test_with_altitude_carries_the_true_altitude():
    sim = simulate(load_truth("calibration__kiruna"), PROFILES["ssr"], 1, with_altitude=True)
    assert sim.plots.altitude_m is not None
    np.testing.assert_allclose(sim.plots.altitude_m, sim.altitude)
    plain = simulate(load_truth("calibration__kiruna"), PROFILES["ssr"], 1)
    np.testing.assert_array_equal(plain.plots.range_m, sim.plots.range_m)
    assert plain.plots.altitude_m is None


def test_profiles_match_profiles_md():
    p = PROFILES
    assert (p["seed000"].scan_s, p["seed001"].scan_s, p["ssr"].scan_s) == (19.0, 10.0, 4.8)
    assert p["seed000"].sigma_r == pytest.approx(500 / 3)
    assert p["seed000"].sigma_psi == pytest.approx(np.deg2rad(0.5))
    assert p["seed001"].sigma_psi == 0.01 and p["seed001"].pd == 1.0
    assert p["ssr"].sigma_r == 50.0 and p["ssr"].pd == 0.97
    radar = p["seed000"].radar()
    assert radar.sigma_r == pytest.approx(500 / 3) and radar.range_error_m == 500.0
    assert radar.max_elevation_rad == pytest.approx(np.pi / 3)


def test_bias_variance_noise_free_raw_error_is_the_slant_range_excess():
    """Noise-free plots put the raw point at the slant range on the true azimuth, so its error is
    ``sqrt(d^2 + h^2) - d`` exactly; the noisy run has the same plot times and larger errors."""
    from benchmarks.bias_variance import errors

    name, seed = "calibration__vienna", 100
    res = errors("ssr", ("raw", "ss-cv-rts"), [name], [seed], progress=False, t_max=600.0)
    sim = simulate(load_truth(name), PROFILES["ssr"], seed, t_max=600.0)
    d = np.hypot(sim.truth.x, sim.truth.z)
    np.testing.assert_allclose(res["raw"]["noise-free"], np.hypot(d, sim.altitude) - d,
                               rtol=1e-9, atol=1e-6)
    for e in res.values():
        assert e["noisy"].shape == e["noise-free"].shape == d.shape
    rms = {k: np.sqrt(np.mean(v**2)) for k, v in res["raw"].items()}
    assert rms["noisy"] > 2 * rms["noise-free"]


def test_penalty_oracle_scales_the_four_penalties_and_matches_the_benchmark():
    """``scaled`` multiplies exactly the four penalty weights; at scale 1 the oracle's error is
    the benchmark's own refined estimator's on the same plots, and the scale changes the result."""
    from benchmarks.estimators import registry
    from benchmarks.penalty_oracle import scaled, squared_errors
    from solver.config import RefineSettings

    assert scaled(1.0) == RefineSettings()
    d, s2 = RefineSettings(), scaled(2.0)
    assert (s2.switch_penalty_u, s2.switch_penalty_w, s2.level_penalty_u, s2.level_penalty_w) == (
        2 * d.switch_penalty_u, 2 * d.switch_penalty_w, 2 * d.level_penalty_u,
        2 * d.level_penalty_w)
    assert dataclasses.replace(s2, switch_penalty_u=d.switch_penalty_u,
                               switch_penalty_w=d.switch_penalty_w,
                               level_penalty_u=d.level_penalty_u,
                               level_penalty_w=d.level_penalty_w) == d

    name, seed, t_max = "calibration__vienna", 100, 900.0
    scales = [0.35, 0.7, 1.0, 1.4, 2.8]
    sse, sse_mean, sse_ss, plots = squared_errors("seed001", [name], [seed], scales,
                                                  progress=False, t_max=t_max)
    sim = simulate(load_truth(name), PROFILES["seed001"], seed, t_max=t_max)
    reg = registry()
    for est, value in (("recon-refined-m3-R2", sse[0, 2]), ("ss-cv-rts", sse_ss[0])):
        st = reg[est].run(sim.plots, PROFILES["seed001"].radar(), "seed001").states
        assert value == pytest.approx(np.sum((st.x - sim.truth.x) ** 2 + (st.z - sim.truth.z) ** 2))
    assert plots[0] == sim.plots.t.size
    assert np.ptp(sse[0]) > 0.01 * sse[0, 2]
    # the ensemble is the mean of the 0.7, 1, 1.4 solutions: by convexity its squared error is
    # at most the mean of theirs
    assert 0 < sse_mean[0] <= np.mean(sse[0, 1:4]) + 1e-9
    with pytest.raises(ValueError, match="must include"):
        squared_errors("seed001", [name], [seed], [1.0], progress=False, t_max=t_max)


def test_the_example_requests_are_what_their_generators_write():
    """`examples/*.json`, whose answers the README quotes, are exactly what the README's
    commands write (the seed track's was not, after the benchmarks' copy of the track moved
    to 3 km)."""
    from examples import make_seed_batch, make_sensors_batch

    assert make_seed_batch.text(make_seed_batch.seed_batch()) == \
        make_seed_batch.OUT.read_text()
    assert make_sensors_batch.text(make_sensors_batch.sensors_batch()) == \
        make_sensors_batch.OUT.read_text()
