"""Request and response bodies of the jobs endpoints (``/v1/jobs``; contract:
``../shared/spec/recordings.md``, "Jobs (HTTP)")."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AfterValidator, ConfigDict, Field, StringConstraints

from solver.inputs import InputError
from solver.io.asterix import edition_choices, parse_edition
from solver.io.dates import parse_date

from .models import (
    BoundsIn,
    DiagnosticsOut,
    FilterName,
    FilterOut,
    FilterStateOut,
    ManoeuvreOut,
    Method,
    PlotIn,
    PlotStateOut,
    ReferenceIn,
    SegmentOut,
    SensorIn,
    SensorOut,
    StateOut,
    WindowIn,
    _In,
    _optional,
    _Out,
    filter_gate_field,
)

JobState = Literal["queued", "running", "done", "failed", "cancelled"]
TrackStatus = Literal["pending", "done", "failed", "cancelled"]

_EXAMPLE_TRACKS = {
    "sensors": [{"id": "R1", "kind": "radar", "lat_deg": 46.0, "lon_deg": 14.0,
                 "height_m": 300.0, "range_error_m": 150.0, "azimuth_error_deg": 0.24}],
    "tracks": {"4CA2D1": [{"t": 0.0, "sensor": "R1", "range_m": 30512.0, "azimuth_deg": 61.2},
                          {"t": 4.0, "sensor": "R1", "range_m": 31240.5, "azimuth_deg": 61.9},
                          {"t": 8.0, "sensor": "R1", "range_m": 31972.1, "azimuth_deg": 62.5}]},
}


_BOUNDS_DOC = "Control and speed bounds, for every track."
_FILTERS_DOC = ("Recursive estimators run beside the reconstruction of every track, each "
                "answered under the track's `filters.<name>` and in `filters.parquet` (a "
                "filter that cannot run on a track is a warning of that track). Default: none. "
                "`alpha_beta`'s `cov` is its gains' noise on a straight line only, "
                "over-confident in manoeuvres (its 95 % ellipse held the truth 42-57 % of the "
                "time on a calibration flight, the others' 85-98 %).")
_METHOD_DOC = ("How every track is reconstructed, as the single-track request's `method`: "
               "`refined` (default), one bounded piecewise-constant-control NLP over the whole "
               "track; `sliding`, the seed's sliding windows.")
_WINDOW_DOC = ("The sliding windows' settings (`method: sliding`), as the single-track "
               "request's `window`; a track shorter than `plots` is one window, with a warning.")
_CRITERION_DOC = "The sliding windows' fit criterion, as the single-track request's `criterion`."
_SAMPLES_DOC = ("Keep every track's state every this many seconds (s, > 0; from its first plot "
                "to its last, with the covariance): the track's `trajectory.samples` and "
                "`samples.parquet`. A track that would have more than `max_samples` (a service "
                "setting) keeps none, with a warning. Default: none kept.")


EditionCategory = Literal["21", "34", "48"]


def _real_date(text: str) -> str:
    """``options.date``: a calendar day ``YYYY-MM-DD`` (else a 422 naming it)."""
    try:
        return parse_date(text)
    except InputError as e:
        raise ValueError(e.message) from None


_DATE_DOC = ("The UTC date (`YYYY-MM-DD`) of the midnight the recording's times of day count "
             "from (its first plot's day; the command line's `--date`), which gives every "
             "state its `time_utc`. A raw ASTERIX or IOSS recording does not carry it; a pcap "
             "capture's packet times do (this date overrides theirs: a `date_override` problem "
             "naming both), and a plot table's `timestamp` column (a date that contradicts it "
             "fails the job, naming both). Default: the recording's own, if any (else "
             "`time_utc` is null).")
_TIME_UTC_DOC = ("`t` as a UTC time, ISO 8601 ending in `Z` (`2024-03-09T10:00:00.007812Z`), "
                 "where the recording's date is known (its capture's packet times, its table's "
                 "`timestamp`, or the job's `options.date`); null otherwise.")


def _known_editions(editions: dict[str, str]) -> dict[str, str]:
    """``options.editions``: each an edition libasterix has of its category (else a 422
    listing them)."""
    for cat, name in editions.items():
        parse_edition(f"{cat}={name}")
    return editions


class JobOptions(_In):
    """How every track of a job is reconstructed: the optional `options` part of an upload (a
    JSON text), the same fields in a JSON body of tracks."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"bounds": {"u": [-7.0, 7.0], "w": [-2.0, 3.0], "v": [30.0, 330.0]},
         "filters": ["imm_smoother"], "sample_step_s": 1.0}]})

    method: Method = Field("refined", description=_METHOD_DOC)
    window: WindowIn = Field(default_factory=WindowIn, description=_WINDOW_DOC)
    criterion: Literal["R1", "R2"] = Field("R2", description=_CRITERION_DOC)
    bounds: BoundsIn = Field(default_factory=BoundsIn, description=_BOUNDS_DOC)
    filters: list[FilterName] = Field(  # type: ignore[valid-type]
        default_factory=list, description=_FILTERS_DOC)
    filter_gate_sigma: float | None = filter_gate_field()
    sample_step_s: float | None = Field(None, gt=0, description=_SAMPLES_DOC)
    aircraft: list[Annotated[str, StringConstraints(min_length=1, max_length=200)]] | None = \
        Field(None, min_length=1, max_length=10_000, description="Reconstruct only these "
              "aircraft of the recording (keys as in its tracks, e.g. a Mode S address "
              "`3C6DD4` in either case; a key takes its later pieces `KEY#2` ... too, and a "
              "radar track associated into another's key, e.g. `R2:track:40` in "
              "`R1:track:12`, that aircraft): an "
              "incident's aircraft out of a long recording. A key the recording does not hold "
              "is an `aircraft_not_found` problem of the job. Default: every aircraft.")
    editions: Annotated[dict[EditionCategory, str], AfterValidator(_known_editions)] = Field(
        default_factory=dict, examples=[{"21": "0.26"}], description="The ASTERIX edition a "
        "category of the recording is read as, by category number (the command line's "
        "`--edition 21=0.26`): ASTERIX data do not say their edition, and a category's "
        "editions differ (CAT021 0.2x, from older ADS-B ground stations, has another layout "
        "than 2.x): read as another edition, records come out garbage or not at all (the "
        "job's `other_edition`, `bad_record`, `missing_item` problems). libasterix's: "
        f"{edition_choices()}. Categories not named: their default. A plot table ignores it.")
    date: Annotated[str, StringConstraints(pattern=r"^\d{4}-\d{2}-\d{2}$"),
                    AfterValidator(_real_date)] | None = Field(
        None, examples=["2024-03-09"], description=_DATE_DOC)


class JobTracksRequest(_In):
    """Many aircraft's plots as JSON: the sensors (as in the sensor file, without ASTERIX
    codes) and, per aircraft key, its plots (each naming its sensor)."""

    model_config = ConfigDict(json_schema_extra={"examples": [_EXAMPLE_TRACKS]})

    sensors: list[SensorIn] = Field(  # type: ignore[valid-type]
        min_length=1, max_length=64, description="The sensors (sensors.md): radars at their "
        "sites, position sensors.")
    reference: ReferenceIn | None = Field(
        None, description="Tangent point of the plane every track is reconstructed in. "
        "Default: the first radar's site, else the first position plot.")
    tracks: dict[str, list[PlotIn]] = Field(
        min_length=1, description="Plots per aircraft key (the key is the track's name in "
        "every result). Plots of one sensor in time order, checked as the single-track "
        "request's `plots` (a bad one is a 422 at `tracks.<key>[i]`); at least 3 plots per "
        "track (shorter tracks are reported in the job's problems, an empty one is a 422).")
    method: Method = Field("refined", description=_METHOD_DOC)
    window: WindowIn = Field(default_factory=WindowIn, description=_WINDOW_DOC)
    criterion: Literal["R1", "R2"] = Field("R2", description=_CRITERION_DOC)
    bounds: BoundsIn = Field(default_factory=BoundsIn, description=_BOUNDS_DOC)
    filters: list[FilterName] = Field(  # type: ignore[valid-type]
        default_factory=list, description=_FILTERS_DOC)
    filter_gate_sigma: float | None = filter_gate_field()
    sample_step_s: float | None = Field(None, gt=0, description=_SAMPLES_DOC)


class ProblemsOut(_Out):
    """What the ingest left out or noticed, counted by kind (nothing is dropped silently)."""

    total: int = Field(description="Problems in all.")
    counts: dict[str, int] = Field(description="Problems per kind (e.g. `truncated_block`, "
                                   "`unknown_sensor`, `short_track`).")
    dropped: dict[str, int] = Field(default_factory=dict, description="Plots (or records) "
                                    "left out per kind.")
    examples: list[str] = Field(description="The first problems, each with its location "
                                "(byte offset, row, aircraft).")


class JobOptionsOut(_Out):
    """What every track of the job is reconstructed with."""

    method: str = Field("refined", description="The method (`refined` or `sliding`).")
    window: dict[str, int | float] = Field(default_factory=dict, description="The sliding windows' "
                                     "`plots` and `trial_step_s`.")
    criterion: str = Field("R2", description="The sliding windows' criterion.")
    bounds: dict[str, list[float]] = Field(description="The bounds `u`, `w` (m/s^2) and `v` "
                                           "(m/s), each [min, max].")
    filters: list[str] = Field(description="The recursive filters run beside.")
    filter_gate_sigma: float | None = Field(
        None, description="Their validation gate (sigmas; null: every plot used).")
    sample_step_s: float | None = Field(None, description="The step of the regular samples "
                                        "kept (null: none).")
    aircraft: list[str] | None = Field(None, description="The aircraft asked for (null: "
                                       "every aircraft).")
    editions: dict[str, str] = Field(default_factory=dict, description="The ASTERIX editions "
                                     "chosen other than the defaults, by category (e.g. "
                                     "`{\"21\": \"0.26\"}`; empty: the defaults).")
    date: str | None = Field(None, description="The recording's date given (`options.date`; "
                             "null: its own, if any).")


class JobStatus(_Out):
    """A job's state, progress and timing."""

    id: str = Field(description="Job id.")
    kind: Literal["recording", "tracks"] = Field(description="`recording`: an uploaded "
                                                 "recording; `tracks`: a JSON body of tracks.")
    state: JobState = Field(description="queued, running, done, failed or cancelled. "
                            "`failed`: the input could not be read, or the job ran to its end "
                            "without reconstructing one track (`error` says why; its "
                            "`summary.json`, `problems.txt` and each track's reason stay "
                            "readable).")
    tracks_total: int | None = Field(None, description="Aircraft tracks found (null until the "
                                     "recording has been read).")
    tracks_done: int = Field(0, description="Tracks reconstructed and stored.")
    tracks_failed: int = Field(0, description="Tracks whose reconstruction failed (see "
                               "/tracks for the reasons).")
    plots: int | None = Field(None, description="Plots in the job's tracks.")
    plots_done: int = Field(0, description="Plots of the reconstructed tracks.")
    rows: int | None = Field(None, description="Plots read from the recording (before the "
                             "split; see `problems` for the ones left out).")
    problems: ProblemsOut | None = Field(None, description="Partial problems of the input "
                                         "(not fatal).")
    error: str | None = Field(None, description="Why the job failed (or that it was "
                              "cancelled).")
    created: str = Field(description="When the job was accepted (ISO 8601, UTC).")
    started: str | None = Field(None, description="When it first started running.")
    finished: str | None = Field(None, description="When it ended (done, failed, cancelled).")
    elapsed_s: float | None = Field(None, description="From start to end (or to now).")
    runs: int = Field(0, description="Times it was started (more than 1: resumed after a "
                      "restart of the service).")
    input_bytes: int = Field(description="Size of the stored inputs (bytes).")
    options: JobOptionsOut | None = Field(None, description="The bounds, filters and sample "
                                          "step the job was accepted with.")


class JobTrack(_Out):
    """One aircraft of a job."""

    aircraft: str = Field(description="The track's key.")
    plots: int = Field(description="Its plots.")
    status: TrackStatus = Field(description="pending, done or failed.")
    error: str | None = Field(None, description="Why it failed.")
    elapsed_s: float | None = Field(None, description="Its solve time (s).")
    warnings: list[str] = Field(default_factory=list, description="Non-fatal remarks.")


class JobSampleOut(StateOut):
    """A job track's state at one time."""

    time_utc: str | None = Field(None, description=_TIME_UTC_DOC)


class JobSegmentOut(SegmentOut):
    """A job track's constant-control piece."""

    time_utc_start: str | None = Field(None, description="`t_start` as a UTC time (as "
                                       "`at_plots[].time_utc`; null without the date).")
    time_utc_end: str | None = Field(None, description="`t_end` as a UTC time.")


class JobManoeuvreOut(ManoeuvreOut):
    """A job track's turn or speed change."""

    time_utc_start: str | None = Field(None, description="`t_start` as a UTC time (as "
                                       "`at_plots[].time_utc`; null without the date).")
    time_utc_end: str | None = Field(None, description="`t_end` as a UTC time.")


class JobStateOut(PlotStateOut):
    """The state at one plot of a job's track."""

    time_utc: str | None = Field(None, description=_TIME_UTC_DOC)

    plot: int = Field(description="Index of the plot in the track (time order).")
    source: str | None = _optional(
        "Where the plot is in the job's input, as its problems name places: `byte 1234` of an "
        "ASTERIX recording or capture, `row 17` of a plot table, `tracks.A[3]` of a JSON body.")
    sensor: str = Field(description="The plot's sensor.")
    along_track_residual_m: float | None = _optional(
        "A position plot's distance from this state along its velocity, m (ahead positive: a "
        "report late by d s lies about speed * d behind; the sensors' statistics pool these).")
    cross_track_residual_m: float | None = _optional(
        "That distance across the velocity, m (right of the track positive).")


class JobTrajectoryOut(_Out):
    """A job track's trajectory: the segments, the state at every plot and, when the job
    keeps them, the regular samples."""

    segments: list[JobSegmentOut] = Field(description="Constant-control pieces in time order.")
    manoeuvres: list[JobManoeuvreOut] = Field(
        default_factory=list, description="Turns and speed changes, by start time.")
    at_plots: list[JobStateOut] = Field(description="State at every plot, in time order.")
    altitude_m: float | None = _optional(
        "Where the altitude was estimated from several sensors: the time-weighted mean height "
        "above the ellipsoid (m); per state in `altitude_m`. Absent otherwise (sensors.md), as "
        "in the single-track answer.")
    altitude_sigma_m: float | None = _optional("Its standard deviation (m); absent with it.")
    samples: list[JobSampleOut] = Field(
        default_factory=list, description="States every `sample_step_s` of the job's options "
        "over the track (empty when the job keeps none).")


class JobTrackDiagnostics(DiagnosticsOut):
    """What the reconstruction of a job's track did: the single-track answer's diagnostics
    (a track stored by an earlier version has only `elapsed_ms`, the task's, and
    `warnings`)."""

    method: str | None = Field(None, description="Method that produced the trajectory.")
    windows_solved: int | None = Field(None, description="Window NLPs solved (current "
                                       "windows; 0 for the refinement).")
    solver_failures: int | None = Field(None, description="NLP solves that failed.")
    task_ms: float | None = Field(None, description="The whole task on its worker (ms): the "
                                  "reconstruction, the filters, the statistics, the figure.")


class JobFilterStateOut(FilterStateOut):
    """A job track's recursive estimate at one plot."""

    time_utc: str | None = Field(None, description=_TIME_UTC_DOC)


class JobFilterOut(FilterOut):
    """A job track's recursive estimator."""

    states: list[JobFilterStateOut] = Field(description="One estimate per plot, in input "
                                            "order.")


class JobTrackResult(_Out):
    """One reconstructed track of a job (the single-track answer, states at the plots)."""

    aircraft: str = Field(description="The track's key.")
    trajectory: JobTrajectoryOut
    sensors: list[SensorOut] = Field(default_factory=list, description="Each sensor's plots "
                                     "of this track against its reconstruction.")
    filters: dict[str, JobFilterOut] = Field(
        default_factory=dict, description="The job's `filters` on this track: one state per "
        "plot, in the order of `trajectory.at_plots` (a filter that could not run on the track "
        "is absent, the reason in `diagnostics.warnings`).")
    diagnostics: JobTrackDiagnostics


class SensorSummaryOut(_Out):
    """One sensor over all tracks of a finished job (plot-weighted): every field of the job's
    `results/sensors.json` and of the command line's `sensors.json`
    (:data:`solver.sensor_stats.SENSOR_COLUMNS`, in its order). A job finished by an earlier version
    lacks the later fields: null (the counts 0)."""

    sensor: str = Field(description="Sensor id.")
    kind: str = Field(description="`radar` or `position`.")
    tracks: int = Field(description="Reconstructed tracks with plots of this sensor.")
    plots: int = Field(description="Its plots in those tracks.")
    plots_gated: int = Field(description="Plots the reconstruction gave no weight as wild.")
    plots_wild: int = Field(0, description="Plots outside the sensor's own residual "
                            "distribution in their track (as the single-track answer's "
                            "`sensors[].plots_wild`), which the residual statistics leave out.")
    plots_no_reference: int = Field(0, description="Plots where their track is no reference "
                                    "for the sensors (as the single-track answer's "
                                    "`sensors[].plots_no_reference`: near plots far from the "
                                    "track with `u` or `v` at a bound), left out of the "
                                    "residual statistics too; apart from `plots_wild`.")
    scan_period_s: float | None = Field(None, description="From CAT034, else estimated from "
                                        "the tracks' plot intervals (s).")
    detection_rate: float | None = Field(None, description="Plots over the scans expected in "
                                         "the tracks' time within the sensor's coverage (the "
                                         "holes left out).")
    coverage_holes: int | None = Field(None, description="Runs of missed scans too long for "
                                       "the detection rate the track shows elsewhere (under a "
                                       "1 % chance): holes in the sensor's coverage (out of "
                                       "range, masked, cone of silence, outage), counted "
                                       "over all tracks, not as missed detections.")
    coverage_hole_s: float | None = Field(None, description="Their time in all (s).")
    range_residual_mean_m: float | None = Field(None, description="Mean of measured minus "
                                                "predicted slant range (m); radars.")
    range_residual_sigma_m: float | None = Field(None, description="Their standard deviation "
                                                 "(m).")
    range_sigma_estimate_m: float | None = Field(
        None, description="The radar's range sigma estimated from its residuals and their "
        "degrees of freedom over all tracks (as the single-track answer's "
        "`sensors[].range_sigma_estimate_m`: the residuals' own sigma reads low where the "
        "track follows the plots); null without the tracks' covariance (sliding).")
    azimuth_residual_mean_deg: float | None = Field(None, description="Mean azimuth residual "
                                                    "(deg); radars.")
    azimuth_residual_sigma_deg: float | None = Field(None, description="Their standard "
                                                     "deviation (deg).")
    azimuth_sigma_estimate_deg: float | None = Field(None, description="The azimuth sigma "
                                                     "estimated alike (deg).")
    position_residual_rms_m: float | None = Field(None, description="Horizontal RMS of a "
                                                  "position sensor's plots against the tracks "
                                                  "(m).")
    position_sigma_estimate_m: float | None = Field(None, description="A position sensor's "
                                                    "sigma per horizontal axis, estimated "
                                                    "alike (m).")
    along_track_residual_mean_m: float | None = Field(None, description="Mean of a position "
                                                      "sensor's residuals along the track (m; "
                                                      "ahead positive: a latency reads "
                                                      "negative).")
    along_track_residual_sigma_m: float | None = Field(None, description="Their standard "
                                                       "deviation (m).")
    cross_track_residual_mean_m: float | None = Field(None, description="Mean of the "
                                                      "residuals across the track (m; right "
                                                      "positive).")
    cross_track_residual_sigma_m: float | None = Field(None, description="Their standard "
                                                       "deviation (m).")
    range_bias_m: float | None = Field(
        None, description="The radar's range offset estimated over its tracks (m; with "
        "`estimate_bias`): the median of the tracks' offsets weighted by their inverse "
        "variances.")
    range_bias_sigma_m: float | None = Field(None, description="That median's standard "
                                             "deviation (m).")
    azimuth_bias_deg: float | None = Field(None, description="The azimuth offset pooled "
                                           "alike (deg).")
    azimuth_bias_sigma_deg: float | None = Field(None, description="Its standard deviation "
                                                 "(deg).")
    time_bias_s: float | None = Field(None, description="The time offset pooled alike (s), "
                                      "against `time_bias_reference`.")
    time_bias_sigma_s: float | None = Field(None, description="Its standard deviation (s).")
    offset_tracks: int | None = Field(None, description="Tracks whose estimated offsets "
                                      "were pooled (null: none estimated).")
    time_bias_reference: str | None = Field(
        None, description="What the time offset is against: the sensors not estimating their "
        "offsets (e.g. ADS-B's time) where its tracks have any, else the mean of the "
        "estimating sensors.")
