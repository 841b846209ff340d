"""Seed 004's fusion variants A/B/C (spec filters.md section 4) against hand-worked cases, and the
paper's ordering on a simulated seed-004 setting beside the asynchronous Kalman filter."""

from __future__ import annotations

import numpy as np
import pytest

from solver import Plots, Radar
from solver.estimation import FUSION_NAMES, run_filter
from solver.frames import LocalFrame
from solver.plots import PlotTable
from solver.sensors import PositionSensor

FRAME = LocalFrame(46.0, 14.8)


def two_sources(t1, p1, s1, t2, p2, s2):
    """A table of two position sensors ("fine" sigma s1, "coarse" s2) with plane positions
    ``p (n, 2)``, rows: source 2 first (so table order differs from time order)."""
    lat1, lon1 = FRAME.to_geodetic(p1[:, 0], p1[:, 1])
    lat2, lon2 = FRAME.to_geodetic(p2[:, 0], p2[:, 1])
    sensors = (PositionSensor("fine", s1), PositionSensor("coarse", s2))
    return PlotTable.build(sensors, np.concatenate([t2, t1]),
                           ["coarse"] * len(t2) + ["fine"] * len(t1),
                           lat_deg=np.concatenate([lat2, lat1]),
                           lon_deg=np.concatenate([lon2, lon1]), reference=FRAME)


def plane(table):
    """The plots' plane positions (the sensors' projection, not the code under test)."""
    x, z = FRAME.to_plane(table.lat_deg, table.lon_deg)
    return np.column_stack([x, z])


def alpha_beta(tau, y, k_max):
    """The spec's capped growing-memory alpha-beta, written out: ``x = y``, ``v = 0`` at step 0,
    then ``alpha = 2(2k+1)/((k+1)(k+2))``, ``beta = 6/((k+1)(k+2))``, ``k <= k_max``."""
    x, v = [np.array(y[0], float)], [np.zeros(2)]
    for k in range(1, len(tau)):
        kk = min(k, k_max)
        a, b = 2 * (2 * kk + 1) / ((kk + 1) * (kk + 2)), 6 / ((kk + 1) * (kk + 2))
        T = tau[k] - tau[k - 1]
        xp = x[-1] + v[-1] * T
        r = y[k] - xp
        x.append(xp + a * r)
        v.append(v[-1] + b / T * r)
    return np.array(x), np.array(v)


# a small case: the fine source at 0, 3, 6 s, the coarse one at 1, 2, 4, 5, 6, 7 s
T1 = np.array([0.0, 3.0, 6.0])
T2 = np.array([1.0, 2.0, 4.0, 5.0, 6.0, 7.0])
P1 = np.array([[1000.0, 2000.0], [1620.0, 2290.0], [2190.0, 2610.0]])
P2 = np.array([[1180.0, 2150.0], [1430.0, 2160.0], [1790.0, 2420.0], [2050.0, 2440.0],
               [2240.0, 2580.0], [2400.0, 2700.0]])
S1, S2 = 10.0, 40.0


def small_case():
    table = two_sources(T1, P1, S1, T2, P2, S2)
    y = plane(table)
    coarse, fine = y[: len(T2)], y[len(T2):]
    return table, fine, coarse


def predicted(table, tau, x, v, first_plots):
    """At every row: the last step at or before its time predicted to it; before the first
    step, the plot itself (``first_plots``: positions of those rows)."""
    j = np.searchsorted(tau, table.t, side="right") - 1
    jj = np.maximum(j, 0)
    pos = x[jj] + v[jj] * (table.t - tau[jj])[:, None]
    pos[j < 0] = first_plots[j < 0]
    vel = np.where((j < 0)[:, None], 0.0, v[jj])
    return pos, vel


def test_fusion_a_by_hand():
    table, y1, y2 = small_case()
    c1, c2 = 40 / 50, 10 / 50  # sigma_2 / (sigma_1 + sigma_2), sigma_1 / (sigma_1 + sigma_2)
    # steps at the faster (coarse, 1 s) source's plots; each source's latest value held
    tau = T2
    y = np.array([c1 * y1[0] + c2 * y2[0], c1 * y1[0] + c2 * y2[1], c1 * y1[1] + c2 * y2[2],
                  c1 * y1[1] + c2 * y2[3], c1 * y1[2] + c2 * y2[4], c1 * y1[2] + c2 * y2[5]])
    x, v = alpha_beta(tau, y, k_max=4)
    est = run_filter("fusion_a", table).states
    t_rows = table.t
    pos, vel = predicted(table, tau, x, v, plane(table))
    np.testing.assert_allclose(est.t, t_rows)
    np.testing.assert_allclose(np.column_stack([est.x, est.z]), pos, atol=1e-6)
    np.testing.assert_allclose(np.column_stack([est.vx, est.vz]), vel, atol=1e-9)
    # covariance: the fine plot at 0 s before the first step; the first step: the fused
    # variance c1^2 s1^2 + c2^2 s2^2 = 64 + 64 on the position
    row0 = int(np.flatnonzero(t_rows == 0.0)[0])
    row1 = int(np.flatnonzero(t_rows == 1.0)[0])
    # the velocity's start spread, 300 m/s on the ground: the plane's scale times it
    k = float(np.asarray(table.frame.scale(est.x[row0], est.z[row0])))
    assert est.cov[row0, 0, 0] == pytest.approx(S1**2)
    assert est.cov[row0, 2, 2] == pytest.approx((300.0 * k) ** 2, rel=1e-6) and k > 1.0
    assert est.cov[row1, 0, 0] == pytest.approx(128.0)
    assert est.cov[row1, 1, 1] == pytest.approx(128.0)


def test_fusion_b_by_hand():
    table, y1, y2 = small_case()
    # median update periods T1 = 3 s, T2 = 1 s; c1 = s2 T2 / (s1 T1 + s2 T2) = 40 / 70
    c1, c2 = 40 / 70, 30 / 70
    tau = T2
    y = np.array([c1 * y1[0] + c2 * y2[0], c1 * y1[0] + c2 * y2[1], c1 * y1[1] + c2 * y2[2],
                  c1 * y1[1] + c2 * y2[3], c1 * y1[2] + c2 * y2[4], c1 * y1[2] + c2 * y2[5]])
    x, v = alpha_beta(tau, y, k_max=2)  # a capped memory: steps 2.. use k = 2's gains
    est = run_filter("fusion_b", table, k_max=2).states
    pos, vel = predicted(table, tau, x, v, plane(table))
    np.testing.assert_allclose(np.column_stack([est.x, est.z]), pos, atol=1e-6)
    np.testing.assert_allclose(np.column_stack([est.vx, est.vz]), vel, atol=1e-9)


def test_fusion_c_by_hand():
    table, y1, y2 = small_case()
    c1, c2 = 40 / 50, 10 / 50
    # steps at the fine source's plots only: 0 (no coarse value yet), 3 (coarse fresh: t = 2),
    # 6 (coarse fresh: t = 6, the same instant)
    tau = T1
    y = np.array([y1[0], c1 * y1[1] + c2 * y2[1], c1 * y1[2] + c2 * y2[4]])
    x, v = alpha_beta(tau, y, k_max=4)
    est = run_filter("fusion_c", table).states
    got = np.column_stack([est.x, est.z])
    # coarse-only instants: the last step predicted, x + v (t - t_step)
    for row, t in enumerate(table.t):
        j = np.searchsorted(tau, t, side="right") - 1
        np.testing.assert_allclose(got[row], x[j] + v[j] * (t - tau[j]), atol=1e-6)
        np.testing.assert_allclose([est.vx[row], est.vz[row]], v[j], atol=1e-9)
    # the fine source alone would give a different answer (the coarse values do enter)
    x_alone, _ = alpha_beta(tau, y1, k_max=4)
    assert np.max(np.abs(x_alone[1:] - x[1:])) > 10


def test_fusion_c_skips_a_stale_coarse_source():
    """The coarse source stops at the fine source's first plot (same instant): fresh there,
    stale afterwards, so C is then the fine source alone; before the first fine plot C returns
    the coarse plot itself with an unknown velocity."""
    t1, t2 = np.array([10.0, 20.0, 30.0]), np.array([0.0, 5.0, 10.0])
    p1 = np.array([[0.0, 0.0], [2000.0, 100.0], [4000.0, 250.0]])
    p2 = np.array([[-2000.0, -100.0], [-900.0, 0.0], [60.0, -40.0]])
    table = two_sources(t1, p1, 5.0, t2, p2, 50.0)
    y = plane(table)  # rows: coarse 0, 5, 10 s, then fine 10, 20, 30 s
    est = run_filter("fusion_c", table).states
    c1, c2 = 50 / 55, 5 / 55
    x, _ = alpha_beta(t1, np.array([c1 * y[3] + c2 * y[2], y[4], y[5]]), k_max=4)
    got = np.column_stack([est.x, est.z])
    np.testing.assert_allclose(got[3:], x, atol=1e-6)
    np.testing.assert_allclose(got[2], x[0], atol=1e-6)  # the coarse plot at the first step
    np.testing.assert_allclose(got[:2], y[:2], atol=1e-9)
    k = float(np.asarray(table.frame.scale(est.x[0], est.z[0])))  # as in fusion_a
    assert est.cov[0, 0, 0] == pytest.approx(50.0**2)
    assert est.cov[0, 2, 2] == pytest.approx((300.0 * k) ** 2, rel=1e-6) and k > 1.0


@pytest.mark.parametrize("name", FUSION_NAMES)
def test_fusion_needs_exactly_two_sources(name):
    table, _, _ = small_case()
    three = PlotTable.build((*table.sensors, PositionSensor("third", 20.0)),
                            np.append(table.t, 9.0), [*(table.sensors[k].id
                                                        for k in table.sensor), "third"],
                            lat_deg=np.append(table.lat_deg, 46.01),
                            lon_deg=np.append(table.lon_deg, 14.81), reference=FRAME)
    with pytest.raises(ValueError, match=r"exactly two sources.*3 sensors"):
        run_filter(name, three)
    plots = Plots.from_arrays([0.0, 10.0], [50_000.0, 51_000.0], [0.1, 0.1])
    with pytest.raises(ValueError, match=r"exactly two sources.*1 sensor"):
        run_filter(name, plots, Radar(300.0, 0.01))
    with pytest.raises(ValueError, match="k_max"):
        run_filter(name, table, k_max=0)


def seed004(seed, sigma2=75.0, age=0.05, dur=600.0):
    """Seed 004's setting: an accurate slow source (sigma 50 m per axis every 10 s) and a coarse
    one ten times faster (``sigma2`` every 1 s, reporting ``age`` s before each accurate plot),
    a straight flight at 200 m/s."""
    rng = np.random.default_rng(seed)
    t1 = np.arange(0.0, dur, 10.0)
    t2 = np.arange(1.0 - age, dur, 1.0)

    def truth(t):
        return np.column_stack([10_000 + 173.2 * t, -5000 + 100.0 * t])

    p1 = truth(t1) + rng.normal(0, 50.0, (t1.size, 2))
    p2 = truth(t2) + rng.normal(0, sigma2, (t2.size, 2))
    return two_sources(t1, p1, 50.0, t2, p2, sigma2), truth


def seed004_rms(seeds, **setting):
    """RMS position errors at the accurate source's plots after 30 s (C's steps): the fusion
    variants, ``cv_rts`` (smoother), ``kf`` (its filter), each source alone (the same
    alpha-beta on that source, predicted to the accurate plots' times) and the Kalman filter
    on the accurate source alone."""
    err: dict[str, list[np.ndarray]] = {}
    for seed in seeds:
        table, truth = seed004(seed, **setting)
        fine = (table.sensor == 0) & (table.t > 30)
        y = plane(table)
        p = truth(table.t)
        for name in (*FUSION_NAMES, "cv_rts"):
            e = run_filter(name, table).states
            err.setdefault(name, []).append(np.hypot(e.x - p[:, 0], e.z - p[:, 1])[fine])
        e = run_filter("cv_rts", table, smooth=False).states
        err.setdefault("kf", []).append(np.hypot(e.x - p[:, 0], e.z - p[:, 1])[fine])
        rows = np.flatnonzero(table.sensor == 0)
        alone = PlotTable.build(table.sensors[:1], table.t[rows], np.zeros(rows.size, int),
                                lat_deg=table.lat_deg[rows], lon_deg=table.lon_deg[rows],
                                reference=FRAME)
        e = run_filter("cv_rts", alone, smooth=False).states
        err.setdefault("kf fine alone", []).append(
            np.hypot(e.x - p[rows, 0], e.z - p[rows, 1])[table.t[rows] > 30])
        for j, name in ((0, "fine alone"), (1, "coarse alone")):
            rows = np.flatnonzero(table.sensor == j)
            x, v = alpha_beta(table.t[rows], y[rows], k_max=4)
            last = np.searchsorted(table.t[rows], table.t[fine], side="right") - 1
            at = x[last] + v[last] * (table.t[fine] - table.t[rows][last])[:, None]
            err.setdefault(name, []).append(np.hypot(*(at - p[fine]).T))
    return {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in err.items()}


def test_seed004_ordering():
    """The paper's ordering: C better than either source alone, A worse than the accurate one.
    The asynchronous Kalman filter (cv_rts, smooth=False) beats A/B by far; its smoother beats
    everything."""
    rms = seed004_rms(range(6))
    assert rms["fusion_c"] < 0.97 * min(rms["fine alone"], rms["coarse alone"]), rms
    assert rms["fusion_a"] > 2 * rms["fine alone"], rms
    assert rms["kf"] < 0.5 * min(rms["fusion_a"], rms["fusion_b"]), rms
    assert rms["kf"] < 0.97 * rms["kf fine alone"], rms
    assert rms["cv_rts"] < 0.8 * min(v for k, v in rms.items() if k != "cv_rts"), rms


@pytest.mark.parametrize("setting", [{"sigma2": 500.0}, {"age": 0.95}])
def test_seed004_ordering_needs_a_close_fresh_coarse_source(setting):
    """The 1/sigma weights help only where sigma_2 < (1 + sqrt 2) sigma_1 (the fused value's
    variance is 2 s1^2 s2^2 / (s1 + s2)^2) and the coarse value is fresh: a coarse source ten
    times worse, or values 0.95 s old (190 m at 200 m/s), make C worse than the accurate source
    alone, as the paper's weights imply (1/sigma^2 weights would not); for the asynchronous
    Kalman filter the second source helps in both settings (against the same filter on the
    accurate source alone)."""
    rms = seed004_rms(range(3), **setting)
    assert rms["fusion_c"] > 1.05 * rms["fine alone"], rms
    assert rms["kf"] < 0.99 * rms["kf fine alone"], rms  # paired: the same source-1 noise
