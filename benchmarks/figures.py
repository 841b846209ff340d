"""Figures of the report (matplotlib, Agg): trajectory with uncertainty ellipses in the style of the
seed's figures 4-8, control histories u(t), w(t), position error against time, summary bars.

Axes are map-like: east ``z`` to the right, north ``x`` up, in km.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Ellipse

from solver.geometry import plot_points, uncertainty_ellipses
from solver.inputs import FloatArray

from .estimators import Estimate
from .metrics import CHI2_2DOF_95
from .simulate import SimulatedTrack
from .truth import load_truth

SHOWN = ("ss-cv-rts", "fp-imm", "filter-imm", "recon-sliding-m3-R2", "recon-refined-m3-R2")
COLOURS = {"ss-cv-rts": "tab:blue", "fp-imm": "tab:cyan", "filter-imm": "tab:olive",
           "recon-sliding-m3-R2": "tab:orange", "recon-refined-m3-R2": "tab:red"}
DPI = 90


def _shown(estimates: dict[str, Estimate]) -> list[str]:
    return [n for n in SHOWN if n in estimates]


def _manoeuvre_window(track: SimulatedTrack, span_s: float = 400.0) -> tuple[float, float]:
    """The ``span_s`` interval holding the most turning (integral of |turn rate|)."""
    t = track.truth.t
    truth = load_truth(track.truth_name)
    grid = np.arange(t[0], t[-1], 5.0)
    rate = np.abs(truth.turn_rate_at(grid))
    width = max(1, int(span_s / 5.0))
    k = int(np.argmax(np.convolve(rate, np.ones(width), mode="valid"))) if grid.size > width else 0
    return float(grid[k]), float(grid[k] + span_s)


def _cov_ellipse(x: float, z: float, cov: FloatArray, **kw) -> Ellipse:
    """95 % ellipse of a position covariance over ``(x, z)``, drawn in (z, x) axes, km."""
    p = np.array([[cov[1, 1], cov[0, 1]], [cov[0, 1], cov[0, 0]]])  # (z, x) order
    vals, vecs = np.linalg.eigh(p)
    vals = np.maximum(vals, 0.0)
    angle = np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1]))
    w, h = 2 * np.sqrt(CHI2_2DOF_95 * vals[::-1]) / 1e3
    return Ellipse((z / 1e3, x / 1e3), w, h, angle=angle, **kw)


def trajectory(track: SimulatedTrack, estimates: dict[str, Estimate], path: Path) -> None:
    """Whole track (left) and its hardest manoeuvre (right): plots with their a priori
    uncertainty ellipses (reconstruction.md section 3), truth, estimates, 95 % ellipses of the
    refined reconstruction's covariance where it has one."""
    truth = load_truth(track.truth_name)
    radar = track.profile.radar()
    px, pz = plot_points(track.plots)
    t0, t1 = _manoeuvre_window(track)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2))
    tt = np.arange(track.truth.t[0], track.truth.t[-1], 2.0)
    dense = truth.at(tt)
    for ax, zoom in zip(axes, (False, True), strict=True):
        sel = (track.plots.t >= t0) & (track.plots.t <= t1) if zoom else slice(None)
        tsel = (tt >= t0) & (tt <= t1) if zoom else slice(None)
        ax.plot(dense.z[tsel] / 1e3, dense.x[tsel] / 1e3, "k-", lw=1.2, label="truth")
        ax.plot(pz[sel] / 1e3, px[sel] / 1e3, ".", color="0.5", ms=3, label="plots")
        if zoom:
            ell = uncertainty_ellipses(track.plots, radar)
            for i in np.flatnonzero(sel):
                ax.add_patch(Ellipse((ell.cz[i] / 1e3, ell.cx[i] / 1e3), 2 * ell.B[i] / 1e3,
                                     2 * ell.A[i] / 1e3, angle=90 - np.degrees(ell.psi[i]),
                                     fill=False, color="0.6", lw=0.6))
        for name in _shown(estimates):
            est = estimates[name]
            rec = est.reconstruction
            if rec is not None and len(rec.samples):
                s = rec.samples
                ssel = (s.t >= t0) & (s.t <= t1) if zoom else slice(None)
                ax.plot(s.z[ssel] / 1e3, s.x[ssel] / 1e3, "-", color=COLOURS[name], lw=1,
                        label=name)
            else:
                st = est.states
                ax.plot(st.z[sel] / 1e3, st.x[sel] / 1e3, "-", color=COLOURS[name], lw=1,
                        label=name)
            if zoom and name == "recon-refined-m3-R2" and est.states.cov is not None:
                for i in np.flatnonzero(sel)[::2]:
                    c = est.states.cov[i]
                    if np.all(np.isfinite(c[:2, :2])):
                        ax.add_patch(_cov_ellipse(est.states.x[i], est.states.z[i], c,
                                                  fill=False, color=COLOURS[name], lw=0.6))
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("east z (km)")
        ax.set_ylabel("north x (km)")
        ax.grid(alpha=0.3)
        ax.set_title(f"{track.truth_name}, {track.profile.name}, seed {track.seed}" if not zoom
                     else f"t = {t0:.0f}-{t1:.0f} s: plot ellipses, 95 % ellipses")
    axes[0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def controls(track: SimulatedTrack, estimates: dict[str, Estimate], path: Path) -> None:
    """Piecewise-constant u(t), w(t) of the reconstructions against the truth's
    ``u = v phi'`` and ``w = v'``."""
    truth = load_truth(track.truth_name)
    tt = np.arange(track.truth.t[0], track.truth.t[-1], 2.0)
    st = truth.at(tt)
    v = st.speed
    u_true = v * truth.turn_rate_at(tt)
    w_true = np.gradient(v, tt)
    fig, axes = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
    axes[0].plot(tt, u_true, "k-", lw=1, label="truth")
    axes[1].plot(tt, w_true, "k-", lw=1, label="truth")
    for name in _shown(estimates):
        rec = estimates[name].reconstruction
        if rec is None or not rec.segments:
            continue
        ts = np.array([[s.t_start, s.t_end] for s in rec.segments]).ravel()
        for ax, attr in zip(axes, ("u", "w"), strict=True):
            vals = np.repeat([getattr(s, attr) for s in rec.segments], 2)
            ax.plot(ts, vals, "-", color=COLOURS[name], lw=1, label=name)
    axes[0].set_ylabel("u lateral (m/s²)")
    axes[1].set_ylabel("w longitudinal (m/s²)")
    axes[1].set_xlabel("t (s)")
    axes[0].set_title(f"controls: {track.truth_name}, {track.profile.name}, seed {track.seed}")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def error_history(track: SimulatedTrack, estimates: dict[str, Estimate], path: Path,
                  span_s: float = 120.0) -> None:
    """Running RMS (over ``span_s``) of the horizontal position error against time;
    manoeuvres (|turn rate| > 1 deg/s) shaded."""
    fig, ax = plt.subplots(figsize=(10, 3.8))
    t = track.truth.t
    man = track.manoeuvre.astype(float)
    ax.fill_between(t, 0, 1, where=man > 0, transform=ax.get_xaxis_transform(),
                    color="0.9", step="mid", label="manoeuvre")
    k = max(1, round(span_s / track.profile.scan_s))
    kernel = np.ones(k)
    count = np.convolve(np.ones(t.size), kernel, mode="same")  # fewer plots near the ends
    names = ["raw", *_shown(estimates)] if "raw" in estimates else _shown(estimates)
    for name in names:
        st = estimates[name].states
        err2 = (st.x - track.truth.x) ** 2 + (st.z - track.truth.z) ** 2
        ax.plot(st.t, np.sqrt(np.convolve(err2, kernel, mode="same") / count), "-",
                lw=1.0 if name != "raw" else 0.7, color=COLOURS.get(name, "0.6"), label=name)
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"position error, running RMS over {span_s:.0f} s (m)")
    ax.set_ylim(bottom=0)
    ax.set_title(f"error: {track.truth_name}, {track.profile.name}, seed {track.seed}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=4, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def summary_bars(overall: dict[str, dict[str, dict]], best: dict[str, float],
                 path: Path) -> None:
    """RMS position error of each estimator relative to the best baseline, per profile."""
    profiles = sorted(overall)
    names = sorted({n for p in profiles for n in overall[p] if not n.endswith("+alt")},
                   key=lambda n: (not n.startswith("recon"), n))
    fig, ax = plt.subplots(figsize=(10, 0.28 * len(names) * len(profiles) / 2 + 2))
    height = 0.8 / len(profiles)
    for k, p in enumerate(profiles):
        vals = [overall[p].get(n, {}).get("rms_pos", np.nan) / best[p] for n in names]
        ax.barh(np.arange(len(names)) + k * height, vals, height, label=p)
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_yticks(np.arange(len(names)) + 0.4 - height / 2, names, fontsize=7)
    ax.set_xlabel("RMS position error / best baseline's (lower is better)")
    ax.grid(alpha=0.3, axis="x")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
