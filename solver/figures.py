"""Figures a person would rather look at than read (matplotlib, Agg; PNG bytes or files).

- :func:`track_figure`: one aircraft, in the style of seed 000's figures 4-8: the plots of
  every sensor with their 3-sigma ellipses (the a priori maximum errors of a radar whose sigmas
  are a third of them), the reconstructed trajectory with its switch points and 95 % ellipses,
  and beside it the controls ``u(t)``, ``w(t)``, the speed and, where estimated, the altitude;
  the manoeuvres (:mod:`solver.manoeuvres`) numbered on the map and shaded on the controls.
- :func:`recording_map`: every track of a recording on one map, with the radar sites.
- :func:`residuals_figure`: each radar's plots against the reconstruction over a run, by
  range and by azimuth (:mod:`solver.assessment`).

Map axes: east to the right, north up, in km in the local plane (with latitude/longitude ticks'
labels when the plane has a frame).
"""

from __future__ import annotations

import io
import textwrap
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
from matplotlib.patches import Ellipse

from .inputs import FloatArray
from .manoeuvres import Manoeuvre, from_segments
from .plots import PlotTable
from .results import Reconstruction
from .sensors import RadarSensor

if TYPE_CHECKING:
    from .assessment import SensorResiduals

CHI2_2DOF_95 = 5.991464547107979  # 95 % quantile of chi-square with 2 degrees of freedom
MAX_ELLIPSES = 400  # drawn per figure (every k-th plot beyond): more only hide the track
COLOURS = ("tab:blue", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive",
           "tab:cyan", "tab:gray")
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


def _fix_covariances(table: PlotTable) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Plot centres and their one-sigma covariances in the plane."""
    e = table.fixes().ellipses
    c, s = np.cos(e.psi), np.sin(e.psi)
    cov = np.empty((len(table), 2, 2))
    cov[:, 0, 0] = c * c * e.B**2 + s * s * e.A**2
    cov[:, 1, 1] = s * s * e.B**2 + c * c * e.A**2
    cov[:, 0, 1] = cov[:, 1, 0] = s * c * (e.B**2 - e.A**2)
    return e.cx, e.cz, cov


def _map_axes(ax: Axes, title: str) -> None:
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (km)")
    ax.set_ylabel("north (km)")
    ax.set_title(title)
    ax.grid(True, lw=0.3)


def track_figure(table: PlotTable, rec: Reconstruction, title: str = "") -> Figure:
    """One aircraft's plots, reconstruction and controls (see the module docstring)."""
    has_alt = rec.samples.h is not None
    fig = plt.figure(figsize=(13, 7.5), dpi=DPI)
    grid = fig.add_gridspec(4 if has_alt else 3, 2, width_ratios=(1.3, 1))
    ax = fig.add_subplot(grid[:, 0])
    cx, cz, cov = _fix_covariances(table)
    for k, sensor in enumerate(table.sensors):
        rows = np.flatnonzero(table.sensor == k)
        colour = COLOURS[k % len(COLOURS)]
        ax.plot(cz[rows] / 1e3, cx[rows] / 1e3, "+", ms=4, color=colour,
                label=f"{sensor.id} ({sensor.kind}, {rows.size} plots)")
        sel = rows[_thin(rows.size)]
        patches = _ellipse_patches(cx[sel], cz[sel], 9.0 * cov[sel])  # 3 sigma
        ax.add_collection(PatchCollection(patches, facecolor="none", edgecolor=colour, lw=0.4,
                                          alpha=0.6))
    s = rec.samples
    ax.plot(s.z / 1e3, s.x / 1e3, "-", color="tab:red", lw=1.2, label="reconstruction")
    starts = np.array([[seg.z, seg.x] for seg in rec.segments[1:]]) / 1e3
    if starts.size:
        ax.plot(starts[:, 0], starts[:, 1], ".", color="k", ms=3,
                label=f"control switches ({len(rec.segments) - 1})")
    a = rec.at_plots
    if a.cov is not None:
        sel = _thin(len(a))
        patches = _ellipse_patches(a.x[sel], a.z[sel], CHI2_2DOF_95 * a.cov[sel, :2, :2])
        ax.add_collection(PatchCollection(patches, facecolor="tab:red", edgecolor="none",
                                          alpha=0.25))
    ax.legend(loc="best", fontsize=8)
    _map_axes(ax, title or f"{len(table)} plots, {len(table.sensors)} sensor(s)")
    t = np.array([seg.t_start for seg in rec.segments] + [rec.segments[-1].t_end])
    panels = [("u (m/s^2)", [seg.u for seg in rec.segments]),
              ("w (m/s^2)", [seg.w for seg in rec.segments])]
    control_axes = []
    for i, (label, values) in enumerate(panels):
        axc = fig.add_subplot(grid[i, 1])
        axc.step(t, [*values, values[-1]], where="post", color="tab:red", lw=1)
        axc.set_ylabel(label)
        axc.grid(True, lw=0.3)
        control_axes.append(axc)
    _mark_manoeuvres(ax, control_axes, from_segments(rec.segments))
    axv = fig.add_subplot(grid[2, 1])
    axv.plot(s.t, s.speed, color="tab:red", lw=1)
    axv.set_ylabel("speed (m/s)")
    axv.grid(True, lw=0.3)
    if has_alt:
        assert s.h is not None and s.h_sigma is not None
        axh = fig.add_subplot(grid[3, 1])
        axh.plot(s.t, s.h, color="tab:red", lw=1, label="estimated height")
        axh.fill_between(s.t, s.h - 2 * s.h_sigma, s.h + 2 * s.h_sigma, color="tab:red",
                         alpha=0.2, lw=0)
        known = np.isfinite(table.altitude_m)
        if known.any():
            axh.plot(table.t[known], table.altitude_m[known], ".", ms=2, color="k",
                     label="reported altitude")
            axh.legend(fontsize=7)
        axh.set_ylabel("height (m)")
        axh.grid(True, lw=0.3)
    fig.axes[-1].set_xlabel("t (s)")
    fig.tight_layout()
    return fig


MANOEUVRE_COLOURS = {"right": "tab:orange", "left": "tab:blue", "increase": "tab:green",
                     "decrease": "tab:purple"}


def _mark_manoeuvres(ax: Axes, control_axes: list[Axes], found: list[Manoeuvre]) -> None:
    """Number the manoeuvres where they start on the map and shade their spans on the ``u``
    (turns) and ``w`` (speed changes) panels, labelled with the number and the change (deg,
    m/s)."""
    for i, m in enumerate(found, 1):
        colour = MANOEUVRE_COLOURS[m.direction]
        ax.annotate(str(i), (m.z_start / 1e3, m.x_start / 1e3), xytext=(4, 4),
                    textcoords="offset points", fontsize=7, color=colour, weight="bold",
                    bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none",
                          "alpha": 0.8})
        turn = m.kind == "turn"
        axc = control_axes[0 if turn else 1]
        axc.axvspan(m.t_start, m.t_end, color=colour, alpha=0.15, lw=0)
        change = f"{m.heading_change_deg:+.0f}" if turn else f"{m.speed_change:+.0f}"
        # staggered over three rows: neighbours' labels do not overprint
        axc.text((m.t_start + m.t_end) / 2, 0.98 - 0.09 * (i % 3), f"{i}: {change}",
                 color=colour, fontsize=6, ha="center", va="top",
                 transform=axc.get_xaxis_transform())


def recording_map(tracks: Sequence[tuple[str, FloatArray, FloatArray]],
                  sensors: Sequence[tuple[str, float, float]] = (), title: str = "") -> Figure:
    """Every track ``(key, x, z)`` (metres in one plane) and sensor sites ``(id, x, z)``."""
    fig, ax = plt.subplots(figsize=(10, 9), dpi=DPI)
    for i, (_, x, z) in enumerate(tracks):
        ax.plot(np.asarray(z) / 1e3, np.asarray(x) / 1e3, "-", lw=0.7,
                color=plt.cm.tab20(i % 20))
    for sid, x, z in sensors:
        ax.plot(z / 1e3, x / 1e3, "^", color="k", ms=8)
        ax.annotate(sid, (z / 1e3, x / 1e3), textcoords="offset points", xytext=(5, 5),
                    fontsize=8)
    _map_axes(ax, title or f"{len(tracks)} tracks")
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
                       "m", (m0, sd0), 1, "bias"),
                      (1, 3, res.second, AZIMUTH_BIN_DEG, 1.0, "azimuth (deg)",
                       "azimuth residual", "deg", (m1, sd1), 4, "bias"))
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
            row[1].set_xlim(0.0, 360.0)
        row[0].annotate(f"{res.plots} plots, {res.wild} wild"
                        + (f", {res.no_reference} where the track is no reference"
                           if res.no_reference else ""), (0.01, 0.97),
                        xycoords="axes fraction", va="top", fontsize=8)
    # wrapped: on one line the title ran past both edges of the figure (cut off)
    fig.suptitle(textwrap.fill(
        "Plots against the reconstruction (measured minus reconstructed; after the offsets of "
        "sensors with estimate_bias, and without it an offset shows only in part, the track "
        "drawn towards the plots; along-track: ahead positive, a late report lies behind; "
        "bands: binned mean +- sigma; estimated: the sensor's sigma from the residuals' degrees "
        "of freedom)", 120), fontsize=10)
    fig.tight_layout()
    return fig


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
    if ok.size:
        ax.set_xlim(0.0, float(ok.max()) * scale * 1.05)
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
