"""One aircraft's sensor tracks without a Mode S address, seen by several sensors, as one
(issue 16): the cross-sensor association of :mod:`solver.io.split`.

A Mode A/C-only aircraft (or a PSR-only one with a radar track number) seen by radars R1 and
R2 has the keys ``R1:track:12`` and ``R2:track:40``; those sensor tracks (pieces after the
gap split, on the ground left out) are joined here when their plots say they are one
aircraft. Only keys of a sensor track number are looked at: never the user's own
``aircraft`` keys, Mode S keys (an address is an identity) nor ``<sensor>:mode3a:<code>``
keys (a code is shared by many aircraft: such a key may hold several).

Evidence (:func:`compare`), both ways: each plot of one track is compared with the other's
position at its time, linearly interpolated in the recording's plane between the other's
neighbouring plots within :data:`WINDOW_S` (one-sided: its nearest). A plot agrees when at
some common height (the plots' positions at :data:`LEVELS`, linear between them; a plot with
Mode C, or a position, is at its own at every height) the distance is within the gate::

    G = 3 hypot(sigma_a, sigma_b) + bias_a + bias_b + bend_a + bend_b + motion + SLACK

``sigma``: a radar plot's ``max(sigma_r, r sigma_psi)``, a position plot's
``position_sigma_m``; ``bias``: a radar's maximum systematic error ``eps_r + r eps_psi``
(unregistered radars disagree by it); ``bend``: how far a plot without Mode C's positions
between two levels (2 km apart) leave their chord (the sagitta, from their second difference; 0
with Mode C); ``motion``: how far the speed bound ``v`` lets the aircraft stray from the
interpolation, ``2 v tau0 tau1 / (tau0 + tau1)`` between neighbours ``tau0``, ``tau1`` s away,
``v tau`` from one (a plot whose ``motion`` exceeds :data:`MAX_MOTION_M` is not compared: such
a gate tells aircraft 10 km apart from none). Two radars' plots of one aircraft meet at its
height; at a common height the unknown height costs no gate (a gate widened by each plot's
whole spread over 0-20 km, 2.7 km at 40 km from a radar, let two aircraft 3 km apart agree; one
widened by half the 2-km step to the next level, 2.8 km near the top for a plot 20 km from its
radar, two aircraft 12 km apart in the association benchmark without Mode C). Mode C altitudes,
where both have them, must agree within :data:`ALTITUDE_GATE_M` plus :data:`CLIMB_MS` times the
time between them. A plot whose Mode 3/A code differs from each known code of the other's
neighbours is a code conflict (a squawk change shows one radar's new code between the other's
old and new: none).

Tracks of different sensors are associated when :data:`MIN_COMPARED` plots or more were
compared, :data:`MIN_AGREEING` of them or more agree and fewer than :data:`CODE_CONFLICTS`
conflict (equal codes prove nothing: 7000, 2000, 1200 and conspicuity codes are many
aircraft's), and the offset between them is nearly constant (:attr:`Verdict.scatter` at most
:data:`MAX_SCATTER`: two unregistered radars see one aircraft offset by their biases; two
aircraft crossing, by a vector that turns). Limit: two aircraft at one code and level (or
without Mode C) closer than the gate, each seen by one radar only, flying in trail (a
constant offset) are joined (the reviewer's cases: 4 of 32 at 60-150 km, 2-3 km apart; the
compared plots' time span tells nothing more: a 20-s hand-over of one aircraft spans 25 s,
a crossing 23 s). Candidate pairs come from an index of the plots by time slot
(:data:`WINDOW_S`) and plane cell (:data:`CELL_M`, the widest gate used): no all-pairs.
Pairs join in order of their mean normalised distance ``mean(min(d / G, 2))`` over the plots
compared (then plots compared; keys break ties), not of reading (the share within the gate
is the acceptance test only: two aircraft in trail 2 km apart 150 km from the radars agree
100 % either way, at a mean of 0.09 rightly, 0.67 wrongly), into aircraft (chains: R1's with
R2's with R3's, hand-overs), but two groups are not joined when that would put two
overlapping tracks of one sensor in one aircraft or two tracks whose own comparison says
apart (:func:`resolve`), and a track that agrees with two overlapping tracks of another
sensor (two aircraft) joins neither unless the better's mean is :data:`AMBIGUOUS_FACTOR`
times smaller ("ambiguous": none rather than a guess that swaps two aircraft); such a
refused pair is reported (``association_refused``), each join too (``tracks_associated``:
the keys, plots compared, share agreeing). The aircraft's key is its members' smallest key
(``R1:track:12`` with ``R2:track:40``): stable, one of the keys the sensors gave.

Streaming (:func:`associate` with ``final_before``): a pair's evidence is final once the
track that ends first can get no more plots (the split's horizon: a later plot of its key
starts a new piece) and the recording is :data:`WINDOW_S` past its end (the horizon is the
gap split's ``gap_s``, more than twice the window, before the time up to which every plot
has arrived); the tracks joined by final associations or by pairs still open form a
component, resolved once all its tracks are complete (the split's rule), so streamed pieces
give the whole's aircraft.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..frames import LocalFrame
from ..sensors import ALTITUDE_RANGE_M, RadarSensor
from .sensors_file import SensorSet
from .tables import FL_M, PlotRows

WINDOW_S = 30.0
"""A plot's neighbours in the other track are looked for this far in time (s; a few scans:
missed detections, a hand-over), the time slot of the candidate index; what the speed bound
allows over that time limits the comparisons further (:data:`MAX_MOTION_M`)."""
CELL_M = 20_000.0
"""Plane cell of the candidate index (m); a gate wider than it says nothing: not compared."""
GATE_SIGMAS = 3.0
SLACK_M = 100.0
"""Added to every gate (m): Mode C's pressure altitude against the geometric height
(100-300 m, moving a plot along its ray by that times ``h / d``), the plane's curvature."""
ALTITUDE_GATE_M = 300 * 0.3048
"""Mode C altitudes of one aircraft seen by two radars agree to this (m, 300 ft) plus
:data:`CLIMB_MS` times the time between the plots."""
CLIMB_MS = 40.0
MAX_MOTION_M = 2_000.0
"""A plot is compared only where the speed bound's term of its gate is within this (m): a
12-s radar's plot between a 4-s radar's (6 s each side, 1.98 km at 330 m/s), one-sided up
to 6 s past the other track's end. Extrapolated 30 s (10 km) two aircraft 10-14 km apart
agreed on all 27 plots compared at the ends of a 43-s overlap (the association benchmark
without Mode C: refused only by a conflict)."""
MIN_COMPARED = 10
MIN_AGREEING = 0.8
"""Share of the compared plots within the gate for one aircraft (wild plots and reflections
are a few per cent; two aircraft crossing agree only near the crossing)."""
DISTANCE_CAP = 2.0
"""A compared plot's distance over its gate counts at most this in :attr:`Verdict.mean` (a wild
plot or a reflection does not outweigh the others)."""
MAX_SCATTER = 2.5
"""Largest :attr:`Verdict.scatter` of one aircraft: measured 0.8-1.2 for one aircraft seen by
two radars (30-150 km, 11-180 plots, with and without Mode C), 1.3-1.5 for one passing 1-10
km from a radar whose range bias is its whole 150-m allowance (the offset turns with the
azimuth; without Mode C 0.8), 8.0-8.1 for two crossing at
right angles (11 plots in 23 s), 3.4-5.2 for two in trail 2-4 km apart 60-100 km out without
Mode C; not told apart: 0.9-1.5 for two in trail at 150 km or with Mode C 2 km apart (a
constant offset within the bias allowances)."""
AMBIGUOUS_FACTOR = 2.0
"""A track that agrees with two overlapping tracks of another sensor (two aircraft) joins the
better only when its :attr:`Verdict.mean` is this many times smaller; else neither (in the
reviewer's trail cases the right pairs' means were 0.07-0.09, the wrong ones' 0.41-1.4)."""
CODE_CONFLICTS = 2
"""Plots whose Mode 3/A differs from the other's at the same time that make two aircraft
(one garbled reply does not)."""
LEVELS = np.linspace(*ALTITUDE_RANGE_M, 11)
"""Heights (m) at which a plot without Mode C is placed: two radars' plots of one aircraft
meet at a common height (two aircraft's, generally, at none); 2 km apart."""
_K = LEVELS.size
PLANE_COLUMNS = 4 + 3 * _K
"""Per row: corrected time, sigma, bias, half the span of its positions over the heights,
then the plane ``x`` and ``z`` at each of :data:`LEVELS` and the bend there (the sagitta of
its segments: all alike, bend 0, for a plot with Mode C or a position) (:func:`plane_points`)."""


def plane_points(rows: PlotRows, sensors: SensorSet, sensor_idx: np.ndarray,
                 frame: LocalFrame | None, which: np.ndarray,
                 corrected: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
                 ) -> np.ndarray:
    """``(n, PLANE_COLUMNS)`` plane points (module docstring) of rows ``which`` (bool); NaN
    elsewhere and where the plane is unknown."""
    out = np.full((len(rows), PLANE_COLUMNS), np.nan)
    idx = np.flatnonzero(which)
    if not idx.size:
        return out
    t, r, az = corrected(idx)
    out[idx, 0] = t
    alt = np.where(np.isfinite(rows.altitude_m[idx]), rows.altitude_m[idx],
                   rows.flight_level[idx] * FL_M)
    for k in np.unique(sensor_idx[idx]).tolist():
        s = sensors.sensors[k]
        sel = sensor_idx[idx] == k
        i = idx[sel]
        if isinstance(s, RadarSensor):
            rr, psi, h = r[sel], np.deg2rad(az[sel]), alt[sel]
            known = np.isfinite(h)
            x = np.empty((i.size, _K))
            z = np.empty((i.size, _K))
            xk, zk = s.positions(frame, rr[known], psi[known], h[known])
            x[known], z[known] = xk[:, None], zk[:, None]
            free = ~known  # the levels only where there is no Mode C (11 times the geodesy)
            for j, level in enumerate(LEVELS.tolist()):
                if free.any():
                    x[free, j], z[free, j] = s.positions(frame, rr[free], psi[free],
                                                         np.full(int(free.sum()), level))
            out[i, 1] = np.maximum(s.sigma_r, rr * s.sigma_psi)
            out[i, 2] = s.range_error_m + rr * s.azimuth_error_rad
        elif frame is not None:
            x1, z1 = frame.to_plane(rows.lat_deg[i], rows.lon_deg[i])
            x, z = np.repeat(x1[:, None], _K, axis=1), np.repeat(z1[:, None], _K, axis=1)
            out[i, 1] = float(getattr(s, "position_sigma_m", 0.0))
            out[i, 2] = 0.0
        else:
            continue
        # a segment's sagitta, from the second difference at its ends (a parabola's: 1/8)
        bend = np.hypot(np.diff(x, 2, axis=1), np.diff(z, 2, axis=1)) / 8.0
        out[i, 3] = 0.5 * np.hypot(x[:, -1] - x[:, 0], z[:, -1] - z[:, 0])
        out[i, 4:4 + _K], out[i, 4 + _K:4 + 2 * _K] = x, z
        out[i, 4 + 2 * _K:] = np.pad(bend, ((0, 0), (1, 1)), mode="edge")
    return out


@dataclass(frozen=True)
class Piece:
    """One sensor track (a piece of a key between gaps): its ``key``, ``sensor`` index and,
    in time order, its rows (``rows``: indexes of the split's buffer) with their time, plane
    point columns (``x``, ``z``, ``bend``: one column per level), altitude (NaN: none) and
    Mode 3/A code (-1: none)."""

    key: str
    sensor: int
    rows: np.ndarray
    t: np.ndarray
    sigma: np.ndarray
    bias: np.ndarray
    span: np.ndarray
    x: np.ndarray
    z: np.ndarray
    bend: np.ndarray
    alt: np.ndarray
    code: np.ndarray

    @classmethod
    def of(cls, key: str, sensor: int, members: np.ndarray, plane: np.ndarray,
           rows: PlotRows) -> Piece:
        p = plane[members]
        order = np.argsort(p[:, 0], kind="stable")
        m, p = members[order], p[order]
        alt = np.where(np.isfinite(rows.altitude_m[m]), rows.altitude_m[m],
                       rows.flight_level[m] * FL_M)
        return cls(key, sensor, m, p[:, 0], p[:, 1], p[:, 2], p[:, 3], p[:, 4:4 + _K],
                   p[:, 4 + _K:4 + 2 * _K], p[:, 4 + 2 * _K:], alt, rows.mode_3a[m])

    @property
    def first(self) -> float:
        return float(self.t[0])

    @property
    def last(self) -> float:
        return float(self.t[-1])


@dataclass(frozen=True)
class Verdict:
    """What comparing two tracks found: plots compared, within the gate, in code conflict."""

    compared: int
    agreeing: int
    conflicts: int
    distance: float = 0.0
    """Sum over the compared plots of their distance over their gate, each at most
    :data:`DISTANCE_CAP` (:attr:`mean`)."""
    first: float = np.inf
    last: float = -np.inf
    """Times of the first and last plot compared (s)."""
    moments: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    """Over the agreeing plots between two of the other's: their count, sums of the
    displacement ``a - b`` (x, z; at the common height),
    of its squared length and of ``sigma_a^2 + sigma_b^2`` (:attr:`scatter`)."""

    @property
    def scatter(self) -> float:
        """RMS of the displacement around its mean over the RMS of ``hypot(sigma_a, sigma_b)``
        (agreeing plots): one aircraft seen by two radars is offset by their nearly constant
        biases (about 1 or less), two aircraft crossing by a changing vector (0: none)."""
        n, sx, sz, sq, ss = self.moments
        if n < 2 or ss <= 0.0:
            return 0.0
        return float(np.sqrt(max(sq / n - (sx / n) ** 2 - (sz / n) ** 2, 0.0) / (ss / n)))

    @property
    def mean(self) -> float:
        """Mean normalised distance ``sum(min(d / G, cap)) / n`` over the compared plots: the
        graded measure pairs are ranked by (1.0: none compared)."""
        return self.distance / self.compared if self.compared else 1.0

    @property
    def span(self) -> float:
        """Time from the first to the last plot compared (s)."""
        return max(self.last - self.first, 0.0)

    @property
    def share(self) -> float:
        return self.agreeing / self.compared if self.compared else 0.0

    @property
    def same(self) -> bool:
        """One aircraft (module docstring)."""
        return (self.compared >= MIN_COMPARED and self.share >= MIN_AGREEING
                and self.conflicts < CODE_CONFLICTS and self.scatter <= MAX_SCATTER)

    @property
    def apart(self) -> bool:
        """Two aircraft: a code conflict, or enough compared plots and too few agreeing or
        an offset that moves (:attr:`scatter`)."""
        return self.conflicts >= CODE_CONFLICTS or (self.compared >= MIN_COMPARED and (
            self.share < MIN_AGREEING or self.scatter > MAX_SCATTER))


def _one_way(a: Piece, b: Piece, v: float, window: float) -> Verdict:
    """``a``'s plots against ``b``'s track: compared, agreeing, code conflicts, summed
    normalised distance and the compared plots' time span."""
    n = b.t.size
    j1 = np.searchsorted(b.t, a.t, side="left")
    j0 = j1 - 1
    c1, c0 = np.minimum(j1, n - 1), np.maximum(j0, 0)
    tau1 = np.where(j1 < n, b.t[c1] - a.t, np.inf)
    tau0 = np.where(j0 >= 0, a.t - b.t[c0], np.inf)
    has1 = tau1 <= window
    has0 = (tau0 <= window) & ~(has1 & (tau1 == 0.0))
    both = has0 & has1
    tau0, tau1 = np.where(has0, tau0, 0.0), np.where(has1, tau1, 0.0)
    span = np.where(both, tau0 + tau1, 1.0)
    w = np.where(both, tau0 / span, np.where(has1, 1.0, 0.0))
    motion = np.where(both, 2.0 * v * tau0 * tau1 / span, v * (tau0 + tau1))

    def worst(col: np.ndarray) -> np.ndarray:
        return np.maximum(np.where(has0, col[c0].T, 0.0), np.where(has1, col[c1].T, 0.0)).T

    gate = (GATE_SIGMAS * np.hypot(a.sigma, worst(b.sigma)) + a.bias + worst(b.bias)
            + motion + SLACK_M)
    # the difference to the other's interpolated position at each common height
    wk = w[:, None]
    dx = a.x - ((1.0 - wk) * b.x[c0] + wk * b.x[c1])
    dz = a.z - ((1.0 - wk) * b.z[c0] + wk * b.z[c1])
    if dx.shape[1] == 1:
        ratio = np.hypot(dx[:, 0], dz[:, 0]) / gate
        ox, oz = dx[:, 0], dz[:, 0]
    else:  # its least length over the heights: on each segment between levels
        ex, ez = np.diff(dx, axis=1), np.diff(dz, axis=1)
        u = np.clip(-(dx[:, :-1] * ex + dz[:, :-1] * ez) / np.maximum(ex * ex + ez * ez,
                                                                     1e-9), 0.0, 1.0)
        least = np.hypot(dx[:, :-1] + u * ex, dz[:, :-1] + u * ez)
        bend = a.bend + worst(b.bend)
        scaled = least / (gate[:, None] + np.maximum(bend[:, :-1], bend[:, 1:]))
        best = np.argmin(np.where(np.isfinite(scaled), scaled, np.inf), axis=1)[:, None]
        ratio = np.take_along_axis(scaled, best, axis=1)[:, 0]
        ox = np.take_along_axis(dx[:, :-1] + u * ex, best, axis=1)[:, 0]
        oz = np.take_along_axis(dz[:, :-1] + u * ez, best, axis=1)[:, 0]
    near = ratio <= 1.0
    compared = (has0 | has1) & (motion <= MAX_MOTION_M) & (
        gate + a.span + worst(b.span) <= CELL_M) & np.isfinite(
        gate + a.x[:, 0] + worst(b.x[:, 0]))
    # Mode C: the nearest neighbour used that has one
    alt0 = np.where(has0, b.alt[c0], np.nan)
    alt1 = np.where(has1, b.alt[c1], np.nan)
    use1 = np.isfinite(alt1) & (~np.isfinite(alt0) | (tau1 <= tau0))
    b_alt = np.where(use1, alt1, alt0)
    alt_bad = np.isfinite(a.alt) & np.isfinite(b_alt) & (
        np.abs(a.alt - b_alt) > ALTITUDE_GATE_M + CLIMB_MS * np.where(use1, tau1, tau0))
    agreeing = compared & near & ~alt_bad
    k0 = np.where(has0, b.code[c0], -1)
    k1 = np.where(has1, b.code[c1], -1)
    conflict = (a.code >= 0) & ((k0 >= 0) | (k1 >= 0)) & ((k0 < 0) | (k0 != a.code)) & (
        (k1 < 0) | (k1 != a.code))
    tc = a.t[compared]
    g = agreeing & both  # interpolated: one-sided, the aircraft's motion moves the offset
    ss = a.sigma[g] ** 2 + worst(b.sigma)[g] ** 2
    return Verdict(int(compared.sum()), int(agreeing.sum()), int(conflict.sum()),
                   float(np.minimum(np.nan_to_num(ratio[compared], nan=DISTANCE_CAP),
                                    DISTANCE_CAP).sum()),
                   float(tc.min()) if tc.size else np.inf,
                   float(tc.max()) if tc.size else -np.inf,
                   (float(g.sum()), float(ox[g].sum()), float(oz[g].sum()),
                    float((ox[g] ** 2 + oz[g] ** 2).sum()), float(ss.sum())))


def _near(p: Piece, t0: float, t1: float, levels: bool) -> Piece:
    """``p``'s plots from ``t0`` to ``t1`` (the others have nothing to be compared with), at
    one level where no plot of either track is without Mode C (``levels`` False: the levels
    are alike; 11 times less work)."""
    i = int(np.searchsorted(p.t, t0, side="left"))
    j = int(np.searchsorted(p.t, t1, side="right"))
    k = slice(None) if levels else slice(0, 1)
    return Piece(p.key, p.sensor, p.rows[i:j], p.t[i:j], p.sigma[i:j], p.bias[i:j],
                 p.span[i:j], p.x[i:j, k], p.z[i:j, k], p.bend[i:j, k], p.alt[i:j],
                 p.code[i:j])


def compare(a: Piece, b: Piece, max_speed: float, window: float = WINDOW_S) -> Verdict:
    """Both tracks' plots against each other (module docstring)."""
    levels = bool(np.any(a.span > 0) or np.any(b.span > 0))
    t0, t1 = max(a.first, b.first) - window, min(a.last, b.last) + window
    a, b = _near(a, t0, t1, levels), _near(b, t0, t1, levels)
    if not a.t.size or not b.t.size:
        return Verdict(0, 0, 0)
    ab, ba = _one_way(a, b, max_speed, window), _one_way(b, a, max_speed, window)
    return Verdict(ab.compared + ba.compared, ab.agreeing + ba.agreeing,
                   ab.conflicts + ba.conflicts, ab.distance + ba.distance,
                   min(ab.first, ba.first), max(ab.last, ba.last),
                   (ab.moments[0] + ba.moments[0], ab.moments[1] - ba.moments[1],
                    ab.moments[2] - ba.moments[2], ab.moments[3] + ba.moments[3],
                    ab.moments[4] + ba.moments[4]))


def candidate_pairs(pieces: list[Piece], window: float) -> list[tuple[int, int]]:
    """Pairs of tracks of different sensors with plots in neighbouring time slots
    (``window``) and plane cells (:data:`CELL_M`): each track's plots are put in their
    (slot, cell) once, and each occupied (slot, cell) looks at its 18 neighbours ahead in
    time; cost linear in the plots and the pairs found."""
    cells: dict[tuple[int, int, int], list[int]] = {}
    for p, piece in enumerate(pieces):
        x, z = piece.x[:, _K // 2], piece.z[:, _K // 2]  # the middle height's
        ok = np.isfinite(x) & np.isfinite(z)
        if not ok.any():
            continue
        key = np.column_stack([np.floor(piece.t[ok] / window), np.floor(x[ok] / CELL_M),
                               np.floor(z[ok] / CELL_M)]).astype(np.int64)
        for s, cx, cz in np.unique(key, axis=0).tolist():
            cells.setdefault((s, cx, cz), []).append(p)
    pairs: set[tuple[int, int]] = set()
    for (s, cx, cz), here in cells.items():
        for ds in (0, 1):
            for dx in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    there = cells.get((s + ds, cx + dx, cz + dz))
                    if there is None:
                        continue
                    for i in here:
                        for j in there:
                            if i != j and pieces[i].sensor != pieces[j].sensor:
                                pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


@dataclass
class Join:
    """One association made or refused: the two tracks' keys, their verdict, and why it was
    refused (None: made)."""

    a: str
    b: str
    verdict: Verdict
    refused: str | None = None


@dataclass
class Aircraft:
    """Tracks found to be one aircraft: their indexes, its key, the joins that made it and
    the associations refused on its way."""

    members: list[int]
    key: str
    joins: list[Join] = field(default_factory=list)


@dataclass
class Component:
    """Tracks linked by associations, resolved: its tracks' indexes, the aircraft of several
    of them and the associations refused."""

    members: list[int]
    aircraft: list[Aircraft]
    refused: list[Join]


@dataclass
class Associations:
    """:func:`associate`'s answer: the resolved components and the tracks whose component is
    not resolved yet (streaming: it may still change)."""

    components: list[Component]
    waiting: set[int]


def _find(parent: list[int], i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def _rivals(pieces: list[Piece], accepted: list[tuple[int, int, Verdict]],
            twins: Callable[[int, int], bool]) -> tuple[dict[int, str], set[int]]:
    """Accepted pairs (by index in ``accepted``) in which one track agrees with two tracks of
    another sensor that overlap in time: ``ambiguous`` (the reason), when the better's
    :attr:`Verdict.mean` is not :data:`AMBIGUOUS_FACTOR` times smaller and the two are two
    aircraft (not ``twins``: one aircraft tracked twice), and ``demoted``, the one of twins
    with fewer plots compared (more evidence goes first)."""
    by_track: dict[int, list[tuple[int, int, Verdict]]] = {}
    for e, (i, j, v) in enumerate(accepted):
        by_track.setdefault(i, []).append((e, j, v))
        by_track.setdefault(j, []).append((e, i, v))
    ambiguous: dict[int, str] = {}
    demoted: set[int] = set()
    for t, seen in by_track.items():
        for n, (e, j, v) in enumerate(seen):
            for f, k, w in seen[n + 1:]:
                pj, pk = pieces[j], pieces[k]
                if pj.sensor != pk.sensor or pj.first > pk.last or pk.first > pj.last:
                    continue
                if max(v.mean, w.mean) >= AMBIGUOUS_FACTOR * min(v.mean, w.mean):
                    continue  # the better is clearly better: the order decides
                if twins(j, k):
                    demoted.add(f if (v.compared, pk.key) > (w.compared, pj.key) else e)
                    continue
                a, b = sorted((pj.key, pk.key))
                why = (f"ambiguous: {pieces[t].key} agrees with {a} and {b}, which overlap in "
                       f"time, about as well (mean distance over the gate {v.mean:.2f} and "
                       f"{w.mean:.2f}, less than {AMBIGUOUS_FACTOR:g} times apart)")
                ambiguous.setdefault(e, why)
                ambiguous.setdefault(f, why)
    return ambiguous, demoted


def resolve(pieces: list[Piece], component: list[int], accepted: list[tuple[int, int, Verdict]],
            verdict: Callable[[int, int], Verdict],
            twins: Callable[[int, int], bool] = lambda i, j: False
            ) -> tuple[list[Aircraft], list[Join]]:
    """A component's associations joined best first (:attr:`Verdict.mean`, then plots
    compared, then the keys), none that is ambiguous (:func:`_rivals`): two groups join unless
    they would hold two tracks of one sensor overlapping in time or two tracks of different
    sensors whose own :func:`compare` says apart."""
    root = {i: i for i in component}  # each track's group (its first track)
    groups: dict[int, list[int]] = {i: [i] for i in component}
    joins: dict[int, list[Join]] = {i: [] for i in component}
    refused: list[Join] = []
    ambiguous, demoted = _rivals(pieces, accepted, twins)

    def conflict(g: list[int], h: list[int]) -> str | None:
        for i in g:
            for j in h:
                a, b = sorted((pieces[i], pieces[j]), key=lambda p: p.key)
                if a.sensor == b.sensor:
                    if a.first <= b.last and b.first <= a.last:
                        return f"{a.key} and {b.key}, one sensor's, overlap in time"
                else:
                    v = verdict(i, j)  # symmetric
                    if v.apart:
                        return (f"{a.key} and {b.key} are apart ({v.agreeing} of {v.compared} "
                                f"plots within the gate, {v.conflicts} Mode 3/A conflicts)")
        return None

    order = sorted(range(len(accepted)), key=lambda e: (
        e in demoted, accepted[e][2].mean, -accepted[e][2].compared,
        sorted((pieces[accepted[e][0]].key, pieces[accepted[e][1]].key))))
    for e in order:
        i, j, v = accepted[e]
        a, b = sorted((pieces[i].key, pieces[j].key))
        if e in ambiguous:
            refused.append(Join(a, b, v, ambiguous[e]))
            continue
        gi, gj = root[i], root[j]
        if gi == gj:
            continue
        why = conflict(groups[gi], groups[gj])
        if why is not None:
            refused.append(Join(a, b, v, why))
            continue
        for k in groups[gj]:
            root[k] = gi
        groups[gi] += groups.pop(gj)
        joins[gi] += [*joins.pop(gj), Join(a, b, v)]
    out = [Aircraft(sorted(g), min(pieces[k].key for k in g), joins[r])
           for r, g in groups.items() if len(g) > 1]
    return out, refused


VerdictCache = dict[tuple[object, object], Verdict]
"""Streaming: the final verdicts of pairs still in the split's buffer, by the pieces'
identities (their key and first row: a key may name another piece later)."""


def associate(pieces: list[Piece], done: np.ndarray, max_speed: float, window: float,
              final_before: float, idents: list[object] | None = None,
              cache: VerdictCache | None = None) -> Associations:
    """The aircraft of several of ``pieces`` (module docstring). Streaming: a pair whose
    earlier last plot is at or after ``final_before`` (a track ending before it gets no more
    plots, and every plot up to ``window`` after it has arrived) is still open; a component
    (tracks linked by associations or open pairs) is resolved once every track in it is
    ``done``, else its tracks wait. ``cache``: final verdicts of earlier calls by ``idents``
    (kept for the pairs of these pieces only: what the buffer holds)."""
    parent = list(range(len(pieces)))
    ids = idents if idents is not None else list(range(len(pieces)))
    known = cache if cache is not None else {}
    kept: VerdictCache = {}

    def verdict(i: int, j: int) -> Verdict:
        i, j = min(i, j), max(i, j)
        k = (ids[i], ids[j])
        if k not in known:  # only final verdicts are asked for (closed pairs, done tracks)
            known[k] = compare(pieces[i], pieces[j], max_speed, window)
        kept[k] = known[k]
        return known[k]

    def twins(i: int, j: int) -> bool:
        """Two tracks of one sensor that are one aircraft: compared without bias allowances
        (one radar's bias is common to both)."""
        a, b = (dataclasses.replace(pieces[k], bias=np.zeros_like(pieces[k].bias))
                for k in (i, j))
        return compare(a, b, max_speed, window).same

    accepted: list[tuple[int, int, Verdict]] = []
    for i, j in candidate_pairs(pieces, window):
        if min(pieces[i].last, pieces[j].last) >= final_before:
            linked = True  # open: later plots may still decide it
        else:
            v = verdict(i, j)
            linked = v.same
            if linked:
                accepted.append((i, j, v))
        if linked:
            ri, rj = _find(parent, i), _find(parent, j)
            if ri != rj:
                parent[rj] = ri
    components: dict[int, list[int]] = {}
    for i in range(len(pieces)):
        components.setdefault(_find(parent, i), []).append(i)
    resolved: list[Component] = []
    waiting: set[int] = set()
    for comp in components.values():
        if len(comp) < 2:
            continue
        if not all(bool(done[i]) for i in comp):
            waiting.update(comp)
            continue
        inside = set(comp)
        found, refused = resolve(pieces, comp, [e for e in accepted if e[0] in inside], verdict,
                                 twins)
        resolved.append(Component(comp, found, refused))
    if cache is not None:
        cache.clear()
        cache.update(kept)
    return Associations(resolved, waiting)


__all__ = ["Associations", "Piece", "Verdict", "associate", "compare", "plane_points"]
