"""Aircraft without a Mode S address seen by several radars come out as one track
(solver.io.association through solver.io.split; issue 16): three Mode A/C aircraft crossing
and flying in parallel under one code, different codes, hand-overs and chains, a Mode S
aircraft beside, streamed alike."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_io_asterix import SENSOR_FILE, SENSORS
from test_io_split import assert_streamed_alike, concat, split, streamed_as_whole

from solver.frames import LocalFrame, slant_and_azimuth
from solver.io.association import Piece, Verdict, resolve
from solver.io.problems import Problems
from solver.io.reading import Selection
from solver.io.sensors_file import parse_sensors
from solver.io.split import split_aircraft, split_stream
from solver.io.tables import FL_M, PlotRows

PLANE = LocalFrame(46.0, 14.0)  # R1's site: the recording's plane
SCANS = {"R1": (4.0, 0.3), "R2": (5.0, 1.1), "R3": (6.0, 2.2)}
R3 = {"id": "R3", "kind": "radar", "lat_deg": 46.6, "lon_deg": 14.2, "height_m": 800.0,
      "range_error_m": 150.0, "azimuth_error_deg": 0.24}
SITES = {s["id"]: (s["lat_deg"], s["lon_deg"], s["height_m"]) for s in [*SENSOR_FILE[:2], R3]}


@dataclasses.dataclass(frozen=True)
class Flight:
    """A straight flight in the plane: at ``(x0, z0)`` m at ``t = 0``, velocity ``(vx, vz)``
    m/s, flight level ``fl``; each radar's track number (radars not named do not see it) and
    time span, the Mode 3/A code (-1 none), the Mode S address (-1 none)."""

    x0: float
    z0: float
    vx: float
    vz: float
    fl: float | None
    tracks: dict[str, tuple[int, float, float]]
    code: int = 0o7000
    mode_s: int = -1

    def rows(self, rng: np.random.Generator, code_of=None) -> list[PlotRows]:
        out = []
        for sensor, (tn, t0, t1) in self.tracks.items():
            step, phase = SCANS[sensor]
            t = np.arange(phase, t1, step)
            t = t[t >= t0] + rng.uniform(-0.05, 0.05)
            lat, lon = PLANE.to_geodetic(self.x0 + self.vx * t, self.z0 + self.vz * t)
            h = np.full(t.size, (self.fl or 0.0) * FL_M)
            r, az, _ = slant_and_azimuth(SITES[sensor], lat, lon, h)
            code = np.full(t.size, self.code) if code_of is None else code_of(sensor, t)
            out.append(PlotRows.from_columns(
                t.size, t=t, sensor=np.full(t.size, sensor, dtype=object),
                range_m=r + rng.normal(0.0, 50.0, t.size) + (60.0 if sensor == "R1" else 0.0),
                azimuth_deg=np.rad2deg(az) + rng.normal(0.0, 0.08, t.size)
                + (0.1 if sensor == "R2" else 0.0),
                altitude_m=h if self.fl is not None else np.full(t.size, np.nan),
                flight_level=np.full(t.size, np.nan if self.fl is None else self.fl),
                mode_s=np.full(t.size, self.mode_s), track_number=np.full(t.size, tn),
                mode_3a=code))
        return out


def recording(flights, seed: int = 0, **kw) -> PlotRows:
    rng = np.random.default_rng(seed)
    parts = [p for f in flights for p in f.rows(rng, **kw)]
    rows = PlotRows.concat(parts)
    return concat([rows.take(np.argsort(rows.t, kind="stable"))])


def three_aircraft() -> tuple[Flight, ...]:
    """Two aircraft squawking 7000 on parallel tracks 3 km apart at FL 50, eastbound at 150
    m/s 30 km north of R1, and a third squawking 7000 at the same level crossing both
    northbound at 120 m/s at t = 200 s (all three within 1.5 km then)."""
    return (Flight(30e3, 10e3, 0.0, 150.0, 50.0, {"R1": (11, 0, 400), "R2": (41, 0, 400)}),
            Flight(33e3, 10e3, 0.0, 150.0, 50.0, {"R1": (12, 0, 400), "R2": (40, 0, 400)}),
            Flight(31.5e3 - 120.0 * 200, 40e3, 120.0, 0.0, 50.0,
                   {"R1": (13, 0, 400), "R2": (42, 0, 400)}))


def owners(rows: PlotRows, tracks: dict, flights) -> dict[str, set[int]]:
    """Each track's true aircraft (by sensor and track number)."""
    who = {(s, tn): k for k, f in enumerate(flights) for s, (tn, _, _) in f.tracks.items()}
    return {key: {who[(str(rows.sensor[i]), int(rows.track_number[i]))]
                  for i in tr.rows.tolist()} for key, tr in tracks.items()}


@pytest.mark.parametrize("mode_c", [True, False])
def test_three_mode_ac_aircraft_seen_by_two_radars_are_three_tracks(mode_c):
    """Six sensor tracks -> exactly three aircraft, each with every plot of both radars and
    none of another's; each association reported with its keys and evidence. Without Mode C
    (an unknown height moves a plot along its ray by up to 0.9 km here) the same."""
    flights = three_aircraft()
    if not mode_c:
        flights = tuple(dataclasses.replace(f, fl=None) for f in flights)
    rows = recording(flights)
    tracks, problems = split(rows)
    assert sorted(tracks) == ["R1:track:11", "R1:track:12", "R1:track:13"]
    assert owners(rows, tracks, flights) == {"R1:track:11": {0}, "R1:track:12": {1},
                                             "R1:track:13": {2}}
    assert sum(len(tr.table) for tr in tracks.values()) == len(rows)
    for tr in tracks.values():
        assert {s.id for s in tr.table.sensors} == {"R1", "R2"}
    assert problems.counts == {"tracks_associated": 3}
    said = {e.where: e.message for e in problems.of_kind("tracks_associated")}
    assert said["aircraft R1:track:12"].startswith("R1:track:12 and R2:track:40: ")
    assert "plots compared" in said["aircraft R1:track:12"]
    assert "(100%) within the gate" in said["aircraft R1:track:12"]
    assert tracks["R1:track:12"].members == ("R1:track:12", "R2:track:40")
    # a sensor track's key selects the aircraft it is in (the command line's --aircraft)
    chosen = Selection(["R2:track:40", "R2:track:99"])
    assert [tr.key for tr in chosen.filter(iter(tracks.values()))] == ["R1:track:12"]
    assert chosen.missing() == ["R2:track:99"]
    # switched off: one track per radar, as before
    off = {tr.key for tr in split_aircraft(rows, SENSORS, associate_tracks=False)}
    assert off == {f"R{r}:track:{n}" for r, n in ((1, 11), (1, 12), (1, 13), (2, 40),
                                                  (2, 41), (2, 42))}
    assert_streamed_alike(rows, tracks, 23)


def test_different_codes_at_the_same_time_are_never_one_aircraft():
    """One flight as two radars see it, but R1 says 1234 and R2 4321 throughout: two
    aircraft (positions cannot overrule codes). A squawk change (R1 shows the new code from
    200 s, R2 from its next scan) is no conflict: one aircraft."""
    f = Flight(30e3, 10e3, 0.0, 150.0, 50.0, {"R1": (11, 0, 400), "R2": (41, 0, 400)})
    rows = recording([f], code_of=lambda s, t: np.full(t.size, 0o1234 if s == "R1" else 0o4321))
    tracks, problems = split(rows)
    assert sorted(tracks) == ["R1:track:11", "R2:track:41"] and not problems
    changed = recording([f], code_of=lambda s, t: np.where(t < 200.0, 0o1234, 0o4521))
    tracks, problems = split(changed)
    assert list(tracks) == ["R1:track:11"] and problems.counts == {"tracks_associated": 1}


def test_a_hand_over_and_a_chain_of_three_radars_are_one_aircraft():
    """R1 sees the aircraft first, then R1 and R2, then R2 alone: one track (also without
    Mode C and 30 s of overlap), but not another aircraft that R2 starts seeing 2.5 km away as
    R1's ends; R1 -> R2 -> R3
    (R1 and R3 never at once) with R3 seeing it under two track numbers in turn (it lost and
    found it again): one track of the five, reported as four associations."""
    sensors = parse_sensors([*SENSOR_FILE[:2], R3])
    f = Flight(30e3, 10e3, 0.0, 150.0, 50.0, {"R1": (11, 0, 300), "R2": (41, 200, 600)})
    rows = recording([f])
    tracks, problems = split(rows)
    assert list(tracks) == ["R1:track:11"] and len(tracks["R1:track:11"].table) == len(rows)
    assert problems.counts == {"tracks_associated": 1}
    # without Mode C and 30 s of overlap: the same
    short = dataclasses.replace(f, fl=None, tracks={"R1": (11, 0, 300), "R2": (41, 270, 600)})
    tracks, problems = split(recording([short]))
    assert list(tracks) == ["R1:track:11"] and problems.counts == {"tracks_associated": 1}
    # R1's aircraft ends as R2 starts seeing another 2.5 km away (4 s of overlap): too little
    # evidence, two tracks (compared with the other's plots extrapolated up to 30 s at the
    # speed bound, gates of up to 10 km, they were one)
    other = Flight(32.5e3, 10e3, 0.0, 150.0, None, {"R2": (41, 296, 600)})
    rows = recording([dataclasses.replace(f, fl=None, tracks={"R1": (11, 0, 300)}), other])
    tracks, problems = split(rows)
    assert sorted(tracks) == ["R1:track:11", "R2:track:41"] and not problems
    chain = Flight(-20e3, 10e3, 100.0, 100.0, 80.0, {"R1": (7, 0, 300), "R2": (8, 200, 800)})
    r3 = dataclasses.replace(chain, tracks={"R3": (31, 500, 700)})
    r3b = dataclasses.replace(chain, tracks={"R3": (32, 712, 900)})
    rows = recording([chain, r3, r3b])
    problems = Problems()
    tracks = {tr.key: tr for tr in split_aircraft(rows, sensors, problems=problems)}
    assert list(tracks) == ["R1:track:7"] and len(tracks["R1:track:7"].table) == len(rows)
    assert {s.id for s in tracks["R1:track:7"].table.sensors} == {"R1", "R2", "R3"}
    assert problems.counts == {"tracks_associated": 3}  # R3's two tracks each with R2's
    streamed = [tr.key for tr in split_stream(
        [rows.take(np.arange(k, min(k + 40, len(rows)))) for k in range(0, len(rows), 40)],
        sensors)]
    assert streamed == ["R1:track:7"]


def test_a_mode_s_aircraft_beside_is_not_absorbed():
    """A Mode S aircraft 1 km from a Mode A/C aircraft, both seen by both radars: the Mode S
    key keeps its own plots (addresses are identities, never associated); the Mode A/C
    aircraft's two radar tracks are one."""
    flights = (Flight(30e3, 10e3, 0.0, 150.0, 50.0, {"R1": (11, 0, 400), "R2": (41, 0, 400)}),
               Flight(31e3, 10e3, 0.0, 150.0, 50.0, {"R1": (12, 0, 400), "R2": (42, 0, 400)},
                      code=0o2000, mode_s=0x4CA2D1))
    rows = recording(flights)
    tracks, problems = split(rows)
    assert sorted(tracks) == ["4CA2D1", "R1:track:11"]
    assert (rows.mode_s[tracks["4CA2D1"].rows] == 0x4CA2D1).all()
    assert (rows.mode_s[tracks["R1:track:11"].rows] < 0).all()
    assert len(tracks["R1:track:11"].table) + len(tracks["4CA2D1"].table) == len(rows)
    assert problems.counts == {"tracks_associated": 1}


def test_one_track_of_a_radar_does_not_join_two_of_another_at_once():
    """R1 tracks one aircraft twice at once (track 11 throughout, a duplicate 12 from 100 to
    300 s), R2 once: R2's track agrees with both, but one aircraft cannot hold two of R1's
    tracks at once: it joins the one with more evidence (11: more plots compared, whatever
    the rows' order), the other stays apart, reported. A track swapping to another aircraft 10
    km away half-way agrees with neither (about half its plots): none joins it, and the
    split's safety net tells its two aircraft apart (aircraft_apart)."""
    f = Flight(30e3, 10e3, 0.0, 150.0, 50.0, {"R1": (11, 0, 400), "R2": (40, 0, 400)})
    dup = dataclasses.replace(f, tracks={"R1": (12, 100, 300)})
    rows = recording([f, dup])
    tracks, problems = split(rows)
    assert sorted(tracks) == ["R1:track:11", "R1:track:12"]
    assert {s.id for s in tracks["R1:track:11"].table.sensors} == {"R1", "R2"}
    assert problems.counts == {"tracks_associated": 1, "association_refused": 1}
    (refused,) = problems.of_kind("association_refused")
    assert refused.message.startswith("R1:track:12 and R2:track:40: ")
    assert "R1:track:11 and R1:track:12, one sensor's, overlap in time" in refused.message
    backwards, _ = split(concat([rows.take(np.arange(len(rows))[::-1])]))
    assert {k: tr.rows.size for k, tr in backwards.items()} == {
        k: tr.rows.size for k, tr in tracks.items()}
    a = Flight(30e3, 10e3, 0.0, 150.0, 50.0, {"R1": (11, 0, 400), "R2": (40, 0, 196)})
    b = Flight(40e3, 10e3, 0.0, 150.0, 50.0, {"R1": (12, 0, 400), "R2": (40, 200, 400)})
    rows = recording([a, b])
    tracks, problems = split(rows)
    assert problems.counts == {"aircraft_apart": 1}
    assert sorted(tracks) == ["R1:track:11", "R1:track:12", "R2:track:40", "R2:track:40~2"]


def random_aircraft(rng: np.random.Generator, n: int) -> list[Flight]:
    """``n`` Mode A/C aircraft in a 40-km square over 10 minutes, each seen by R1 and R2 over
    random spans (overlapping or not, reused track numbers), codes from a small set, some
    without Mode C."""
    out = []
    for _ in range(n):
        spans = {}
        start = float(rng.uniform(0, 600))
        for s in ("R1", "R2"):
            if rng.random() < 0.9:
                t0 = start + float(rng.uniform(-60, 60))
                spans[s] = (int(rng.integers(1, 4)), t0, t0 + float(rng.uniform(20, 200)))
        heading = rng.uniform(0, 2 * np.pi)
        out.append(Flight(float(rng.uniform(20e3, 60e3)), float(rng.uniform(10e3, 50e3)),
                          150 * np.cos(heading), 150 * np.sin(heading),
                          None if rng.random() < 0.3 else float(rng.integers(30, 80)), spans,
                          code=int(rng.choice([0o7000, 0o2000, 0o1234]))))
    return out


def test_streaming_association_gives_the_same_tracks():
    """split_stream over random recordings of Mode A/C aircraft seen by two radars, in random
    chunks, rows out of time order by less than disorder_s (5 s), gives split_aircraft's
    tracks, keys, rows and problems on the whole (gap_s 40 s: pieces, reused track numbers,
    associations final 20 s after the earlier track's end); tracks come out early too."""
    rng = np.random.default_rng(5)
    made = closed_early = 0
    for case in range(12):
        rows = recording(random_aircraft(rng, int(rng.integers(3, 9))), seed=case)
        rows = rows.take(np.argsort(rows.t + rng.uniform(0.0, 5.0, len(rows)), kind="stable"))
        early, whole_p = streamed_as_whole(rows, int(rng.integers(5, 60)), gap_s=40.0,
                                           case=case)
        closed_early += early
        made += whole_p.counts.get("tracks_associated", 0)
    assert made > 10 and closed_early > 10, (made, closed_early)


def test_the_safety_net_still_parts_a_merged_track_and_user_keys_stay_apart():
    """R1's track 11 and R2's track 41 are one aircraft to 300 s; R1 gives track 11 again at
    330 s (within the 300-s gap split) to another aircraft 60 km away that R2 does not see:
    the association joins the two tracks (the later plots have nothing of R2's to be compared
    with), and the merged track is told apart (``R1:track:11~2``, reported). The user's own
    keys are never associated, even when they are one aircraft."""
    f = Flight(30e3, 10e3, 0.0, 150.0, 50.0, {"R1": (11, 0, 300), "R2": (41, 0, 300)})
    other = Flight(-30e3, 10e3, 0.0, 150.0, 90.0, {"R1": (11, 330, 600)})
    rows = recording([f, other])
    tracks, problems = split(rows)
    assert sorted(tracks) == ["R1:track:11", "R1:track:11~2"]
    assert problems.counts == {"tracks_associated": 1, "aircraft_apart": 1}
    assert {s.id for s in tracks["R1:track:11"].table.sensors} == {"R1", "R2"}
    later = tracks["R1:track:11~2"]
    assert later.table.t.min() > 329.0 and {s.id for s in later.table.sensors} == {"R1"}
    user = recording([f])
    user = dataclasses.replace(user, aircraft=np.where(user.sensor == "R1", "A1", "A2").astype(
        object))
    tracks, problems = split(user)
    assert sorted(tracks) == ["A1", "A2"] and not problems


@pytest.mark.parametrize("fl, trail", [(100.0, 2e3), (None, 3e3)])
@pytest.mark.parametrize("numbers", [(41, 42), (42, 41)])
def test_two_aircraft_in_trail_seen_by_both_radars_are_never_swapped(fl, trail, numbers):
    """Two aircraft squawking 7000 in trail 2 km apart (Mode C) or 3 km (none) 150 km from
    the radars, each seen by R1 and R2: every pairing agrees on all plots within the gates
    (bias allowances), so R2's numbering decided (issue: swapped). Ranked by the mean
    distance over the gate (0.09 against 0.67 here) each track holds one aircraft, with
    either numbering."""
    a = Flight(150e3, 0.0, 0.0, 150.0, fl, {"R1": (11, 0, 400), "R2": (numbers[0], 0, 400)})
    b = Flight(150e3, -trail, 0.0, 150.0, fl, {"R1": (12, 0, 400), "R2": (numbers[1], 0, 400)})
    rows = recording([a, b])
    tracks, problems = split(rows)
    assert owners(rows, tracks, [a, b]) == {"R1:track:11": {0}, "R1:track:12": {1}}
    assert tracks["R1:track:11"].members == ("R1:track:11", f"R2:track:{numbers[0]}")
    assert problems.counts["tracks_associated"] == 2


def _piece(key: str, sensor: int, t0: float, t1: float) -> Piece:
    t = np.arange(t0, t1, 4.0)
    one = np.zeros((t.size, 1))
    return Piece(key, sensor, np.arange(t.size), t, t * 0, t * 0, t * 0, one, one, one,
                 t * np.nan, np.full(t.size, 0o7000))


def test_a_track_agreeing_about_as_well_with_two_aircraft_joins_neither():
    """R2:41 agrees with R1:11 and R1:12, which overlap in time (two aircraft), with mean
    distances over the gate 0.30 and 0.45 (less than AMBIGUOUS_FACTOR apart): neither join is
    made, both reported ambiguous; 0.10 against 0.45 joins the better; one aircraft tracked
    twice by R1 (twins) joins the track with more plots compared."""
    pieces = [_piece("R1:track:11", 0, 0, 400), _piece("R1:track:12", 0, 100, 400),
              _piece("R2:track:41", 1, 0, 400)]

    def run(m11: float, m12: float, twins: bool):
        accepted = [(0, 2, Verdict(100, 100, 0, 100 * m11)),
                    (1, 2, Verdict(80, 80, 0, 80 * m12))]
        return resolve(pieces, [0, 1, 2], accepted, lambda i, j: Verdict(0, 0, 0),
                       lambda i, j: twins)

    found, refused = run(0.30, 0.45, False)
    assert found == [] and len(refused) == 2
    assert all(j.refused.startswith("ambiguous: R2:track:41 agrees with R1:track:11 and "
                                    "R1:track:12") for j in refused)
    found, refused = run(0.10, 0.45, False)
    assert [ac.members for ac in found] == [[0, 2]] and len(refused) == 1
    assert "overlap in time" in refused[0].refused
    found, refused = run(0.45, 0.30, True)
    assert [ac.members for ac in found] == [[0, 2]]


def test_parts_told_apart_name_the_sensor_tracks_they_hold():
    """R1:11 with R2:41 to 300 s; from 320 s (within the gap split) another aircraft 6 km away
    as R1:12 and R2:41 again (its number reused): one association chain, parted by the safety
    net. Each part's members are the sensor tracks whose plots it holds (was: all on the
    first, none on ``~2``), so a sensor track's key selects the aircraft it is in, and each
    join is reported under the part that holds both its tracks."""
    a = Flight(30e3, 10e3, 0.0, 150.0, 80.0, {"R1": (11, 0, 300), "R2": (41, 0, 300)})
    b = Flight(36e3, 10e3 + 150 * 320, 0.0, 150.0, 80.0,
               {"R1": (12, 320, 620), "R2": (41, 320, 620)})
    rows = recording([a, b])
    tracks, problems = split(rows)
    assert problems.counts["aircraft_apart"] == 1
    for tr in tracks.values():
        held = {f"{rows.sensor[i]}:track:{rows.track_number[i]}" for i in tr.rows.tolist()}
        assert set(tr.members) == held
    chosen = Selection(["R1:track:12"])
    (got,) = chosen.filter(iter(tracks.values()))
    assert rows.t[got.rows].min() > 315.0
    said = {e.message.split(": ")[0]: e.where for e in problems.of_kind("tracks_associated")}
    assert said == {"R1:track:11 and R2:track:41": "aircraft R1:track:11",
                    "R1:track:12 and R2:track:41": f"aircraft {got.key}"}


@pytest.mark.parametrize("fl", [80.0, None])
def test_a_crossing_hand_over_and_one_each_in_trail_stay_two_aircraft(fl):
    """Two aircraft squawking 7000 crossing at right angles 80 km out, R1 dropping A 10 s after
    the crossing, R2 picking up B 10 s before it: 11 plots agree (was: joined, a 90-degree
    turn), but their offset turns through the crossing (scatter 8 against one aircraft's
    0.8-1.2). In trail 3 km apart 100 km out, R1 seeing only A and R2 only B, no Mode C:
    the best common height wanders (scatter 4.9): two."""
    a = Flight(80e3, 10e3 - 150 * 200, 0.0, 150.0, fl, {"R1": (11, 0, 210)})
    b = Flight(80e3 - 150 * 200, 10e3, 150.0, 0.0, fl, {"R2": (42, 190, 400)})
    tracks, problems = split(recording([a, b]))
    assert sorted(tracks) == ["R1:track:11", "R2:track:42"] and not problems
    if fl is None:
        a = Flight(100e3, 0.0, 0.0, 150.0, None, {"R1": (11, 0, 400)})
        b = Flight(100e3, -3e3, 0.0, 150.0, None, {"R2": (42, 0, 400)})
        tracks, problems = split(recording([a, b]))
        assert sorted(tracks) == ["R1:track:11", "R2:track:42"] and not problems


def test_one_aircraft_passing_close_to_a_radar_is_still_one():
    """The offset between two radars' plots of one aircraft turns with the azimuth as it passes
    1 km from R1 (R1's range bias, R2's azimuth bias): scatter 1.1, within MAX_SCATTER."""
    f = Flight(1e3, -30e3, 0.0, 150.0, 50.0, {"R1": (11, 0, 400), "R2": (41, 0, 400)})
    tracks, problems = split(recording([f]))
    assert list(tracks) == ["R1:track:11"] and problems.counts == {"tracks_associated": 1}
