"""The command line (spec recordings.md):

    trajrecon reconstruct RECORDING --sensors SENSORS.json --out DIR [--scheduler ADDRESS]
        [--workers N] [--method refined|sliding] [--bounds NAME=MIN,MAX ...]
        [--filters NAME ...] [--samples STEP] [--aircraft KEY ...] [--edition CAT=EDITION ...]
        [--date YYYY-MM-DD] [--figures] ...
    trajrecon plot RECORDING --sensors SENSORS.json --out DIR [--aircraft KEY ...] [--map]

(``trajrecon RECORDING ...`` is ``trajrecon reconstruct RECORDING ...``.) ``reconstruct`` reads a
recording (raw ASTERIX or a pcap/pcapng capture of it: CAT048, CAT021, CAT034; or a plot table
in CSV or Parquet, see ``solver/io/README.md``) and the sensor file, splits it into aircraft
as it reads (:mod:`solver.io.reading`), reconstructs every track on Dask (an embedded
``LocalCluster`` sized to the cores, or the cluster at ``--scheduler``; the task:
:mod:`solver.track_task`) with a progress bar, and writes into ``DIR``:

- with the recording's date (``--date``, else a capture's packet times or a table's
  ``timestamp``: :mod:`solver.io.dates`) ``time_utc`` beside ``t`` in every output;
- ``tracks.parquet/``, ``segments.parquet/``, with ``--filters`` ``filters.parquet/`` and
  with ``--samples STEP`` ``samples.parquet/`` (at most :data:`solver.config.MAX_SAMPLES`
  a track: one that would have more keeps none, with a warning; streamed as tracks finish; a rerun
  resumes), ``progress.jsonl`` (:mod:`solver.batch`), and at the end ``tracks.csv`` and
  ``tracks.geojsonl`` (one GeoJSON feature per aircraft, for maps) and ``manoeuvres.csv``
  (every track's turns and speed changes) (:mod:`solver.outputs`);
- ``sensors.json`` and ``sensors.csv``: per sensor, against the reconstruction
  (SASS-C/TRES-style assessment, :mod:`solver.sensor_stats`): plots, detection rate, wild
  plots, bias and sigma of the range and azimuth residuals, estimated offsets where asked;
- ``run.json``: the method, bounds, filters, sample step and ASTERIX editions chosen
  (``--edition 21=0.26``) and ``--date``; a rerun resumes only a run with the same
  (:mod:`solver.run_settings`);
- ``sensors.png``: each radar's range and azimuth residuals over range and azimuth
  (:mod:`solver.assessment`);
- ``problems.txt`` (everything left out of the recording, located and counted), ``map.png``
  (every track with the radar sites), ``figures/<track>.png`` with ``--figures`` (named by
  :func:`solver.track_task.track_file_name`: distinct keys, distinct files),
  ``summary.json``; a summary is printed at the end (tracks, plots, failures, plots/s).

``plot`` draws ``figures/<aircraft>.png`` for the named aircraft and, with ``--map``,
``map.png`` and ``sensors.png`` again.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

from .assessment import write_sensors_figure
from .batch import (
    BatchSummary,
    TrackOutcome,
    dask_settings,
    embedded_cluster,
    ledger_entries,
    quiet_interrupted_sync,
    reconstruct_many,
)
from .config import FILTER_GATE_SIGMA, MAX_SAMPLES, MIN_TRIAL_STEP_S, ReconstructionConfig
from .inputs import Bounds, InputError
from .io.altitudes import offsets_summary
from .io.asterix import edition_choices, parse_edition
from .io.dates import parse_date
from .io.reading import Selection, Streamed, check_recording, stream
from .io.sensors_file import load_sensors
from .outputs import output_state, write_csv_and_geojson, write_manoeuvres, write_map
from .run_settings import RunSettings, keep_inputs, parse_bounds
from .run_settings import keep as keep_settings
from .run_settings import stored as stored_settings
from .sensor_stats import SensorStats, iter_stats, write_sensor_csv
from .stopping import STOP_SIGNALS, Stopped
from .track_task import AssessedTrack, assess_track, track_file_name

GC_YOUNG_THRESHOLD = 10_000
"""Allocations between two collections of the cyclic garbage collector's youngest generation
while the command line runs (Python's default: 700). libasterix builds and drops several
objects per item it parses, and every young collection walks what survived: measured on the
200-aircraft benchmark recording decoded in a process that has imported what the command line
imports, 0.25 ms CPU a plot with the default, 0.16-0.17 with this (gc disabled: 0.19-0.21, in
the noise of a shared machine); the reference counts free almost everything anyway."""


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The whole pipeline; returns the summary (also written as ``summary.json``)."""
    with _young_collections(GC_YOUNG_THRESHOLD):
        return _run(args)


@contextmanager
def _young_collections(threshold: int) -> Iterator[None]:
    """The garbage collector's first threshold set to ``threshold``, restored at the end."""
    old = gc.get_threshold()
    gc.set_threshold(threshold, *old[1:])
    try:
        yield
    finally:
        gc.set_threshold(*old)


def _run(args: argparse.Namespace) -> dict[str, Any]:
    out = Path(args.out)
    _check_out(out, Path(args.sensors))
    started = time.perf_counter()
    load_sensors(Path(args.sensors))  # a bad sensor file is refused before a cluster starts
    check_recording(Path(args.recording))  # a missing one too (it took 25 s: the cluster's)
    settings = _settings(args)
    keep_settings(out, settings)  # a rerun resumes only the same run
    keep_inputs(out, Path(args.recording), Path(args.sensors))  # ... of the same files
    with _cluster(args.scheduler, args.workers) as client:
        on_cluster = args.decode == "cluster" or (args.decode == "auto"
                                                  and args.scheduler is not None)
        loaded = stream(Path(args.recording), Path(args.sensors),
                        executor=client if on_cluster else None,
                        max_speed=settings.config().bounds.v[1],
                        editions=settings.asterix_editions(), date=settings.date)
        chosen = Selection(getattr(args, "aircraft", None))
        loaded.tracks = chosen.filter(loaded.tracks)
        summary, first_result_s = _reconstruct(args, settings, out, loaded, client, started)
    return _finish(args, settings, out, loaded, summary, first_result_s, started, chosen)


def _settings(args: argparse.Namespace) -> RunSettings:
    given = [name for name, value in (("--window-plots", args.window_plots),
                                      ("--trial-step", args.trial_step),
                                      ("--criterion", args.criterion)) if value is not None]
    if given and args.method != "sliding":
        raise InputError(("method",), f"{', '.join(given)} set the sliding windows, which the "
                         f"{args.method} method does not use: add --method sliding, or leave "
                         "them out")
    return RunSettings(args.method, parse_bounds(args.bounds), tuple(args.filters),
                       args.samples, **_windows(args, RunSettings()),
                       filter_gate_sigma=args.filter_gate, editions=tuple(args.edition or ()),
                       date=args.date)


def _check_out(out: Path, sensors: Path) -> None:
    """``--out`` must be a directory (or not yet exist), and the statistics' ``sensors.json``
    must not overwrite the sensor file given."""
    if out.exists() and not out.is_dir():
        raise InputError(("out",), f"{out} is a file, not a directory")
    target = out / "sensors.json"
    if target.exists() and sensors.exists() and target.samefile(sensors):
        raise InputError(("out",), f"{out} holds the sensor file {sensors}, which the run "
                         "would overwrite with the sensors' statistics: choose another --out")


@contextmanager
def _cluster(scheduler: str | None, workers: int | None) -> Iterator[Any]:
    """A Dask client of the scheduler at ``scheduler``, else of an embedded ``LocalCluster``
    of ``workers`` processes (default: the usable cores; as :func:`solver.batch.
    reconstruct_many` would start), closed at the end. A stop (SIGINT, SIGTERM) while it
    starts or closes is held until it has (:mod:`solver.stopping`)."""
    import dask
    from distributed import Client

    stack = ExitStack()
    try:
        with STOP_SIGNALS.deferred(), dask.config.set(dask_settings()):
            if scheduler is not None:
                try:
                    client = stack.enter_context(Client(scheduler))
                except OSError as e:  # distributed's connection timeout is an OSError too
                    raise InputError(("scheduler",), f"no Dask scheduler answers at "
                                     f"{scheduler} ({e})") from None
            else:
                cluster = stack.enter_context(embedded_cluster(workers))
                client = stack.enter_context(Client(cluster))
        yield client
    finally:
        with STOP_SIGNALS.deferred():
            stack.close()


def _reconstruct(args: argparse.Namespace, settings: RunSettings, out: Path, loaded: Streamed,
                 client: Any, started: float) -> tuple[BatchSummary, float | None]:
    """Every track of ``loaded`` on ``client``, with the sensors' statistics recorded as
    they come; the summary and the time to the first result."""
    config = settings.config()
    stats_path = out / "sensor_stats.jsonl"
    first_result: list[float] = []
    bar = _progress(args.no_progress)

    def on_outcome(o: TrackOutcome) -> None:
        if not first_result:
            first_result.append(time.perf_counter() - started)
        if isinstance(o, AssessedTrack) and o.sensors:  # on disk only, read back at the end
            with open(stats_path, "a", encoding="utf-8") as f:
                f.write(json.dumps({"aircraft": o.key, "sensors": o.sensors}) + "\n")
        if bar is not None:
            bar.update(1)
            bar.set_postfix(plots=o.plots, failed=o.status == "failed", refresh=False)

    figures = str(out / "figures") if args.figures else None

    task = partial(assess_track, figures_dir=figures, filters=settings.filters,
                   filter_gate=settings.filter_gate_sigma,
                   times_of_day=bool(loaded.times_of_day), date=loaded.date,
                   samples=settings.sample_step_s is not None, max_samples=MAX_SAMPLES)
    summary: BatchSummary = reconstruct_many(
        loaded.tracks, out, config=config, executor=client,
        time_limit_s=args.time_limit or None, retry_failed=args.retry_failed,
        on_outcome=on_outcome, task=task)
    if bar is not None:
        bar.close()
    return summary, first_result[0] if first_result else None


def _finish(args: argparse.Namespace, settings: RunSettings, out: Path, loaded: Streamed,
            summary: BatchSummary, first_result_s: float | None, started: float,
            chosen: Selection | None = None) -> dict[str, Any]:
    """The whole-recording outputs once every track is in."""
    stats_path = out / "sensor_stats.jsonl"
    stats = SensorStats(loaded.sensors, loaded.scan_periods)  # the periods read by now
    for reports in iter_stats(stats_path):
        stats.add(reports)
    sensor_rows = stats.rows()
    write_sensor_csv(out, sensor_rows)
    (out / "sensors.json").write_text(json.dumps(sensor_rows, indent=1) + "\n",
                                      encoding="utf-8")
    (out / "summary.json").unlink(missing_ok=True)  # stale while the files below are written
    csv_rows, geo_tracks = write_csv_and_geojson(out)
    manoeuvres = write_manoeuvres(out, loaded.frame, loaded.date)
    state = output_state(out)
    write_map(out, loaded.sensors, frame=loaded.frame)
    write_sensors_figure(out, [s.id for s in loaded.sensors.sensors])
    (out / "problems.txt").write_text(loaded.problems.summary() + "\n", encoding="utf-8")
    result = {
        "recording": str(args.recording), **settings.as_json(),
        "tracks": summary.tracks, "done": summary.done,
        "failed": summary.failed, "skipped": summary.skipped, "plots": summary.plots,
        "rows_in_recording": loaded.rows_read, "recording_date": loaded.date,
        "elapsed_s": time.perf_counter() - started,
        "reconstruct_s": summary.elapsed_s, "plots_per_s": summary.plots_per_s,
        "time_to_first_result_s": first_result_s,
        "mode_c_offsets": offsets_summary(loaded.mode_c_offsets),
        "problems": dict(loaded.problems.counts),
        "dropped": loaded.problems.left_out(), "failures": summary.failures,
        "csv_rows": csv_rows, "geojson_tracks": geo_tracks, "manoeuvres": manoeuvres,
        "output": state, "sensors": sensor_rows}
    if chosen is not None and chosen.keys is not None:
        result.update(aircraft=sorted(chosen.keys), aircraft_not_found=chosen.missing())
    (out / "summary.json").write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    return result


def _progress(disabled: bool) -> Any:
    if disabled:
        return None
    from tqdm import tqdm

    return tqdm(unit="track", desc="reconstructing", dynamic_ncols=True)


def print_summary(result: dict[str, Any], file: Any = None) -> None:
    """The end-of-run summary: counts, rate, problems, failures, the sensors' table."""
    file = file or sys.stdout
    p = result
    print(f"tracks: {p['tracks']} ({p['done']} reconstructed by {p.get('method', 'refined')}, "
          f"{p['failed']} failed, "
          f"{p['skipped']} finished before); plots: {p['plots']}; "
          f"{p['plots_per_s']:.0f} plots/s; {p['elapsed_s']:.1f} s in all", file=file)
    if p["problems"]:
        lost = p.get("dropped") or {}
        print("left out or reported: " + ", ".join(
            f"{k} {n}" + (f" ({lost[k]} plots left out)" if lost.get(k) else "")
            for k, n in p["problems"].items()), file=file)
    for key, why in list(p["failures"].items())[:10]:
        print(f"failed {key}: {why}", file=file)
    state = p.get("output")
    if state:
        earlier = {k: v for k, v in state["failures"].items() if k not in p["failures"]}
        if earlier:
            print(f"{len(earlier)} track(s) failed in an earlier run and were not retried "
                  "(--retry-failed redoes them):", file=file)
            for key, why in list(earlier.items())[:10]:
                print(f"failed {key}: {why}", file=file)
        if state["tracks_with_warnings"]:
            print(f"{state['tracks_with_warnings']} of {state['tracks_done']} track(s) "
                  "reconstructed with warnings (all of them in warnings.csv), e.g.:", file=file)
            for key, texts in list(state["warnings"].items())[:5]:
                print(f"  {key}: {texts[0][:200]}", file=file)
    # residuals after the estimated offsets (those on the lines below)
    # and the sensors' sigmas estimated from them (sigma_estimates)
    print(f"{'sensor':<12}{'plots':>8}{'det.':>7}{'wild':>6}{'no ref':>7}{'range res.':>12}"
          f"{'sigma':>8}"
          f"{'az res.':>10}{'sigma':>8}{'est. sigma r / az / pos':>26}", file=file)
    for r in p["sensors"]:
        def f(v: Any, fmt: str) -> str:
            return format(v, fmt) if v is not None else "-"
        estimated = (f"{f(r.get('range_sigma_estimate_m'), '.1f')} / "
                     f"{f(r.get('azimuth_sigma_estimate_deg'), '.3f')} / "
                     f"{f(r.get('position_sigma_estimate_m'), '.1f')}")
        print(f"{r['sensor']:<12}{r['plots']:>8}{f(r['detection_rate'], '.2f'):>7}"
              f"{r['plots_wild']:>6}{r.get('plots_no_reference', 0):>7}"
              f"{f(r['range_residual_mean_m'], '.1f'):>12}"
              f"{f(r['range_residual_sigma_m'], '.1f'):>8}"
              f"{f(r['azimuth_residual_mean_deg'], '.3f'):>10}"
              f"{f(r['azimuth_residual_sigma_deg'], '.3f'):>8}{estimated:>26}", file=file)
    for r in p["sensors"]:
        if r.get("range_bias_m") is not None:
            print(f"{r['sensor']}: estimated offsets range {r['range_bias_m']:+.1f}"
                  f"{_pm(r, 'range_bias_sigma_m', '.1f')} m, azimuth "
                  f"{r['azimuth_bias_deg']:+.4f}{_pm(r, 'azimuth_bias_sigma_deg', '.4f')} deg, "
                  f"time {r['time_bias_s']:+.3f}{_pm(r, 'time_bias_sigma_s', '.3f')} s "
                  f"(pooled over {r['offset_tracks']} "
                  f"tracks, weighted by their precision; time against "
                  f"{r['time_bias_reference']}; to take them off every track it sees, those "
                  "it sees alone too, add them to its sensor-file entry's range_offset_m, "
                  "azimuth_offset_deg and time_offset_s)", file=file)
    for r in p["sensors"]:
        if r.get("along_track_residual_mean_m") is not None:
            print(f"{r['sensor']}: along the track {r['along_track_residual_mean_m']:+.1f} m "
                  f"(sigma {r['along_track_residual_sigma_m']:.1f}; a late report lies behind), "
                  f"across {r['cross_track_residual_mean_m']:+.1f} m "
                  f"(sigma {r['cross_track_residual_sigma_m']:.1f})"
                  + ("" if r.get("time_bias_s") is None
                     else f"; time offset {r['time_bias_s']:+.3f} s"), file=file)


def _pm(row: dict[str, Any], key: str, fmt: str) -> str:
    """`` +- value`` of ``row[key]``, or nothing where it is None."""
    return "" if row.get(key) is None else f" +- {format(row[key], fmt)}"


COMMANDS = ("reconstruct", "plot")
UNUSABLE_PATH = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)
"""A path given that cannot be read or written: a one-line error, exit status 2."""


def parser() -> argparse.ArgumentParser:
    """``trajrecon reconstruct ...`` and ``trajrecon plot ...`` (spec recordings.md)."""
    from .estimation import FILTER_NAMES

    ap = argparse.ArgumentParser(
        prog="trajrecon", description="Reconstruct every aircraft of a recording (ASTERIX "
        "CAT048/021/034, pcap, pcapng, or a CSV/Parquet plot table) with its sensors' "
        "statistics, and draw its figures. `trajrecon RECORDING ...` is `trajrecon "
        "reconstruct RECORDING ...`.")
    sub = ap.add_subparsers(dest="command", required=True, metavar="{reconstruct,plot}")
    rec = sub.add_parser("reconstruct", help="reconstruct every aircraft into --out",
                         description="Reconstruct every aircraft of RECORDING into --out "
                         "(Parquet, CSV, GeoJSON lines, sensor statistics, map, summary); "
                         "a rerun resumes.")
    _inputs(rec)
    rec.add_argument("--scheduler", default=None, help="address of an existing Dask "
                     "scheduler (default: an embedded LocalCluster)")
    rec.add_argument("--workers", type=_count, default=None, help="embedded cluster's worker "
                     "processes (default: the usable cores)")
    rec.add_argument("--time-limit", type=partial(_seconds, zero=True), default=300.0,
                     help="per-track limit (s; 0: none)")
    rec.add_argument("--decode", choices=("local", "cluster", "auto"), default="auto",
                     help="where ASTERIX is decoded: in this process, a reading thread "
                     "overlapping the reconstruction; on the cluster's workers; or auto "
                     "(default): on the cluster named by --scheduler (this process would "
                     "hold back its many workers), here with the embedded one (decoding on "
                     "its workers cost the machine 11 %% more CPU for the same wall time: "
                     "benchmarks/results/cli_overhead.md)")
    _method(rec, "refined")
    _bounds(rec, [])
    _edition(rec, "")
    rec.add_argument("--date", type=_date_arg, default=None, metavar="YYYY-MM-DD",
                     help="the UTC date of the midnight the recording's times of day count "
                     "from (its first plot's day), for the UTC times of the outputs "
                     "(time_utc): a raw ASTERIX or IOSS recording does not carry it; a pcap "
                     "capture's packet times give it (a date given overrides theirs, reported: "
                     "date_override), a table's timestamp column too (a date that "
                     "contradicts it is an error)")
    rec.add_argument("--filters", nargs="+", default=[], choices=FILTER_NAMES,
                     metavar="FILTER", help="recursive filters run beside the reconstruction "
                     f"into --out/filters.parquet ({', '.join(FILTER_NAMES)})")
    rec.add_argument("--filter-gate", type=_gate, default=FILTER_GATE_SIGMA, metavar="SIGMA",
                     help="the filters' validation gate: a plot farther than SIGMA sigmas from "
                     "a filter's prediction, and not borne out by the next plot, is left out "
                     f"(filters.parquet's gated column); 'off': every plot used (default "
                     f"{FILTER_GATE_SIGMA:g}; alpha_beta and fusion_* use every plot)")
    rec.add_argument("--aircraft", nargs="+", default=None, metavar="KEY",
                     help="reconstruct only these aircraft (keys as in tracks.parquet, e.g. a "
                     "Mode S address 3C6DD4, in either case; a key takes its later pieces "
                     "KEY#2 ... too, a radar track associated into another's key, e.g. "
                     "R2:track:40 in R1:track:12, that aircraft); the whole recording is "
                     "still read, and a key it does not hold makes the exit status 2 after the "
                     "others are written")
    rec.add_argument("--samples", type=_seconds, default=None, metavar="STEP",
                     help="also write every track's state every STEP seconds (from its first "
                     "plot to its last, with the covariance) into --out/samples.parquet; a "
                     f"track that would have more than {MAX_SAMPLES:,} samples keeps none, with "
                     "a warning (warnings.csv)")
    rec.add_argument("--figures", action="store_true", help="also draw every track's figure")
    rec.add_argument("--retry-failed", action="store_true", help="redo tracks that failed in "
                     "an earlier run")
    rec.add_argument("--no-progress", action="store_true", help="no progress bar")
    plot = sub.add_parser("plot", help="draw figures of named aircraft and the map",
                          description="Draw --out/figures/<aircraft>.png for each named "
                          "aircraft of RECORDING (its plots with their ellipses, the "
                          "reconstruction, the controls over time; reconstructed again here "
                          "with the method and bounds of the run in --out, if there is one) "
                          "and, with --map, --out/map.png from the tracks `reconstruct` wrote "
                          "there. The reading stops once every named aircraft is complete.")
    _inputs(plot)
    plot.add_argument("--aircraft", nargs="+", default=[], metavar="KEY",
                      help="aircraft keys as in tracks.parquet (e.g. a Mode S address 3C6DD4)")
    plot.add_argument("--map", action="store_true", help="redraw map.png and sensors.png "
                      "from --out's tracks")
    _method(plot, None)
    _bounds(plot, None)
    _edition(plot, "; default: the run's in --out")
    return ap


def _seconds(text: str, *, zero: bool = False) -> float:
    """A finite number of seconds: positive (``--samples``), or 0 too (``zero``:
    ``--time-limit``, where 0 is no limit)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not ((0 <= value) if zero else (0 < value)) or value == math.inf:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds >= 0" if zero
                                         else f"{text!r} is not a positive number of seconds")
    return value


def _gate(text: str) -> float | None:
    """``--filter-gate``: a positive number of sigmas, or ``off``."""
    if text.strip().lower() == "off":
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of sigmas or off")
    return value


def _count(text: str) -> int:
    """``--workers``: a positive whole number."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive whole number")
    return value


def _inputs(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("recording", help="raw ASTERIX file, pcap/pcapng capture, or "
                    ".csv/.parquet table")
    ap.add_argument("--sensors", required=True, help="sensor file (JSON, solver/io/README.md)")
    ap.add_argument("--out", required=True, help="output directory")


def _method(ap: argparse.ArgumentParser, default: str | None) -> None:
    """``--method`` and the sliding windows' settings (``default`` None: the run's in --out)."""
    d = ReconstructionConfig()
    run = "" if default else "; default: the run's in --out"
    ap.add_argument("--method", choices=("refined", "sliding"), default=default,
                    help="refined (the full-track NLP, default) or sliding (the seed's windows "
                    "alone, over every sensor's plots in time order; no covariance, no sensor "
                    f"offsets){run}")
    ap.add_argument("--window-plots", type=int, default=None, metavar="M",
                    help=f"sliding: plots per window (>= 2; default {d.window_plots}{run})")
    ap.add_argument("--trial-step", type=float, default=None, metavar="S",
                    help="sliding: spacing of the extra trial start points between plots (s, "
                    f">= {MIN_TRIAL_STEP_S:g}; default {d.trial_step_s:g}{run})")
    ap.add_argument("--criterion", choices=("R1", "R2"), default=None,
                    help="sliding: window fit criterion, R1 plain least squares or R2 weighted "
                    f"by each plot's ellipse (default {d.criterion}{run})")


def _windows(args: argparse.Namespace, run: RunSettings) -> dict[str, Any]:
    """The sliding windows' settings given on the command line, else ``run``'s; checked
    (:class:`InputError` at ``window.plots`` / ``window.trial_step_s``)."""
    out = {"window_plots": run.window_plots if args.window_plots is None else args.window_plots,
           "trial_step_s": run.trial_step_s if args.trial_step is None else args.trial_step,
           "criterion": args.criterion or run.criterion}
    ReconstructionConfig(**out).validate()
    return out


def _edition(ap: argparse.ArgumentParser, run: str) -> None:
    """``--edition CAT=EDITION`` (repeatable): the ASTERIX edition a category is read as."""
    ap.add_argument("--edition", action="append", type=_edition_arg, default=None,
                    metavar="CAT=EDITION", help="read the recording's ASTERIX category CAT as "
                    "this edition (repeatable; e.g. --edition 21=0.26 for an older ADS-B "
                    "ground station: ASTERIX data do not say their edition, and another "
                    "edition's records read as garbage or not at all, reported in problems.txt)"
                    f": {edition_choices()}{run}")


def _date_arg(text: str) -> str:
    try:
        return parse_date(text)
    except InputError as e:
        raise argparse.ArgumentTypeError(e.message) from None


def _edition_arg(text: str) -> tuple[int, str]:
    try:
        return parse_edition(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _bounds(ap: argparse.ArgumentParser, default: list[str] | None) -> None:
    d = Bounds()
    ap.add_argument("--bounds", nargs="+", default=default, metavar="NAME=MIN,MAX",
                    help="the aircraft model's bounds for every track: u (lateral "
                    "acceleration, m/s^2), w (longitudinal, m/s^2), v (ground speed, m/s); "
                    f"unnamed ones keep their defaults u={d.u[0]:g},{d.u[1]:g} "
                    f"w={d.w[0]:g},{d.w[1]:g} v={d.v[0]:g},{d.v[1]:g} (e.g. --bounds v=15,250 "
                    "for slower aircraft)" + ("" if default is not None else "; default: the "
                                              "run's in --out"))


def plot(args: argparse.Namespace) -> tuple[list[Path], list[str]]:
    """The figures of ``trajrecon plot`` written, and the aircraft named that the recording
    does not hold (the map is drawn all the same, as ``reconstruct --aircraft`` writes the
    others); raises :class:`InputError` for a map without tracks."""
    from .figures import save, track_figure
    from .reconstruct import reconstruct

    out = Path(args.out)
    if not args.aircraft and not args.map:
        raise InputError(("aircraft",), "name at least one aircraft, or --map")
    written: list[Path] = []
    chosen = Selection(args.aircraft)  # an address in either case, an associated track's key
    run = stored_settings(out) or RunSettings()
    bounds = run.bounds if args.bounds is None else parse_bounds(args.bounds)
    if args.edition is not None:
        run = replace(run, editions=tuple(args.edition))
    # its plane: after the first part; its aircraft told apart as the run's
    loaded = stream(Path(args.recording), Path(args.sensors), max_speed=bounds.v[1],
                    editions=run.asterix_editions())
    if chosen.keys:
        config = RunSettings(args.method or run.method, bounds, **_windows(args, run)).config()
        for track in chosen.filter(loaded.tracks):
            rec = reconstruct(track.table, config=config)
            written.append(save(track_figure(track.table, rec, title=track.key,
                                             times_of_day=bool(loaded.times_of_day),
                                             date=loaded.date),
                                out / "figures" / f"{track_file_name(track.key)}.png"))
            if chosen.found == chosen.keys:  # each key's first track drawn: the rest unread
                break
    if args.map:
        path = write_map(out, loaded.sensors, frame=loaded.frame)
        if path is None:
            raise InputError(("out",), f"{out} holds no reconstructed track: run "
                             "`trajrecon reconstruct` first")
        written.append(path)
        radars = write_sensors_figure(out, [s.id for s in loaded.sensors.sensors])
        if radars is not None:
            written.append(radars)
    return written, chosen.missing()


def main(argv: Sequence[str] | None = None) -> int:
    """Exit status: 0 all tracks done (or figures drawn), 1 some failed (in this run, or in an
    earlier one of the output directory and not retried), 2 bad input (also a recording of
    which no aircraft's track could be read), 130 /
    143 stopped by SIGINT / SIGTERM (the cluster closed, the finished tracks kept: the same
    command resumes)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] not in (*COMMANDS, "-h", "--help"):
        argv.insert(0, "reconstruct")  # the form before the subcommands
    args = parser().parse_args(argv)
    if args.command == "plot":
        try:
            written, missing = plot(args)
        except (InputError, *UNUSABLE_PATH) as e:
            print(f"trajrecon: {e}", file=sys.stderr)
            return 2
        for path in written:
            print(path)
        if missing:  # after the others are written, as reconstruct --aircraft
            print(f"trajrecon: aircraft {', '.join(missing)} not in the recording (or too "
                  f"short to reconstruct: {args.out}/problems.txt of a reconstruct run names "
                  "them)", file=sys.stderr)
            return 2
        return 0
    quiet_interrupted_sync()
    try:
        with STOP_SIGNALS.installed():
            result = run(args)
    except (InputError, *UNUSABLE_PATH) as e:
        print(f"trajrecon: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        name = "SIGTERM" if isinstance(e, Stopped) else "SIGINT"
        print(f"trajrecon: stopped by {name}; {len(ledger_entries(args.out))} finished "
              f"tracks are kept in {args.out}: the same command resumes from there",
              file=sys.stderr)
        return 143 if isinstance(e, Stopped) else 130
    print_summary(result)
    if not result["tracks"] and result.get("aircraft") is None:
        print(f"trajrecon: no aircraft's track could be read from {args.recording} (what was "
              f"left out, and why: {Path(args.out) / 'problems.txt'})", file=sys.stderr)
        return 2
    if result.get("aircraft_not_found"):
        print(f"trajrecon: not in the recording (or too short to reconstruct: "
              f"{Path(args.out) / 'problems.txt'} names those): "
              f"{', '.join(result['aircraft_not_found'])}", file=sys.stderr)
        return 2
    return 1 if result["output"]["tracks_failed"] else 0


if __name__ == "__main__":
    # ``python -m solver.cli`` runs this file as ``__main__``, whose functions Dask pickles by
    # value (a task defined here was sent at 8.5 KB with its result class and helpers, and
    # every result twice: plain pickle, then cloudpickle on seeing ``__main__``; 3.1 ms a
    # track instead of 1.1). The importable module's ``main`` runs instead, so nothing of
    # ``__main__`` reaches Dask; its task, ``solver.track_task.assess_track``, lives in a
    # module of its own and is pickled by reference.
    from solver.cli import main as _main

    raise SystemExit(_main())
