"""The per-track task of a run, on a worker (the command line's, and a service job's by
``service.jobs.job_track``): a track reconstructed (:func:`solver.batch.solve_track`) with
its sensors' statistics (:mod:`solver.sensor_stats`) and, where asked, its figure (drawn now)
or what its figure needs to be drawn later (:mod:`solver.figure_data`).

Submitted by reference (``solver.track_task.assess_track``): a worker imports this module,
and what it imports, not the command line's.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from .batch import TrackOutcome, solve_track
from .config import FILTER_GATE_SIGMA, MAX_SAMPLES, ReconstructionConfig
from .figure_data import figure_rows, from_reconstruction
from .plots import PlotTable
from .results import Reconstruction
from .sensor_stats import sensor_spans


@dataclass
class AssessedTrack(TrackOutcome):
    """A track's outcome with its sensors' statistics (:class:`solver.results.SensorReport`
    as dicts, plus each sensor's plot times span and median interval for the detection
    rate)."""

    sensors: list[dict[str, Any]] = field(default_factory=list)


def assess_track(key: str, table: PlotTable, config: ReconstructionConfig | None,
                 time_limit_s: float | None, figures_dir: str | None = None,
                 filters: Sequence[str] = (), filter_gate: float | None = FILTER_GATE_SIGMA,
                 times_of_day: bool = False, samples: bool = False,
                 max_samples: int | None = MAX_SAMPLES, figure_data: bool = False,
                 date: str | None = None) -> AssessedTrack:
    """:func:`solver.batch.solve_track` (with its keyword arguments) plus the
    per-sensor statistics and, with ``figures_dir``, the track's figure (drawn on the
    worker); with ``figure_data``, the rows its figure is drawn from later
    (:func:`solver.figure_data.figure_rows`, the samples among them unless ``samples.parquet``
    keeps them: about 1 KB for a three-plot track, where drawing its figure took 0.8 s of
    the worker against 63 ms to solve it)."""
    spans = sensor_spans(table)

    def extras(rec: Reconstruction) -> dict[str, Any]:
        if figures_dir is not None:
            from .figures import save, track_figure

            save(track_figure(table, rec, title=key, times_of_day=times_of_day, date=date),
                 Path(figures_dir) / f"{track_file_name(key)}.png")
        more: dict[str, Any] = {"sensors": [{**asdict(r), **spans.get(r.id, {})}
                                            for r in rec.sensors]}
        if figure_data:
            more["figure"] = from_reconstruction(table, rec)
        return more

    out = solve_track(key, table, config, time_limit_s, extras=extras, filters=filters,
                      filter_gate=filter_gate, times_of_day=times_of_day, samples=samples,
                      max_samples=max_samples, date=date)
    data = out.extras.get("figure")
    figure = None if data is None else figure_rows(key, data, samples=out.samples is None)
    return AssessedTrack(**{k: v for k, v in vars(out).items() if k not in ("extras", "figure")},
                         figure=figure, sensors=out.extras.get("sensors", []))


def track_file_name(key: str) -> str:
    """A file name for a track's key, distinct for distinct keys and readable: the key itself
    when it is a safe name ([A-Za-z0-9_.-], 1-120 characters; a Mode S address ``3C6DD4``),
    else the key made safe (a gap piece's ``#n`` as ``-gapn``, another aircraft's ``~n`` as
    ``-apartn``, other characters as ``_``, cut at 120) and ``-`` the first 10 hex digits of
    the key's SHA-256 (so too a safe key ending like that): keys ``AB 1`` and ``AB/1`` were
    both ``AB_1``, one figure over the other (a tester's). The same key always gives the same
    name (a rerun's figure replaces its own)."""
    if _SAFE.fullmatch(key) and not _HASHED.search(key):  # never a made name's form
        return key
    safe = _UNSAFE.sub("_", key.replace("#", "-gap").replace("~", "-apart"))[:120]
    return f"{safe}-{hashlib.sha256(key.encode()).hexdigest()[:10]}"


_SAFE = re.compile(r"(?![.]{1,2}$)[A-Za-z0-9_.-]{1,120}")
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]+")
_HASHED = re.compile(r"-[0-9a-f]{10}$")
