"""Manoeuvres read off the constant-control segments: turns and speed changes as events.

A reconstruction of a noisy track has many segments (the seed-like sample request: 164 for 236
plots), most of them small corrections; what an engineer investigating a track asks is when the
aircraft turned, by how much and how fast, and when it changed speed. Those are the runs of
segments with a marked control, in the terms of ASTERIX CAT062 I062/200 (mode of movement):
transversal right / left turn, longitudinal increasing / decreasing ground speed.

Per segment of duration ``T``, from the motion model (:func:`solver.motion.propagate`):
heading change ``dphi`` (``phi' = u / v``) and speed change ``dv = w T``; its rates are
``dphi / T`` and ``w``. A **turn** is a maximal run of segments turning the same way at a mean
rate of at least half ``turn_rate_deg_s``, holding one segment at ``turn_rate_deg_s`` or more,
with ``|sum dphi| >= min_heading_change_deg``; a **speed change** likewise with ``w``,
``acceleration`` and ``min_speed_change``. The half-threshold extension (hysteresis) takes in
the ramps a noisy track's turn onset is made of: on the seed-like sample its 50 m/s speed-up
(``w`` 1 m/s^2 for 50 s) comes out as 47 m/s with it and 35 m/s without.

The defaults keep the noise out: on the sample request the largest control of a segment away
from the true manoeuvres is 0.33 m/s^2 (0.1 deg/s at its speed) lateral and 0.18 m/s^2
longitudinal (an 8-10 m/s change over 57 s); a standard-rate turn is 3 deg/s, an airliner's
turn at cruise about 1 deg/s.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from .inputs import FloatArray
from .motion import propagate
from .results import Segment

TURN_RATE_DEG_S = 0.25
MIN_HEADING_CHANGE_DEG = 10.0
ACCELERATION = 0.2  # m/s^2
MIN_SPEED_CHANGE = 10.0  # m/s


@dataclass(frozen=True)
class ManoeuvreSettings:
    """Detection thresholds (module docstring): the rate a turn (deg/s) or speed change (m/s^2)
    must reach in one segment, and the least total heading (deg) or speed (m/s) change."""

    turn_rate_deg_s: float = TURN_RATE_DEG_S
    min_heading_change_deg: float = MIN_HEADING_CHANGE_DEG
    acceleration: float = ACCELERATION
    min_speed_change: float = MIN_SPEED_CHANGE


@dataclass(frozen=True)
class Manoeuvre:
    """One turn or speed change: ``[t_start, t_end]`` (s), the position (m), heading (deg
    clockwise from north) and ground speed (m/s) at both ends, the signed changes (heading:
    positive to the right), and the largest rate of its segments (deg/s or m/s^2, signed)."""

    kind: Literal["turn", "speed_change"]
    direction: Literal["right", "left", "increase", "decrease"]
    t_start: float
    t_end: float
    x_start: float
    z_start: float
    x_end: float
    z_end: float
    heading_start_deg: float
    heading_end_deg: float
    heading_change_deg: float
    speed_start: float
    speed_end: float
    speed_change: float
    peak_rate: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return asdict(self)


def find_manoeuvres(t_start: FloatArray, t_end: FloatArray, x: FloatArray, z: FloatArray,
                    heading_rad: FloatArray, speed: FloatArray, u: FloatArray, w: FloatArray,
                    settings: ManoeuvreSettings = ManoeuvreSettings()) -> list[Manoeuvre]:
    """Turns and speed changes of one track's segments (arrays in time order, as
    :class:`solver.results.Segment` or ``segments.parquet`` has them), ordered by start."""
    t0, t1 = np.asarray(t_start, float), np.asarray(t_end, float)
    keep = t1 > t0  # a zero-length segment changes nothing and breaks no run
    t0, t1 = t0[keep], t1[keep]
    if t0.size == 0:
        return []
    x0, z0, phi0, v0, uu, ww = (np.asarray(a, float)[keep]
                                for a in (x, z, heading_rad, speed, u, w))
    dur = t1 - t0
    x1, z1, phi1, v1 = propagate(x0, z0, phi0, v0, uu, ww, dur)
    dh = np.rad2deg(phi1 - phi0)
    track = _Track(t0, t1, x0, z0, x1, z1, np.rad2deg(phi0), dh, v0, v1)
    found = _runs(track, "turn", ("right", "left"), dh / dur, dh,
                  settings.turn_rate_deg_s, settings.min_heading_change_deg)
    found += _runs(track, "speed_change", ("increase", "decrease"), ww, v1 - v0,
                   settings.acceleration, settings.min_speed_change)
    return sorted(found, key=lambda m: (m.t_start, m.kind))


def from_segment_rows(table: Any,
                      settings: ManoeuvreSettings = ManoeuvreSettings()) -> list[Manoeuvre]:
    """:func:`find_manoeuvres` of one track's rows of ``segments.parquet`` (an Arrow table,
    heading in degrees)."""
    c = {k: table.column(k).to_numpy() for k in (
        "t_start", "t_end", "x", "z", "heading_deg", "speed", "u", "w")}
    return find_manoeuvres(c["t_start"], c["t_end"], c["x"], c["z"],
                           np.deg2rad(c["heading_deg"]), c["speed"], c["u"], c["w"], settings)


def from_segments(segments: list[Segment],
                  settings: ManoeuvreSettings = ManoeuvreSettings()) -> list[Manoeuvre]:
    """:func:`find_manoeuvres` of a reconstruction's segments."""
    cols = np.array([[s.t_start, s.t_end, s.x, s.z, s.heading, s.speed, s.u, s.w]
                     for s in segments], dtype=float).reshape(-1, 8)
    return find_manoeuvres(*cols.T, settings=settings)


@dataclass(frozen=True)
class _Track:
    """Per segment: times, positions at both ends, heading at the start and its change (deg),
    speed at both ends."""

    t0: np.ndarray
    t1: np.ndarray
    x0: np.ndarray
    z0: np.ndarray
    x1: np.ndarray
    z1: np.ndarray
    h0: np.ndarray
    dh: np.ndarray
    v0: np.ndarray
    v1: np.ndarray


def _runs(g: _Track, kind: Any, names: tuple[str, str], rate: np.ndarray, change: np.ndarray,
          threshold: float, least: float) -> list[Manoeuvre]:
    """Maximal runs of segments whose ``rate`` has one sign and at least half ``threshold``,
    holding one at ``threshold``, whose summed ``change`` is at least ``least`` in size."""
    sign = np.sign(rate) * (np.abs(rate) >= threshold / 2)
    if not np.any(sign):
        return []
    edges = np.flatnonzero(np.diff(sign) != 0) + 1
    starts = np.concatenate([[0], edges])
    stops = np.append(edges, sign.size)
    out = []
    for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
        s = sign[a]
        if s == 0 or np.max(np.abs(rate[a:b])) < threshold:
            continue
        total = float(change[a:b].sum())
        if abs(total) < least:
            continue
        peak = rate[a:b][np.argmax(np.abs(rate[a:b]))]
        turned = float(g.dh[a:b].sum())
        out.append(Manoeuvre(
            kind, names[0] if s > 0 else names[1], float(g.t0[a]), float(g.t1[b - 1]),
            float(g.x0[a]), float(g.z0[a]), float(g.x1[b - 1]), float(g.z1[b - 1]),
            float(g.h0[a] % 360.0), float((g.h0[a] + turned) % 360.0), turned,
            float(g.v0[a]), float(g.v1[b - 1]), float(g.v1[b - 1] - g.v0[a]), float(peak)))
    return out
