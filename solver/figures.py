"""Figures a person would rather look at than read (matplotlib, Agg; PNG bytes or files).

- :func:`track_figure`: one aircraft, in the style of seed 000's figures 4-8: the plots of
  every sensor with their 3-sigma ellipses (the a priori maximum errors of a radar whose sigmas
  are a third of them), the reconstructed trajectory with its switch points and 95 % ellipses,
  and beside it the controls ``u(t)``, ``w(t)``, the speed and, where estimated, the altitude;
  the manoeuvres (:mod:`solver.manoeuvres`) numbered on the map and shaded on the controls.
- :func:`recording_map`: every track of a recording on one map, with the radar sites.
- :func:`residuals_figure`: each radar's plots against the reconstruction over a run, by
  range and by azimuth (:mod:`solver.assessment`).

Map axes: east to the right, north up, in km in the local plane (about the request's
``reference`` or the recording's, :func:`solver.io.split.recording_frame`).
"""

from __future__ import annotations

import io
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import PatchCollection
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse, Patch
from matplotlib.ticker import FuncFormatter, MultipleLocator

from .figure_data import TrackFigureData, from_reconstruction
from .inputs import FloatArray
from .manoeuvres import Manoeuvre, from_segments
from .plots import PlotTable
from .results import Reconstruction
from .sensors import RadarSensor

if TYPE_CHECKING:
    from .assessment import SensorResiduals

CHI2_2DOF_95 = 5.991464547107979  # 95 % quantile of chi-square with 2 degrees of freedom
MAX_ELLIPSES = 400  # drawn per figure (every k-th plot beyond): more only hide the track
COLOURS = ("#0072B2", "#E69F00", "#009E73", "#CC79A7", "#56B4E9", "#D55E00", "#999999")
"""The sensors' colours (Okabe and Ito's, told apart with red-green colour blindness; a
reviewer measured the earlier blue against purple and green against the red track at a
colour difference of 6-8 for deuteranopes), each with its own marker (:data:`MARKERS`); the
reconstruction is black."""
MARKERS = ("+", "x", "1", "2", "3", "4", ".")
DPI = 100


def _ellipse_patches(cx: FloatArray, cz: FloatArray, cov: FloatArray) -> list[Ellipse]:
    """Ellipses of ``(x, z)`` covariances ``(n, 2, 2)`` in (east, north) km axes."""
    out = []
    for x, z, c in zip(cx, cz, cov, strict=True):
        p = np.array([[c[1, 1], c[0, 1]], [c[0, 1], c[0, 0]]])  # (east, north) order
        vals, vecs = np.linalg.eigh(p)
        vals = np.maximum(vals, 0.0)
        angle = np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1]))
        w, h = 2 * np.sqrt(vals[::-1]) / 1e3
        out.append(Ellipse((z / 1e3, x / 1e3), w, h, angle=angle))
    return out


def _thin(n: int) -> np.ndarray:
    return np.arange(0, n, max(1, int(np.ceil(n / MAX_ELLIPSES))))


def _map_axes(ax: Axes, title: str) -> None:
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east of the plane's origin (km)")
    ax.set_ylabel("north (km)")
    ax.set_title(title)
    ax.grid(True, lw=0.3)


CLOCK_STEPS_S = (10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200)


def clock(t: float) -> str:
    """Seconds from a UTC midnight as ``HH:MM:SS`` (``+1d`` past the next midnight)."""
    day, rest = divmod(int(np.rint(t)), 86_400)
    text = f"{rest // 3600:02d}:{rest % 3600 // 60:02d}:{rest % 60:02d}"
    return text + (f" +{day}d" if day else "")


def _time_axis(ax: Axes, times_of_day: bool) -> None:
    if times_of_day:  # ticks on whole clock steps (10 s to 2 h), about six of them
        lo, hi = ax.get_xlim()
        step = next((s for s in CLOCK_STEPS_S if (hi - lo) / s <= 7), CLOCK_STEPS_S[-1])
        ax.xaxis.set_major_locator(MultipleLocator(step))
        ax.xaxis.set_major_formatter(FuncFormatter(  # "+1d" below: the ticks were one line
            lambda v, _: clock(v).replace(" +", "\n+")))  # and ran into each other
        ax.set_xlabel("time of day (UTC)")
    else:
        ax.set_xlabel("t (s)")


def track_figure(table: PlotTable, rec: Reconstruction, title: str = "",
                 times_of_day: bool = False, date: str | None = None) -> Figure:
    """One aircraft's plots, reconstruction and controls (see the module docstring);
    ``times_of_day``: the table's times are seconds from a UTC midnight (a recording's),
    shown as clock times, ``date`` that midnight's (in the title). :func:`draw_track_figure`
    of :func:`solver.figure_data.from_reconstruction`."""
    return draw_track_figure(from_reconstruction(table, rec), title, times_of_day, date)


DRAWING = threading.Lock()
"""Held while a track figure is drawn and rendered (:func:`track_png`): matplotlib's mathtext
parser (the controls' ``m/s^2`` labels) is one object per process, and figures drawn at once
in threads failed its parse (``ParseException ... at char 0``: 4 threads, 24 figures)."""


def track_png(data: TrackFigureData, title: str = "", times_of_day: bool = False,
              date: str | None = None) -> bytes:
    """:func:`draw_track_figure` as PNG bytes, one figure at a time in this process
    (:data:`DRAWING`; drawing is Python under the GIL: threads gained nothing anyway)."""
    with DRAWING:
        return png(draw_track_figure(data, title, times_of_day, date))


def _covariances(terms: FloatArray) -> FloatArray:
    """``(n, 2, 2)`` symmetric covariances of their ``(n, 3)`` terms ``xx, xz, zz``."""
    cov = np.empty((len(terms), 2, 2))
    cov[:, 0, 0], cov[:, 1, 1] = terms[:, 0], terms[:, 2]
    cov[:, 0, 1] = cov[:, 1, 0] = terms[:, 1]
    return cov


def draw_track_figure(data: TrackFigureData, title: str = "",
                      times_of_day: bool = False, date: str | None = None) -> Figure:
    """:func:`track_figure` of its content (a reconstruction's, or one a run stored:
    :mod:`solver.figure_data`). A figure of its own, not pyplot's (drawn in the service's
    threads, beside other figures)."""
    has_alt = data.sample_h is not None
    fig = Figure(figsize=(13, 7.5), dpi=DPI)
    grid = fig.add_gridspec(4 if has_alt else 3, 2, width_ratios=(1.3, 1))
    ax = fig.add_subplot(grid[:, 0])
    cx, cz, cov = data.plot_x, data.plot_z, _covariances(data.plot_cov)
    counts = []
    for k, (sensor_id, kind) in enumerate(data.sensors):
        rows = np.flatnonzero(data.plot_sensor == k)
        colour = COLOURS[k % len(COLOURS)]
        ax.plot(cz[rows] / 1e3, cx[rows] / 1e3, MARKERS[k % len(MARKERS)], ms=4, color=colour,
                label=f"{sensor_id} ({kind}, {rows.size} plots; 3-sigma ellipses)",
                zorder=2)
        sel = rows[_thin(rows.size)]
        patches = _ellipse_patches(cx[sel], cz[sel], 9.0 * cov[sel])  # 3 sigma
        ax.add_collection(PatchCollection(patches, facecolor="none", edgecolor=colour, lw=0.4,
                                          alpha=0.6, zorder=1))
        counts.append(f"{sensor_id} {rows.size}")
    if data.at_cov is not None:
        sel = _thin(len(data.at_x))
        patches = _ellipse_patches(data.at_x[sel], data.at_z[sel],
                                   CHI2_2DOF_95 * _covariances(data.at_cov[sel]))
        ax.add_collection(PatchCollection(patches, facecolor="0.5", edgecolor="none",
                                          alpha=0.3, zorder=3))
    st, sx, sz = data.sample_t, data.sample_x, data.sample_z
    segments = data.segments
    ax.plot(sz / 1e3, sx / 1e3, "-", color="k", lw=1.2, label="reconstruction", zorder=4)
    starts = np.array([[seg.z, seg.x] for seg in segments[1:]]) / 1e3
    if starts.size:  # under the line, small: 160 of them on a noisy track buried it
        ax.plot(starts[:, 0], starts[:, 1], "o", mfc="white", mec="0.35", mew=0.5, ms=2.5,
                label=f"control switches ({len(segments) - 1})", zorder=3.5)
    ax.plot(sz[:1] / 1e3, sx[:1] / 1e3, "o", color="k", ms=6, zorder=5,
            label=f"start ({clock(st[0]) if times_of_day else f't = {st[0]:g} s'})")
    if len(st) > 1:
        heading = np.degrees(np.arctan2(sz[-1] - sz[-2], sx[-1] - sx[-2]))
        ax.plot(sz[-1:] / 1e3, sx[-1:] / 1e3, marker=(3, 0, -heading), color="k", ms=8,
                ls="none", zorder=5, label="end")
    handles, _ = ax.get_legend_handles_labels()
    if data.at_cov is not None:  # after the reconstruction's line
        at = len(data.sensors) + 1
        handles.insert(at, Patch(facecolor="0.5", alpha=0.3, label="its 95 % ellipses"))
    ax.legend(handles=handles, loc="best", fontsize=7)
    _map_axes(ax, title or f"{len(data)} plots, {len(data.sensors)} sensor(s)")
    found = from_segments(segments)
    span = (f"{date + ' ' if date else ''}{clock(st[0])} to {clock(st[-1])} UTC" if times_of_day
            else f"t {st[0]:g} to {st[-1]:g} s")
    switches = max(len(segments) - 1, 0)
    fig.suptitle(f"{title + ': ' if title else ''}{span}, {len(data)} plots "
                 f"({', '.join(counts)}), {switches} control switches, "
                 f"{len(found)} manoeuvre(s)", fontsize=10)
    # no segment (one instant's plots by the sliding windows): empty control panels
    t = np.array([seg.t_start for seg in segments] + [seg.t_end for seg in segments[-1:]])
    panels = [("u, lateral (m/s$^2$, + right)", [seg.u for seg in segments]),
              ("w, along track (m/s$^2$)", [seg.w for seg in segments])]
    control_axes: list[Axes] = []
    for i, (label, values) in enumerate(panels):
        axc = fig.add_subplot(grid[i, 1], sharex=control_axes[0] if control_axes else None)
        axc.step(t, [*values, *values[-1:]], where="post", color="k", lw=1)
        axc.set_ylabel(label, fontsize=8)
        axc.grid(True, lw=0.3)
        control_axes.append(axc)
    _mark_manoeuvres(ax, control_axes, found)
    axv = fig.add_subplot(grid[2, 1], sharex=control_axes[0])
    axv.plot(st, data.sample_speed, color="k", lw=1)
    axv.set_ylabel("speed (m/s)", fontsize=8)
    axv.grid(True, lw=0.3)
    if has_alt:
        h, h_sigma = data.sample_h, data.sample_h_sigma
        assert h is not None and h_sigma is not None
        axh = fig.add_subplot(grid[3, 1], sharex=control_axes[0])
        axh.plot(st, h, color="k", lw=1, label="estimated height")
        axh.fill_between(st, h - 2 * h_sigma, h + 2 * h_sigma, color="0.5",
                         alpha=0.3, lw=0, label="+-2 sigma")
        known = np.isfinite(data.plot_altitude_m)
        if known.any():
            axh.plot(data.plot_t[known], data.plot_altitude_m[known], ".", ms=2,
                     color=COLOURS[0], label="reported altitude")
        low = float(np.min(h - 2 * h_sigma))
        if low < HEIGHT_FLOOR_M:  # an unobservable height's band reached -2 km
            axh.set_ylim(bottom=HEIGHT_FLOOR_M)
        axh.legend(fontsize=7, loc="best")
        axh.set_ylabel("height (m)", fontsize=8)
        axh.grid(True, lw=0.3)
    for axr in fig.axes[1:-1]:
        axr.tick_params(labelbottom=False)
    _time_axis(fig.axes[-1], times_of_day)
    fig.tight_layout()
    return fig


HEIGHT_FLOOR_M = -500.0
"""The height panel's lowest value (the band of a height the plots hardly tell went below)."""


MANOEUVRE_HATCHES = {"right": "////", "left": "\\\\\\\\", "increase": "////",
                     "decrease": "\\\\\\\\"}
"""Manoeuvres are shaded grey (the colours are the sensors'), hatched by direction."""


def _mark_manoeuvres(ax: Axes, control_axes: list[Axes], found: list[Manoeuvre]) -> None:
    """Number the manoeuvres where they start on the map and shade their spans on the ``u``
    (turns) and ``w`` (speed changes) panels, labelled above the panel with the number and
    the change (deg, m/s; two rows, so that neighbours do not overprint the line or each
    other)."""
    for i, m in enumerate(found, 1):
        ax.annotate(str(i), (m.z_start / 1e3, m.x_start / 1e3), xytext=(6, 6),
                    textcoords="offset points", fontsize=7, weight="bold", zorder=6,
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "0.3", "lw": 0.5,
                          "alpha": 0.9},
                    arrowprops={"arrowstyle": "-", "lw": 0.5, "color": "0.3"})
        turn = m.kind == "turn"
        axc = control_axes[0 if turn else 1]
        axc.axvspan(m.t_start, m.t_end, facecolor="0.85", edgecolor="0.6", lw=0,
                    hatch=MANOEUVRE_HATCHES[m.direction], alpha=0.6)
        change = (f"{m.heading_change_deg:+.0f} deg" if turn
                  else f"{m.speed_change:+.0f} m/s")
        axc.text((m.t_start + m.t_end) / 2, 1.01 + 0.12 * (i % 2), f"{i}: {change}",
                 fontsize=7, ha="center", va="bottom", clip_on=False,
                 transform=axc.get_xaxis_transform())


MAP_LABELS_UP_TO = 50
"""A recording map names its tracks (at their ends) when it has at most this many."""


def recording_map(tracks: Sequence[tuple[str, FloatArray, FloatArray]],
                  sensors: Sequence[tuple[str, float, float]] = (), title: str = "") -> Figure:
    """Every track ``(key, x, z)`` (metres in one plane; coloured in the order of the keys, so
    a track keeps its colour from run to run; a dot at its start, its key at its end when
    there are at most :data:`MAP_LABELS_UP_TO`) and sensor sites ``(id, x, z)``."""
    fig, ax = plt.subplots(figsize=(10, 9), dpi=DPI)
    ordered = sorted(tracks, key=lambda track: track[0])
    for i, (key, x, z) in enumerate(ordered):
        x, z = np.asarray(x) / 1e3, np.asarray(z) / 1e3
        colour = plt.cm.tab10(i % 10)
        ax.plot(z, x, "-", lw=0.9, color=colour)
        if x.size:
            ax.scatter(z[:1], x[:1], s=8, color=colour, zorder=3)
            if len(ordered) <= MAP_LABELS_UP_TO:
                ax.annotate(key, (z[-1], x[-1]), textcoords="offset points", xytext=(3, 3),
                            fontsize=6, color=colour)
    for j, (sid, x, z) in enumerate(sensors):
        ax.plot(z / 1e3, x / 1e3, "^", color="k", ms=8, label="radar" if j == 0 else None)
        ax.annotate(sid, (z / 1e3, x / 1e3), textcoords="offset points", xytext=(5, 5),
                    fontsize=8)
    ax.scatter([], [], s=8, color="0.3", label="track start")
    ax.legend(loc="best", fontsize=8)
    n = len(tracks)
    _map_axes(ax, title or f"{n} track{'s' * (n != 1)}")
    fig.tight_layout()
    return fig


def residuals_figure(sensors: Sequence[SensorResiduals],
                     estimated: Mapping[str, Mapping[str, Any]] | None = None) -> Figure:
    """One row per sensor: a radar's range residual (m) over the slant range and azimuth
    residual (deg) over the azimuth; a position sensor's along- and across-track residuals (m)
    over the ground speed. In each panel a sample of the plots (wild ones as red crosses),
    the binned mean (line) and mean +- sigma (band); the axes span the mean +- 5 sigma of the
    plots kept. ``estimated``: per sensor id its ``sensors.json`` row, whose sigmas estimated
    from the residuals' degrees of freedom a radar's titles give beside the residuals' own."""
    from .assessment import AZIMUTH_BIN_DEG, RANGE_BIN_M, SPEED_BIN_MS

    fig, axes = plt.subplots(len(sensors), 2, figsize=(12, 3.2 * len(sensors) + 0.6), dpi=DPI,
                             squeeze=False)
    for row, res in zip(axes, sensors, strict=True):
        m0, sd0, m1, sd1 = res.bias_sigma()
        smp = res.sample
        if res.kind == "radar":
            panels = ((0, 2, res.first, RANGE_BIN_M, 1e-3, "slant range (km)", "range residual",
                       "m", (m0, sd0), 1, "mean"),
                      (1, 3, res.second, AZIMUTH_BIN_DEG, 1.0, "azimuth (deg)",
                       "azimuth residual", "deg", (m1, sd1), 4, "mean"))
        else:
            panels = ((0, 2, res.first, SPEED_BIN_MS, 1.0, "ground speed (m/s)",
                       "along-track residual", "m", (m0, sd0), 1, "mean"),
                      (1, 3, res.second, SPEED_BIN_MS, 1.0, "ground speed (m/s)",
                       "cross-track residual", "m", (m1, sd1), 1, "mean"))
        row_est = (estimated or {}).get(res.sensor, {})
        sigmas = ((row_est.get("range_sigma_estimate_m"), row_est.get("azimuth_sigma_estimate_deg"))
                  if res.kind == "radar" else (None, None))
        for ax, panel, est in zip(row, panels, sigmas, strict=True):
            _residual_panel(ax, smp, res.sensor, *panel, estimate=est)
        if res.kind == "radar":
            row[1].set_xlim(*_azimuth_span(smp[smp[:, 4] == 0, 1]))
        offsets = _offsets_text(row_est)
        row[0].annotate(f"{res.plots} plots, {res.wild} wild"
                        + (f", {res.no_reference} where the track is no reference"
                           if res.no_reference else "")
                        + (f"\n{offsets}" if offsets else ""), (0.01, 0.97),
                        xycoords="axes fraction", va="top", fontsize=8)
    fig.suptitle("Plots against the reconstruction: measured minus reconstructed, after the "
                 "estimated offsets; band: binned mean +- sigma; x: left out\n(along track: "
                 "ahead positive, a late report lies behind; estimated: the sensor's sigma from "
                 "the residuals' degrees of freedom)", fontsize=10)
    fig.tight_layout()
    return fig


def _offsets_text(row: Mapping[str, Any]) -> str:
    """A sensor's estimated offsets (a ``sensors.json`` row), which its residuals are after:
    the figure said "bias -0.1 m" of a radar whose 119.6-m offset was estimated (a reviewer)."""
    parts = [f"{name} {row[key]:+.{digits}f}{unit}"
             for name, key, digits, unit in (("range", "range_bias_m", 1, " m"),
                                              ("azimuth", "azimuth_bias_deg", 3, " deg"),
                                              ("time", "time_bias_s", 2, " s"))
             if row.get(key) is not None]
    return "estimated offsets taken off: " + ", ".join(parts) if parts else ""


def _azimuth_span(az: FloatArray) -> tuple[float, float]:
    """The azimuth axis: 0-360 deg, or the plots' span +- 5 deg where they cover less than
    half the circle without crossing north (a sector radar's 25-50 deg filled 7 % of it)."""
    az = np.sort(np.mod(np.asarray(az, dtype=float), 360.0))
    if az.size < 2:
        return 0.0, 360.0
    gaps = np.diff(np.append(az, az[0] + 360.0))
    if gaps[-1] < 180.0:  # the largest stretch without plots is not across north
        return 0.0, 360.0
    return max(0.0, float(az[0]) - 5.0), min(360.0, float(az[-1]) + 5.0)


def _residual_panel(ax: Axes, smp: np.ndarray, sensor: str, col: int, res: int, binned: Any,
                    width: float, scale: float, xlabel: str, name: str, unit: str,
                    stats: tuple[float, float], digits: int, word: str,
                    estimate: float | None = None) -> None:
    """One panel of :func:`residuals_figure`: sample column ``res`` over column ``col``."""
    wild = smp[:, 4] > 0
    ax.plot(smp[~wild, col] * scale, smp[~wild, res], ".", ms=1.5, color="0.75", alpha=0.5,
            rasterized=True, zorder=1)
    ax.plot(smp[wild, col] * scale, smp[wild, res], "x", ms=3, color="tab:red", zorder=2)
    mean, sigma = binned.mean_sigma()
    centre = (np.arange(mean.size) + 0.5) * width * scale
    ax.fill_between(centre, mean - sigma, mean + sigma, color="tab:blue", alpha=0.25, lw=0,
                    zorder=3)
    for edge in (mean - sigma, mean + sigma):
        ax.plot(centre, edge, "-", color="tab:blue", lw=0.6, zorder=4)
    ax.plot(centre, mean, "-", color="navy", lw=1.5, zorder=4)
    ax.axhline(0.0, color="k", lw=0.6)
    m, sd = stats
    if np.isfinite(m) and sd > 0:
        ax.set_ylim(m - 5 * sd, m + 5 * sd)
    ok = smp[~wild, col]
    if ok.size:  # from the nearest plot (0 when it is within a third of the farthest's)
        lo, hi = float(ok.min()) * scale, float(ok.max()) * scale
        ax.set_xlim(0.0 if lo < hi / 3 else 0.95 * lo, hi * 1.05)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(f"{name} ({unit})")
    also = "" if estimate is None else f", estimated {estimate:.{digits}f} {unit}"
    ax.set_title(f"{sensor}: {word} {m:+.{digits}f} {unit}, sigma {sd:.{digits}f} {unit}{also}",
                 fontsize=9)
    ax.grid(True, lw=0.3)


def sensor_sites(table: PlotTable) -> list[tuple[str, float, float]]:
    """Radar sites of a table in its plane (the origin for a radar without a site)."""
    out = []
    for s in table.sensors:
        if not isinstance(s, RadarSensor):
            continue
        if table.frame is None or s.site is None:
            out.append((s.id, 0.0, 0.0))
        else:
            x, z = table.frame.to_plane(np.array([s.site.lat_deg]), np.array([s.site.lon_deg]))
            out.append((s.id, float(x[0]), float(z[0])))
    return out


def png(fig: Figure) -> bytes:
    """The figure as PNG bytes (and closed)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def save(fig: Figure, path: Path) -> Path:
    """Write the figure (format from the suffix) and close it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
