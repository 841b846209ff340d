"""Figures of a track and of a recording render (PNG) for one radar and for several sensors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pyarrow.parquet as pq
from test_refine_multisensor import SSR_A, SSR_B, _simulate

from solver.figures import png, recording_map, sensor_sites, track_figure
from solver.inputs import Plots, Radar
from solver.reconstruct import reconstruct

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_track_figure_of_two_radars_has_the_altitude_panel():
    table, *_ = _simulate((SSR_A, SSR_B), ((4.8, 0.3), (12.0, 1.1)), noise=1.0, t_end=400.0)
    rec = reconstruct(table)
    fig = track_figure(table, rec)
    assert len(fig.axes) == 5  # map, u, w, speed, height
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert any(label.startswith("A (radar") for label in labels)
    data = png(fig)
    assert data.startswith(PNG_MAGIC) and len(data) > 20_000


def test_track_figure_of_the_seed_radar_and_a_recording_map():
    t = 10.0 * np.arange(30)
    plots = Plots.from_arrays(t, 80e3 + 200.0 * t, np.deg2rad(30.0 + 0.01 * t))
    rec = reconstruct(plots, Radar(300.0, np.deg2rad(0.5)))
    from solver.plots import PlotTable

    table = PlotTable.from_plots(plots, Radar(300.0, np.deg2rad(0.5)))
    fig = track_figure(table, rec, title="seed radar")
    assert len(fig.axes) == 4 and fig.axes[0].get_title() == "seed radar"
    assert png(fig).startswith(PNG_MAGIC)
    tracks = [("a", rec.samples.x, rec.samples.z), ("b", rec.samples.x + 5e3, rec.samples.z)]
    fig = recording_map(tracks, sensor_sites(table))
    assert len(fig.axes[0].lines) == 3  # two tracks and the radar
    assert png(fig).startswith(PNG_MAGIC)


def test_track_figure_marks_the_manoeuvres():
    """The seed-like sample's five manoeuvres: numbered on the map, the two turns shaded and
    labelled on the u panel, the three speed changes on the w panel."""
    import json
    from pathlib import Path

    from service.convert import to_job
    from service.models import ReconstructionRequest
    from solver.plots import PlotTable

    body = json.loads((Path(__file__).resolve().parents[1] / "examples" / "seed_track.json")
                      .read_text())
    job = to_job(ReconstructionRequest.model_validate(body), "sqpmethod", 500, 20_000)
    rec = reconstruct(job.plots, job.radar, job.config)
    fig = track_figure(PlotTable.from_plots(job.plots, job.radar), rec)
    assert sorted(t.get_text() for t in fig.axes[0].texts) == ["1", "2", "3", "4", "5"]
    u_labels = [t.get_text() for t in fig.axes[1].texts]
    w_labels = [t.get_text() for t in fig.axes[2].texts]
    assert [s.split(":")[0] for s in u_labels] == ["2", "4"]
    assert [s.split(":")[0] for s in w_labels] == ["1", "3", "5"]
    assert len(fig.axes[1].patches) == 2 and len(fig.axes[2].patches) == 3


def test_what_a_figure_reviewer_asked_for():
    """A reviewer's points, each checked: clock times for a recording's track (seconds from a
    UTC midnight), the reconstruction's 95 % ellipses and the plots' 3-sigma ones in the
    legend, a sector radar's azimuth axis zoomed to its plots (and not across north), the
    estimated offsets said beside residuals that are after them ("bias -0.1 m" of a radar
    whose 119.6-m offset was taken off), a map's tracks coloured by key (a track kept its
    colour from run to run only by chance) with "1 track" in the singular."""
    from solver.figures import _azimuth_span, _offsets_text, clock

    assert clock(22_997.4) == "06:23:17" and clock(86_400 + 61) == "00:01:01 +1d"
    table, *_ = _simulate((SSR_A, SSR_B), ((4.8, 0.3), (12.0, 1.1)), noise=1.0, t_end=400.0)
    table = dataclasses.replace(table, t=table.t + 22_000.0)
    fig = track_figure(table, reconstruct(table), title="4CA2D1", times_of_day=True)
    assert fig.axes[-1].get_xlabel() == "time of day (UTC)"
    assert fig.axes[-1].xaxis.get_major_formatter()(22_020.0, 0) == "06:07:00"
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "its 95 % ellipses" in labels and any("3-sigma ellipses" in x for x in labels)
    assert fig._suptitle.get_text().startswith("4CA2D1: 06:06:40 to 06:13:")
    assert _azimuth_span(np.array([25.0, 40.0, 50.0])) == (20.0, 55.0)
    assert _azimuth_span(np.array([350.0, 5.0, 20.0])) == (0.0, 360.0)  # across north
    assert _azimuth_span(np.linspace(0, 350, 36)) == (0.0, 360.0)
    assert _offsets_text({"range_bias_m": 119.6, "azimuth_bias_deg": 0.0033,
                          "time_bias_s": -0.02}) == (
        "estimated offsets taken off: range +119.6 m, azimuth +0.003 deg, time -0.02 s")
    assert _offsets_text({"range_bias_m": None}) == ""
    x = np.linspace(0, 1e4, 5)
    one = recording_map([("B", x, x), ("A", x, -x)])
    two = recording_map([("A", x, -x), ("B", x, x)])
    assert [line.get_color() for line in one.axes[0].lines] == [
        line.get_color() for line in two.axes[0].lines]
    assert recording_map([("A", x, x)]).axes[0].get_title() == "1 track"


def drawn(fig) -> list:
    """What a figure draws, axes by axes: its lines' data, markers, colours and labels, its
    collections' paths (ellipses, bands) and colours, its patches (manoeuvre spans, in data
    coordinates), texts with their places, titles, axis labels, legend entries and limits."""
    out: list = [("suptitle", fig._suptitle.get_text() if fig._suptitle else None)]
    for ax in fig.axes:
        out.append(("axes", ax.get_title(), ax.get_xlabel(), ax.get_ylabel()))
        for line in ax.lines:
            out.append(("line", line.get_label(), str(line.get_marker()), str(line.get_color()),
                        line.get_drawstyle(), np.asarray(line.get_xydata(), float)))
        for c in ax.collections:
            out.append(("collection", type(c).__name__, np.asarray(c.get_facecolor()),
                        np.asarray(c.get_edgecolor()), len(c.get_paths()),
                        *(np.asarray(p.vertices, float) for p in c.get_paths())))
        for p in ax.patches:
            out.append(("patch", p.get_hatch(), p.get_patch_transform().transform(
                p.get_path().vertices)))
        for t in ax.texts:
            out.append(("text", t.get_text(), np.asarray(t.get_position(), float),
                        np.asarray(getattr(t, "xy", (0.0, 0.0)), float)))
        legend = ax.get_legend()
        out.append(("legend", None if legend is None else
                    [t.get_text() for t in legend.get_texts()]))
        out.append(("limits", np.array([*ax.get_xlim(), *ax.get_ylim()])))
    return out


def difference(a: list, b: list, rtol: float = 1e-9) -> str | None:
    """The first difference of two :func:`drawn` lists (numbers within ``rtol``, and 1e-9 of
    a km or a m/s^2 near zero), or None."""
    if len(a) != len(b):
        return f"{len(a)} items against {len(b)}"
    for i, (x, y) in enumerate(zip(a, b, strict=True)):
        if len(x) != len(y):
            return f"item {i}: {x[:2]} against {y[:2]}"
        for u, v in zip(x, y, strict=True):
            if isinstance(u, np.ndarray) or isinstance(v, np.ndarray):
                u, v = np.asarray(u), np.asarray(v)
                if u.shape != v.shape or not np.allclose(u, v, rtol=rtol, atol=1e-9,
                                                         equal_nan=True):
                    return f"item {i} {x[:2]}: {u!r} against {v!r}"
            elif u != v:
                return f"item {i} {x[:2]}: {u!r} against {v!r}"
    return None


def test_a_figure_drawn_from_a_runs_stored_rows_is_the_one_drawn_from_its_reconstruction(
        tmp_path):
    """A job keeps what each track's figure needs (solver.figure_data) instead of drawing it on
    the worker (0.8 s a figure against 63 ms to solve a three-plot track); drawn from the rows
    committed to disk it shows what the figure drawn from the live reconstruction shows: the
    plots with their 3-sigma ellipses per sensor, the reconstruction with its 95 % ellipses
    and switches, the manoeuvres, the controls, speed and height over time, the titles and
    legends; with the samples kept in the figure's rows or (asked for) in samples.parquet; by
    the refinement, and by the sliding windows for plots of one instant (no segment: that
    figure raised an IndexError). A changed ellipse or sample step is told apart."""
    import concurrent.futures as cf
    from functools import partial

    from solver.batch import TrackProblem, ledger_entries, reconstruct_many
    from solver.config import ReconstructionConfig
    from solver.figure_data import FIGURE_DATA, read_stored
    from solver.figures import draw_track_figure
    from solver.plots import PlotTable
    from solver.sensors import PositionSensor
    from solver.track_task import assess_track

    legs = ((0, 0, 40), (2.0, 0.1, 80), (0, -0.5, 40), (0, 0, 40))  # a turn, a slowing
    table, *_ = _simulate((SSR_A, SSR_B), ((4.8, 0.3), (12.0, 1.1)), noise=1.0, t_end=200.0,
                          legs=legs)
    table = dataclasses.replace(table, t=table.t + 22_000.0)  # a recording's times of day
    instant = PlotTable.build((SSR_A, SSR_B, PositionSensor("ADSB", 30.0)), [50.0] * 3,
                              ["A", "B", "ADSB"], range_m=[60e3, 70e3, np.nan],
                              azimuth_rad=[0.5, 0.6, np.nan], lat_deg=[np.nan, np.nan, 46.5],
                              lon_deg=[np.nan, np.nan, 14.9], altitude_m=[9e3, 9e3, 9e3])
    cases = (("two radars", table, ReconstructionConfig(), False, True),
             ("samples kept", table, ReconstructionConfig(sample_step_s=7.0), True, True),
             ("one instant", instant, ReconstructionConfig(method="sliding"), False, False))
    figures = {}
    for name, tab, config, keep, times_of_day in cases:
        out = tmp_path / name
        date = "2024-02-28" if times_of_day else None
        with cf.ThreadPoolExecutor(1) as pool:
            reconstruct_many([TrackProblem(name, tab)], out, config=config, executor=pool,
                             task=partial(assess_track, figure_data=True, samples=keep,
                                          times_of_day=times_of_day, date=date))
        (entry,) = ledger_entries(out)
        assert entry["status"] == "done", entry
        assert (out / "samples.parquet").is_dir() == keep
        data, tod, stored_date = read_stored(out, entry["part"], name)
        assert (tod, stored_date) == (times_of_day, date)
        lazy = drawn(draw_track_figure(data, title="K", times_of_day=tod, date=stored_date))
        live = track_figure(tab, reconstruct(tab, config=config), title="K",
                            times_of_day=times_of_day, date=date)
        assert difference(lazy, drawn(live)) is None, (name, difference(lazy, drawn(live)))
        assert len(live.axes) == (5 if data.sample_h is not None else 4)
        figures[name] = (data, lazy)
        if name == "two radars":
            assert data.sample_h is not None and len(data.segments) > 1
            assert [t.get_text() for t in live.axes[0].texts] == ["1", "2"]  # manoeuvres
            assert live._suptitle.get_text().startswith("K: 2024-02-28 06:06:40 to ")
            tick = live.axes[-1].xaxis.get_major_formatter()
            assert tick(86_400.0 + 60.0, 0) == "00:01:00\n+1d"  # two lines: no overlap
            assert len(live.axes[0].collections) == 3  # each radar's plots, the track's
            rows = pq.read_table(out / FIGURE_DATA)
            assert rows.column("item").to_pylist().count("plot") == len(tab)
            assert rows.column("item").to_pylist().count("sample") == len(data.sample_t)
            moved = dataclasses.replace(data, plot_cov=data.plot_cov * 1.01)
            assert "collection" in difference(
                drawn(draw_track_figure(moved, "K", tod, stored_date)), lazy)
        if name == "one instant":
            assert data.segments == [] and live.axes[1].lines[0].get_xydata().size == 0
    # another sample step draws another line: told apart
    assert difference(figures["two radars"][1], figures["samples kept"][1]) is not None


def test_track_figures_drawn_in_threads_at_once_are_those_drawn_one_by_one():
    """The service draws figures in threads; matplotlib's mathtext parser (the controls'
    m/s^2 labels) is one per process, and figures drawn at once failed its parse
    (ParseException: 4 threads, 24 figures). track_png draws one at a time: the same bytes."""
    import concurrent.futures as cf

    from solver.figure_data import from_reconstruction
    from solver.figures import track_png
    from solver.plots import PlotTable

    t = 10.0 * np.arange(12)
    plots = Plots.from_arrays(t, 80e3 + 200.0 * t, np.deg2rad(30.0 + 0.01 * t))
    radar = Radar(300.0, np.deg2rad(0.5))
    data = from_reconstruction(PlotTable.from_plots(plots, radar), reconstruct(plots, radar))
    with cf.ThreadPoolExecutor(4) as pool:
        drawn_at_once = list(pool.map(lambda _: track_png(data, "T"), range(4)))
    assert drawn_at_once == [track_png(data, "T")] * 4
