"""Between the HTTP models (degrees, lists of objects) and ``solver`` (radians, arrays).

``to_job`` validates through the solver's own ``validate()`` methods, so every physical check
exists once; it renames the solver's radian fields back to the degree fields the client sent.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from solver.config import FILTER_GATE_SIGMA, ReconstructionConfig
from solver.estimation import FUSION_NAMES
from solver.estimation.gating import gate_warnings
from solver.frames import LocalFrame
from solver.inputs import Bounds, InputError, Plots, Radar, format_loc
from solver.io.altitudes import MAX_OFFSET_M, geometric_altitudes, moved_note
from solver.io.sensors_file import KnownOffsets, offset_arrays, take_off_offsets
from solver.io.tables import FL_M
from solver.manoeuvres import from_segments
from solver.plots import PlotTable, validate_sensors
from solver.results import (
    FilterEstimate,
    PlotResiduals,
    Reconstruction,
    SensorReport,
    StateSeries,
    full_turn,
)
from solver.sensors import PositionSensor, RadarSensor, Sensor, Site

from .models import PlotIn, PositionSensorIn, RadarIn, ReconstructionRequest

DEFAULT_WINDOW_PLOTS: int = ReconstructionConfig().window_plots

# solver field name -> request field name
_RENAMED = {
    "azimuth_error_rad": "azimuth_error_deg",
    "azimuth_sigma_rad": "azimuth_sigma_deg",
    "max_elevation_rad": "max_elevation_deg",
    "azimuth_rad": "azimuth_deg",
}



def client_loc(loc: tuple[str | int, ...]) -> tuple[str | int, ...]:
    """The solver's field path in the request's terms (``azimuth_rad`` -> ``azimuth_deg``)."""
    return tuple(_RENAMED.get(p, p) if isinstance(p, str) else p for p in loc)



@dataclass(frozen=True)
class Job:
    """One validated reconstruction, ready to send to a worker (picklable)."""

    table: PlotTable
    config: ReconstructionConfig
    filters: tuple[str, ...]
    omit: frozenset[str] = frozenset()
    notes: tuple[str, ...] = ()  # the request's own warnings (the answer's diagnostics)
    sensors: tuple[tuple[str, str], ...] = ()  # the request's (id, kind), in its order
    filter_gate: float | None = FILTER_GATE_SIGMA  # the filters' validation gate (None: none)

    @property
    def plots(self) -> Plots | PlotTable:
        """What ``reconstruct`` and ``run_filters`` take first: the single flat radar's
        :class:`Plots`, else the table (with ``radar`` None)."""
        return self.table.legacy()[0] if self.table.is_legacy else self.table

    @property
    def radar(self) -> Radar | None:
        return self.table.legacy()[1] if self.table.is_legacy else None


def to_job(req: ReconstructionRequest, nlp_solver: str, max_plots: int,
           max_samples: int, max_nodes: int | None = None) -> Job:
    """Validate a request into solver inputs; raise :class:`InputError` (client field names).

    Beyond the solver's checks: the service's size limits (plots, samples, the refinement's
    nodes)."""
    if max_nodes is None:  # the service's default (one source: Settings)
        from .settings import Settings

        max_nodes = int(Settings.model_fields["max_nodes"].default)
    try:
        return _to_job(req, nlp_solver, max_plots, max_samples, max_nodes)
    except InputError as e:
        raise InputError(client_loc(e.loc), e.message) from None


def refinement_nodes(t: np.ndarray, max_step_s: float) -> int:
    """Node intervals of the refinement of plots at times ``t``: one per gap between
    consecutive plot times (zero-length ones included), long gaps cut to ``max_step_s``
    (:func:`solver.refine.nodes.node_grid`)."""
    gaps = np.diff(np.sort(t))
    return int(np.maximum(np.ceil(gaps / max_step_s - 1e-9), 1).sum())


def _to_job(req: ReconstructionRequest, nlp_solver: str, max_plots: int,
            max_samples: int, max_nodes: int) -> Job:
    n = len(req.plots)
    if n > max_plots:
        raise InputError(("plots",), f"has {n} plots; this service accepts at most {max_plots}")
    if req.radar is not None and req.sensors is not None:
        raise InputError(("sensors",), "cannot be given with `radar`: send the single radar "
                         "as `radar` or every sensor in `sensors`")
    if req.radar is None and req.sensors is None:
        raise InputError(("radar",), "is required (or `sensors` for several sensors)")
    if req.radar is not None and req.reference is not None:
        raise InputError(("reference",), "applies to `sensors` only: the single `radar` is at "
                         "the origin of a flat plane, with no place on the earth")
    notes: list[str] = []
    table = _legacy_table(req) if req.radar is not None else _sensor_table(req, notes)
    b = req.bounds
    config = ReconstructionConfig(
        bounds=Bounds(u=(b.u[0], b.u[1]), w=(b.w[0], b.w[1]), v=(b.v[0], b.v[1])),
        window_plots=DEFAULT_WINDOW_PLOTS if req.window.plots is None else req.window.plots,
        trial_step_s=req.window.trial_step_s,
        criterion=req.criterion,
        sample_step_s=req.sample_step_s,
        method=req.method,
        nlp_solver=nlp_solver,  # type: ignore[arg-type]
    )
    config.validate()  # a window longer than the track is one window over it, warned
    with np.errstate(over="ignore"):
        span = float(table.t.max() - table.t.min())
    if not np.isfinite(span):  # each t finite, their difference not (-1e308 .. 1e308)
        raise InputError(("plots",), f"span from t = {table.t.min():g} to {table.t.max():g} s, "
                         "more than a float holds: give times from a nearer origin")
    if "samples" in req.omit:  # none answered: no limit, and a few computed (as solver.batch)
        config = replace(config, sample_step_s=span / 2 or 1.0)
    elif span / config.sample_step_s >= max_samples:
        raise InputError(("sample_step_s",), f"({config.sample_step_s:g} s) gives more than "
                         f"{max_samples} samples over the {span:g}-s track; this service's "
                         "limit is max_samples")
    if not table.is_legacy and n < 3:
        raise InputError(("plots",), f"has {n} plot(s); reconstructing from `sensors` needs at "
                         "least 3")
    for i, name in enumerate(req.filters):
        if name in FUSION_NAMES and len(table.sensors) != 2:
            raise InputError(("filters", i), f"{name} is seed 004's fusion of exactly two "
                             f"sensors; this request has {len(table.sensors)}")
    if config.method == "refined":
        nodes = refinement_nodes(table.t, config.refine.max_node_step_s)
        if nodes > max_nodes:
            raise InputError(("plots",), f"span {span:g} s with their gaps: the refinement would "
                             f"solve {nodes if nodes < 10**12 else f'{float(nodes):.3g}'} node "
                             "intervals (gaps cut to "
                             f"{config.refine.max_node_step_s:g} s); this service's limit is "
                             f"max_nodes = {max_nodes}: split the track at its long gaps")
    return Job(table, config, tuple(dict.fromkeys(req.filters)), frozenset(req.omit),
               tuple(notes), tuple((s.id, s.kind) for s in req.sensors or ()),
               req.filter_gate_sigma)


def _radar(r: RadarIn) -> dict:
    """The accuracies of a request radar in the solver's units."""
    return {
        "range_error_m": r.range_error_m,
        "azimuth_error_rad": np.deg2rad(r.azimuth_error_deg),
        "range_sigma_m": r.range_sigma_m,
        "azimuth_sigma_rad": (None if r.azimuth_sigma_deg is None
                              else np.deg2rad(r.azimuth_sigma_deg)),
        "max_altitude_m": r.max_altitude_m,
        "max_elevation_rad": np.deg2rad(r.max_elevation_deg),
        "altitude_sigma_m": r.altitude_sigma_m,
    }


def _legacy_table(req: ReconstructionRequest) -> PlotTable:
    """The single ``radar`` at the origin of a flat plane: plots carry range and azimuth."""
    assert req.radar is not None
    radar = Radar(**_radar(req.radar))
    radar.validate()
    for i, p in enumerate(req.plots):
        for name in ("sensor", "lat_deg", "lon_deg", "flight_level"):
            if getattr(p, name) is not None:
                raise InputError(("plots", i, name), "is only allowed with `sensors` (this "
                                 "request has the single `radar`)")
        for name in ("range_m", "azimuth_deg"):
            if getattr(p, name) is None:
                raise InputError(("plots", i, name), "is required")
    cols = np.array([(p.t, p.range_m, p.azimuth_deg) for p in req.plots], dtype=float)
    alt = None
    if any(p.altitude_m is not None for p in req.plots):
        alt = np.array([np.nan if p.altitude_m is None else p.altitude_m for p in req.plots])
    plots = Plots.from_arrays(cols[:, 0], cols[:, 1], np.deg2rad(cols[:, 2]), alt)
    return PlotTable.from_plots(plots, radar)


def _sensor_table(req: ReconstructionRequest, notes: list[str]) -> PlotTable:
    """Several sensors on WGS-84: each plot names its sensor. Sensors without plots (a site
    list shared by many requests) are checked and left out, with a note; the plane stays
    where it would be with them (the first radar's site listed, when no `reference`)."""
    assert req.sensors is not None
    sensors: list[RadarSensor | PositionSensor] = []
    for j, s in enumerate(req.sensors):
        if isinstance(s, PositionSensorIn):
            sensors.append(PositionSensor(s.id, s.position_sigma_m, s.altitude_sigma_m,
                                          estimate_bias=s.estimate_bias))
            continue
        if s.lat_deg is None and s.lon_deg is None and "height_m" in s.model_fields_set:
            raise InputError(("sensors", j, "height_m"), "needs lat_deg and lon_deg (a radar "
                             "without a site is at `reference`, at height 0)")
        if (s.lat_deg is None) != (s.lon_deg is None):
            missing = "lat_deg" if s.lat_deg is None else "lon_deg"
            raise InputError(("sensors", j, missing), "is required with the other site "
                             "coordinate (or omit both to put the radar at `reference`)")
        site = None if s.lat_deg is None else Site(s.lat_deg, s.lon_deg, s.height_m)  # type: ignore[arg-type]
        sensors.append(RadarSensor(**_radar(s), id=s.id, site=site,
                                   estimate_bias=s.estimate_bias))
    validate_sensors(tuple(sensors))  # every one, at its own index (an id given twice first)
    for i, p in enumerate(req.plots):
        if p.sensor is None:
            raise InputError(("plots", i, "sensor"), "is required with `sensors`")
    reference = None
    if req.reference is not None:
        reference = LocalFrame(req.reference.lat_deg, req.reference.lon_deg)
        reference.validate()
    sent = reference is not None
    listed = list(sensors)  # the request's indexes, for the messages
    used = {p.sensor for p in req.plots}
    if used <= {s.id for s in sensors} and len(used) < len(sensors):
        idle = [s.id for s in sensors if s.id not in used]
        notes.append(f"sensor{'s' * (len(idle) > 1)} {', '.join(map(repr, idle))} "
                     f"ha{'ve' if len(idle) > 1 else 's'} no plots: left out")
        sited = next((s for s in sensors if isinstance(s, RadarSensor) and s.site is not None),
                     None)
        if reference is None and sited is not None and sited.id not in used:
            assert sited.site is not None
            reference = LocalFrame(sited.site.lat_deg, sited.site.lon_deg)
            try:
                reference.validate()
            except InputError as e:
                raise unsent_reference(e, listed, ("plots",)) from None
        sensors = [s for s in sensors if s.id in used]
    offsets = {s.id: KnownOffsets(getattr(s, "range_offset_m", 0.0),
                                  getattr(s, "azimuth_offset_deg", 0.0), s.time_offset_s)
               for s in req.sensors}
    try:
        return plot_table(sensors, req.plots, reference, offsets=offsets, notes=notes)
    except InputError as e:
        if sent or e.loc[:1] != ("reference",):
            raise
        position = {s.id for s in sensors if isinstance(s, PositionSensor)}
        first = next((("plots", i) for i, p in enumerate(req.plots) if p.sensor in position),
                     ("plots",))
        raise unsent_reference(e, listed, first) from None


def require_fields(plot: PlotIn, kind: str | None, loc: tuple[str | int, ...]) -> None:
    """A plot's fields its sensor's ``kind`` needs (``range_m`` and ``azimuth_deg`` of a
    radar, ``lat_deg`` and ``lon_deg`` of a position sensor; none of an unknown sensor, named
    elsewhere), a missing one named as such rather than as a NaN value."""
    need = {"radar": ("range_m", "azimuth_deg"), "position": ("lat_deg", "lon_deg")}
    for name in need.get(kind or "", ()):
        if getattr(plot, name) is None:
            raise InputError((*loc, name), f"is required for a plot of {plot.sensor!r} (a "
                             f"{kind} sensor)")


def plot_table(sensors: Sequence[Sensor], plots: Sequence[PlotIn],
               reference: LocalFrame | None, loc: tuple[str | int, ...] = ("plots",),
               offsets: Mapping[str, KnownOffsets] | None = None,
               notes: list[str] | None = None) -> PlotTable:
    """The validated table of request plots, each naming one of ``sensors`` (every one
    used), each sensor's known ``offsets`` (by id) taken off its plots, pressure altitudes
    made geometric as a recording's (:func:`solver.io.altitudes.geometric_altitudes`, said
    in ``notes``); an error at a plot is named at ``loc`` (a job's track ``("tracks", key)``:
    the plot's index within the track)."""
    kinds = {s.id: s.kind for s in sensors}
    for i, p in enumerate(plots):
        require_fields(p, kinds.get(p.sensor), (*loc, i))

    def col(name: str) -> np.ndarray:
        return np.array([np.nan if getattr(p, name) is None else getattr(p, name)
                         for p in plots], dtype=float)

    index = {s.id: j for j, s in enumerate(sensors)}
    t, r, az = take_off_offsets(
        offset_arrays([(offsets or {}).get(s.id, KnownOffsets()) for s in sensors]),
        np.array([index.get(p.sensor or "", 0) for p in plots], dtype=int),
        col("t"), col("range_m"), col("azimuth_deg"))
    altitude = _geometric(t, col("altitude_m"), col("flight_level"),
                          np.array([kinds.get(p.sensor) == "position" for p in plots]), notes)
    try:
        return PlotTable.build(sensors, t, [p.sensor for p in plots], r, np.deg2rad(az),
                               col("lat_deg"), col("lon_deg"), altitude,
                               reference=reference)
    except InputError as e:
        if loc == ("plots",) or e.loc[:1] != ("plots",):
            raise
        # the message may name another plot too ("is not after plots[4].t")
        raise InputError((*loc, *e.loc[1:]), e.message.replace("plots[", f"{format_loc(loc)}[")
                         ) from None


def _geometric(t: np.ndarray, altitude: np.ndarray, flight_level: np.ndarray,
               position: np.ndarray, notes: list[str] | None) -> np.ndarray:
    """The plots' altitudes: a flight level without an altitude gives its pressure altitude,
    and pressure altitudes are moved by the ADS-B offset where there is one (in time order,
    as :func:`geometric_altitudes` takes them)."""
    if not np.isfinite(flight_level).any():
        return altitude
    altitude = np.where(np.isnan(altitude), flight_level * FL_M, altitude)
    order = np.argsort(t, kind="stable")
    got = geometric_altitudes(t[order], altitude[order], flight_level[order], position[order])
    if got.rejected and notes is not None:
        notes.append(f"{got.rejected} geometric height(s) differ from the aircraft's barometric "
                     f"altitude by more than {MAX_OFFSET_M:g} m: not used to make its Mode C "
                     "geometric")
    moved = moved_note(got)
    if moved is None:
        return altitude
    if notes is not None:
        notes.append(moved)
    out = np.empty_like(altitude)
    out[order] = got.altitude_m
    return out


def unsent_reference(e: InputError, sensors: Sequence[Sensor],
                     first_position: tuple[str | int, ...]) -> InputError:
    """``e``, an error of the plane's default tangent point (the client sent no `reference`),
    at the field it came from: the first radar's site, else the first position plot (at
    ``first_position``), with the way out."""
    j = next((j for j, s in enumerate(sensors)
              if isinstance(s, RadarSensor) and s.site is not None), None)
    loc, what = ((first_position, "the first position plot") if j is None
                 else (("sensors", j), "the first radar's site"))
    way_out = "; pass a `reference` away from the pole" if e.loc[1:] == ("lat_deg",) else ""
    return InputError((*loc, *e.loc[1:]), f"{e.message}: the plane's `reference` defaults to "
                      f"{what}{way_out}")


# ----------------------------------------------------------------------------------- results


def _states(s: StateSeries, with_heading: bool, frame: LocalFrame | None = None) -> list[dict]:
    """Rows of a state series; ``cov`` as nested lists (or None); latitude and longitude when
    the plane has a frame; the estimated height where there is one."""
    cols = {"t": s.t, "x": s.x, "z": s.z, "vx": s.vx, "vz": s.vz}
    if with_heading:
        cols["heading_deg"], cols["speed"] = s.heading_deg_and_speed(frame)
    if s.lat_deg is None and frame is not None:
        s.lat_deg, s.lon_deg = frame.to_geodetic(s.x, s.z)
    if s.lat_deg is not None and s.lon_deg is not None:
        cols["lat_deg"], cols["lon_deg"] = s.lat_deg, s.lon_deg
    if s.h is not None and s.h_sigma is not None:
        cols["altitude_m"], cols["altitude_sigma_m"] = s.h, s.h_sigma
    names = list(cols)
    rows = [dict(zip(names, vals, strict=True))
            for vals in np.column_stack(list(cols.values())).tolist()]
    if s.cov is not None:
        for row, c in zip(rows, np.asarray(s.cov).tolist(), strict=True):
            row["cov"] = c
    return rows


def response_dict(rec: Reconstruction, estimates: dict[str, FilterEstimate],
                  omit: frozenset[str] = frozenset(), notes: tuple[str, ...] = (),
                  sensors: Sequence[tuple[str, str]] = ()) -> dict:
    """The JSON-ready body of a 200 (validated against ``ReconstructionResponse`` by the
    caller); ``omit``: ``samples`` (an empty list) and/or ``covariances`` (``cov`` null).
    Every filter's warning (e.g. a numerical fallback) joins ``diagnostics.warnings``;
    ``sensors``: the request's, one report each in its order."""
    if "covariances" in omit:
        for s in (rec.at_plots, rec.samples, *(e.states for e in estimates.values())):
            s.cov = None
    segments = [
        {"t_start": s.t_start, "t_end": s.t_end, "u": s.u, "w": s.w, "x": s.x, "z": s.z,
         "heading_deg": float(full_turn(np.rad2deg(s.heading), 360.0)), "speed": s.speed}
        for s in rec.segments
    ]
    trajectory: dict = {
        "segments": segments,
        "manoeuvres": [m.as_dict() for m in from_segments(rec.segments)],
        "at_plots": _with_residuals(_states(rec.at_plots, True, rec.frame), rec.residuals),
        "samples": [] if "samples" in omit else _states(rec.samples, True, rec.frame),
    }
    if rec.altitude_m is not None:
        trajectory["altitude_m"] = rec.altitude_m
        trajectory["altitude_sigma_m"] = rec.altitude_sigma_m
    diagnostics = rec.diagnostics.as_dict()
    diagnostics["warnings"] = [*notes, *diagnostics["warnings"]]
    diagnostics["warnings"] += [f"filters.{name}: {e.info['warning']}"
                                for name, e in estimates.items() if e.info.get("warning")]
    gated = {name: np.flatnonzero(e.info.get("gated", ())).tolist()
             for name, e in estimates.items()}
    diagnostics["warnings"] += gate_warnings(gated, rec.no_weight)
    return {
        "trajectory": trajectory,
        "filters": {name: {"states": _states(e.states, False, rec.frame), "gated": gated[name]}
                    for name, e in estimates.items()},
        "sensors": _in_request_order(rec.sensors, sensors),
        "diagnostics": diagnostics,
    }


def _in_request_order(reports: list[SensorReport], sensors: Sequence[tuple[str, str]]
                      ) -> list[dict]:
    """One report per request sensor, in its order (sensors.md); a sensor without plots (left
    out of the reconstruction) with none. No ``sensors``: the reconstruction's own."""
    got = {r.id: r for r in reports}
    if not sensors:
        return [_sensor(r) for r in reports]
    return [_sensor(got.get(sid) or SensorReport(id=sid, kind=kind, plots=0))
            for sid, kind in sensors]


def _with_residuals(rows: list[dict], res: PlotResiduals | None) -> list[dict]:
    """Each plot's residuals beside its state (those that apply; none without ``res``)."""
    if res is None:
        return rows
    cols = {"range_residual_m": res.range_m, "azimuth_residual_deg": np.rad2deg(res.azimuth_rad),
            "position_residual_m": res.position_m}
    for name, values in cols.items():
        for row, v in zip(rows, values.tolist(), strict=True):
            if math.isfinite(v):
                row[name] = v
    for row, g in zip(rows, res.gated.tolist(), strict=True):
        row["gated"] = bool(g)
    return rows


def _sensor(r: SensorReport) -> dict:
    """A sensor report in the request's units (degrees)."""
    out = {k: v for k, v in vars(r).items() if not k.endswith("_rad")}
    for k, v in vars(r).items():
        if k.endswith("_rad"):
            out[k[:-4] + "_deg"] = None if v is None else float(np.rad2deg(v))
    return out
