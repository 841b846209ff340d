"""Every filter on several sensors (issue 15): the legacy single flat radar unchanged, the
measurement set, the asynchronous Kalman update in closed form, two radars + ADS-B."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from solver import Plots, Radar
from solver.estimation import SINGLE_SENSOR_NAMES, imm_step, kalman, run_filter
from solver.estimation.cv_rts import run_cv_rts
from solver.estimation.fuzzy import kalman_gains, steady_gain
from solver.estimation.measurements import SensorPlots, borrowed_altitude
from solver.estimation.models import quasi_optimal, singer
from solver.frames import LocalFrame
from solver.geometry import weight_entries
from solver.plots import PlotTable
from solver.sensors import PositionSensor, RadarSensor, Site

REFERENCE = Path(__file__).with_name("test_estimation_multisensor_reference.npz")
LEGACY_RADAR = Radar(1200.0, 0.03, range_sigma_m=400.0, azimuth_sigma_rad=0.01)
# name, params: the defaults and the non-default measurement / frame / order paths
LEGACY_RUNS: list[tuple[str, dict]] = [
    ("singer", {}), ("singer", {"measurement": "converted"}), ("singer", {"frame": "polar"}),
    ("quasi_optimal", {}), ("quasi_optimal", {"lam": "auto"}),
    ("quasi_optimal", {"discretisation": "taylor"}), ("fuzzy", {}),
    ("fuzzy", {"n_terms": 5, "shape": "gaussian"}), ("alpha_beta", {}),
    ("alpha_beta", {"order": 3, "k_max": 6}), ("cv_rts", {}),
    ("cv_rts", {"measurement": "converted", "smooth": False}), ("imm", {}),
    ("imm", {"measurement": "converted"}),
]


def legacy_cases() -> dict[str, Plots]:
    """Two seeded single-radar tracks: a turn with irregular steps and Mode C on some plots,
    and a straight pass across azimuth 0 / 2 pi."""
    rng = np.random.default_rng(15)
    n = 30
    t = np.cumsum(rng.choice([4.0, 4.0, 8.0, 12.0], n))
    heading = np.deg2rad(60.0) + np.where(t > 60, np.minimum(t - 60, 60) * np.deg2rad(1.5), 0)
    dt = np.diff(t, prepend=t[0])
    x = -70_000 + np.cumsum(180 * np.cos(heading) * dt)
    z = 20_000 + np.cumsum(180 * np.sin(heading) * dt)
    h = np.where(rng.random(n) < 0.5, 7000.0, np.nan)
    r = np.sqrt(x**2 + z**2 + np.nan_to_num(h) ** 2) + rng.normal(0, 400, n)
    psi = np.arctan2(z, x) + rng.normal(0, 0.01, n)
    turn = Plots.from_arrays(t, r, psi, h)
    t2 = 10.0 * np.arange(20)
    x2, z2 = np.full(20, 60_000.0), -5000 + 180 * t2
    north = Plots.from_arrays(t2, np.hypot(x2, z2) + rng.normal(0, 400, 20),
                              np.arctan2(z2, x2) + rng.normal(0, 0.01, 20))
    return {"turn": turn, "north": north}


def _key(case: str, name: str, params: dict) -> str:
    return "|".join([case, name, *(f"{k}={v}" for k, v in sorted(params.items()))])


@pytest.mark.parametrize("iterated", [False, True], ids=["single-ekf-update", "iterated"])
@pytest.mark.parametrize("case", ["turn", "north"])
def test_legacy_single_radar_is_unchanged(case, iterated, monkeypatch):
    """``(plots, radar)`` gives the numbers of the code before several sensors (stored), to
    1e-12 of each array's scale: their last bits move with the CPU (numpy and OpenBLAS pick
    their SIMD kernels at run time: on an AVX-512 machine they differ by up to 1e-10 m from
    the stored AVX2 ones, 2e-15 of the scale); and the same plots as a legacy PlotTable the
    same to rounding. The stored numbers are the single EKF update's: the iterated update
    (``measurements.LINEARISATION_TOLERANCE``, which came later) is held to one pass for
    them; iterated, the runs without a polar EKF update give them as before (those with one
    differ where the update iterated: on ``north`` the first plots, whose velocity is
    unknown), and the table and the plots agree."""
    if not iterated:
        monkeypatch.setattr(kalman, "MAX_LINEARISATIONS", 1)
        monkeypatch.setattr(imm_step, "MAX_LINEARISATIONS", 1)
    ref = np.load(REFERENCE)
    plots = legacy_cases()[case]
    table = PlotTable.from_plots(plots, LEGACY_RADAR)
    assert table.is_legacy
    for name, params in LEGACY_RUNS:
        key = _key(case, name, params)
        est = run_filter(name, plots, LEGACY_RADAR, **params).states
        ekf = (name in ("singer", "cv_rts", "imm") and params.get("frame") != "polar"
               and params.get("measurement", "ekf") == "ekf")
        for got, want in ((est.states, ref[key + "|states"]), (est.cov, ref[key + "|cov"])):
            if not (iterated and ekf):
                np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max(),
                                           err_msg=key)
        via_table = run_filter(name, table, **params).states
        np.testing.assert_allclose(via_table.states, est.states, rtol=0, atol=1e-6,
                                   err_msg=key)
        np.testing.assert_allclose(via_table.cov, est.cov, rtol=1e-9, atol=1e-9, err_msg=key)


# --- several sensors ------------------------------------------------------------------------

FRAME = LocalFrame(46.0, 14.8)
PSR = RadarSensor(450.0, np.deg2rad(0.6), id="PSR", site=Site(46.22, 14.46, 380.0))
SSR = RadarSensor(150.0, np.deg2rad(0.24), id="SSR", site=Site(45.7, 15.2, 900.0))
ADSB = PositionSensor("ADSB", 30.0)


def truth(t):
    """200 m/s from heading 60 deg, a 90 deg right turn (1.2 deg/s) from 100 to 175 s."""
    t = np.asarray(t, float)
    v, w, h0 = 200.0, np.deg2rad(1.2), np.deg2rad(60.0)
    before, s, after = np.minimum(t, 100), np.clip(t - 100, 0, 75), np.maximum(t - 175, 0)
    h1 = h0 + w * 75
    x = (-40_000 + v * np.cos(h0) * before + v / w * (np.sin(h0 + w * s) - np.sin(h0))
         + v * np.cos(h1) * after)
    z = (-30_000 + v * np.sin(h0) * before - v / w * (np.cos(h0 + w * s) - np.cos(h0))
         + v * np.sin(h1) * after)
    return x, z


def simulate(sensors=(PSR, SSR, ADSB), seed=0, dur=300.0):
    """Plots of the sensors through the curved earth (aircraft at 10 km, Mode C on every radar
    plot), rows grouped by sensor (not in time order). The PSR turns every 10 s, the SSR every
    4 s on even seconds, ADS-B every 2 s with a gap from 120 to 200 s: SSR and ADS-B share
    instants."""
    rng = np.random.default_rng(seed)
    cols: dict[str, list] = {k: [] for k in ("t", "s", "r", "a", "lat", "lon", "h")}
    for s in sensors:
        if s is PSR:
            t = np.arange(0.3, dur, 10.0)
        elif s is SSR:
            t = np.arange(2.0, dur, 4.0)
        else:
            t = np.arange(0.0, dur, 2.0)
            t = t[(t < 120) | (t > 200)]
        x, z = truth(t)
        h = np.full(t.size, 10_000.0)
        nan = np.full(t.size, np.nan)
        if isinstance(s, RadarSensor):
            r, a = s.measure(FRAME, x, z, h)
            cols["r"].append(r + rng.normal(0, s.sigma_r, t.size))
            cols["a"].append(a + rng.normal(0, s.sigma_psi, t.size))
            cols["lat"].append(nan)
            cols["lon"].append(nan)
        else:
            lat, lon = FRAME.to_geodetic(x + rng.normal(0, 30, t.size),
                                         z + rng.normal(0, 30, t.size))
            cols["lat"].append(lat)
            cols["lon"].append(lon)
            cols["r"].append(nan)
            cols["a"].append(nan)
        cols["t"].append(t)
        cols["s"].append([s.id] * t.size)
        cols["h"].append(h)
    c = {k: np.concatenate(v) for k, v in cols.items()}
    return PlotTable.build(sensors, c["t"], c["s"], c["r"], c["a"], c["lat"], c["lon"], c["h"],
                           reference=FRAME)


def test_sensor_plots_are_the_table_in_time_order():
    table = simulate()
    meas = SensorPlots.from_table(table)
    assert np.all(np.diff(meas.t) >= 0) and np.any(np.diff(meas.t) == 0)
    np.testing.assert_array_equal(np.sort(meas.rows), np.arange(len(table)))
    np.testing.assert_array_equal(meas.t, table.t[meas.rows])
    assert not meas.polar.any()  # a geodetic frame: every plot is a fix
    ell = table.fixes().ellipses
    np.testing.assert_array_equal(meas.centre, np.column_stack([ell.cx, ell.cz])[meas.rows])
    # R is the inverse of the ellipse's weight matrix M (solver.geometry)
    a, b, c = weight_entries(ell.psi, ell.A, ell.B).T
    M = np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)[meas.rows]
    np.testing.assert_allclose(meas.cov @ M, np.broadcast_to(np.eye(2), M.shape), atol=1e-9)
    last = meas.same_instant()
    assert np.all(meas.t[last] == meas.t) and np.all(np.diff(last) >= 0)
    assert np.all((last == len(meas) - 1) | (meas.t[np.minimum(last + 1, len(meas) - 1)]
                                             > meas.t))


def combined_table(sigma1=30.0, sigma2=60.0, seed=3):
    """Two ADS-B-like sensors reporting at the same instants, and one sensor carrying their
    inverse-variance combination ``(z1 / s1^2 + z2 / s2^2) / (1 / s1^2 + 1 / s2^2)`` with sigma
    ``s1 s2 / sqrt(s1^2 + s2^2)``."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.choice([1.0, 2.0, 5.0], 40))
    x, z = truth(t)
    p1 = np.column_stack([x, z]) + rng.normal(0, sigma1, (t.size, 2))
    p2 = np.column_stack([x, z]) + rng.normal(0, sigma2, (t.size, 2))
    w1, w2 = 1 / sigma1**2, 1 / sigma2**2
    pc = (w1 * p1 + w2 * p2) / (w1 + w2)
    geo = [FRAME.to_geodetic(p[:, 0], p[:, 1]) for p in (p1, p2, pc)]
    a, b = PositionSensor("a", sigma1), PositionSensor("b", sigma2)
    # rows: b's plots first, then a's (a's come first in time order at each instant)
    pair = PlotTable.build((a, b), np.concatenate([t, t]), np.repeat([1, 0], t.size),
                           lat_deg=np.concatenate([geo[1][0], geo[0][0]]),
                           lon_deg=np.concatenate([geo[1][1], geo[0][1]]), reference=FRAME)
    one = PlotTable.build((PositionSensor("c", 1 / np.sqrt(w1 + w2)),), t, np.zeros(t.size, int),
                          lat_deg=geo[2][0], lon_deg=geo[2][1], reference=FRAME)
    return pair, one, p1, p2


@pytest.mark.parametrize(("name", "params"), [("cv_rts", {}), ("cv_rts", {"smooth": False}),
                                              ("singer", {})])
def test_two_sensors_at_one_instant_equal_one_combined_update(name, params):
    """Sequential updates after a zero-length step = one update with the inverse-variance
    combined measurement (linear Kalman filter, exact): filter and smoother."""
    pair, one, p1, p2 = combined_table()
    n = len(one)
    est = run_filter(name, pair, **params).states
    ref = run_filter(name, one, **params).states
    for half in (slice(0, n), slice(n, 2 * n)):  # both rows of an instant: the same state
        np.testing.assert_allclose(est.states[half], ref.states, rtol=0, atol=1e-5)
        np.testing.assert_allclose(est.cov[half], ref.cov, rtol=1e-7, atol=1e-7)
    # the first instant in closed form: prior = plot a (velocity unknown), then plot b
    # the sensors' sigmas in plane metres: times the plane's scale at the plot
    k1, k2 = (float(np.asarray(FRAME.scale(*p[0]))) for p in (p1, p2))
    R1, R2 = (30.0 * k1) ** 2 * np.eye(2), (60.0 * k2) ** 2 * np.eye(2)
    P = np.linalg.inv(np.linalg.inv(R1) + np.linalg.inv(R2))
    x = P @ (np.linalg.solve(R1, p1[0]) + np.linalg.solve(R2, p2[0]))
    if not params.get("smooth", True) or name == "singer":
        np.testing.assert_allclose([est.x[n], est.z[n]], x, atol=1e-6)
        np.testing.assert_allclose(est.cov[n, :2, :2], P, rtol=1e-9)


def test_sequential_fix_updates_with_full_covariances():
    """The same identity with correlated 2x2 covariances, on the measurement set directly."""
    rng = np.random.default_rng(5)
    n = 25
    t = np.cumsum(rng.uniform(1, 6, n))
    L = rng.normal(0, 40, (2, n, 2, 2))
    R = L @ np.swapaxes(L, -1, -2) + 100 * np.eye(2)
    x, z = truth(t)
    y = np.column_stack([x, z]) + rng.normal(0, 50, (2, n, 2))
    Ri = np.linalg.inv(R)
    Rc = np.linalg.inv(Ri[0] + Ri[1])
    yc = np.einsum("nij,nj->ni", Rc, np.einsum("knij,knj->ni", Ri, y))

    def fixes(tt, yy, RR, sensor, n_sensors):
        m = tt.size
        nan = np.full(m, np.nan)
        return SensorPlots(t=tt, rows=np.arange(m), sensor=sensor, n_sensors=n_sensors,
                           polar=np.zeros(m, bool), d=nan, sigma_d=nan, psi=nan, sigma_psi=nan,
                           centre=yy, cov=RR)

    pair = fixes(np.repeat(t, 2), y.transpose(1, 0, 2).reshape(-1, 2),
                 R.transpose(1, 0, 2, 3).reshape(-1, 2, 2), np.tile([0, 1], n), 2)
    one = fixes(t, yc, Rc, np.zeros(n, int), 1)
    a, b = run_cv_rts(pair), run_cv_rts(one)
    np.testing.assert_allclose(a.states.states[1::2], b.states.states, atol=1e-5)
    np.testing.assert_allclose(a.states.cov[1::2], b.states.cov, rtol=1e-7, atol=1e-6)


def test_every_filter_runs_on_two_radars_and_adsb_and_beats_the_single_radar():
    table = simulate()
    alone = simulate((PSR,))
    x, z = truth(table.t)
    xa, za = truth(alone.t)
    psr = table.sensor == 0
    tied = np.flatnonzero(np.isin(table.t, table.t[table.sensor == 2])
                          & (table.sensor == 1))
    assert tied.size > 20
    for name in SINGLE_SENSOR_NAMES:
        est = run_filter(name, table)
        s = est.states
        assert "warning" not in est.info, name
        assert np.all(np.isfinite(s.states)) and np.all(np.isfinite(s.cov)), name
        assert np.all(np.linalg.eigvalsh(s.cov) > 0), name
        np.testing.assert_array_equal(s.t, table.t)
        # plots at one instant (SSR and ADS-B) get the same state
        adsb = [int(np.flatnonzero((table.t == table.t[i]) & (table.sensor == 2))[0])
                for i in tied]
        np.testing.assert_array_equal(s.states[tied], s.states[adsb])
        fused = np.sqrt(np.mean(np.hypot(s.x - x, s.z - z)[psr] ** 2))
        single = run_filter(name, alone).states
        one = np.sqrt(np.mean(np.hypot(single.x - xa, single.z - za) ** 2))
        assert fused < 0.6 * one, (name, fused, one)


def test_two_flat_radars_at_the_origin_are_the_single_radar_model():
    """Two radars at the origin of a flat plane (no frame): polar updates as the legacy radar;
    with equal accuracies the Cartesian filters give exactly the single radar's answer on the
    union of their plots (rows interleaved differently)."""
    plots = legacy_cases()["north"]
    n = len(plots)
    r1 = RadarSensor(1200.0, 0.03, range_sigma_m=400.0, azimuth_sigma_rad=0.01, id="one")
    r2 = RadarSensor(1200.0, 0.03, range_sigma_m=400.0, azimuth_sigma_rad=0.01, id="two")
    which = np.arange(n) % 2
    rows = np.concatenate([np.flatnonzero(which == 1), np.flatnonzero(which == 0)])
    table = PlotTable.build((r1, r2), plots.t[rows], which[rows], plots.range_m[rows],
                            plots.azimuth_rad[rows])
    assert table.frame is None and not table.is_legacy
    assert SensorPlots.from_table(table).polar.all()
    for name in ("singer", "cv_rts", "imm", "imm_smoother"):
        ref = run_filter(name, plots, LEGACY_RADAR).states
        est = run_filter(name, table).states
        np.testing.assert_allclose(est.states, ref.states[rows], rtol=0, atol=1e-6)
        np.testing.assert_allclose(est.cov, ref.cov[rows], rtol=1e-9, atol=1e-6)
    for name in SINGLE_SENSOR_NAMES:  # per-axis forms: finite and near the legacy answer
        est = run_filter(name, table).states
        ref = run_filter(name, plots, LEGACY_RADAR).states
        assert np.all(np.isfinite(est.cov))
        assert np.sqrt(np.mean((est.states[:, :2] - ref.states[rows, :2]) ** 2)) < 500, name


def test_alpha_beta_on_several_sensors_is_weighted_least_squares():
    """Each plot's estimate = numpy's weighted polynomial fit through every sensor's last
    ``k_max`` update periods (isotropic sensors: the 2-D fit separates per axis)."""
    rng = np.random.default_rng(8)
    t1 = np.cumsum(rng.uniform(4.0, 6.0, 30))
    t2 = np.cumsum(rng.uniform(0.8, 1.2, 150))
    t2 = t2[t2 < t1[-1]]
    s1, s2 = 20.0, 90.0
    pts = []
    for tt, s in ((t1, s1), (t2, s2)):
        x, z = truth(tt)
        pts.append(np.column_stack([x, z]) + rng.normal(0, s, (tt.size, 2)))
    geo = [FRAME.to_geodetic(p[:, 0], p[:, 1]) for p in pts]
    table = PlotTable.build((PositionSensor("fine", s1), PositionSensor("coarse", s2)),
                            np.concatenate([t1, t2]), np.repeat([0, 1], [t1.size, t2.size]),
                            lat_deg=np.concatenate([geo[0][0], geo[1][0]]),
                            lon_deg=np.concatenate([geo[0][1], geo[1][1]]), reference=FRAME)
    y = np.column_stack(FRAME.to_plane(table.lat_deg, table.lon_deg))
    # the sensors' sigmas in plane metres: times the plane's scale at the plot
    sig = np.where(table.sensor == 0, s1, s2) * np.asarray(FRAME.scale(y[:, 0], y[:, 1]))
    k_max = 4
    span = np.array([(k_max - 0.5) * np.median(np.diff(t1)),
                     (k_max - 0.5) * np.median(np.diff(t2))])
    for order in (2, 3):
        est = run_filter("alpha_beta", table, order=order, k_max=k_max).states
        for k in rng.choice(len(table), 40, replace=False):
            tau = table.t - table.t[k]
            win = (tau <= 0) & (tau > -span[table.sensor])
            if np.unique(tau[win]).size < order:
                continue
            for axis, (p, v) in enumerate([(est.x, est.vx), (est.z, est.vz)]):
                c = np.polynomial.polynomial.polyfit(tau[win], y[win, axis], order - 1,
                                                     w=1 / sig[win])
                assert p[k] == pytest.approx(c[0], abs=1e-5), (order, k)
                assert v[k] == pytest.approx(c[1], abs=1e-7), (order, k)


def test_fuzzy_gain_bounds_converge_to_the_steady_gains():
    """On one regular sensor the time-varying bounds approach the steady-state gains."""
    T, R = 5.0, 150.0**2
    Phi, Q = singer(np.full(60, T), 1 / 20, 2.0)
    P0 = np.diag([R, 300.0**2, 4.0])[None]
    K = kalman_gains(P0, Phi[:, None], Q[:, None], np.full((61, 1), R))
    np.testing.assert_allclose(K[-1, 0], steady_gain(Phi[:1], Q[:1], np.array([R]))[0],
                               rtol=1e-6)
    assert abs(K[2, 0, 0] - K[-1, 0, 0]) > 0.05  # not there at once: the test can fail


def test_bad_requests_on_several_sensors():
    table = simulate((PSR, ADSB), dur=60.0)
    with pytest.raises(ValueError, match="frame='cartesian'"):
        run_filter("singer", table, frame="polar")
    with pytest.raises(TypeError, match="inside the PlotTable"):
        run_filter("cv_rts", table, LEGACY_RADAR)
    with pytest.raises(TypeError, match="need their radar"):
        run_filter("cv_rts", legacy_cases()["north"])
    with pytest.raises(ValueError, match="measurement mode"):
        run_filter("cv_rts", table, measurement="ukf")


def test_taylor_discretisation_of_a_zero_step_is_still():
    Phi, Q = quasi_optimal(np.array([0.0, 5.0]), 1e-3, 0.01, 2000.0, "taylor")
    np.testing.assert_array_equal(Phi[0], np.eye(3))
    np.testing.assert_array_equal(Q[0], np.zeros((3, 3)))
    assert np.all(np.isfinite(Q[1])) and Q[1][0, 0] > 0


def without_radar_altitude(table):
    h = table.altitude_m.copy()
    h[table.radar_rows()] = np.nan
    return PlotTable.build(table.sensors, table.t, table.sensor, table.range_m,
                           table.azimuth_rad, table.lat_deg, table.lon_deg, h,
                           reference=table.frame)


def test_radar_plots_without_altitude_borrow_the_adsb_altitude():
    """Radar plots without Mode C beside ADS-B altitudes are placed at the interpolated ADS-B
    altitude: as accurate as with Mode C. Without any altitude in the table they stay at the
    site height, with the h^2 / 2r bias (~1 km here: 10 km high, ~50 km away)."""
    full = simulate()
    bare = without_radar_altitude(full)
    h = borrowed_altitude(bare)
    np.testing.assert_allclose(h, 10_000.0)  # constant here; interpolation below
    x, z = truth(full.t)
    for name in ("cv_rts", "singer"):
        a, b = run_filter(name, full).states, run_filter(name, bare).states
        rms_a = np.sqrt(np.mean(np.hypot(a.x - x, a.z - z) ** 2))
        rms_b = np.sqrt(np.mean(np.hypot(b.x - x, b.z - z) ** 2))
        assert rms_b < 1.1 * rms_a + 2.0, (name, rms_a, rms_b)
    radars = without_radar_altitude(simulate((PSR, SSR)))
    assert np.all(np.isnan(borrowed_altitude(radars)))
    s = run_filter("cv_rts", radars).states
    xr, zr = truth(radars.t)
    assert np.sqrt(np.mean(np.hypot(s.x - xr, s.z - zr) ** 2)) > 500  # the known limitation


def test_borrowed_altitude_interpolates_in_time():
    table = simulate((PSR, ADSB), dur=60.0)
    h = table.altitude_m.copy()
    adsb = np.flatnonzero(table.sensor == 1)
    h[adsb] = 9000.0 + 10.0 * table.t[adsb]  # climbing 10 m/s
    h[table.radar_rows()] = np.nan
    t2 = PlotTable.build(table.sensors, table.t, table.sensor, table.range_m, table.azimuth_rad,
                         table.lat_deg, table.lon_deg, h, reference=FRAME)
    got = borrowed_altitude(t2)
    np.testing.assert_allclose(got, 9000.0 + 10.0 * np.clip(table.t, 0.0, table.t[adsb].max()))
