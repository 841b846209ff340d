"""The sensors' statistics of a run (SASS-C/TRES-style assessment, against the
reconstruction), ``sensors.json`` and ``sensors.csv`` (:data:`SENSOR_COLUMNS`): per sensor,
its plots, detection rate (plots over expected scans at the estimated scan period, holes in
coverage apart: :data:`HOLE_CHANCE`), wild plots, bias and sigma of the range and azimuth
residuals, estimated offsets where asked.

Each track's share is computed on the worker beside its reconstruction (the
:class:`solver.results.SensorReport` of each sensor with :func:`sensor_spans`), recorded a line
a track in ``sensor_stats.jsonl`` (:func:`iter_stats` reads it back) and pooled over the tracks
by :class:`SensorStats`. The figure of the residuals, ``sensors.png``, is
:mod:`solver.assessment`'s.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv

from .io.scans import scan_step
from .io.sensors_file import SensorSet
from .plots import PlotTable
from .refine.output import sigma_estimates
from .sensors import RadarSensor

SENSOR_COLUMNS = ("sensor", "kind", "tracks", "plots", "plots_gated", "plots_wild",
                  "plots_no_reference", "scan_period_s",
                  "detection_rate", "coverage_holes", "coverage_hole_s",
                  "range_residual_mean_m", "range_residual_sigma_m", "range_sigma_estimate_m",
                  "azimuth_residual_mean_deg", "azimuth_residual_sigma_deg",
                  "azimuth_sigma_estimate_deg", "position_residual_rms_m",
                  "position_sigma_estimate_m", "along_track_residual_mean_m",
                  "along_track_residual_sigma_m", "cross_track_residual_mean_m",
                  "cross_track_residual_sigma_m", "range_bias_m", "range_bias_sigma_m",
                  "azimuth_bias_deg", "azimuth_bias_sigma_deg", "time_bias_s",
                  "time_bias_sigma_s", "offset_tracks", "time_bias_reference")


HOLE_CHANCE = 0.01
"""A run of missed scans is a hole in the sensor's coverage of the track (the aircraft out of
range, masked, in the cone of silence, an outage), not missed detections, when a detection
rate of what the track shows elsewhere gives it less than this chance anywhere in the track
(runs of more than ``log(HOLE_CHANCE / scans) / log(1 - rate)`` misses, at least
:data:`MIN_HOLE_MISSES`): 5-6 misses in a row at 0.9 over 750 scans, 17 at 0.5, 50 at 0.2.
The detection rate then counts the scans expected over the track's time within coverage, as a
radar assessment does; the holes are counted beside it."""
MIN_HOLE_MISSES = 5


def sensor_spans(table: PlotTable) -> dict[str, dict[str, float]]:
    """Per sensor of the track: the time its plots cover without the holes of
    :data:`HOLE_CHANCE` (``span_s``), in how many stretches (``stretches``), the holes' count
    and time, and its scan period estimated from the track (``median_step_s``)."""
    out: dict[str, dict[str, float]] = {}
    for k, s in enumerate(table.sensors):
        t = np.sort(table.t[table.sensor == k])
        if not t.size:
            continue
        dt = np.diff(t)
        step = scan_step(dt) if t.size > 1 else 0.0
        hole = np.zeros(dt.size, dtype=bool)
        if step > 0:
            steps = np.round(dt / step)  # scans from plot to plot (0: a split plot)
            misses = np.maximum(steps - 1.0, 0.0)
            for _ in range(2):  # the rate without the holes found, then the holes again
                scans = float(steps[~hole].sum()) + np.count_nonzero(hole) + 1.0
                # scans with a plot: a split plot (a second in one scan) is no detection more
                # (counted as one, 40 % split plots at 0.6 read holes in 205 of 300 tracks)
                seen = np.count_nonzero(steps[~hole] > 0) + np.count_nonzero(hole) + 1.0
                rate = min(max(seen / scans, 1e-3), 1.0 - 1e-9)
                longest = max(MIN_HOLE_MISSES,
                              math.log(HOLE_CHANCE / scans) / math.log(1.0 - rate))
                hole = misses > longest
        out[s.id] = {"span_s": float(dt[~hole].sum()), "stretches": int(hole.sum()) + 1,
                     "holes": int(hole.sum()), "hole_s": float(dt[hole].sum()),
                     "median_step_s": step}
    return out


class SensorStats:
    """Per-sensor statistics pooled over tracks (plot-weighted means and variances), in
    accumulators of a fixed size whatever the number of tracks: sums, and for the medians
    (of the tracks' median plot intervals, of their estimated offsets) the values themselves
    up to :data:`MEDIAN_SAMPLE` per sensor, beyond that a uniform sample of that many
    (reservoir sampling, seeded: the same tracks in the same order give the same result)."""

    def __init__(self, sensors: SensorSet, periods: dict[str, float]):
        self.sensors = sensors
        self.periods = dict(periods)
        self.acc: dict[str, dict[str, Any]] = {
            s.id: {"tracks": 0, "plots": 0, "plots_gated": 0, "plots_wild": 0,
                   "plots_no_reference": 0, "used": 0,
                   "steps": _Sample(MEDIAN_SAMPLE), "span_s": 0.0, "spans": 0,
                   "holes": 0, "hole_s": 0.0,
                   "r1": 0.0, "r2": 0.0, "a1": 0.0, "a2": 0.0, "p2": 0.0,
                   "along": [0, 0.0, 0.0], "cross": [0, 0.0, 0.0],
                   # the tracks with degrees of freedom: plots, sums, the dof (range,
                   # azimuth, position)
                   "dof": {"n": 0, "r1": 0.0, "r2": 0.0, "a1": 0.0, "a2": 0.0, "p2": 0.0,
                           "range": 0.0, "azimuth": 0.0, "position": 0.0},
                   "biases": _Sample(MEDIAN_SAMPLE)} for s in sensors.sensors}

    def add(self, reports: Sequence[dict[str, Any]]) -> None:
        # a track with a sensor whose offsets were not estimated has its time (ADS-B's, a
        # radar's without estimate_bias); without one the estimating sensors' mean is held
        anchored = any(r.get("time_bias_s") is None and r.get("plots") for r in reports)
        for r in reports:
            a = self.acc.get(r["id"])
            if a is None:
                continue
            wild = r.get("plots_wild", r["plots_gated"])  # (a report of before the field)
            far = r.get("plots_no_reference", 0)
            n = r["plots"] - wild - far  # the plots its statistics are of
            a["tracks"] += 1
            a["plots"] += r["plots"]
            a["plots_gated"] += r["plots_gated"]
            a["plots_wild"] += wild
            a["plots_no_reference"] += far
            a["span_s"] += r.get("span_s", 0.0)
            a["spans"] += r.get("stretches", 1)
            a["holes"] += r.get("holes", 0)
            a["hole_s"] += r.get("hole_s", 0.0)
            if r.get("median_step_s"):
                a["steps"].add(r["median_step_s"])
            if n <= 0:
                continue
            a["used"] += n
            if r["range_residual_mean_m"] is not None:
                a["r1"] += n * r["range_residual_mean_m"]
                a["r2"] += n * r["range_residual_rms_m"] ** 2
                a["a1"] += n * r["azimuth_residual_mean_rad"]
                a["a2"] += n * r["azimuth_residual_rms_rad"] ** 2
            if r["position_residual_rms_m"] is not None:
                a["p2"] += n * r["position_residual_rms_m"] ** 2
            e = a["dof"]
            if r.get("range_dof") is not None and r["range_residual_mean_m"] is not None:
                e["n"] += n
                e["r1"] += n * r["range_residual_mean_m"]
                e["r2"] += n * r["range_residual_rms_m"] ** 2
                e["a1"] += n * r["azimuth_residual_mean_rad"]
                e["a2"] += n * r["azimuth_residual_rms_rad"] ** 2
                e["range"] += r["range_dof"]
                e["azimuth"] += r["azimuth_dof"]
            if r.get("position_dof") is not None and r["position_residual_rms_m"] is not None:
                e["p2"] += n * r["position_residual_rms_m"] ** 2
                e["position"] += r["position_dof"]
            for name in ("along", "cross"):  # count, sum, sum of squares
                mean = r.get(f"{name}_track_residual_mean_m")
                if mean is not None:
                    sigma = r[f"{name}_track_residual_sigma_m"]
                    acc = a[name]
                    acc[0] += n
                    acc[1] += n * mean
                    acc[2] += n * (sigma**2 + mean**2)
            if r.get("time_bias_s") is not None:  # a position sensor: its time offset alone
                a["biases"].add((anchored, *(math.nan if r.get(k) is None else r[k] for k in (
                    "range_bias_m", "azimuth_bias_rad", "time_bias_s", "range_bias_sigma_m",
                    "azimuth_bias_sigma_rad", "time_bias_sigma_s"))))

    def rows(self) -> list[dict[str, Any]]:
        out = []
        for s in self.sensors.sensors:
            a = self.acc[s.id]
            n = a["used"]
            row: dict[str, Any] = {"sensor": s.id, "kind": s.kind, "tracks": a["tracks"],
                                   "plots": a["plots"], "plots_gated": a["plots_gated"],
                                   "plots_wild": a["plots_wild"],
                                   "plots_no_reference": a["plots_no_reference"]}
            steps = a["steps"].values
            period = self.periods.get(s.id) or (float(np.median(steps)) if steps else None)
            row["scan_period_s"] = period
            # sum over the tracks' stretches within coverage of (span / period + 1)
            expected = a["span_s"] / period + a["spans"] if period else 0.0
            row["detection_rate"] = min(a["plots"] / expected, 1.0) if expected else None
            row["coverage_holes"], row["coverage_hole_s"] = a["holes"], a["hole_s"]
            radar = isinstance(s, RadarSensor)
            if radar and n:
                r_mean, a_mean = a["r1"] / n, a["a1"] / n
                row["range_residual_mean_m"] = r_mean
                row["range_residual_sigma_m"] = float(np.sqrt(max(a["r2"] / n - r_mean**2, 0)))
                row["azimuth_residual_mean_deg"] = float(np.rad2deg(a_mean))
                row["azimuth_residual_sigma_deg"] = float(np.rad2deg(
                    np.sqrt(max(a["a2"] / n - a_mean**2, 0.0))))
            if not radar and n:
                row["position_residual_rms_m"] = float(np.sqrt(a["p2"] / n))
            est = sigma_estimates(a["dof"])
            row["range_sigma_estimate_m"] = est.get("range_sigma_estimate_m")
            row["position_sigma_estimate_m"] = est.get("position_sigma_estimate_m")
            if est.get("azimuth_sigma_estimate_rad") is not None:
                row["azimuth_sigma_estimate_deg"] = float(np.rad2deg(
                    est["azimuth_sigma_estimate_rad"]))
            for name in ("along", "cross"):
                count, total, squares = a[name]
                if count:
                    mean = total / count
                    row[f"{name}_track_residual_mean_m"] = mean
                    row[f"{name}_track_residual_sigma_m"] = float(
                        np.sqrt(max(squares / count - mean**2, 0.0)))
            if a["biases"].values:
                row.update(pooled_offsets(np.array(a["biases"].values, dtype=float), radar))
            out.append({k: row.get(k) for k in SENSOR_COLUMNS})
        return out


def pooled_offsets(values: np.ndarray, radar: bool) -> dict[str, Any]:
    """A sensor's offsets over its tracks (rows: anchored, range, azimuth, time, and their
    sigmas): each the median weighted by the tracks' inverse variances (a track whose offsets
    are barely observable counted as much as a well-registered one: +-184 m against +-7 m),
    with the sigma of that median (``1.2533 / sqrt(sum of the weights)``, the median's
    efficiency for Gaussian errors); of one or two tracks their weighted mean and its sigma
    (the lower median of two read 100 m for 100 and 120, -0.65 sigma on average; a
    reviewer's); the sigma scaled by the square root of the reduced chi-square of the tracks
    about their weighted mean where it is above 1 (the Birge ratio: ADS-B latencies differing
    by aircraft scatter a radar's time offsets beyond their sigmas). The time offset pools
    the tracks with a sensor that did not estimate its own
    (their time reference, e.g. ADS-B's) where there are any, else those whose estimating
    sensors' mean time is held: the two are other quantities (a radar without an offset read
    -0.54 s, its tracks' ADS-B latency, where the pooled median of both kinds had mixed -0.56
    and -0.19 s; a tester's)."""
    anchored = values[:, 0] > 0
    keep = anchored if anchored.any() else np.ones(len(values), bool)
    out: dict[str, Any] = {
        "offset_tracks": int(np.count_nonzero(np.isfinite(values[:, 1:4]).any(axis=1))),
        "time_bias_reference": ("the sensors not estimating their offsets" if anchored.any()
                                else "the mean of the estimating sensors")}
    terms = (("time_bias_s", 3, 6, keep, 1.0),) + ((
        ("range_bias_m", 1, 4, np.ones(len(values), bool), 1.0),
        ("azimuth_bias_deg", 2, 5, np.ones(len(values), bool), float(np.rad2deg(1.0))))
        if radar else ())
    for name, col, sig, rows, unit in terms:
        v, sd = values[rows, col], values[rows, sig]
        v, sd = v[np.isfinite(v)], sd[np.isfinite(v)]
        if not v.size:
            continue
        if not np.all(np.isfinite(sd) & (sd > 0)):  # reports without sigmas: the median
            out[name] = float(np.median(v)) * unit
            continue
        w = 1.0 / sd**2
        if v.size <= 2:
            value, sigma = float(w @ v / w.sum()), float(1.0 / np.sqrt(w.sum()))
        else:
            value, sigma = weighted_median(v, w), float(1.2533 / np.sqrt(w.sum()))
        if v.size > 1:  # tracks scattered beyond their sigmas (ADS-B latency differing by
            # aircraft: reduced chi-square 10.7, the sigma 3x small; a tester's): scaled
            chi2 = float(w @ (v - w @ v / w.sum()) ** 2) / (v.size - 1)
            sigma *= float(np.sqrt(max(chi2, 1.0)))
        out[name] = value * unit
        out[name.replace("_bias", "_bias_sigma")] = sigma * unit
    return out


def weighted_median(v: np.ndarray, w: np.ndarray) -> float:
    """The value with half the weight on either side (where a cut falls between two values
    exactly at half, their midpoint: the median of equal weights)."""
    order = np.argsort(v)
    v, cum = v[order], np.cumsum(w[order])
    half = 0.5 * cum[-1]
    k = int(np.searchsorted(cum, half))
    if np.isclose(cum[k], half, rtol=1e-12, atol=0.0) and k + 1 < v.size:
        return float((v[k] + v[k + 1]) / 2)
    return float(v[k])


MEDIAN_SAMPLE = 4096
"""Values kept per sensor for a median of :class:`SensorStats` (all of them up to this)."""


class _Sample:
    """Up to ``size`` values: all of them, then a uniform sample (reservoir sampling)."""

    def __init__(self, size: int, seed: int = 16):
        self.size = size
        self.seen = 0
        self.values: list[Any] = []
        self._rng = np.random.default_rng(seed)

    def add(self, value: Any) -> None:
        self.seen += 1
        if len(self.values) < self.size:
            self.values.append(value)
            return
        j = int(self._rng.integers(self.seen))
        if j < self.size:
            self.values[j] = value


def write_sensor_csv(out: Path, rows: list[dict[str, Any]]) -> None:
    """``out/sensors.csv``: the sensors' statistics (:data:`SENSOR_COLUMNS`)."""
    cols = {k: [r[k] for r in rows] for k in SENSOR_COLUMNS}
    types = {k: pa.string() if k in ("sensor", "kind", "time_bias_reference") else
             pa.int64() if k in ("tracks", "plots", "plots_gated", "plots_wild",
                                 "plots_no_reference", "coverage_holes", "offset_tracks")
             else pa.float64()
             for k in SENSOR_COLUMNS}
    pacsv.write_csv(pa.table({k: pa.array(v, types[k]) for k, v in cols.items()}),
                    out / "sensors.csv")


def iter_stats(path: Path) -> Iterator[list[dict[str, Any]]]:
    """The per-track sensor statistics of this run and earlier ones (a resumed run keeps
    them), one track at a time; a track written twice counts once, its last line. Streamed
    (twice through the file: the last line of each aircraft, then the lines): what is held
    is the aircraft keys, not their statistics."""
    if not path.exists():
        return
    last: dict[str, int] = {}
    for i, entry in _stats_lines(path):
        last[entry["aircraft"]] = i
    for i, entry in _stats_lines(path):
        if last[entry["aircraft"]] == i:
            yield entry["sensors"]


def _stats_lines(path: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    with open(path, encoding="utf-8") as f:
        for i, line in enumerate(f):
            try:
                entry = json.loads(line)
            except ValueError:  # torn by a killed run
                continue
            yield i, entry
