"""Figures of a track and of a recording render (PNG) for one radar and for several sensors."""

from __future__ import annotations

import dataclasses

import numpy as np
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
