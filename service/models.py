"""Request and response bodies of ``POST /v1/reconstructions`` (contract: spec/api.md, v1).

Units are in the field names; angles are degrees at this edge (radians inside ``solver``).
Frame: ``x`` north, ``z`` east (metres, radar at the origin); azimuth and heading clockwise
from north. Pydantic checks types, finiteness and list shapes here; the physical checks
(positive range, increasing times, bounds order...) live in ``solver`` ``validate()`` methods
and come back as the same 422 error body.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from solver.config import FILTER_GATE_SIGMA, MAX_FILTER_GATE_SIGMA, MIN_TRIAL_STEP_S
from solver.estimation import FILTER_NAMES, GATING_NAMES
from solver.io.sensors_file import MAX_OFFSETS
from solver.manoeuvres import (
    ACCELERATION,
    MIN_HEADING_CHANGE_DEG,
    MIN_SPEED_CHANGE,
    TURN_RATE_DEG_S,
)

FilterName = Literal[FILTER_NAMES]  # type: ignore[valid-type]


def filter_gate_field() -> Any:
    """The filters' validation gate, one field for the request and a job's options."""
    return Field(
        FILTER_GATE_SIGMA, gt=0, le=MAX_FILTER_GATE_SIGMA, description="The filters' "
        f"validation gate, in sigmas of the normalised innovation (> 0, <= "
        f"{MAX_FILTER_GATE_SIGMA:g}): a plot farther than this from a filter's prediction is "
        "left out when the next plot is likelier without it (a wild plot; named in "
        "`filters.<name>.gated` and the warnings); more than two in a row are used (the "
        "aircraft is elsewhere). null: every plot used. Applies to "
        f"{', '.join(GATING_NAMES)}; the others use every plot. Default "
        f"{FILTER_GATE_SIGMA:g} (4 caught a few more false plots in the benchmark, but left out "
        "genuine ones where the declared sigmas were too small).",
        examples=[FILTER_GATE_SIGMA])
Method = Literal["refined", "sliding"]


class _In(BaseModel):
    """Request parts: unknown fields are errors, NaN and Infinity are rejected, and types are
    strict: a JSON boolean or string is not a number (``true`` was taken as 1 m), a number
    with a fraction is not an integer; integers are still numbers."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)


class _Out(BaseModel):
    """Response parts: finite numbers only (a NaN would be a solver bug, not a value)."""

    model_config = ConfigDict(allow_inf_nan=False)


# ----------------------------------------------------------------------------------- request


class RadarIn(_In):
    """A priori accuracies and geometry limits of the radar that produced the plots."""

    range_error_m: float = Field(
        description="A priori maximum slant-range error `eps_r` (m, > 0); sizes the "
        "uncertainty ellipses.", examples=[500.0])
    azimuth_error_deg: float = Field(
        description="A priori maximum azimuth error `eps_psi` (degrees, > 0).", examples=[1.5])
    range_sigma_m: float | None = Field(
        None, description="Slant-range standard deviation (m, > 0) for statistical weighting "
        "and the filters. Default: `range_error_m / 3`.", examples=[166.7])
    azimuth_sigma_deg: float | None = Field(
        None, description="Azimuth standard deviation (degrees, > 0). Default: "
        "`azimuth_error_deg / 3`.", examples=[0.5])
    max_altitude_m: float = Field(
        0.0, description="Highest possible aircraft altitude `h_max` (m, >= 0) for the "
        "unknown-altitude correction. 0 = no correction.", examples=[15000.0])
    max_elevation_deg: float = Field(
        0.0, description="Highest elevation angle `alpha_max` (degrees, 0 <= value < 90) for "
        "the unknown-altitude correction. 0 = no correction.", examples=[60.0])
    altitude_sigma_m: float = Field(
        0.0, description="Standard deviation (m, 0 or >= 0.001) of the plots' `altitude_m` as "
        "a height above the radar (flat plane) or the ellipsoid (`sensors`). 0 = exact (the "
        "default). A Mode C flight level is a pressure altitude, some 100-300 m from the geometric "
        "height: a plot's ground range moves by that times `h / d` (elevation), so near the "
        "radar the plot's along-ray sigma grows accordingly. With another sensor (`sensors`) "
        "the height is then estimated, this radar's altitudes a measurement of it with this "
        "sigma, and its residuals (`sensors[]` statistics) taken at the estimate.",
        examples=[150.0])


class SiteFields(_In):
    """A sensor's site on WGS-84."""

    lat_deg: float | None = Field(
        None, description="Site latitude (degrees, WGS-84, [-90, 90]). Omit (with `lon_deg`) "
        "to put the radar at the `reference` point.", examples=[46.2237])
    lon_deg: float | None = Field(None, description="Site longitude (degrees, WGS-84).",
                                  examples=[14.4576])
    height_m: float = Field(0.0, description="Site height above the WGS-84 ellipsoid (m).",
                            examples=[380.0])


class AsterixCodes(_In):
    """The ASTERIX codes a sensor file gives a sensor (recordings.md), accepted so that the
    same list serves a recording and JSON plots; JSON plots name their sensor by `id`."""

    sac: int | None = Field(None, ge=0, le=255, description="ASTERIX System Area Code "
                            "(recordings find the sensor by SAC/SIC; not used for JSON plots).")
    sic: int | None = Field(None, ge=0, le=255, description="ASTERIX System Identification "
                            "Code (with `sac`).")


class RadarSensorIn(RadarIn, SiteFields, AsterixCodes):
    """A radar of `sensors`: its accuracies (as the single `radar`) and its site."""

    id: str = Field(min_length=1, max_length=64, description="Unique sensor id; "
                    "`plots[].sensor` names it.", examples=["LJLJ-PSR"])
    kind: Literal["radar"] = Field(description="`radar`: plots carry slant range and azimuth "
                                   "(clockwise from the site's true north).")
    estimate_bias: bool = Field(
        False, description="Estimate this radar's range offset (m), azimuth offset (deg) and "
        "time offset (s) with the trajectory (priors: 300 m, 0.5 deg, 1 s); reported in "
        "`sensors`.")
    range_offset_m: float = Field(
        0.0, ge=-MAX_OFFSETS["range_offset_m"], le=MAX_OFFSETS["range_offset_m"],
        description="Known range offset (m, measured minus true; an earlier registration's "
        "`range_bias_m`), taken off every plot of the radar before anything else.")
    azimuth_offset_deg: float = Field(
        0.0, ge=-MAX_OFFSETS["azimuth_offset_deg"], le=MAX_OFFSETS["azimuth_offset_deg"],
        description="Known azimuth offset (deg, clockwise), taken off every plot.")
    time_offset_s: float = Field(
        0.0, ge=-MAX_OFFSETS["time_offset_s"], le=MAX_OFFSETS["time_offset_s"],
        description="Known time offset (s; a plot late by d s is of d s before: its state is "
        "at `t` minus d), taken off every plot.")


class PositionSensorIn(AsterixCodes):
    """A position sensor of `sensors` (ADS-B, WAM): plots carry latitude and longitude."""

    id: str = Field(min_length=1, max_length=64, description="Unique sensor id.",
                    examples=["ADSB"])
    kind: Literal["position"] = Field(description="`position`: plots carry `lat_deg`, "
                                      "`lon_deg` and optionally `altitude_m`.")
    position_sigma_m: float = Field(description="Horizontal standard deviation per axis (m, "
                                    "> 0).", examples=[30.0])
    altitude_sigma_m: float = Field(15.0, description="Standard deviation of the plots' "
                                    "`altitude_m` (m, > 0).", examples=[15.0])
    estimate_bias: bool = Field(
        False, description="Estimate this sensor's time offset (s; its latency: a report late "
        "by d s gives where the aircraft was d s before) against the other sensors, with the "
        "trajectory (prior 1 s); reported in `sensors` as `time_bias_s`.")
    time_offset_s: float = Field(
        0.0, ge=-MAX_OFFSETS["time_offset_s"], le=MAX_OFFSETS["time_offset_s"],
        description="Known time offset (s, its latency; an earlier run's `time_bias_s`), taken "
        "off every plot: its state is at `t` minus it.")


SensorIn = Annotated[RadarSensorIn | PositionSensorIn, Field(discriminator="kind")]


class ReferenceIn(_In):
    """The tangent point of the local plane of the answer (`x` north, `z` east)."""

    lat_deg: float = Field(description="Latitude (degrees, WGS-84).", examples=[46.0])
    lon_deg: float = Field(description="Longitude (degrees, WGS-84).", examples=[14.8])


class PlotIn(_In):
    """One plot (one detection of the aircraft)."""

    t: float = Field(description="Time (s, any origin); strictly increasing along `plots` "
                     "within one sensor (several sensors may share a time).", examples=[0.0])
    sensor: str | None = Field(
        None, description="Id of the plot's sensor in `sensors` (required with `sensors`, "
        "refused with the single `radar`).", examples=[None])
    range_m: float | None = Field(
        None, description="Slant range (m, > 0); required on radar plots.", examples=[81234.5])
    azimuth_deg: float | None = Field(
        None, description="Azimuth (degrees, clockwise from north); any real value, normalised "
        "to [0, 360); required on radar plots.", examples=[123.4])
    lat_deg: float | None = Field(None, description="Latitude (degrees, WGS-84); position "
                                  "plots only.", examples=[None])
    lon_deg: float | None = Field(None, description="Longitude (degrees, WGS-84); position "
                                  "plots only.", examples=[None])
    altitude_m: float | None = Field(
        None, description="Known altitude (m), e.g. Mode C from a secondary radar: the plot's "
        "ground position then uses it exactly instead of the unknown-altitude ellipse "
        "correction. With the single `radar`: height above the radar, 0 <= value < range_m; "
        "with `sensors`: height above the WGS-84 ellipsoid. A Mode C flight level FL is a "
        "pressure altitude, `FL * 30.48` m, taken as the height (its difference from the "
        "geometric height, tens to hundreds of metres, moves a plot by about that times "
        "h / r). Omit or null when unknown.", examples=[None])
    flight_level: float | None = Field(
        None, ge=-20.0, le=1000.0, description="Mode C or barometric flight level (FL, 100 ft; "
        "ASTERIX CAT048 I090, CAT021 I145), with `sensors` only. Without `altitude_m` it gives "
        "the pressure altitude `FL * 30.48` m; an `altitude_m` equal to that is one too. As in "
        "a recording, the request's pressure altitudes are made geometric by the aircraft's "
        "own offset where at least 3 position plots (ADS-B) carry both a geometric "
        "`altitude_m` and their `flight_level` (or pair with a radar's within 5 s): the "
        "running median over 120 s of their differences, said in the answer's warnings. "
        "Without such pairs pressure altitudes are taken as heights.", examples=[None])


Pair = list[float]


def _pair(default: tuple[float, float], what: str, unit: str) -> Pair:
    return Field(list(default), min_length=2, max_length=2,
                 description=f"[min, max] of {what} ({unit}); min < max. "
                 f"Default {list(default)}.", examples=[list(default)])


class BoundsIn(_In):
    """Box bounds of the aircraft model (constant controls per segment)."""

    u: Pair = _pair((-7.0, 7.0), "the lateral (normal) acceleration, positive turning right; "
                    "must contain 0", "m/s^2")
    w: Pair = _pair((-2.0, 3.0), "the longitudinal acceleration; must contain 0", "m/s^2")
    v: Pair = _pair((30.0, 330.0), "the ground speed; min > 0", "m/s")


class WindowIn(_In):
    """Sliding-window settings of the reconstruction."""

    plots: int | None = Field(
        None, description="Plots per window `m` (>= 2). The seed used 3-5; 3 follows hard "
        "manoeuvres best. Default (null): 3, or the whole track when it is shorter (one plot "
        "gives only its position, two plots one straight constant-speed segment; see "
        "`diagnostics.warnings`). An explicit value longer than the track makes one window "
        "over the whole track, with a warning.",
        examples=[3])
    trial_step_s: float = Field(
        5.0, description="Spacing (s, at least "
        f"{MIN_TRIAL_STEP_S:g}, the time stamps' resolution) of the extra trial start points "
        "between plots, where the controls may switch.", examples=[5.0])


_EXAMPLE_REQUEST = {
    "radar": {"range_error_m": 500.0, "azimuth_error_deg": 1.5, "range_sigma_m": 166.7,
              "azimuth_sigma_deg": 0.5, "max_altitude_m": 15000.0, "max_elevation_deg": 60.0},
    "plots": [
        {"t": 0.0, "range_m": 126151.5, "azimuth_deg": 161.6461},
        {"t": 19.0, "range_m": 122434.3, "azimuth_deg": 160.9555},
        {"t": 57.0, "range_m": 114945.9, "azimuth_deg": 159.5455},
        {"t": 76.0, "range_m": 110638.8, "azimuth_deg": 159.3499},
        {"t": 114.0, "range_m": 102904.2, "azimuth_deg": 157.4039},
    ],
    "bounds": {"u": [-7.0, 7.0], "w": [-2.0, 3.0], "v": [30.0, 330.0]},
    "window": {"plots": 3, "trial_step_s": 5.0},
    "criterion": "R2",
    "method": "refined",
    "filters": ["singer", "quasi_optimal"],
    "sample_step_s": 1.0,
}


class ReconstructionRequest(_In):
    """A batch of plots of one aircraft from one radar (`radar`) or several sensors on the
    earth (`sensors`), and how to reconstruct it."""

    model_config = ConfigDict(json_schema_extra={"examples": [_EXAMPLE_REQUEST]})

    radar: RadarIn | None = Field(
        None, description="The single radar at the origin of a flat plane (api.md). Exactly "
        "one of `radar` and `sensors`.")
    sensors: list[SensorIn] | None = Field(  # type: ignore[valid-type]
        None, min_length=1, max_length=64, description="Several sensors on WGS-84 "
        "(sensors.md): radars at their sites and position sensors; every plot names one. A "
        "sensor no plot names is checked, then left out with a warning (a site list shared by "
        "many requests); the plane stays where it would be with it.")
    reference: ReferenceIn | None = Field(
        None, description="Tangent point of the answer's local plane (with `sensors`). "
        "Default: the first radar's site, else the first position plot. Within about 7800 km "
        "of every radar site and position plot (the plane's scale at most 1.5), else 422.")
    plots: list[PlotIn] = Field(
        min_length=1, description="The aircraft's plots in time order (at least one; the "
        "service's `max_plots` setting caps the count).")
    bounds: BoundsIn = Field(default_factory=BoundsIn,
                             description="Model bounds. Default: the seed's real-data values.")
    window: WindowIn = Field(default_factory=WindowIn, description="Window settings.")
    criterion: Literal["R1", "R2"] = Field(
        "R2", description="Window fit criterion: `R1` plain least squares, `R2` residuals "
        "weighted by each plot's uncertainty ellipse (default).")
    method: Method = Field(
        "refined", description="`refined` (default): one bounded piecewise-constant-control "
        "NLP over the whole track, which uses every plot before and after each point (started "
        "from a constant-velocity smoother; tracks of fewer than 3 plots take the sliding "
        "path). `sliding`: the seed's pure sliding-window result.")
    filters: list[FilterName] = Field(  # type: ignore[valid-type]
        default_factory=list, description="Recursive estimators to run beside the "
        "reconstruction, each answered under `filters.<name>`. Default: none (the "
        f"reconstruction alone). Known: {', '.join(FILTER_NAMES)}. `alpha_beta`'s `cov` is its "
        "gains' noise on a straight line only, over-confident in manoeuvres (its 95 % ellipse "
        "held the truth 42-57 % of the time on a calibration flight, the others' 85-98 %).",
        examples=[["singer", "quasi_optimal"]])
    filter_gate_sigma: float | None = filter_gate_field()
    sample_step_s: float = Field(
        1.0, description="Spacing (s, > 0) of the regular samples `trajectory.samples`.",
        examples=[1.0])
    omit: list[Literal["samples", "covariances"]] = Field(
        default_factory=list, max_length=2, description="Parts of the answer to leave out: "
        "`samples` (an empty `trajectory.samples`, not computed: the service's `max_samples` "
        "does not apply) and/or `covariances` (every `cov` null); "
        "a 5000-s track's answer is 2.6 MB with both, a tenth without samples.")


# ---------------------------------------------------------------------------------- response

Cov = list[list[float]]
_COV = ("Covariance (4x4, row-major) of (x, z, vx, vz) in m^2, m^2/s, m^2/s^2, in the plane's "
        "metres as x, z, vx, vz are (far from `reference` the plane's scale times the ground's; "
        "divide by its square for ground metres). It does not "
        "include the bias away from the radar that plots without `altitude_m` carry (about "
        "h^2 / 2d for the single flat radar, h^2 / 2d + h d / 2R on the earth: a constant "
        "altitude is not observable from 2-D plots)")


def _absent(value: object) -> bool:
    return value is None


def _optional(description: str) -> Any:
    """A field left out of the JSON, not null, where it does not apply (latitude and longitude
    of the single `radar`'s flat plane), so those answers keep their size."""
    return Field(None, description=description, exclude_if=_absent)


class _GeoOut(_Out):
    """A state that carries its latitude and longitude when the plane has a frame."""

    lat_deg: float | None = _optional("Latitude (degrees, WGS-84); with `sensors` only.")
    lon_deg: float | None = _optional("Longitude (degrees, WGS-84); with `sensors` only.")


class StateOut(_GeoOut):
    """Reconstructed state at one time."""

    t: float = Field(description="Time (s, the request's origin).")
    x: float = Field(description="North position (m).")
    z: float = Field(description="East position (m).")
    vx: float = Field(description="North velocity (m/s).")
    vz: float = Field(description="East velocity (m/s).")
    heading_deg: float = Field(description="Heading (degrees clockwise from true north, "
                               "[0, 360)): on the earth where the answer has latitudes (the "
                               "velocity's plane bearing turned by the meridian convergence), "
                               "the plane's north in the seed's flat plane.")
    speed: float = Field(description="Ground speed (m/s; on the earth where the answer has "
                         "latitudes: the plane's speed over its scale).")
    cov: Cov | None = Field(None, description=f"{_COV}; null when the method gives none.")
    altitude_m: float | None = _optional("Estimated height above the ellipsoid (m), where the "
                                         "altitude was estimated from several sensors.")
    altitude_sigma_m: float | None = _optional("Its standard deviation (m).")


class PlotStateOut(StateOut):
    """The state at one plot, with the plot against it where the reconstruction gives it
    (sensors on the earth or several sensors; the sensors' statistics pool these)."""

    range_residual_m: float | None = _optional(
        "A radar plot's slant range minus the range of this state (after the sensor's "
        "estimated offsets), m.")
    azimuth_residual_deg: float | None = _optional(
        "A radar plot's azimuth minus the azimuth of this state (after the sensor's estimated "
        "offsets), degrees.")
    position_residual_m: float | None = _optional(
        "A position plot's horizontal distance from this state, m.")
    gated: bool | None = _optional("The plot was given no weight as wild.")


class SegmentOut(_Out):
    """One constant-control piece of the trajectory, with the state at its start."""

    t_start: float = Field(description="Start time (s).")
    t_end: float = Field(description="End time (s).")
    u: float = Field(description="Lateral acceleration (m/s^2, positive turning right).")
    w: float = Field(description="Longitudinal acceleration (m/s^2).")
    x: float = Field(description="North position at `t_start` (m).")
    z: float = Field(description="East position at `t_start` (m).")
    heading_deg: float = Field(description="Heading at `t_start` (degrees clockwise from the "
                               "plane's north, its `x` axis: the frame `x`, `z`, `u` and `w` "
                               "are in, so that the segments propagate; `at_plots` and "
                               "`samples` give the heading from true north).")
    speed: float = Field(description="Speed at `t_start` in the plane (m/s; `at_plots` and "
                         "`samples` give the ground speed on the earth).")


class ManoeuvreOut(_Out):
    """A turn or a speed change read off the segments (:mod:`solver.manoeuvres`)."""

    model_config = ConfigDict(allow_inf_nan=False, json_schema_extra={"description": (
        "A turn or a speed change read off the segments: a run of segments turning one way at "
        f"{TURN_RATE_DEG_S / 2:g} deg/s or more, one of them at {TURN_RATE_DEG_S:g} deg/s or "
        f"more, {MIN_HEADING_CHANGE_DEG:g} deg in all; or changing speed one way at "
        f"{ACCELERATION / 2:g} m/s^2 or more, one at {ACCELERATION:g} m/s^2 or more, "
        f"{MIN_SPEED_CHANGE:g} m/s in all (as ASTERIX I062/200's right / left turn, increasing "
        "/ decreasing ground speed).")})

    kind: Literal["turn", "speed_change"] = Field(description="What changed.")
    direction: Literal["right", "left", "increase", "decrease"] = Field(
        description="`right` / `left` for a turn, `increase` / `decrease` for a speed change.")
    t_start: float = Field(description="Start time (s): the first segment's start.")
    t_end: float = Field(description="End time (s): the last segment's end.")
    x_start: float = Field(description="North position at `t_start` (m).")
    z_start: float = Field(description="East position at `t_start` (m).")
    x_end: float = Field(description="North position at `t_end` (m).")
    z_end: float = Field(description="East position at `t_end` (m).")
    heading_start_deg: float = Field(description="Heading at `t_start` (deg clockwise from "
                                     "the plane's north, as the segments').")
    heading_end_deg: float = Field(description="Heading at `t_end` (deg).")
    heading_change_deg: float = Field(description="Heading change over the manoeuvre (deg, "
                                      "positive to the right; may exceed 360).")
    speed_start: float = Field(description="Ground speed at `t_start` (m/s).")
    speed_end: float = Field(description="Ground speed at `t_end` (m/s).")
    speed_change: float = Field(description="`speed_end - speed_start` (m/s).")
    peak_rate: float = Field(description="The largest rate of its segments, signed: mean turn "
                             "rate (deg/s) for a turn, longitudinal acceleration (m/s^2) for a "
                             "speed change.")


class TrajectoryOut(_Out):
    """The reconstructed trajectory."""

    segments: list[SegmentOut] = Field(description="Constant-control pieces in time order.")
    manoeuvres: list[ManoeuvreOut] = Field(
        default_factory=list, description="Turns and speed changes, by start time.")
    at_plots: list[PlotStateOut] = Field(description="State at every plot time, in input "
                                         "order, one per plot.")
    samples: list[StateOut] = Field(description="States every `sample_step_s` over the track.")
    altitude_m: float | None = _optional(
        "Where the altitude was estimated from several sensors: the time-weighted mean height "
        "above the ellipsoid (m); per state in `altitude_m`. Absent otherwise (sensors.md).")
    altitude_sigma_m: float | None = _optional("Its standard deviation (m); absent with it.")


class SensorOut(_Out):
    """One sensor's plots against the reconstruction (the radar assessment of SASS-C/TRES)."""

    id: str = Field(description="Sensor id.")
    kind: str = Field(description="`radar` or `position`.")
    plots: int = Field(description="Plots of this sensor.")
    plots_gated: int = Field(description="Of those, plots the reconstruction gave no weight "
                             "as wild.")
    plots_wild: int = Field(0, description="Of `plots`, those outside the sensor's own "
                            "residual distribution (over 5 robust sigmas from its median, with "
                            "10 plots or more; else the gated ones), which the residual "
                            "statistics leave out. Not a part of `plots_gated`, nor it of this: "
                            "a radar's offset that is not estimated moves its plots beyond the "
                            "reconstruction's gate, not beyond this. Plots out of reach of the "
                            "track's others at the bounds' speed are wild.")
    plots_no_reference: int = Field(0, description="Of `plots`, those where the track is no "
                                    "reference for the sensors, which the residual statistics "
                                    "leave out too: within 60 s of plots far from the track "
                                    "where `u` or `v` sits at a bound (an aircraft flying beyond "
                                    "`bounds`; warned), not the sensor's fault. Apart from "
                                    "`plots_wild`.")
    range_bias_m: float | None = Field(description="Estimated range offset (m; reported "
                                       "minus true); null unless `estimate_bias`.")
    range_bias_sigma_m: float | None = Field(description="Its standard deviation (m).")
    azimuth_bias_deg: float | None = Field(description="Estimated azimuth offset (deg).")
    azimuth_bias_sigma_deg: float | None = Field(description="Its standard deviation (deg).")
    time_bias_s: float | None = Field(description="Estimated time offset (s; reported minus "
                                      "true time).")
    time_bias_sigma_s: float | None = Field(description="Its standard deviation (s).")
    range_residual_mean_m: float | None = Field(
        description="Mean of measured minus predicted slant range (m), after the estimated "
        "offset; radars only.")
    range_residual_rms_m: float | None = Field(description="RMS of those residuals (m).")
    range_residual_sigma_m: float | None = Field(description="Their standard deviation (m).")
    azimuth_residual_mean_deg: float | None = Field(description="Mean azimuth residual (deg).")
    azimuth_residual_rms_deg: float | None = Field(description="RMS azimuth residual (deg).")
    azimuth_residual_sigma_deg: float | None = Field(description="Standard deviation of the "
                                                     "azimuth residuals (deg).")
    position_residual_rms_m: float | None = Field(
        description="Horizontal RMS of the plots against the track (m); position sensors.")
    range_sigma_estimate_m: float | None = Field(
        None, description="The radar's range sigma estimated from its residuals and their "
        "degrees of freedom (each plot's share of its error the track absorbs, from the "
        "track's covariance: the residuals' own sigma reads low where the track follows the "
        "plots, about 10 % for a radar alone); null without the track's covariance (sliding).")
    azimuth_sigma_estimate_deg: float | None = Field(None, description="The same in azimuth "
                                                     "(deg).")
    position_sigma_estimate_m: float | None = Field(None, description="A position sensor's "
                                                    "sigma per horizontal axis, estimated "
                                                    "alike (m).")
    along_track_residual_mean_m: float | None = Field(
        None, description="Mean of the position plots' residuals along the track (m; ahead "
        "positive: a sensor reporting late by d s shows about -speed * d, less what its own "
        "weight in the fit pulls the track towards it); position sensors.")
    along_track_residual_sigma_m: float | None = Field(None, description="Their standard "
                                                       "deviation (m).")
    cross_track_residual_mean_m: float | None = Field(
        None, description="Mean of the residuals across the track (m; right positive); "
        "position sensors.")
    cross_track_residual_sigma_m: float | None = Field(None, description="Their standard "
                                                       "deviation (m).")


class FilterStateOut(_GeoOut):
    """One recursive estimate."""

    t: float = Field(description="Plot time (s).")
    x: float = Field(description="North position (m).")
    z: float = Field(description="East position (m).")
    vx: float = Field(description="North velocity (m/s).")
    vz: float = Field(description="East velocity (m/s).")
    cov: Cov | None = Field(None, description=_COV + "; null with `omit: [covariances]`.")


class FilterOut(_Out):
    """Output of one recursive estimator."""

    states: list[FilterStateOut] = Field(description="One estimate per plot, in input order.")
    gated: list[int] = Field(
        default_factory=list,
        description="Indexes of the plots (in input order) the filter left out: more than its "
        "gate (6 sigma) from its prediction, wild plots; its state there is the prediction. "
        "Empty for `alpha_beta` and the `fusion_*` filters, which use every plot.")


class DiagnosticsOut(_Out):
    """What the reconstruction did."""

    method: str = Field(description="Method that produced the trajectory.")
    windows_solved: int = Field(description="Window NLPs solved (current windows).")
    trial_windows: int = Field(0, description="Trial window NLPs solved.")
    solver_failures: int = Field(description="NLP solves that failed (each survived by a "
                                 "fallback).")
    fallbacks: int = Field(0, description="Times a fallback candidate replaced a failed solve.")
    criterion: str = Field("R2", description="Criterion used (R1 or R2).")
    criterion_values: list[float] = Field(
        default_factory=list, description="Criterion value of every accepted window.")
    nlp_solves: int = Field(0, description="NLP solves timed.")
    nlp_solve_ms_total: float = Field(0.0, description="Time inside NLP solves (ms).")
    elapsed_ms: float = Field(description="Reconstruction time (ms).")
    filters_ms: float = Field(0.0, description="Time running the requested filters (ms).")
    queue_ms: float = Field(0.0, description="Time the request waited for a solver (ms).")
    warnings: list[str] = Field(default_factory=list, description="Non-fatal remarks.")
    extra: dict[str, float | int | str] = Field(
        default_factory=dict, description="Method-specific figures.")


class ReconstructionResponse(_Out):
    """The reconstruction, the requested filter estimates, and diagnostics."""

    trajectory: TrajectoryOut
    filters: dict[str, FilterOut] = Field(
        default_factory=dict, description="Estimates of the requested filters, by name.")
    sensors: list[SensorOut] = Field(
        default_factory=list, description="With `sensors`: one entry per sensor with plots, "
        "in request order (empty for the single `radar`).")
    diagnostics: DiagnosticsOut


# ------------------------------------------------------------------------------------ errors


class ErrorItem(BaseModel):
    """One problem with the request."""

    loc: list[str | int] = Field(description="Path of the field, e.g. [\"plots\", 17, \"t\"].")
    msg: str = Field(description="What is wrong, e.g. \"plots[17].t is not after plots[16].t "
                     "(38.2 <= 40.0)\".")
    type: str = Field(description="Error kind, e.g. `value_error`, `float_type`.")


MAX_ECHO_CHARS = 80
"""A client's value longer than this is shortened where an error message or field path
echoes it (a client's unknown key of a megabyte was echoed twice: a 2-MB answer; a 100-KB job
id came back whole in its 404)."""


def shortened(text: str) -> str:
    """``text`` as an error message echoes it: whole up to :data:`MAX_ECHO_CHARS`
    characters, else its start and its length."""
    if len(text) <= MAX_ECHO_CHARS:
        return text
    return f"{text[:MAX_ECHO_CHARS - 30]}... ({len(text)} characters)"


class ErrorResponse(BaseModel):
    """Every 4xx/5xx answer of the service."""

    message: str = Field(description="Summary naming the field (and plot index).")
    detail: list[ErrorItem] = Field(default_factory=list, description="The problems found "
                                    "(of an invalid body, the first 100; `message` counts them "
                                    "all).")


class Health(BaseModel):
    """Liveness or readiness."""

    status: Literal["ok", "ready", "starting", "failed"]
    detail: str = ""
