"""A recording's plot rows -> one :class:`solver.plots.PlotTable` per aircraft.

Aircraft key of a row (``../shared/spec/recordings.md``), first that applies:

1. ``aircraft`` (the user's own key), as given;
2. the Mode S address, as 6 hex digits (``4CA2D1``): plots of every sensor with that address
   are one track (radar and ADS-B merged);
3. the sensor's track number: ``<sensor>:track:<number>``;
4. the Mode 3/A code: ``<sensor>:mode3a:<octal code>``.

Sensor tracks without Mode S (3., pieces after the gap split, off the ground) of different
sensors that are one aircraft by their plots (positions, Mode C, Mode 3/A:
:mod:`solver.io.association`) are joined under their smallest key (``R1:track:12`` with
``R2:track:40``: ``R1:track:12``), each join reported (``tracks_associated``: the keys, plots
compared, share agreeing; a join refused: ``association_refused``); never the user's keys,
Mode S keys or Mode 3/A keys.

Before keying, a sensor's track (sensor, track number; pieces split at ``gap_s``) whose plots
carry one single Mode S address lends it to its plots without one, so a track with an
intermittent address stays one aircraft. Every key is split where the aircraft is not seen
for more than ``gap_s`` (default 300 s: track numbers and codes are reused, an address may fly
twice in a recording, a reconstruction across a long gap would be a guess); later pieces get
``#2``, ``#3`` ..., and where the aircraft lands or takes off (its reports' ``on_ground``,
:func:`_on_ground`: the reports on the ground are left out, counted as ``on_ground``). Rows
without any key are reported (``no_aircraft_key``). A key with plots
without an address is then told apart into aircraft by reach (:func:`_apart`): another
aircraft under it is ``KEY~2``, ``KEY~3`` ... (``aircraft_apart``).

:func:`split_stream` does the same on a recording that arrives in pieces and yields each
aircraft once no later plot can change it (the same tracks, tested on random recordings):
memory then holds the aircraft in the air, and those within ``gap_s`` of a sensor track
without Mode S that is still in the air (its plots could still be lent an address), and the
sensor tracks associated (or still comparable) with one in the air.

Each aircraft's rows are put in time order (stable); a sensor's second plot at the same time
of the same aircraft is reported (``duplicate_time``) and left out (the first is kept), as are
rows of sensors not in the sensor file (``unknown_sensor``), rows whose measurement does not
fit their sensor's kind (``wrong_measurement``), rows the plots table refuses (its message, the
row's byte offset or row number) and tracks of fewer than ``min_plots`` plots (``short_track``,
with their key and count). Nothing is dropped without a counted problem.

Every track is built in the recording's plane (:func:`recording_frame`), so all tracks share
one ``x``/``z`` plane.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..frames import LocalFrame
from ..inputs import Bounds, FloatArray, InputError, format_loc
from ..plots import PlotTable
from ..sensors import RadarSensor
from .altitudes import MAX_OFFSET_M, geometric_altitudes, moved_note
from .association import (
    PLANE_COLUMNS,
    WINDOW_S,
    Associations,
    Piece,
    VerdictCache,
    associate,
    plane_points,
)
from .problems import Problems
from .scans import scan_step
from .sensors_file import SensorSet, take_off_offsets
from .tables import PlotRows

GAP_S = 300.0
DISORDER_S = 60.0
"""How far (s) a row of a recording read in parts may come after a later-timed one
(:func:`split_stream`)."""
MIN_PLOTS = 3
MAX_SPEED_MS = Bounds().v[1]
"""The fastest ground speed (m/s) by which a key's plots are told apart into aircraft (the
aircraft model's default bound; the command line and jobs pass their run's)."""
_MAX_ROW_RETRIES = 50


@dataclass(frozen=True)
class AircraftTrack:
    """One aircraft's plots: its ``key``, the validated ``table`` (rows in time order) and, for
    each table row, its index in the recording's :class:`PlotRows` (``rows``) and where it is
    in the input (``origin``, in ``origin_unit``: :attr:`PlotRows.origin`)."""

    key: str
    table: PlotTable
    rows: np.ndarray
    origin: np.ndarray
    origin_unit: str = "row"
    pressure_offset_m: float | None = None
    """The median geometric minus pressure altitude its ADS-B gave, by which its Mode C
    altitudes were moved (:mod:`solver.io.altitudes`); None: none moved."""
    members: tuple[str, ...] = ()
    """The keys of the sensor tracks associated into it (:mod:`solver.io.association`), its
    own among them; empty: none associated."""
    notes: tuple[str, ...] = ()
    """What the track's answer says before its reconstruction's warnings (its Mode C made
    geometric, as a single request's answer says it: :func:`solver.batch.run_batch`)."""


def recording_frame(sensors: SensorSet, rows: PlotRows) -> LocalFrame | None:
    """The plane every track of a recording is reconstructed in: the sensor file's
    ``reference``, else the first radar's site, else the first position plot; None (flat, no
    geodesy) when there is none of these."""
    if sensors.reference is not None:
        return sensors.reference
    for s in sensors.sensors:
        if isinstance(s, RadarSensor) and s.site is not None:
            return LocalFrame(s.site.lat_deg, s.site.lon_deg)
    pos = np.flatnonzero(np.isfinite(rows.lat_deg) & np.isfinite(rows.lon_deg))
    if pos.size:
        return LocalFrame(float(rows.lat_deg[pos[0]]), float(rows.lon_deg[pos[0]]))
    return None


def aircraft_keys(rows: PlotRows, gap_s: float = GAP_S,
                  pieces_done: dict[str, int] | None = None) -> np.ndarray:
    """The aircraft key of every row (``""``: none), see the module docstring.
    ``pieces_done``: per base key, how many of its pieces were already split off (streaming:
    the next piece is numbered after them)."""
    return _segments(_unsplit_keys(rows, gap_s), rows.t, gap_s, pieces_done,
                     rows.on_ground)[0]


TrackMemory = dict[str, list[tuple[float, int]]]
"""Streaming: per sensor track (``<sensor>:track:<n>``) still in the air, ``(t, Mode S)`` of
its plots already split off with an aircraft: they still decide what the track lends."""


def _unsplit_keys(rows: PlotRows, gap_s: float, memory: TrackMemory | None = None
                  ) -> np.ndarray:
    """Aircraft keys before the split at time gaps (``str`` array)."""
    n = len(rows)
    mode_s = rows.mode_s.copy()
    sensor = rows.sensor.astype(str)
    # a sensor's track with one single Mode S address lends it to its plots without one
    has_tn = rows.track_number >= 0
    if np.any(has_tn & (mode_s < 0)):
        idx = np.flatnonzero(has_tn)
        tn_key = np.char.add(np.char.add(sensor[idx], ":track:"),
                             rows.track_number[idx].astype(str))
        ghosts = [(k, t, a) for k in set(tn_key.tolist()) for t, a in (memory or {}).get(k, [])]
        keys = np.concatenate([tn_key, np.array([g[0] for g in ghosts], dtype=str)])
        times = np.concatenate([rows.t[idx], np.array([g[1] for g in ghosts], dtype=float)])
        addr = np.concatenate([mode_s[idx], np.array([g[2] for g in ghosts], dtype=np.int64)])
        for _, members in _groups(_segments(keys, times, gap_s)[0].astype(str)):
            addresses = np.unique(addr[members][addr[members] >= 0])
            if addresses.size == 1:
                own = idx[members[members < idx.size]]
                mode_s[own[mode_s[own] < 0]] = addresses[0]
    key = np.full(n, "", dtype=object)
    tn = np.char.add(np.char.add(sensor, ":track:"), rows.track_number.astype(str))
    code = np.char.add(np.char.add(sensor, ":mode3a:"),
                       np.array([f"{v:04o}" for v in rows.mode_3a.tolist()], dtype=str)
                       if n else np.array([], dtype=str))
    hexs = np.array([f"{v:06X}" for v in mode_s.tolist()], dtype=str) if n else np.array([])
    key = np.where(rows.mode_3a >= 0, code, key)
    key = np.where(rows.track_number >= 0, tn, key)
    key = np.where(mode_s >= 0, hexs, key)
    user = rows.aircraft.astype(str) != ""
    return np.where(user, rows.aircraft.astype(str), key).astype(str)


def _base_and_piece(rows: PlotRows, gap_s: float, pieces_done: dict[str, int],
                    memory: TrackMemory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(key before the gap split, key with its piece number, on the ground) of every row."""
    base = _unsplit_keys(rows, gap_s, memory)
    keys, ground = _segments(base, rows.t, gap_s, pieces_done, rows.on_ground)
    return base, keys.astype(str), ground


def _groups(keys: np.ndarray) -> Iterator[tuple[str, np.ndarray]]:
    """``(key, indexes)`` of every distinct non-empty key, indexes in row order."""
    if keys.size == 0:
        return
    uniq, inverse = np.unique(keys, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.flatnonzero(np.diff(inverse[order])) + 1
    for members in np.split(order, bounds):
        k = str(uniq[inverse[members[0]]])
        if k:
            yield k, members


def _segments(keys: np.ndarray, t: np.ndarray, gap_s: float,
              pieces_done: dict[str, int] | None = None, said: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """``keys`` with ``#2``, ``#3`` ... appended after each time gap of more than ``gap_s``
    (numbered after ``pieces_done[key]`` pieces split off before) and, with ``said`` (each
    row's ``on_ground``: 1, 0 or -1 not said), where the aircraft lands or takes off; and
    whether each row is of the aircraft on the ground (:func:`_on_ground`; none without
    ``said``)."""
    out = keys.astype(object).copy()
    ground = np.zeros(keys.size, dtype=bool)
    done = pieces_done or {}
    for k, members in _groups(keys):
        tm = t[members]
        order = np.argsort(tm, kind="stable")
        gap = np.diff(tm[order]) > gap_s
        if said is not None:
            # the vote within gap_s: a streamed piece is out once gap_s past its last plot
            on = _on_ground(said[members[order]], tm[order], gap, min(GROUND_VOTE_S, gap_s))
            ground[members[order]] = on
            gap = gap | (on[1:] != on[:-1])
        piece = np.concatenate([[0], np.cumsum(gap)]) + done.get(k, 0)
        if piece[-1] == 0:
            continue
        labels = np.array([k if p == 0 else f"{k}#{p + 1}" for p in piece.tolist()],
                          dtype=object)
        out[members[order]] = labels
    return out, ground


GROUND_VOTE_S = 15.0
"""A row is of the aircraft on the ground when the reports within this time of it say so: at
least :data:`MIN_GROUND_REPORTS` of them, more than say airborne."""
MIN_GROUND_REPORTS = 3
"""Fewer reports saying on the ground are no time on the ground (one spurious ground bit cut a
flight in two, a reviewer's)."""


def _gap_piece_ends(base: np.ndarray, t: np.ndarray, gap_s: float) -> np.ndarray:
    """Each row's last time of its key's piece between time gaps."""
    gap_keys = _segments(base, t, gap_s)[0]
    out = np.array(t, dtype=float)
    for _, members in _groups(gap_keys.astype(str)):
        out[members] = t[members].max()
    return out


def _on_ground(said: np.ndarray, t: np.ndarray, gap: np.ndarray, vote_s: float = GROUND_VOTE_S
               ) -> np.ndarray:
    """Whether the aircraft is on the ground at each of its rows (time order; ``said``: what
    each row says, 1 on the ground, 0 airborne, -1 nothing; ``gap``: a time gap after each row
    but the last): within each piece between gaps, the reports within ``vote_s`` of the row
    that say on the ground are :data:`MIN_GROUND_REPORTS` or more and outnumber those that
    say airborne. So a radar plot between ADS-B ground reports is on the ground (kept, it was
    150 m RMS off in a tester's recording); rows that say nothing more than ``vote_s`` after
    the last ground report are airborne (CAT021 encoders leave I040's extension, and its
    ground bit, out in the air: carried on, the ground state took a whole flight after its
    take-off, a reviewer's); sensors that disagree (a radar's flight status saying ground
    against 1-Hz ADS-B saying airborne: 250 pieces) and a lone ground bit cut nothing. Each
    row's state depends on rows within ``vote_s`` of it only, so a streamed split is the
    whole's for ``vote_s`` up to ``gap_s``."""
    out = np.zeros(said.size, dtype=bool)
    starts = np.concatenate([[0], np.flatnonzero(gap) + 1, [said.size]])
    for a, b in itertools.pairwise(starts.tolist()):
        s, tp = said[a:b], t[a:b]
        known = np.flatnonzero(s >= 0)
        if not known.size:
            continue
        tk = tp[known]
        ground = np.concatenate([[0], np.cumsum(s[known] == 1)])
        airborne = np.concatenate([[0], np.cumsum(s[known] == 0)])
        lo = np.searchsorted(tk, tp - vote_s, side="left")
        hi = np.searchsorted(tk, tp + vote_s, side="right")
        g, f = ground[hi] - ground[lo], airborne[hi] - airborne[lo]
        out[a:b] = (g >= MIN_GROUND_REPORTS) & (g > f)
    return out


def split_aircraft(rows: PlotRows, sensors: SensorSet, *, reference: LocalFrame | None = None,
                   min_plots: int = MIN_PLOTS, gap_s: float = GAP_S,
                   problems: Problems | None = None, max_speed: float = MAX_SPEED_MS,
                   associate_tracks: bool = True) -> Iterator[AircraftTrack]:
    """Yield one :class:`AircraftTrack` per aircraft (in order of first plot), recording every
    row left out in ``problems`` (see the module docstring). ``reference``: the plane (default
    :func:`recording_frame`). ``AircraftTrack.rows`` index ``rows``. ``associate_tracks``:
    False keeps each sensor's tracks without Mode S apart (measurements)."""
    frame = reference if reference is not None else recording_frame(sensors, rows)
    yield from split_stream([rows], sensors, reference=frame, min_plots=min_plots,
                            gap_s=gap_s, disorder_s=np.inf, problems=problems,
                            max_speed=max_speed, associate_tracks=associate_tracks)


def split_stream(chunks: Iterable[PlotRows], sensors: SensorSet, *,
                 reference: LocalFrame | None = None, min_plots: int = MIN_PLOTS,
                 gap_s: float = GAP_S, disorder_s: float = DISORDER_S,
                 problems: Problems | None = None, max_speed: float = MAX_SPEED_MS,
                 associate_tracks: bool = True) -> Iterator[AircraftTrack]:
    """:func:`split_aircraft` over a recording that arrives in pieces (in recording order):
    an aircraft is yielded as soon as no later plot can change it: the recording has moved
    ``gap_s + disorder_s`` past its last plot (a later plot of its key starts a new piece), no
    plot without Mode S of a sensor track that may still get plots lies within ``gap_s`` of it
    (it could still be lent its address, or lose it), its key's earlier pieces are out and,
    for a sensor track without Mode S, every track associated with it, or still comparable
    with one that is (:func:`solver.io.association.associate`), can go too. So
    memory holds the aircraft in the air (and those near a sensor track without Mode S in the
    air). The same tracks, keys, rows and problems as :func:`split_aircraft` on the whole when
    no row arrives more than ``disorder_s`` after a later-timed one. ``AircraftTrack.rows``
    count rows across all chunks. ``reference``: default :func:`recording_frame` of the first
    chunk that has one (the sensor file's reference or a radar site: the first)."""
    problems = problems if problems is not None else Problems()
    frame = reference
    index = sensors.index()
    is_radar_sensor = np.array([isinstance(s, RadarSensor) for s in sensors.sensors] + [False])
    buffer: PlotRows | None = None
    numbers = np.array([], dtype=np.int64)  # each buffered row's number in the recording
    plane = np.empty((0, PLANE_COLUMNS))  # each buffered row's plane point (association)
    window = min(WINDOW_S, gap_s / 2)  # a pair's evidence is final before its tracks are
    verdicts: VerdictCache = {}  # final verdicts of pairs still buffered (not computed again)
    pieces_done: dict[str, int] = {}
    memory: TrackMemory = {}
    seen, latest = 0, -np.inf
    for rows in itertools.chain(chunks, [None]):
        if rows is not None:
            if frame is None:  # set by the first chunk that has one, then kept
                frame = recording_frame(sensors, rows)
            keep = _usable(rows, sensors, index, is_radar_sensor, problems)
            part = rows.take(keep)
            _report_late(part, latest, disorder_s, problems)
            buffer = part if buffer is None else PlotRows.concat([buffer, part])
            numbers = np.concatenate([numbers, seen + np.flatnonzero(keep)])
            if associate_tracks:
                plane = np.concatenate([plane, _plane_of(part, sensors, index, frame)])
            seen += len(rows)
            if len(part):
                latest = max(latest, float(np.max(part.t)))
            horizon = latest - disorder_s - gap_s
        else:
            horizon = np.inf
        if buffer is None or not len(buffer):
            continue
        base, keys, ground = _base_and_piece(buffer, gap_s, pieces_done, memory)
        sensor_idx = np.array([index[s] for s in buffer.sensor.tolist()], dtype=int)
        # a plot without Mode S of a sensor track that may still get plots may still be lent
        # an address (or lose it): no aircraft within gap_s of such a plot is final yet
        pending = np.sort(buffer.t[_undecided(buffer, memory, gap_s, horizon)])
        # the pieces a landing or take-off cuts come out with their whole piece between time
        # gaps: their rows' ground states are voted over its rows (_on_ground)
        spans = _gap_piece_ends(base, buffer.t, gap_s)
        pieces: dict[str, _Piece] = {}
        for key, members in _groups(keys):
            first, last = float(np.min(buffer.t[members])), float(spans[members].max())
            near = np.searchsorted(pending, first - gap_s, side="left") < np.searchsorted(
                pending, last + gap_s, side="right")
            pieces[key] = _Piece(first, last < horizon and not near, str(base[members[0]]),
                                 members)
        found = (_associations(buffer, base, ground, plane, sensor_idx, pieces, max_speed,
                               window, horizon, numbers, verdicts)
                 if associate_tracks else None)
        complete = _complete(pieces, found)
        if not complete:
            continue
        taken = np.zeros(len(buffer), dtype=bool)
        parts: list[tuple[str, tuple[str, ...]]] = []  # each part yielded: key, members
        for key, names, members in complete:
            taken[members] = True
            for name in names:
                b = pieces[name].base
                pieces_done[b] = pieces_done.get(b, 0) + 1
            if ground[members].any():  # the aircraft on the ground: no flight to fit
                for i in members[ground[members]].tolist():
                    problems.add("on_ground", buffer.where(i), f"aircraft {key}: report of "
                                 "the aircraft on the ground (or between such reports): left "
                                 "out, ground movements are not reconstructed (the aircraft "
                                 "model is that of flight)", key=key, dropped=1)
                members = members[~ground[members]]
            track = _build(key, members, buffer, sensors, sensor_idx, frame, min_plots,
                           problems) if members.size else None
            for part in _apart(track, buffer, sensors, sensor_idx, frame, min_plots, gap_s,
                               max_speed, problems):
                held = _held(part.rows, names, pieces)
                parts.append((part.key, held))
                yield replace(part, rows=numbers[part.rows], members=held)
        if found is not None:
            _report_associations(found, taken, parts, problems)
        _remember(memory, buffer.take(taken), buffer.take(~taken), horizon)
        buffer = buffer.take(~taken)
        numbers = numbers[~taken]
        if associate_tracks:
            plane = plane[~taken]


@dataclass
class _Piece:
    """A key's piece between gaps (or ground changes) in the split's buffer: its first time,
    whether no later plot can change it, its key before the split and its rows."""

    first: float
    done: bool
    base: str
    members: np.ndarray


@dataclass
class _Found:
    """The association of the buffer's sensor tracks: the pieces looked at (their keys in
    the order of :attr:`Associations` indexes) and the answer."""

    keys: list[str]
    pieces: list[Piece]
    answer: Associations


def _plane_of(rows: PlotRows, sensors: SensorSet, index: dict[str, int],
              frame: LocalFrame | None) -> np.ndarray:
    """Plane points (:func:`solver.io.association.plane_points`) of rows that may be a
    sensor track without Mode S (track number, no address, no user key), computed once as
    they arrive."""
    sensor_idx = np.array([index[s] for s in rows.sensor.tolist()], dtype=int)
    which = (rows.track_number >= 0) & (rows.mode_s < 0) & (rows.aircraft.astype(str) == "")
    return plane_points(rows, sensors, sensor_idx, frame, which,
                        _corrected(rows, sensors, sensor_idx))


def _associations(rows: PlotRows, base: np.ndarray, ground: np.ndarray, plane: np.ndarray,
                  sensor_idx: np.ndarray, pieces: dict[str, _Piece], max_speed: float,
                  window: float, final_before: float, numbers: np.ndarray,
                  cache: VerdictCache) -> _Found:
    """:func:`solver.io.association.associate` over the pieces keyed by a sensor's track
    number (their base key ``<sensor>:track:<n>``: no address lent, no user key) off the
    ground."""
    tn_key = np.char.add(np.char.add(rows.sensor.astype(str), ":track:"),
                         rows.track_number.astype(str))
    looked = (rows.track_number >= 0) & (rows.aircraft.astype(str) == "") & (
        base.astype(str) == tn_key) & ~ground & np.isfinite(plane[:, 0])
    keys, found, done, idents = [], [], [], []
    for key, p in pieces.items():
        if looked[p.members].all():
            keys.append(key)
            found.append(Piece.of(key, int(sensor_idx[p.members[0]]), p.members, plane, rows))
            done.append(p.done)
            idents.append((key, int(numbers[p.members[0]])))
    return _Found(keys, found, associate(found, np.array(done, dtype=bool), max_speed, window,
                                         final_before, idents, cache))


def _complete(pieces: dict[str, _Piece], found: _Found | None
              ) -> list[tuple[str, list[str], np.ndarray]]:
    """The aircraft to yield now, in order of their first row: ``(key, piece keys, rows)``.
    A key's pieces go in time order (their numbers) up to the first that is not done; the
    tracks of a component of associations go all together or wait (whose tracks wait, and
    with them their key's later pieces)."""
    done = {k: p.done for k, p in pieces.items()}
    groups: list[list[str]] = []
    aircraft: dict[str, tuple[str, list[str]]] = {}  # piece key -> (aircraft key, its pieces)
    if found is not None:
        for i in found.answer.waiting:
            done[found.keys[i]] = False
        for comp in found.answer.components:
            groups.append([found.keys[i] for i in comp.members])
            for ac in comp.aircraft:
                names = [found.keys[i] for i in ac.members]
                for n in names:
                    aircraft[n] = (ac.key, names)
    by_base: dict[str, list[tuple[float, str]]] = {}
    for k, p in pieces.items():
        by_base.setdefault(p.base, []).append((p.first, k))
    while True:
        taken: set[str] = set()
        for group in by_base.values():
            for _, k in sorted(group):
                if not done[k]:
                    break
                taken.add(k)
        held = [g for g in groups if not taken.issuperset(g) and taken.intersection(g)]
        if not held:
            break
        for g in held:
            for k in g:
                done[k] = False
    out: list[tuple[str, list[str], np.ndarray]] = []
    for k in taken:
        if k in aircraft:
            key, names = aircraft[k]
            if k == min(names):
                members = np.sort(np.concatenate([pieces[n].members for n in names]))
                out.append((key, names, members))
        else:
            out.append((k, [k], pieces[k].members))
    return sorted(out, key=lambda c: int(c[2][0]))


def _held(rows: np.ndarray, names: list[str], pieces: dict[str, _Piece]) -> tuple[str, ...]:
    """The associated sensor tracks (``names``) whose rows a yielded part holds (after
    :func:`_apart` a part may hold a few of them); empty when fewer than two."""
    if len(names) < 2:
        return ()
    held = tuple(sorted(n for n in names if np.isin(pieces[n].members, rows).any()))
    return held if len(held) > 1 else ()


def _report_associations(found: _Found, taken: np.ndarray,
                         parts: list[tuple[str, tuple[str, ...]]], problems: Problems) -> None:
    """Each association made (``tracks_associated``) and refused (``association_refused``)
    of the components yielded, as its aircraft came out: keys, plots compared, share
    agreeing, mean distance over the gate and offset scatter; a join is named by the part
    yielded that holds both its tracks (``parts``: after :func:`_apart`, ``KEY~2`` may)."""
    for comp in found.answer.components:
        if not taken[found.pieces[comp.members[0]].rows[0]]:
            continue
        for ac in comp.aircraft:
            for j in ac.joins:
                v = j.verdict
                name = next((k for k, held in parts if j.a in held and j.b in held), ac.key)
                problems.add("tracks_associated", f"aircraft {name}", f"{j.a} and {j.b}: "
                             f"{v.compared} plots compared, {v.agreeing} ({v.share:.0%}) within "
                             f"the gate (mean distance {v.mean:.2f} of it, offset scatter "
                             f"{v.scatter:.1f} sigma): one aircraft without Mode S seen by "
                             f"several sensors, reconstructed as {name}")
        for j in comp.refused:
            v = j.verdict
            problems.add("association_refused", f"aircraft {j.a}", f"{j.a} and {j.b}: "
                         f"{v.compared} plots compared, {v.agreeing} ({v.share:.0%}) within the "
                         f"gate (mean distance {v.mean:.2f} of it, offset scatter "
                         f"{v.scatter:.1f} sigma), but {j.refused}: kept apart")


def _report_late(rows: PlotRows, latest: float, disorder_s: float, problems: Problems
                 ) -> None:
    """Rows timed more than ``disorder_s`` before the ``latest`` of the parts read before
    may belong to an aircraft already yielded: it then comes out in overlapping tracks.
    Counted and located, each row (the command line sorts what it finds out of order before
    splitting: a table by its times, an ASTERIX recording by sampled times; these got past)."""
    for i in np.flatnonzero(rows.t < latest - disorder_s).tolist():
        problems.add("late_plots", rows.where(i), f"timed {latest - rows.t[i]:.0f} s before "
                     f"the latest plot read earlier (more than {disorder_s:g} s): its "
                     "aircraft may have been finished already and come out again as "
                     "overlapping tracks; sort the recording by time", key="late")


def _undecided(rows: PlotRows, memory: TrackMemory, gap_s: float, horizon: float
               ) -> np.ndarray:
    """Rows whose key may still change: without Mode S or a user key, in a sensor track
    (pieces split at ``gap_s``, with its plots split off before) that may still get plots
    (last plot at or after ``horizon``)."""
    out = np.zeros(len(rows), dtype=bool)
    idx = np.flatnonzero((rows.track_number >= 0) & (rows.mode_s < 0)
                         & (rows.aircraft.astype(str) == ""))
    if not idx.size or not np.isfinite(horizon):
        return out
    tn = np.flatnonzero(rows.track_number >= 0)
    tn_key = np.char.add(np.char.add(rows.sensor[tn].astype(str), ":track:"),
                         rows.track_number[tn].astype(str))
    ghosts = [(k, t) for k in set(tn_key.tolist()) for t, _ in memory.get(k, [])]
    keys = np.concatenate([tn_key, np.array([g[0] for g in ghosts], dtype=str)])
    times = np.concatenate([rows.t[tn], np.array([g[1] for g in ghosts], dtype=float)])
    for _, members in _groups(_segments(keys, times, gap_s)[0].astype(str)):
        if float(np.max(times[members])) >= horizon:
            out[tn[members[members < tn.size]]] = True
    return out & np.isin(np.arange(len(rows)), idx)


def _remember(memory: TrackMemory, gone: PlotRows, kept: PlotRows, horizon: float) -> None:
    """Note the sensor-track plots split off; forget a sensor track when none of its plots is
    left and the recording is ``gap_s + disorder_s`` past its last (no plot can go on from
    it)."""
    for i in np.flatnonzero(gone.track_number >= 0).tolist():
        k = f"{gone.sensor[i]}:track:{gone.track_number[i]}"
        memory.setdefault(k, []).append((float(gone.t[i]), int(gone.mode_s[i])))
    live = {f"{s}:track:{n}" for s, n in zip(kept.sensor.tolist(),
                                             kept.track_number.tolist(), strict=True) if n >= 0}
    for k in [k for k, plots in memory.items()
              if k not in live and max(t for t, _ in plots) < horizon]:
        del memory[k]


def _usable(rows: PlotRows, sensors: SensorSet, index: dict[str, int],
            is_radar_sensor: np.ndarray, problems: Problems) -> np.ndarray:
    """Rows that can belong to an aircraft; the others reported (unknown sensor, a
    measurement that does not fit the sensor, no key at all)."""
    n = len(rows)
    sensor_idx = np.array([index.get(s, -1) for s in rows.sensor.tolist()], dtype=int)
    usable = np.ones(n, dtype=bool)
    for i in np.flatnonzero(sensor_idx < 0).tolist():
        problems.add("unknown_sensor", rows.where(i), f"sensor {rows.sensor[i]!r} is not in "
                     "the sensor file: its plots are left out", key=str(rows.sensor[i]),
                     dropped=1)
    usable &= sensor_idx >= 0
    radar_row = is_radar_sensor[sensor_idx]
    has_radar = rows.is_radar()
    has_pos = np.isfinite(rows.lat_deg) & np.isfinite(rows.lon_deg)
    wrong = usable & np.where(radar_row, ~has_radar | has_pos, has_radar | ~has_pos)
    for i in np.flatnonzero(wrong).tolist():
        s = sensors.sensors[sensor_idx[i]]
        need = "range_m + azimuth_deg" if isinstance(s, RadarSensor) else "lat_deg + lon_deg"
        problems.add("wrong_measurement", rows.where(i), f"a plot of {s.kind} sensor {s.id!r} "
                     f"must carry {need} only: left out", key=s.id, dropped=1)
    usable &= ~wrong
    no_key = usable & (rows.aircraft.astype(str) == "") & (rows.mode_s < 0) & (
        rows.track_number < 0) & (rows.mode_3a < 0)
    for i in np.flatnonzero(no_key).tolist():
        problems.add("no_aircraft_key", rows.where(i), "plot without aircraft key, Mode S "
                     "address, track number or Mode 3/A code: left out", key=str(rows.sensor[i]),
                     dropped=1)
    return usable & ~no_key


def _corrected(rows: PlotRows, sensors: SensorSet, sensor_idx: np.ndarray
               ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``(t, range_m, azimuth_deg)`` of rows ``m`` with their sensors' known offsets taken
    off (a report late by ``time_s`` is of that much earlier)."""
    known = sensors.known_offsets()

    def at(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return take_off_offsets(known, sensor_idx[m], rows.t[m], rows.range_m[m],
                                rows.azimuth_deg[m])

    return at


def _build(key: str, members: np.ndarray, rows: PlotRows, sensors: SensorSet,
           sensor_idx: np.ndarray, frame: LocalFrame | None, min_plots: int,
           problems: Problems) -> AircraftTrack | None:
    """One aircraft's validated table, or None (reported) when too little is left; the
    sensors' known offsets (:class:`solver.io.sensors_file.KnownOffsets`) taken off its
    plots."""
    t_r_az = _corrected(rows, sensors, sensor_idx)
    m = members[np.argsort(t_r_az(members)[0], kind="stable")]
    # a sensor's second plot at the same instant: keep the first
    s, t = sensor_idx[m], t_r_az(m)[0]
    order = np.lexsort((np.arange(m.size), t, s))
    dup_sorted = np.zeros(m.size, dtype=bool)
    dup_sorted[1:] = (s[order][1:] == s[order][:-1]) & (t[order][1:] == t[order][:-1])
    dup = np.zeros(m.size, dtype=bool)
    dup[order] = dup_sorted
    for j in np.flatnonzero(dup).tolist():
        i = int(m[j])
        problems.add("duplicate_time", rows.where(i), f"aircraft {key}: a second plot of sensor "
                     f"{rows.sensor[i]!r} at t = {rows.t[i]:.3f} s: left out (the first is "
                     "kept)", key=key, dropped=1)
    m = m[~dup]
    for attempt in range(_MAX_ROW_RETRIES):
        if m.size < min_plots:
            problems.add("short_track", f"aircraft {key}", f"{m.size} plot(s), fewer than the "
                         f"{min_plots} a reconstruction needs: left out", dropped=int(m.size))
            return None
        used = np.unique(sensor_idx[m])
        local = np.searchsorted(used, sensor_idx[m])
        position = np.array([not isinstance(sensors.sensors[k], RadarSensor)
                             for k in used.tolist()])[local]
        t, r, az = t_r_az(m)
        heights = geometric_altitudes(t, rows.altitude_m[m], rows.flight_level[m], position)
        if heights.rejected and attempt == 0:  # once, not per bad plot retried
            problems.add("implausible_altitude", f"aircraft {key}", f"{heights.rejected} "
                         f"geometric height(s) differ from the aircraft's barometric altitude "
                         f"by more than {MAX_OFFSET_M:g} m: not used to make its Mode C "
                         "geometric", key=key)
        try:
            table = PlotTable.build(
                [sensors.sensors[k] for k in used.tolist()], t, local,
                range_m=r, azimuth_rad=np.deg2rad(az),
                lat_deg=rows.lat_deg[m], lon_deg=rows.lon_deg[m],
                altitude_m=heights.altitude_m, reference=frame)
        except InputError as e:
            if len(e.loc) >= 2 and e.loc[0] == "plots" and isinstance(e.loc[1], int):
                i = int(m[e.loc[1]])
                problems.add("bad_plot", rows.where(i), f"aircraft {key}: "
                             f"{format_loc(e.loc[2:]) or 'plot'} {e.message}: left out",
                             dropped=1)
                m = np.delete(m, e.loc[1])
                continue
            problems.add("bad_track", f"aircraft {key}", f"{e}: left out",
                         dropped=int(m.size))
            return None
        moved = moved_note(heights)
        return AircraftTrack(key, table, m, rows.origin[m], rows.origin_unit,
                             heights.median_m if heights.corrected else None,
                             notes=() if moved is None else (moved,))
    problems.add("bad_track", f"aircraft {key}", f"more than {_MAX_ROW_RETRIES} bad plots: "
                 "left out", dropped=int(m.size))
    return None


MIN_APART_DENSITY = 0.5
"""Plots of a key out of reach of its aircraft make another aircraft only when its sensor sees
them on this share of its scans over their span or more, as it scans the aircraft (an
aircraft's own plots, at the detection rate; a radar's reflections of it, 5 % of its plots
in a tester's recording, came out as a ghost aircraft 13 km off, seen on 36 % of the scans)."""


def _sparse(table: PlotTable, label: np.ndarray, k: int, main: int) -> bool:
    """Whether piece ``k``'s plots of its main sensor are seen on fewer than
    :data:`MIN_APART_DENSITY` of that sensor's scans over their span, the scan period taken
    from the ``main`` piece's plots of that sensor (else from piece ``k``'s own)."""
    sensor = np.bincount(table.sensor[label == k]).argmax()
    t = np.sort(table.t[(label == k) & (table.sensor == sensor)])
    ref = np.sort(table.t[(label == main) & (table.sensor == sensor)])
    period = scan_step(np.diff(ref if ref.size >= 5 else t))
    if period <= 0 or t.size < 2:
        return False
    return t.size < MIN_APART_DENSITY * ((t[-1] - t[0]) / period + 1.0)


EARTH_RADIUS_M = 6_371_000.0
JUMP_MARGIN = 0.8
""":func:`_jumps` takes a pair out of reach from this share of the reach on: its flat planes
are no stricter than the partition's (a reviewer's pair at 0.968 of the reach was parted by
the partition and not looked at)."""


def _ground(slant: FloatArray, dh: Any) -> FloatArray:
    """Flat ground distance of a slant range ``dh`` above or below the radar."""
    return np.sqrt(np.maximum(slant**2 - dh**2, 0.0))


def _jumps(table: PlotTable, max_speed: float) -> bool:
    """Whether some sensor's plot lies out of reach of its plot before (as
    :func:`solver.refine.gate.aircraft_apart` judges reach), each sensor's plots placed on a
    flat plane of its own (a radar's about its site, at the middle of the heights they may
    take; a position sensor's by latitude and longitude): vectorised, no geodesy, so the split
    of a recording without addresses costs little where no key holds two aircraft (the plane
    fixes and the loop tripled the split's time for a recording with an address on a third of
    the plots, a reviewer's). A sensor whose plots all are one aircraft's cannot part them."""
    from ..refine.gate import reach_m

    lo, hi = table.heights()
    for k, s in enumerate(table.sensors):
        rows = np.flatnonzero(table.sensor == k)
        if rows.size < 2:
            continue
        if isinstance(s, RadarSensor):
            r, az = table.range_m[rows], table.azimuth_rad[rows]
            site_h = s.site.height_m if s.site is not None else 0.0
            alt = table.altitude_m[rows]

            known = np.isfinite(alt)
            d = np.where(known, _ground(r, np.where(known, alt, 0.0) - site_h),
                         _ground(r, (lo + hi) / 2 - site_h))
            spread = np.where(known, 0.0, np.abs(_ground(r, lo - site_h)
                                                 - _ground(r, hi - site_h)))
            x, z = d * np.cos(az), d * np.sin(az)
            sigma = np.maximum(s.sigma_r, d * s.sigma_psi)
        else:
            lat, lon = table.lat_deg[rows], table.lon_deg[rows]
            x = np.deg2rad(lat - lat[0]) * EARTH_RADIUS_M
            z = np.deg2rad(lon - lon[0]) * EARTH_RADIUS_M * np.cos(np.deg2rad(lat[0]))
            spread = np.zeros(rows.size)
            sigma = np.full(rows.size, float(getattr(s, "position_sigma_m", 0.0)))
        far = np.hypot(np.diff(x), np.diff(z)) > JUMP_MARGIN * reach_m(
            np.diff(table.t[rows]), sigma[1:] + sigma[:-1], spread[1:] + spread[:-1], max_speed)
        if far.any():
            return True
    return False


MIN_APART_PLOTS = 10
"""Plots of a key out of reach of its aircraft make another aircraft from this many on (fewer
stay with it: wild plots, which the reconstruction gives no weight)."""


def _apart(track: AircraftTrack | None, rows: PlotRows, sensors: SensorSet,
           sensor_idx: np.ndarray, frame: LocalFrame | None, min_plots: int, gap_s: float,
           max_speed: float, problems: Problems) -> list[AircraftTrack]:
    """The track, or the aircraft its key holds told apart
    (:func:`solver.refine.gate.aircraft_apart`): a radar's track number or a Mode 3/A code
    used again for another aircraft, or a Mode S address a radar track lent to plots that are
    another's (a tester's recording: its track number went on to a 7000-squawking aircraft 60
    km away, whose plots came out in the Mode S aircraft's track). Plots that carry a Mode S
    address and keys the user gave stay together; only keys with plots without an address are
    looked at. The others are named ``KEY~2``, ``KEY~3`` ... by their first plot, and
    reported (``aircraft_apart``)."""
    if track is None:
        return []
    m = track.rows
    own = rows.mode_s[m] >= 0
    if own.all() or (rows.aircraft[m].astype(str) != "").any() or m.size < 2 * MIN_APART_PLOTS:
        return [track]
    table = track.table
    if not _jumps(table, max_speed):  # one aircraft as its sensors see it: nothing to part
        return [track]
    from ..refine.gate import aircraft_apart

    fx = table.fixes()
    low, high = table.heights()
    lo = fx.centre_at(np.full(m.size, low))
    hi = fx.centre_at(np.full(m.size, high))
    spread = np.where(fx.altitude_free, np.hypot(*(hi - lo).T), 0.0)
    sigma = np.maximum(fx.ellipses.A, fx.ellipses.B)
    centre = fx.centre_at(fx.h_mid)
    scale = float(np.max(frame.scale(*centre.T))) if frame is not None else 1.0
    label = aircraft_apart(table.t, table.sensor, centre, sigma, spread, max_speed * scale,
                           gap_s)
    sizes = np.bincount(label)
    anchored = np.unique(label[own])
    main = int(anchored[np.argmax(sizes[anchored])]) if anchored.size else int(np.argmax(sizes))
    for k in range(sizes.size):
        if k in anchored or sizes[k] < MIN_APART_PLOTS or _sparse(table, label, k, main):
            label[label == k] = main
    others = [k for k in dict.fromkeys(label.tolist()) if k != main]  # by first plot
    if not others:
        return [track]
    out = []
    for n, k in enumerate([main, *others], 1):
        name = track.key if k == main else f"{track.key}~{n}"
        sel = label == k
        if k != main:
            problems.add("aircraft_apart", f"aircraft {track.key}", f"{int(sel.sum())} plots "
                         f"from t = {table.t[sel].min():.1f} s out of reach of the aircraft's "
                         "others: another aircraft under the same key (a radar track number or "
                         "Mode 3/A code used again, an address lent by a radar track): "
                         f"reconstructed apart as {name}")
        # the key's plots were built once already: what that said (an implausible altitude)
        # is said once, a part's other problems are its own
        said = Problems()
        part = _build(name, m[sel], rows, sensors, sensor_idx, frame, min_plots, said)
        problems.extend(said.without("implausible_altitude"))
        if part is not None:
            out.append(part)
    return out


__all__ = ["AircraftTrack", "aircraft_keys", "recording_frame", "split_aircraft", "split_stream"]
