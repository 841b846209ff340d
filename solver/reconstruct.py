"""The public entry point: plots in, reconstructed trajectory out."""

from __future__ import annotations

import logging
import time

import numpy as np

from .config import ReconstructionConfig
from .inputs import InputError, Plots, Radar
from .plots import PlotTable
from .results import Reconstruction
from .sensors import RadarSensor

log = logging.getLogger(__name__)

NUMERICAL_FAILURES = (FloatingPointError, ZeroDivisionError, OverflowError,
                      np.linalg.LinAlgError, RuntimeError)
"""What a refinement may raise on numbers it cannot handle (RuntimeError: CasADi's own
evaluation errors); answered by the sliding-window fallback, reported."""
FAR_SCALE = 0.005  # the plane's scale excess that warns (speeds 0.5 % too large)


def reconstruct(plots: Plots | PlotTable, radar: Radar | None = None,
                config: ReconstructionConfig | None = None,
                deadline: float | None = None) -> Reconstruction:
    """Reconstruct one aircraft's trajectory from its plots.

    ``plots`` is either the seed's single radar's :class:`Plots` with its ``radar`` (at the
    origin of a flat plane) or a :class:`PlotTable` of any sensors (``radar`` None).

    ``config.method == "sliding"``: the seed's sliding constant-control windows (spec section
    6); over sensors on the earth (a table), over every plot's fix in the plane
    (:func:`solver.sliding.reconstruct_sliding_table`). ``"refined"`` (default): one
    bounded full-track NLP over every plot of every sensor (``solver.refine``); single-radar
    tracks of fewer than 3 plots take the sliding path, which defines their behaviour.
    ``deadline`` (``time.monotonic()``): the refinement stops at its next IPOPT iteration after
    it and raises :class:`solver.refine.DeadlineExceeded`.
    On a frame on the earth, every state carries its latitude and longitude.
    """
    config = config or ReconstructionConfig()
    if isinstance(plots, PlotTable):
        table = plots
        table.validate()
    else:
        if radar is None:
            raise TypeError("reconstruct(plots, radar): the radar of the plots is missing")
        radar.validate()
        plots.validate()
        table = PlotTable.from_plots(plots, radar)
    config.validate()
    start = time.perf_counter()
    if table.is_legacy:
        legacy_plots, legacy_radar = table.legacy()
        result = _reconstruct_single(legacy_plots, legacy_radar, config, deadline)
    else:
        from .refine import refine_table
        from .sliding import reconstruct_sliding_table

        if len(table) < 3:
            raise InputError(("plots",), f"has {len(table)} plot(s); reconstructing from "
                             "`sensors` needs at least 3")
        if config.method == "sliding":
            result = reconstruct_sliding_table(table, config, deadline)
        else:
            result = refine_table(table, config, deadline=deadline)
        _warn_heights_not_estimated(table, result)
        _warn_mirrored_heights(table, result)
        _warn_one_instant(table, result)
    if table.frame is not None:
        result.frame = table.frame
        for s in (result.at_plots, result.samples):
            s.lat_deg, s.lon_deg = table.frame.to_geodetic(s.x, s.z)
        _warn_far_from_reference(result)
    result.diagnostics.elapsed_ms = (time.perf_counter() - start) * 1e3
    return result


def _warn_heights_not_estimated(table: PlotTable, result: Reconstruction) -> None:
    """Radar plots without altitude on a track whose height is not estimated (a lone sensor:
    nothing to estimate it from) sit at their radar's height, the seed's convention: their
    ground range is then too long by ``h^2 / 2d`` on a flat earth and ``h^2 / 2d + h d / 2R``
    on the earth's (radius ``R``; the curvature's share grows with the distance ``d``: 396 m
    at 250 km and 10 km, where ``h^2 / 2r`` says 200 m; an audit helper, against the exact
    positions) (985 m in the median for a tester's PSR alone at 10 km), in the
    reconstruction and the filters alike. Say so."""
    if table.estimate_altitude():
        return
    rows = table.radar_rows() & np.isnan(table.altitude_m)
    for k in np.unique(table.sensor[rows]):
        n = int(np.count_nonzero(rows & (table.sensor == k)))
        result.diagnostics.warnings.append(
            f"{n} plot(s) of radar {table.sensors[k].id!r} have no altitude and no other "
            "sensor sees the aircraft: they are placed at the radar's height, so their ground "
            "range is too long by about h^2 / 2d + h d / 2R for an aircraft at height h and "
            "distance d (R the earth's radius: 1.05 km at 50 km and 10 km, 400 m at 250 km); "
            "give their Mode C altitude or a second sensor")


def _warn_one_instant(table: PlotTable, result: Reconstruction) -> None:
    """Plots of several sensors all at one instant fix a position, not a motion: the heading
    and speed then come from the start of the solve, not the plots (a tester's three sensors'
    plots at one time came back at the bounds' lowest speed, heading 0, without a word), as
    the sliding windows say for one plot."""
    said = any(w.startswith("only one plot") for w in result.diagnostics.warnings)
    if len(table) and np.all(table.t == table.t[0]) and not said:
        result.diagnostics.warnings.append(
            f"every plot is at the same time ({float(table.t[0]):.3f} s): a position, no "
            "motion; the heading and speed are not estimated from the plots")


MIRROR_CHI2 = 9.0
"""The mirrored heights' increase of the range residuals' chi-square below which the heights
are called ambiguous (3 sigma of one plot)."""


def _warn_mirrored_heights(table: PlotTable, result: Reconstruction) -> None:
    """Radar plots without altitude fix a height through ``(h - h_site)^2`` only: for an
    aircraft near its radars' height (a TMA radar on a hill, an approach) the height mirrored
    about the sites' height fits the slant ranges about as well, and only the sites' different
    heights tell the two apart. A tester's two radars at 450 and 500 m saw an aircraft at 900 m
    estimated at 0 +- 90 m (positions within 15 m). Said when the mirrored heights, with the
    same horizontal positions (the re-fitted mirror could only fit better), raise the range
    residuals' chi-square by less than :data:`MIRROR_CHI2` and differ from the estimate by
    more than 3 of its sigmas."""
    s, res = result.at_plots, result.residuals
    if (not table.estimate_altitude() or table.frame is None or s.h is None or res is None
            or np.isfinite(table.altitude_m).any()):
        return
    rows = np.flatnonzero(table.radar_rows() & ~res.gated & np.isfinite(res.range_m))
    if rows.size < 3:
        return
    site_h = table.site_heights()[rows]
    sigma_r = np.array([getattr(s, "sigma_r", np.nan) for s in table.sensors])[table.sensor[rows]]
    h = s.h[rows]
    mirror = 2.0 * np.average(site_h, weights=sigma_r**-2) - h
    sd = s.h_sigma[rows] if s.h_sigma is not None else np.zeros(rows.size)
    if np.median(np.abs(mirror - h)) <= 3.0 * max(float(np.median(sd)), 10.0):
        return  # at the sites' height: the mirror is the same place
    dr = np.empty(rows.size)
    for k in np.unique(table.sensor[rows]):
        m = table.sensor[rows] == k
        radar = table.sensors[k]
        assert isinstance(radar, RadarSensor)
        x, z = s.x[rows][m], s.z[rows][m]
        dr[m] = radar.measure(table.frame, x, z, mirror[m])[0] - radar.measure(
            table.frame, x, z, h[m])[0]
    e = res.range_m[rows] / sigma_r
    worse = float(np.sum((e - dr / sigma_r) ** 2 - e**2))
    if worse < MIRROR_CHI2:
        result.diagnostics.warnings.append(
            f"the height is ambiguous: the radars see the aircraft near their own height, "
            f"where heights mirrored about it fit their slant ranges as well (median "
            f"{float(np.median(h)):.0f} m estimated, {float(np.median(mirror)):.0f} m mirrored: "
            f"chi-square +{worse:.1f}); positions are not affected. Give the plots' Mode C "
            "altitude to decide")


def _warn_far_from_reference(result: Reconstruction) -> None:
    """Warn when the track lies so far from the plane's reference that the plane's scale
    (:meth:`solver.frames.LocalFrame.scale`) exceeds ``1 +`` :data:`FAR_SCALE` (about 900 km;
    1.024 at 2000 km): the plane's quantities (``x``, ``z``, segments, manoeuvres) are then
    that much larger than the ground's. Latitudes, longitudes and the states' heading and speed
    are on the earth, and the bounds hold on the ground (:meth:`NodeData.scaled`)."""
    s, frame = result.at_plots, result.frame
    assert frame is not None
    if not len(s):
        return
    scale = np.asarray(frame.scale(s.x, s.z), float)
    far = int(np.argmax(scale))
    if scale[far] - 1.0 > FAR_SCALE:
        km = float(frame.ground_distance(s.lat_deg[far], s.lon_deg[far])) / 1e3
        result.diagnostics.warnings.append(
            f"the track lies up to {km:.0f} km from the plane's reference ({frame.lat_deg:.4f}, "
            f"{frame.lon_deg:.4f}), where the plane's scale is {scale[far]:.3f}: x, z, segments "
            f"and manoeuvres are up to {100 * (scale[far] - 1):.1f} % larger there than on the "
            "ground (latitudes, longitudes and the states' heading and speed are on the earth); "
            "give a reference near the track for the plane to read as the ground")


def _reconstruct_single(plots: Plots, radar: Radar, config: ReconstructionConfig,
                        deadline: float | None) -> Reconstruction:
    """The seed's setting: refined with a sliding-window fallback, or sliding alone."""
    from . import refine as refine_module
    from .sliding import reconstruct_sliding

    result = None
    if config.method == "refined" and len(plots) >= 3:
        initial = (reconstruct_sliding(plots, radar, config, deadline=deadline)
                   if config.refine.init == "sliding" else None)
        try:
            result = refine_module.refine(plots, radar, config, initial, deadline)
        except NUMERICAL_FAILURES as exc:
            # numerical failures only: a programming error (TypeError, IndexError, a shape
            # ValueError...) must surface, not hide behind a fallback
            if isinstance(exc, refine_module.DeadlineExceeded):
                raise
            if "KeyboardInterrupt" in str(exc):
                # CasADi reports a signal handler's exception (Ctrl-C, a time limit) this way:
                # an interruption, not a numerical failure
                raise KeyboardInterrupt(str(exc)) from exc
            # degrade to the seed's method rather than fail the request
            log.warning("refinement failed (%s); falling back to the sliding windows", exc)
            result = reconstruct_sliding(plots, radar, config, deadline=deadline)
            result.diagnostics.solver_failures += 1
            result.diagnostics.fallbacks += 1
            result.diagnostics.warnings.append(
                f"refinement failed ({type(exc).__name__}: {exc}); sliding-window result")
    if result is None:
        result = reconstruct_sliding(plots, radar, config, deadline=deadline)
    return result
