"""Results of the reconstruction and of the filters (plain arrays, no web types)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .frames import LocalFrame
from .inputs import FloatArray


def full_turn(angle: Any, turn: float) -> Any:
    """``angle`` modulo ``turn`` in ``[0, turn)``: ``np.mod`` of a tiny negative angle is
    ``turn`` itself in floating point (a heading of 360.0)."""
    a = np.mod(angle, turn)
    return np.where(a >= turn, 0.0, a)


@dataclass
class StateSeries:
    """Horizontal states at times ``t``: position ``(x, z)`` (m), velocity ``(vx, vz)`` (m/s).

    ``cov``, when present, is the ``(n, 4, 4)`` covariance over ``(x, z, vx, vz)``; ``h`` and
    ``h_sigma`` the estimated height (m) and its standard deviation where the altitude was
    estimated; ``lat_deg``/``lon_deg`` the positions on WGS-84 when the plane has a frame.
    """

    t: FloatArray
    x: FloatArray
    z: FloatArray
    vx: FloatArray
    vz: FloatArray
    cov: FloatArray | None = None
    h: FloatArray | None = None
    h_sigma: FloatArray | None = None
    lat_deg: FloatArray | None = None
    lon_deg: FloatArray | None = None

    @property
    def speed(self) -> FloatArray:
        """Ground speed ``hypot(vx, vz)`` (m/s)."""
        return np.hypot(self.vx, self.vz)

    @property
    def heading(self) -> FloatArray:
        """Heading clockwise from the plane's ``x`` axis (north) in [0, 2 pi) (rad)."""
        return full_turn(np.arctan2(self.vz, self.vx), 2 * np.pi)

    def heading_deg_and_speed(self, frame: LocalFrame | None) -> tuple[FloatArray, FloatArray]:
        """What the answers report: heading (deg clockwise from true north, [0, 360)) and
        ground speed (m/s) on the earth (:meth:`LocalFrame.on_earth`; the plane's own
        without a frame). The plane's grid north turns by the meridian convergence away from
        the reference (1.95 deg at 78 N, 45 deg near the pole, measured), and its scale grows."""
        heading, speed = self.heading, self.speed
        if frame is not None and len(self.t):
            heading, speed = frame.on_earth(self.x, self.z, heading, speed)
        return full_turn(np.rad2deg(heading), 360.0), speed

    @property
    def states(self) -> FloatArray:
        """``(n, 4)`` array of ``(x, z, vx, vz)``."""
        return np.column_stack([self.x, self.z, self.vx, self.vz])

    @classmethod
    def from_states(cls, t: FloatArray, states: FloatArray,
                    cov: FloatArray | None = None) -> StateSeries:
        """Build from an ``(n, 4)`` array of ``(x, z, vx, vz)``."""
        s = np.asarray(states, dtype=float)
        return cls(np.asarray(t, dtype=float), s[:, 0], s[:, 1], s[:, 2], s[:, 3], cov)

    def __len__(self) -> int:
        return int(self.t.shape[0])


@dataclass(frozen=True)
class Segment:
    """One constant-control piece: controls ``u``, ``w`` (m/s^2) on ``[t_start, t_end]`` and
    the state ``(x, z, heading, speed)`` at ``t_start`` (heading in rad)."""

    t_start: float
    t_end: float
    x: float
    z: float
    heading: float
    speed: float
    u: float
    w: float


@dataclass
class Diagnostics:
    """What the reconstruction did: counts, failures, criterion values, time spent."""

    method: str = "sliding"
    windows_solved: int = 0
    trial_windows: int = 0
    solver_failures: int = 0
    fallbacks: int = 0
    criterion: str = "R2"
    criterion_values: list[float] = field(default_factory=list)
    nlp_solve_ms: list[float] = field(default_factory=list)
    elapsed_ms: float = 0.0
    warnings: list[str] = field(default_factory=list)
    extra: dict[str, float | int | str] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: the answer's ``diagnostics`` (spec api.md; the solve times summed)."""
        return {
            "method": self.method,
            "windows_solved": int(self.windows_solved),
            "trial_windows": int(self.trial_windows),
            "solver_failures": int(self.solver_failures),
            "fallbacks": int(self.fallbacks),
            "criterion": self.criterion,
            "criterion_values": [float(v) for v in self.criterion_values],
            "nlp_solves": len(self.nlp_solve_ms),
            "nlp_solve_ms_total": float(np.sum(self.nlp_solve_ms)) if self.nlp_solve_ms
            else 0.0,
            "elapsed_ms": float(self.elapsed_ms),
            "warnings": list(self.warnings),
            "extra": {k: v if isinstance(v, str) else v.item() if isinstance(v, np.generic)
                      else v for k, v in self.extra.items()},
        }


@dataclass
class SensorReport:
    """One sensor's plots against the reconstruction: counts, the estimated systematic offsets
    with their standard deviations (None when not estimated), and the residuals (measured minus
    predicted from the track, after the offsets): mean, RMS and standard deviation in slant
    range (m) and azimuth (rad) for a radar; for a position sensor the horizontal RMS (m) and
    the mean and standard deviation along and across the track (m). ``plots_gated``: plots
    the reconstruction gave no weight; ``plots_wild``: plots outside the sensor's own residual
    distribution (:func:`solver.refine.output.wild_residuals`), ``plots_no_reference``: plots
    where the track is no reference (out of reach of its others; a stretch the aircraft's
    bounds bend it off), both left out of the statistics."""

    id: str
    kind: str
    plots: int
    plots_gated: int = 0
    plots_wild: int = 0
    plots_no_reference: int = 0
    range_bias_m: float | None = None
    range_bias_sigma_m: float | None = None
    azimuth_bias_rad: float | None = None
    azimuth_bias_sigma_rad: float | None = None
    time_bias_s: float | None = None
    time_bias_sigma_s: float | None = None
    range_residual_mean_m: float | None = None
    range_residual_rms_m: float | None = None
    range_residual_sigma_m: float | None = None
    azimuth_residual_mean_rad: float | None = None
    azimuth_residual_rms_rad: float | None = None
    azimuth_residual_sigma_rad: float | None = None
    position_residual_rms_m: float | None = None
    along_track_residual_mean_m: float | None = None
    along_track_residual_sigma_m: float | None = None
    cross_track_residual_mean_m: float | None = None
    cross_track_residual_sigma_m: float | None = None
    range_dof: float | None = None
    azimuth_dof: float | None = None
    position_dof: float | None = None
    range_sigma_estimate_m: float | None = None
    azimuth_sigma_estimate_rad: float | None = None
    position_sigma_estimate_m: float | None = None
    """Degrees of freedom of the residuals above, ``sum (1 - h_i)`` over the plots the
    statistics take, ``h_i`` the share of plot ``i``'s error the track absorbs (its leverage:
    the plot's weight times the variance of the position the track predicts for it, its
    sensor's estimated offsets included, along the radar's range, across it, or half of both
    for a position plot; :func:`solver.refine.output.leverages`): a track fitted to its
    plots leaves residuals smaller than their errors, and ``sum r^2 / dof`` estimates the
    sensor's sigma (None without the track's covariance): ``*_sigma_estimate_*``
    (:func:`solver.refine.output.sigma_estimates`)."""


@dataclass
class PlotResiduals:
    """Each plot (input order) against the reconstruction, measured minus predicted after its
    sensor's estimated offsets: ``range_m`` and ``azimuth_rad`` for radar plots,
    ``position_m`` (horizontal distance) for position plots, split along the track's velocity
    (``along_m``: ahead of the state positive, so a report late by ``d`` s gives about
    ``-speed * d``) and across it (``cross_m``: right of the track positive); NaN where a kind
    does not apply; ``gated``: given no weight as wild; ``wild``: outside the sensor's own
    residual distribution (:func:`solver.refine.output.statistics_wild`); ``no_reference``:
    where the track is no reference for its sensors; both left out of the sensors' statistics
    (:meth:`left_out`)."""

    range_m: FloatArray
    azimuth_rad: FloatArray
    position_m: FloatArray
    gated: np.ndarray
    along_m: FloatArray | None = None
    cross_m: FloatArray | None = None
    wild: np.ndarray | None = None
    leverage: FloatArray | None = None  # (n, 2): along and across the range (a position
    # plot: half the total each), see SensorReport.range_dof
    no_reference: np.ndarray | None = None

    def left_out(self) -> np.ndarray:
        """The plots the sensors' statistics leave out: wild, or where the track is no
        reference (without those flags: the gated ones)."""
        out = self.gated if self.wild is None else self.wild
        return out if self.no_reference is None else out | self.no_reference


@dataclass
class Reconstruction:
    """Piecewise-constant-control trajectory: its segments, the state at every plot time (input
    order), samples on a regular time step, and diagnostics; with several sensors or a frame on
    the earth, one report per sensor, the frame, and the estimated altitude (time-weighted mean
    height and its standard deviation) where it was estimated; ``no_weight``: the plots (input
    indexes) given no weight as wild, on every path (``residuals.gated`` on the table path)."""

    segments: list[Segment]
    at_plots: StateSeries
    samples: StateSeries
    diagnostics: Diagnostics
    sensors: list[SensorReport] = field(default_factory=list)
    residuals: PlotResiduals | None = None
    frame: LocalFrame | None = None
    altitude_m: float | None = None
    altitude_sigma_m: float | None = None
    no_weight: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))


@dataclass
class FilterEstimate:
    """Output of one recursive estimator: the state ``(x, z, vx, vz)`` and its covariance at
    every plot time, plus free-form diagnostics (e.g. IMM model probabilities)."""

    name: str
    states: StateSeries
    info: dict[str, FloatArray | float | str] = field(default_factory=dict)


def non_finite_part(rec: Reconstruction, estimates: dict[str, FilterEstimate] | None = None
                    ) -> str | None:
    """The first part of a result holding a NaN or infinity (its name in the answer), or None:
    the states at the plots and the samples, the segments, the criterion, the filters'
    states. Checked before anything is answered or stored (a stored NaN made every later
    read of a job's track fail its response validation)."""
    series = {"trajectory.at_plots": rec.at_plots, "trajectory.samples": rec.samples,
              **{f"filters.{k}": e.states for k, e in (estimates or {}).items()}}
    for name, s in series.items():
        for a in (s.t, s.x, s.z, s.vx, s.vz, s.cov):
            if a is not None and not np.isfinite(a).all():
                return name
    seg = np.array([[g.t_start, g.t_end, g.x, g.z, g.heading, g.speed, g.u, g.w]
                    for g in rec.segments], dtype=float)
    if not np.isfinite(seg).all():
        return "trajectory.segments"
    if not np.isfinite(np.asarray(rec.diagnostics.criterion_values, dtype=float)).all():
        return "diagnostics.criterion_values"
    return None


def listed(indexes: np.ndarray | list[int], most: int = 50) -> str:
    """``[3, 17, ...]`` for a warning: at most ``most`` plot indexes, saying how many more."""
    values = np.asarray(indexes, dtype=int).tolist()
    shown = str(values[:most])
    return shown if len(values) <= most else f"{shown[:-1]}, ... ({len(values) - most} more)]"
