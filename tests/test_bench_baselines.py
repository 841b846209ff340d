"""Baselines: Stone Soup wiring against an explicit-matrix Kalman/RTS reference; IMM sanity."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.baselines import (
    ImmTuning,
    converted_measurements,
    filterpy_imm,
    raw_plots,
    stonesoup_cv,
)
from benchmarks.profiles import PROFILES
from benchmarks.simulate import simulate
from benchmarks.truth import Truth, load_truth
from solver.inputs import Plots, Radar

RADAR = Radar(range_error_m=300.0, azimuth_error_rad=0.009, range_sigma_m=100.0,
              azimuth_sigma_rad=0.003)


def _reference_kf_rts(t, z, R, x0, P0, q):
    """Textbook KF + RTS on (x, vx, z, vz), explicit matrices."""
    n = len(t)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    xs, Ps, xp, Pp, Fs = [], [], [], [], []
    x, P = x0.copy(), P0.copy()
    for i in range(n):
        if i > 0:
            dt = t[i] - t[i - 1]
            F1 = np.array([[1, dt], [0, 1]])
            Q1 = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
            F = np.kron(np.eye(2), F1)
            Q = np.kron(np.eye(2), Q1)
            x, P = F @ x, F @ P @ F.T + Q
            Fs.append(F)
        xp.append(x)
        Pp.append(P)
        S = H @ P @ H.T + R[i]
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ (z[i] - H @ x)
        P = (np.eye(4) - K @ H) @ P
        xs.append(x)
        Ps.append(P)
    sx, sP = [xs[-1]], [Ps[-1]]
    for i in range(n - 2, -1, -1):
        G = Ps[i] @ Fs[i].T @ np.linalg.inv(Pp[i + 1])
        sx.insert(0, xs[i] + G @ (sx[0] - xp[i + 1]))
        sP.insert(0, Ps[i] + G @ (sP[0] - Pp[i + 1]) @ G.T)
    return np.array(xs), np.array(Ps), np.array(sx), np.array(sP)


def test_converted_covariance_is_the_polar_jacobian_transform():
    plots = Plots.from_arrays([0.0, 5.0], [50e3, 80e3], [0.3, 4.0])
    z, R = converted_measurements(plots, RADAR)
    for i in range(2):
        r, psi = plots.range_m[i], plots.azimuth_rad[i]
        J = np.array([[np.cos(psi), -r * np.sin(psi)], [np.sin(psi), r * np.cos(psi)]])
        np.testing.assert_allclose(R[i], J @ np.diag([100.0**2, 0.003**2]) @ J.T, atol=1e-6)
        np.testing.assert_allclose(z[i], [r * np.cos(psi), r * np.sin(psi)])


def test_stonesoup_filter_and_smoother_match_the_explicit_reference():
    sim = simulate(load_truth("calibration__vienna"), PROFILES["seed000"], 2, t_max=600.0)
    plots, radar = sim.plots, PROFILES["seed000"].radar()
    z, R = converted_measurements(plots, radar)
    x0 = np.array([z[0, 0], 0.0, z[0, 1], 0.0])
    P0 = np.diag([1e10, 9e4, 1e10, 9e4])  # the baseline's diffuse prior (1e5 m, 300 m/s)
    fx, fP, sx, sP = _reference_kf_rts(plots.t, z, R, x0, P0, 30.0)
    kf = stonesoup_cv(plots, radar, q=30.0, smooth=False)
    rts = stonesoup_cv(plots, radar, q=30.0, smooth=True)
    np.testing.assert_allclose(kf.x, fx[:, 0], atol=1e-4)
    np.testing.assert_allclose(kf.vz, fx[:, 3], atol=1e-6)
    np.testing.assert_allclose(kf.cov[:, 1, 1], fP[:, 2, 2], rtol=1e-6)
    np.testing.assert_allclose(rts.z, sx[:, 2], atol=1e-4)
    np.testing.assert_allclose(rts.vx, sx[:, 1], atol=1e-6)
    np.testing.assert_allclose(rts.cov[:, 0, 0], sP[:, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(rts.cov[:, 1, 3], sP[:, 2, 3], rtol=1e-5, atol=1e-6)


def test_smoother_beats_raw_plots_on_a_straight_track():
    t = np.arange(0.0, 801.0, 1.0)
    line = Truth("line", t, 40e3 + 120.0 * t, 30e3 - 160.0 * t, np.zeros(t.size),
                 np.full(t.size, 120.0), np.full(t.size, -160.0))
    sim = simulate(line, PROFILES["seed001"], 0)
    radar = PROFILES["seed001"].radar()
    raw = raw_plots(sim.plots, radar)
    rts = stonesoup_cv(sim.plots, radar, q=1.0)
    e_raw = np.hypot(raw.x - sim.truth.x, raw.z - sim.truth.z)
    e_rts = np.hypot(rts.x - sim.truth.x, rts.z - sim.truth.z)
    assert np.sqrt(np.mean(e_rts**2)) < 0.6 * np.sqrt(np.mean(e_raw**2))


def _circle_truth(v=150.0, radius=5000.0, duration=900.0):
    t = np.arange(0.0, duration + 1, 1.0)
    om = v / radius
    cx, cz = 60e3, 20e3
    return Truth("circle", t, cx + radius * np.sin(om * t), cz + radius * (1 - np.cos(om * t)),
                 np.zeros(t.size), v * np.cos(om * t), v * np.sin(om * t))


def test_imm_follows_a_steady_turn_better_than_a_stiff_cv_filter():
    tr = _circle_truth()
    prof = PROFILES["ssr"]
    sim = simulate(tr, prof, 0)
    radar = prof.radar()
    imm = filterpy_imm(sim.plots, radar, ImmTuning(q_cv=0.1, q_ct=0.1, q_omega=1e-6))
    cv = stonesoup_cv(sim.plots, radar, q=0.1, smooth=False)
    late = sim.truth.t > 200
    e_imm = np.hypot(imm.x - sim.truth.x, imm.z - sim.truth.z)[late]
    e_cv = np.hypot(cv.x - sim.truth.x, cv.z - sim.truth.z)[late]
    raw = raw_plots(sim.plots, radar)
    e_raw = np.hypot(raw.x - sim.truth.x, raw.z - sim.truth.z)[late]
    assert np.sqrt(np.mean(e_imm**2)) < 0.5 * np.sqrt(np.mean(e_cv**2))
    assert np.sqrt(np.mean(e_imm**2)) < 0.75 * np.sqrt(np.mean(e_raw**2))


def test_baselines_return_one_state_per_plot_with_covariance():
    sim = simulate(load_truth("calibration__bornholm"), PROFILES["ssr"], 0, t_max=120.0)
    radar = PROFILES["ssr"].radar()
    for est in (stonesoup_cv(sim.plots, radar), filterpy_imm(sim.plots, radar)):
        assert len(est) == len(sim.plots)
        np.testing.assert_array_equal(est.t, sim.plots.t)
        assert est.cov is not None and est.cov.shape == (len(sim.plots), 4, 4)
        assert np.all(np.linalg.eigvalsh(est.cov[:, :2, :2]) > 0)


@pytest.mark.parametrize("with_alt", [False, True])
def test_converted_measurement_uses_ground_range_when_altitude_known(with_alt):
    plots = Plots.from_arrays([0.0], [10e3], [0.0], [6e3] if with_alt else None)
    z, _ = converted_measurements(plots, RADAR)
    assert z[0, 0] == pytest.approx(8e3 if with_alt else 10e3)
