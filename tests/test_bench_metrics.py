"""Benchmark metrics against hand-computed values; baselines on a simple track."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.metrics import CHI2_2DOF_95, errors, inside_ellipse95, p95, rms, summarize
from solver.results import StateSeries


def _series(t, x, z, vx, vz, cov=None):
    a = [np.asarray(v, dtype=float) for v in (t, x, z, vx, vz)]
    return StateSeries(*a, cov=cov)


def test_errors_and_summary_by_hand():
    truth = _series([0, 1, 2, 3], [0, 0, 0, 0], [0, 0, 0, 0], [100, 100, 100, 100], [0, 0, 0, 0])
    est = _series([0, 1, 2, 3], [3, 0, 0, 6], [4, 0, 5, 8], [100, 84, 96, 100], [0, 63, 0, 0])
    man = np.array([False, True, True, False])
    e = errors(est, truth, man, wall_s=0.5, cpu_s=0.25)
    np.testing.assert_allclose(e.pos, [5, 0, 5, 10])
    np.testing.assert_allclose(e.speed, [0, 5, -4, 0], atol=1e-12)  # |(84, 63)| = 105
    s = summarize([e])
    assert s["rms_pos"] == pytest.approx(np.sqrt((25 + 0 + 25 + 100) / 4))
    assert s["rms_pos_man"] == pytest.approx(np.sqrt(25 / 2))
    assert s["p95_pos"] == pytest.approx(5 + 0.85 * 5)  # sorted 0 5 5 10, rank 2.85
    assert s["plots_per_s"] == pytest.approx(8.0)
    assert s["plots_per_cpu_s"] == pytest.approx(16.0)
    assert np.isnan(s["coverage95"])


def test_speed_error_is_difference_of_ground_speeds():
    truth = _series([0], [0], [0], [30], [40])
    est = _series([0], [0], [0], [0], [52])
    assert errors(est, truth, np.array([False])).speed[0] == pytest.approx(2.0)


def test_pooling_weights_runs_by_their_plots():
    truth = _series([0, 1, 2], [0, 0, 0], [0, 0, 0], [1, 1, 1], [0, 0, 0])
    a = errors(_series([0], [2], [0], [1], [0]), _series([0], [0], [0], [1], [0]),
               np.array([False]), 1.0)
    b = errors(_series([0, 1, 2], [1, 1, 1], [0, 0, 0], [1, 1, 1], [0, 0, 0]), truth,
               np.zeros(3, bool), 1.0)
    s = summarize([a, b])
    assert s["rms_pos"] == pytest.approx(np.sqrt((4 + 3) / 4))
    assert s["wall_s_per_track"] == pytest.approx(1.0)
    assert s["plots_per_s"] == pytest.approx(2.0)
    assert np.isnan(s["rms_pos_man"])


def test_ellipse_coverage_on_the_boundary_and_for_correlated_covariance():
    # axis-aligned sigmas 10 and 2: the 95 % ellipse reaches 10 sqrt(5.991) along x
    cov = np.zeros((4, 4, 4))
    cov[:, 0, 0], cov[:, 1, 1] = 100.0, 4.0
    k = np.sqrt(CHI2_2DOF_95)
    dx = np.array([10 * k * 0.999, 10 * k * 1.001, 0.0, 0.0])
    dz = np.array([0.0, 0.0, 2 * k * 0.999, 2 * k * 1.001])
    np.testing.assert_array_equal(inside_ellipse95(cov, dx, dz), [1, 0, 1, 0])
    # rotated by 30 deg: a point along the rotated major axis is inside, across it outside
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    rot = np.array([[c, -s], [s, c]])
    p = rot @ np.diag([100.0, 4.0]) @ rot.T
    cov2 = np.zeros((2, 4, 4))
    cov2[:, :2, :2] = p
    along, across = rot @ [20.0, 0.0], rot @ [0.0, 20.0]
    got = inside_ellipse95(cov2, np.array([along[0], across[0]]), np.array([along[1], across[1]]))
    np.testing.assert_array_equal(got, [1, 0])
    bad = np.full((1, 4, 4), np.nan)
    assert np.isnan(inside_ellipse95(bad, np.zeros(1), np.zeros(1))[0])


def test_coverage_of_gaussian_errors_with_their_true_covariance_is_95_percent():
    rng = np.random.default_rng(0)
    n = 20000
    p = np.array([[400.0, 150.0], [150.0, 100.0]])
    d = rng.multivariate_normal([0, 0], p, n)
    cov = np.zeros((n, 4, 4))
    cov[:, :2, :2] = p
    assert np.mean(inside_ellipse95(cov, d[:, 0], d[:, 1])) == pytest.approx(0.95, abs=0.005)


def test_rms_and_p95_ignore_nan():
    assert rms(np.array([3.0, np.nan, 4.0])) == pytest.approx(np.sqrt(12.5))
    assert p95(np.arange(101.0)) == pytest.approx(95.0)
    assert np.isnan(rms(np.array([np.nan])))


def test_errors_reject_mismatched_times():
    a = _series([0, 1], [0, 0], [0, 0], [1, 1], [0, 0])
    b = _series([0, 2], [0, 0], [0, 0], [1, 1], [0, 0])
    with pytest.raises(ValueError):
        errors(a, b, np.zeros(2, bool))
