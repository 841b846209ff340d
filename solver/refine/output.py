"""From the node solution to the answer: constant-control segments, states with covariances
at any times, and per-sensor statistics of the plots against the track."""

from __future__ import annotations

import math
from functools import cache

import casadi as ca
import numpy as np

from .. import compiled
from ..inputs import Bounds, FloatArray
from ..motion import propagate, propagate_ca
from ..plots import PlotTable
from ..results import PlotResiduals, Segment, SensorReport, StateSeries
from ..sensors import RadarSensor
from .covariance import NH
from .layout import BIAS_TERMS, Variant


def segments(t_nodes: FloatArray, sol: np.ndarray, bounds: Bounds) -> list[Segment]:
    """Merge node intervals whose controls agree (to 1e-6 of the bound range) into segments
    (zero-length intervals between plots at one instant never start a segment)."""
    n = t_nodes.size
    keep = np.append(np.diff(t_nodes) > 0, True) if n > 1 else np.ones(1, bool)
    idx = np.flatnonzero(keep)
    if idx[-1] != n - 1:
        idx = np.append(idx, n - 1)
    t_n, s_n = t_nodes[idx], sol[idx]
    m = t_n.size
    ctl = s_n[: m - 1, 4:6] if m > 1 else s_n[:, 4:6]
    tol = 1e-6 * np.array([bounds.u[1] - bounds.u[0], bounds.w[1] - bounds.w[0]])
    change = np.any(np.abs(np.diff(ctl, axis=0)) > tol, axis=1)
    starts = np.concatenate([[0], np.flatnonzero(change) + 1])
    ends = np.append(starts[1:], m - 1)
    # each segment's controls: the mean over its intervals [start, end) (a lone node: its own)
    mean = np.add.reduceat(ctl, starts, axis=0) / (ends - starts)[:, None] if m > 1 else ctl
    return [Segment(*map(float, row)) for row in np.column_stack(
        [t_n[starts], t_n[ends], s_n[starts, 0], s_n[starts, 1],
         np.mod(s_n[starts, 2], 2 * math.pi), s_n[starts, 3], mean])]


@cache
def velocity_covariance() -> ca.Function:
    """``(s, tau, vec P) -> C``: the ``(x, z, vx, vz)`` covariance at ``tau`` after a node with
    state ``s = (x, z, phi, v, u, w)`` and covariance ``P`` (6 x 6, column-major):
    ``C = M P M^T`` with ``M = T A``, ``A`` the motion map's Jacobian over ``tau`` (controls in
    the state) and ``T`` the Jacobian of ``(x, z, v cos phi, v sin phi)`` at ``tau``."""
    s, tau = ca.SX.sym("s", NH), ca.SX.sym("tau")
    P = ca.reshape(ca.SX.sym("P", NH * NH), NH, NH)
    moved = propagate_ca(s[:4], s[4], s[5], tau)
    A = ca.jacobian(ca.vertcat(moved, s[4], s[5]), s)
    phi, v = moved[2], moved[3]
    T = ca.SX.zeros(4, NH)
    T[0, 0] = T[1, 1] = 1.0
    T[2, 2], T[2, 3] = -v * ca.sin(phi), ca.cos(phi)
    T[3, 2], T[3, 3] = v * ca.cos(phi), ca.sin(phi)
    M = ca.mtimes(T, A)
    return compiled.function("velocity_covariance", [s, tau, ca.vec(P)],
                             [ca.mtimes(ca.mtimes(M, P), M.T)], ["s", "tau", "P"], ["C"])


def series(t_nodes: FloatArray, sol: np.ndarray, cov_nodes: np.ndarray, t: FloatArray,
           variant: Variant, nodes: np.ndarray | None = None) -> StateSeries:
    """States and ``(x, z, vx, vz)`` covariances at times ``t`` from the node solution,
    propagated from ``nodes`` (default: the last node at or before each time).

    Between nodes the control is constant, so the state at ``tau`` is a deterministic function
    of the node state: ``P(tau) = A(tau) P_k A(tau)^T`` exactly for the linearised model. ``A``
    is block-diagonal (motion; height ``h + tau hd``; constant offsets), so the horizontal
    block (:func:`velocity_covariance`) and the height's variance are computed apart.
    """
    k = (np.clip(np.searchsorted(t_nodes, t, side="right") - 1, 0, t_nodes.size - 1)
         if nodes is None else nodes)
    tau = t - t_nodes[k]
    s = sol[k]
    x, z, phi, v = propagate(s[:, 0], s[:, 1], s[:, 2], s[:, 3], s[:, 4], s[:, 5], tau)
    P6 = cov_nodes[k, :NH, :NH].transpose(0, 2, 1).reshape(-1, NH * NH)  # column-major
    (cov,) = compiled.columns(velocity_covariance(), s[:, :NH].T, tau[None, :], P6.T)
    out = StateSeries(t.copy(), x, z, v * np.cos(phi), v * np.sin(phi), cov)
    if variant.altitude:
        out.h = s[:, NH] + tau * s[:, NH + 1]
        Ph = cov_nodes[k, NH:NH + 2, NH:NH + 2]
        var = Ph[:, 0, 0] + 2 * tau * Ph[:, 0, 1] + tau**2 * Ph[:, 1, 1]
        out.h_sigma = np.sqrt(np.maximum(var, 0.0))
    return out


MIN_SPEED_FOR_TRACK_AXES = 1.0
"""m/s: below it a state has no direction to split a position residual along (NaN there)."""


def leverages(info: FloatArray, d_range: FloatArray, cov: FloatArray) -> FloatArray:
    """``(n, 2)`` share of each plot's error the track absorbs along its range and across it:
    ``lambda_u u^T P u`` and ``lambda_w w^T P w`` with ``P`` the covariance of the position the
    track predicts for the plot (:func:`solver.refine.covariance.plot_covariances`), ``u`` the
    direction of ``d_range`` (the plot's position over its slant range; ``w`` across it) and
    ``lambda`` the plot's weight (``info``: the entries ``(a, b, c)`` of its 2x2 weight) along
    each; a plot without a range (a position plot, a circle) gets half its total ``tr(M P)``
    each."""
    a, b, c = info.T
    length = np.hypot(*d_range.T)
    has = length > 0
    ux = np.where(has, d_range[:, 0] / np.where(has, length, 1.0), 1.0)
    uz = np.where(has, d_range[:, 1] / np.where(has, length, 1.0), 0.0)
    pxx, pxz, pzz = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]

    def along(vx: FloatArray, vz: FloatArray) -> FloatArray:
        return (a * vx * vx + 2 * b * vx * vz + c * vz * vz) * (
            pxx * vx * vx + 2 * pxz * vx * vz + pzz * vz * vz)

    h = np.column_stack([along(ux, uz), along(-uz, ux)])
    total = a * pxx + 2 * b * pxz + c * pzz
    return np.where(has[:, None], h, total[:, None] / 2)


def plot_residuals(table: PlotTable, at_plots: StateSeries, gated: np.ndarray,
                   biases: np.ndarray, bias_sensors: list[int],
                   no_reference: np.ndarray | None = None,
                   leverage: FloatArray | None = None,
                   unreachable: np.ndarray | None = None) -> PlotResiduals:
    """Every plot against the track, measured minus predicted from the track after its
    sensor's estimated offsets (wild plots too, flagged): range and azimuth for radar plots,
    horizontal distance for position plots (NaN where a kind does not apply, or without a
    frame for position plots); ``no_reference``: the plots (indexes) where the track is no
    reference for the sensors (where the bounds bend it off,
    :func:`solver.refine.gate.misfit_stretches`); ``unreachable``: those out of reach of the
    track's others (:func:`solver.refine.gate.unreachable_plots`), wild, as is what lies far
    out in its sensor's residuals' spread (:func:`statistics_wild`, which neither kind
    enters)."""
    n = len(table)
    out = PlotResiduals(np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan),
                        np.zeros(n, bool), np.full(n, np.nan), np.full(n, np.nan))
    out.gated[gated] = True
    for k, sensor in enumerate(table.sensors):
        rows = np.flatnonzero(table.sensor == k)
        if not rows.size:
            continue
        if isinstance(sensor, RadarSensor):
            b = biases[bias_sensors.index(k)] if k in bias_sensors else np.zeros(BIAS_TERMS)
            x = at_plots.x[rows] - b[2] * at_plots.vx[rows]
            z = at_plots.z[rows] - b[2] * at_plots.vz[rows]
            r, az = sensor.measure(table.frame, x, z, _heights(table, at_plots, rows, sensor))
            out.range_m[rows] = table.range_m[rows] - r - b[0]
            out.azimuth_rad[rows] = np.mod(table.azimuth_rad[rows] - az - b[1] + np.pi,
                                           2 * np.pi) - np.pi
        elif table.frame is not None:
            px, pz = table.frame.to_plane(table.lat_deg[rows], table.lon_deg[rows])
            lag = biases[bias_sensors.index(k)][2] if k in bias_sensors else 0.0
            dx = px - (at_plots.x[rows] - lag * at_plots.vx[rows])
            dz = pz - (at_plots.z[rows] - lag * at_plots.vz[rows])
            out.position_m[rows] = np.hypot(dx, dz)
            vx, vz = at_plots.vx[rows], at_plots.vz[rows]
            speed = np.hypot(vx, vz)
            scale = np.where(speed >= MIN_SPEED_FOR_TRACK_AXES,
                             1.0 / np.maximum(speed, MIN_SPEED_FOR_TRACK_AXES), np.nan)
            ux, uz = vx * scale, vz * scale
            assert out.along_m is not None and out.cross_m is not None
            out.along_m[rows] = dx * ux + dz * uz
            out.cross_m[rows] = dz * ux - dx * uz
    far = no_reference_mask(n, unreachable)
    out.no_reference = no_reference_mask(n, no_reference) & ~far
    out.wild = statistics_wild(table, out, far | out.no_reference) | far
    out.leverage = leverage
    return out


WILD_SIGMAS = 5.0
"""A radar plot is wild for the statistics beyond this many robust sigmas of its sensor's
residuals in the track from their median (:func:`wild_residuals`)."""
WILD_MIN_PLOTS = 10
"""Fewer of a sensor's plots in a track: its wild plots are the ones the reconstruction gated."""


def wild_residuals(res: FloatArray, sigma: float) -> np.ndarray:
    """Residuals beyond :data:`WILD_SIGMAS` robust sigmas (``1.4826 MAD``, at least a quarter
    of the declared ``sigma``) from their median. The sensor's own distribution, not the
    reconstruction's gate: a radar with an offset it does not estimate has its good plots
    beyond the gate (a 300 m range offset with a 60 m sigma: 675 of 960 plots gated, the
    range bias reported 233 m and its sigma 35 m), and those are what SASS-C's bias and
    sigma are measured on."""
    med = np.nanmedian(res)
    scale = max(1.4826 * float(np.nanmedian(np.abs(res - med))), 0.25 * sigma)
    return np.abs(res - med) > WILD_SIGMAS * scale


def no_reference_mask(n: int, no_reference: np.ndarray | None) -> np.ndarray:
    """Per plot, whether it is among the indexes ``no_reference``: where the track is no
    reference for its sensor, in a stretch the aircraft's bounds bend the track off (a
    tester's aircraft turning at 10 m/s^2 against the 7 of the bounds: 161 of its 272 plots;
    they were counted wild, 206 of a radar's 2,121 plots of Gaussian noise, as if the radar
    were to blame), or out of reach of the track's others (no plot of this aircraft: a false
    plot, or another aircraft's under one key, whose residuals of tens of km made a radar's
    range bias -47 km in a tester's recording; counted wild)."""
    far = np.zeros(n, dtype=bool)
    if no_reference is not None:
        far[np.asarray(no_reference, dtype=int)] = True
    return far


def statistics_wild(table: PlotTable, residuals: PlotResiduals,
                    far: np.ndarray | None = None) -> np.ndarray:
    """The wild plots, which the sensors' statistics leave out: of those where the track is a
    reference and that it can reach (not ``far``, see :func:`no_reference_mask`) a radar's (with
    :data:`WILD_MIN_PLOTS` in the track) beyond :func:`wild_residuals` in range or azimuth,
    other sensors' the gated ones. ``tracks.parquet`` keeps it (``wild``, beside
    ``no_reference``), so that ``sensors.png`` pools the plots that ``sensors.json`` does (it
    took the gated ones alone: 0 wild and a 97.5-m range sigma in the figure where the table
    said 27 wild and 79.1 m)."""
    far = np.zeros(len(table), dtype=bool) if far is None else far
    wild = residuals.gated & ~far
    for k, sensor in enumerate(table.sensors):
        rows = np.flatnonzero((table.sensor == k) & ~far)
        if isinstance(sensor, RadarSensor) and rows.size >= WILD_MIN_PLOTS:
            wild[rows] = wild_residuals(residuals.range_m[rows], sensor.sigma_r) | (
                wild_residuals(residuals.azimuth_rad[rows], sensor.sigma_psi))
    return wild


def sigma_estimates(e: dict[str, float]) -> dict[str, float]:
    """A sensor's measurement sigmas from its residuals and their degrees of freedom (sums
    over one track or many: plots ``n``, residual sums and sums of squares ``r1, r2`` (range,
    m), ``a1, a2`` (azimuth, rad), ``p2`` (position, m), and the degrees of freedom ``range``,
    ``azimuth``, ``position``: :attr:`solver.results.SensorReport.range_dof`): ``sqrt((sum
    r^2 - n mean^2) / (dof - 1))`` in range and azimuth (rad), ``sqrt(sum |d|^2 / (2 dof))``
    per axis of a position sensor.
    The residuals' own sigma reads low where the track follows the plots: a lone SSR's 60 m and
    0.06 deg read 53.8 m and 0.0541 deg, estimated 59.9 m and 0.0602 deg (4 tracks; with 1-Hz
    ADS-B beside it 59.3 and 59.5 m; the ADS-B's 15 m per axis 14.2 and 15.1 m)."""
    out: dict[str, float] = {}
    n = e["n"]
    if n and e["range"] > 1:
        out["range_sigma_estimate_m"] = float(np.sqrt(max(e["r2"] - e["r1"] ** 2 / n, 0.0)
                                                      / (e["range"] - 1)))
    if n and e["azimuth"] > 1:
        out["azimuth_sigma_estimate_rad"] = float(np.sqrt(max(e["a2"] - e["a1"] ** 2 / n, 0.0)
                                                          / (e["azimuth"] - 1)))
    if e["position"] > 0:
        out["position_sigma_estimate_m"] = float(np.sqrt(e["p2"] / (2 * e["position"])))
    return out


def sensor_reports(table: PlotTable, residuals: PlotResiduals, biases: np.ndarray,
                   bias_cov: np.ndarray, bias_sensors: list[int]) -> list[SensorReport]:
    """Per sensor: plots, plots gated, wild plots, the estimated offsets with their sigmas, and
    the statistics of its plots' :func:`plot_residuals` outside the wild ones
    (:func:`statistics_wild`): mean, RMS and standard deviation in range and azimuth (radars)
    or the horizontal RMS (position sensors)."""
    reports = []
    far = (np.zeros(len(table), dtype=bool) if residuals.no_reference is None
           else residuals.no_reference)
    wild = (residuals.wild if residuals.wild is not None
            else statistics_wild(table, residuals, far))
    left_out = wild | far
    for k, sensor in enumerate(table.sensors):
        rows = np.flatnonzero(table.sensor == k)
        rep = SensorReport(id=sensor.id, kind=sensor.kind, plots=int(rows.size),
                           plots_gated=int(residuals.gated[rows].sum()),
                           plots_wild=int(wild[rows].sum()),
                           plots_no_reference=int(far[rows].sum()))
        keep = rows[~left_out[rows]]
        if residuals.leverage is not None and keep.size:
            free = 1.0 - np.clip(residuals.leverage[keep], 0.0, 1.0)
            if isinstance(sensor, RadarSensor):
                # an estimated offset's degree of freedom is in the leverages (the plots'
                # Jacobian holds the offsets: plot_covariances); taking one more off read
                # the sigmas 1 % high over 48 seeds of two registering radars (a reviewer's)
                rep.range_dof, rep.azimuth_dof = (float(v) for v in free.sum(axis=0))
            else:
                rep.position_dof = float(free.mean(axis=1).sum())
        if isinstance(sensor, RadarSensor):
            if k in bias_sensors:
                j = bias_sensors.index(k)
                sig = np.sqrt(np.maximum(np.diag(bias_cov)[3 * j: 3 * j + 3], 0.0))
                rep.range_bias_m, rep.azimuth_bias_rad, rep.time_bias_s = map(float, biases[j])
                (rep.range_bias_sigma_m, rep.azimuth_bias_sigma_rad,
                 rep.time_bias_sigma_s) = map(float, sig)
            if keep.size:
                dr, da = residuals.range_m[keep], residuals.azimuth_rad[keep]
                rep.range_residual_mean_m = float(dr.mean())
                rep.range_residual_rms_m = float(np.sqrt(np.mean(dr**2)))
                rep.range_residual_sigma_m = float(dr.std())
                rep.azimuth_residual_mean_rad = float(da.mean())
                rep.azimuth_residual_rms_rad = float(np.sqrt(np.mean(da**2)))
                rep.azimuth_residual_sigma_rad = float(da.std())
        elif k in bias_sensors:  # a position sensor's time offset (its latency)
            j = bias_sensors.index(k)
            rep.time_bias_s = float(biases[j][2])
            rep.time_bias_sigma_s = float(np.sqrt(max(np.diag(bias_cov)[3 * j + 2], 0.0)))
        if keep.size and (rep.range_dof is not None or rep.position_dof is not None):
            e = {"n": keep.size, "range": rep.range_dof or 0.0,
                 "azimuth": rep.azimuth_dof or 0.0, "position": rep.position_dof or 0.0,
                 "r1": 0.0, "r2": 0.0, "a1": 0.0, "a2": 0.0, "p2": 0.0}
            if isinstance(sensor, RadarSensor):
                dr, da = residuals.range_m[keep], residuals.azimuth_rad[keep]
                e.update(r1=float(dr.sum()), r2=float(dr @ dr), a1=float(da.sum()),
                         a2=float(da @ da))
            elif table.frame is not None:
                e["p2"] = float(residuals.position_m[keep] @ residuals.position_m[keep])
            for name, value in sigma_estimates(e).items():
                setattr(rep, name, value)
        if not isinstance(sensor, RadarSensor) and keep.size and table.frame is not None:
            rep.position_residual_rms_m = float(np.sqrt(np.mean(residuals.position_m[keep]**2)))
            for name, values in (("along", residuals.along_m), ("cross", residuals.cross_m)):
                v = values[keep] if values is not None else np.empty(0)
                v = v[np.isfinite(v)]
                if v.size:
                    setattr(rep, f"{name}_track_residual_mean_m", float(v.mean()))
                    setattr(rep, f"{name}_track_residual_sigma_m", float(v.std()))
        reports.append(rep)
    return reports


def _heights(table: PlotTable, at_plots: StateSeries, rows: np.ndarray,
             sensor: RadarSensor) -> FloatArray:
    """The aircraft's height at radar plots: reported (estimated instead where the radar calls
    its altitudes uncertain, ``altitude_sigma_m > 0``, and the height was estimated: a Mode C
    250 m high, against a track that ADS-B's geometric heights hold, showed as a -54 to -60 m
    range bias of a radar without one), else estimated, else the convention of a single radar (the
    radar's own height: slant range taken for ground range)."""
    alt = table.altitude_m[rows]
    if at_plots.h is not None:
        own = np.isfinite(alt) & (sensor.altitude_sigma_m == 0)
        return np.where(own, alt, at_plots.h[rows])
    site_h = 0.0 if table.frame is None else sensor.site_in(table.frame)[2]
    return np.where(np.isfinite(alt), alt, site_h)
