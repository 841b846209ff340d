"""Splitting a recording into aircraft (solver.io.split) and the sensor file
(solver.io.sensors_file): keys, merging, and every left-out plot reported."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_io_asterix import SENSOR_FILE, SENSORS

from solver.frames import LocalFrame
from solver.inputs import InputError
from solver.io.problems import Problems
from solver.io.sensors_file import load_sensors, parse_sensors
from solver.io.split import aircraft_keys, recording_frame, split_aircraft, split_stream
from solver.io.tables import PlotRows
from solver.sensors import PositionSensor, RadarSensor


def radar_rows(t, sensor="R1", mode_s=-1, track_number=-1, mode_3a=-1, aircraft="",
               range_m=60_000.0, altitude_m=np.nan, azimuth_deg=45.0) -> PlotRows:
    t = np.asarray(t, dtype=float)
    n = t.size

    def col(v, dtype):
        return np.broadcast_to(np.asarray(v, dtype=dtype), (n,)).copy()

    return PlotRows.from_columns(
        n, t=t, sensor=col(sensor, object), range_m=col(range_m, float) + 100.0 * t,
        azimuth_deg=col(azimuth_deg, float), altitude_m=col(altitude_m, float),
        mode_s=col(mode_s, np.int64), track_number=col(track_number, np.int64),
        mode_3a=col(mode_3a, np.int64), aircraft=col(aircraft, object))


def adsb_rows(t, mode_s) -> PlotRows:
    t = np.asarray(t, dtype=float)
    return PlotRows.from_columns(t.size, t=t, sensor=np.full(t.size, "ADSB", dtype=object),
                                 lat_deg=46.3 + 1e-3 * t, lon_deg=np.full(t.size, 14.4),
                                 mode_s=np.full(t.size, mode_s))


def concat(parts: list[PlotRows]) -> PlotRows:
    """Rows of several parts, numbered 1.. as the rows of one table."""
    rows = PlotRows.concat(parts)
    return dataclasses.replace(rows, origin=np.arange(1, len(rows) + 1))


def split(rows: PlotRows, **kw):
    problems = Problems()
    tracks = {tr.key: tr for tr in split_aircraft(rows, SENSORS, problems=problems, **kw)}
    return tracks, problems


def test_keys_in_order_of_preference():
    rows = concat([
        radar_rows([0, 4, 8], mode_s=0x4CA2D1, track_number=7, mode_3a=0o7000),
        radar_rows([1, 5, 9], track_number=7, mode_3a=0o1234, sensor="R2"),
        radar_rows([2, 6, 10], mode_3a=0o1234, sensor="R2"),
        radar_rows([3, 7, 11], mode_s=0x4CA2D1, aircraft="AFR123"),
    ])
    keys = aircraft_keys(rows).tolist()
    assert keys == ["4CA2D1"] * 3 + ["R2:track:7"] * 3 + ["R2:mode3a:1234"] * 3 + ["AFR123"] * 3


def test_mode_s_merges_sensors_and_is_lent_to_its_track():
    rows = concat([
        radar_rows([0, 4, 8, 12], mode_s=[0x4CA2D1, -1, 0x4CA2D1, -1], track_number=7),
        radar_rows([1, 6, 11], mode_s=0x4CA2D1, sensor="R2"),
        adsb_rows([2, 3, 5], 0x4CA2D1),
        # a track number carrying two addresses lends neither
        radar_rows([20, 24, 28, 32, 36], mode_s=[0x111111, 0x222222, -1, -1, -1],
                   track_number=9),
    ])
    tracks, problems = split(rows)
    assert sorted(tracks) == ["4CA2D1", "R1:track:9"]
    assert problems.counts == {"short_track": 2}  # 111111 and 222222: one plot each
    shorts = {p.where: p.message for p in problems.of_kind("short_track")}
    assert shorts == {f"aircraft {a}": "1 plot(s), fewer than the 3 a reconstruction needs: "
                      "left out" for a in ("111111", "222222")}
    assert tracks["R1:track:9"].rows.tolist() == [12, 13, 14]
    tr = tracks["4CA2D1"]
    assert len(tr.table) == 10
    assert {s.id for s in tr.table.sensors} == {"R1", "R2", "ADSB"}
    np.testing.assert_array_equal(tr.table.t, [0, 1, 2, 3, 4, 5, 6, 8, 11, 12])
    np.testing.assert_array_equal(rows.t[tr.rows], tr.table.t)


def test_time_gaps_split_a_key():
    rows = radar_rows([0, 5, 10, 400, 405, 410, 415], mode_s=0x4CA2D1)
    tracks, problems = split(rows)
    assert {k: len(v.table) for k, v in tracks.items()} == {"4CA2D1": 3, "4CA2D1#2": 4}
    assert not problems
    tracks, _ = split(rows, gap_s=1000.0)
    assert list(tracks) == ["4CA2D1"]


def test_duplicate_times_of_one_sensor_are_reported_and_the_first_kept():
    rows = concat([radar_rows([0, 4, 8, 12], mode_s=0x4CA2D1),
                            radar_rows([4, 8], mode_s=0x4CA2D1, range_m=70_000.0),
                            radar_rows([4], mode_s=0x4CA2D1, sensor="R2")])
    tracks, problems = split(rows)
    assert problems.counts == {"duplicate_time": 2} and problems.dropped["duplicate_time"] == 2
    (p,) = problems.entries
    assert p.where == "row 5" and p.count == 2 and "aircraft 4CA2D1" in p.message
    assert "sensor 'R1' at t = 4.000 s" in p.message
    tr = tracks["4CA2D1"]
    assert tr.rows.tolist() == [0, 1, 6, 2, 3]
    assert np.all(tr.table.range_m < 65_000.0)


def test_rows_that_cannot_be_used_are_reported():
    rows = concat([
        radar_rows([0, 4, 8, 12], mode_s=0x4CA2D1, altitude_m=[9000.0, 9000.0, 1e5 - 1,
                                                                9000.0]),
        radar_rows([1], sensor="NOPE", mode_s=0x4CA2D1),
        radar_rows([2], sensor="ADSB", mode_s=0x4CA2D1),       # radar measurement, ADS-B
        radar_rows([3, 5]),                                      # no key at all
    ])
    tracks, problems = split(rows)
    assert problems.counts == {"unknown_sensor": 1, "wrong_measurement": 1,
                               "no_aircraft_key": 2, "bad_plot": 1}
    bad = problems.of_kind("bad_plot")[0]
    assert bad.where == "row 3" and "altitude_m" in bad.message
    assert problems.of_kind("unknown_sensor")[0].where == "row 5"
    assert problems.of_kind("wrong_measurement")[0].where == "row 6"
    assert tracks["4CA2D1"].rows.tolist() == [0, 1, 3]
    assert sum(problems.dropped.values()) + 3 == len(rows)


def test_every_track_shares_the_recording_plane():
    rows = concat([radar_rows([0, 4, 8], mode_s=1), adsb_rows([1, 2, 3], 2)])
    tracks, _ = split(rows)
    frames = {tr.table.frame for tr in tracks.values()}
    assert frames == {LocalFrame(46.0, 14.0)}  # the first radar's site
    assert recording_frame(SENSORS, rows) == LocalFrame(46.0, 14.0)
    with_ref = parse_sensors({"sensors": SENSOR_FILE, "reference": {"lat_deg": 46.2,
                                                                    "lon_deg": 14.5}})
    assert recording_frame(with_ref, rows) == LocalFrame(46.2, 14.5)
    adsb_only = parse_sensors([SENSOR_FILE[2]])
    frame = recording_frame(adsb_only, adsb_rows([1, 2], 2))  # the first position plot
    assert frame is not None and (frame.lat_deg, frame.lon_deg) == (46.3 + 1e-3, 14.4)


def test_sensor_file(tmp_path):
    path = tmp_path / "sensors.json"
    path.write_text(json.dumps(SENSOR_FILE))
    s = load_sensors(path)
    assert [x.id for x in s.sensors] == ["R1", "R2", "ADSB"]
    assert s.codes == {(25, 201): 0, (25, 202): 1, (25, 1): 2}
    r1 = s.by_code(25, 201)
    assert isinstance(r1, RadarSensor) and r1.site is not None and r1.site.height_m == 300.0
    assert r1.azimuth_error_rad == pytest.approx(np.deg2rad(0.24))
    assert isinstance(s.by_code(25, 1), PositionSensor) and s.by_code(1, 1) is None


@pytest.mark.parametrize(("change", "message"), [
    ({"sac": 300}, r"^sensors\[0\]\.sac must be an integer in \[0, 255\] \(300\)"),
    ({"sic": None, "sac": 1}, r"^sensors\[0\]\.sic must be an integer"),
    ({"range_error_m": "big"}, r"^sensors\[0\]\.range_error_m must be a finite number"),
    ({"azimuth_error_deg": -1}, r"^sensors\[0\]\.azimuth_error_deg must be positive"),
    ({"colour": "red"}, r"^sensors\[0\]\.colour is not a field of a radar sensor"),
    ({"lon_deg": None}, r"^sensors\[0\]\.lon_deg must be a finite number"),
    ({"kind": "sonar"}, r"^sensors\[0\]\.kind must be \"radar\" or \"position\""),
    ({"sic": 202}, r"^sensors\[1\]\.sic SAC 25 / SIC 202 repeats sensors\[0\]"),
    ({"range_offset_m": 1e4}, r"^sensors\[0\]\.range_offset_m must be within \+-5000"),
    ({"azimuth_offset_deg": "0.2"}, r"^sensors\[0\]\.azimuth_offset_deg must be a finite"),
    ({"time_offset_s": -61}, r"^sensors\[0\]\.time_offset_s must be within \+-60"),
])
def test_sensor_file_errors_are_named(change, message):
    first = {**SENSOR_FILE[0], **change}
    with pytest.raises(InputError, match=message):
        parse_sensors([first, *SENSOR_FILE[1:]])


def test_known_offsets_in_the_sensor_file():
    """A radar's range, azimuth and time offsets and a position sensor's time offset, default
    none; a position sensor has no range offset."""
    s = parse_sensors([{**SENSOR_FILE[0], "range_offset_m": 57.2, "azimuth_offset_deg": 0.05},
                       SENSOR_FILE[1], {**SENSOR_FILE[2], "time_offset_s": 1.0}])
    r, a, t = s.known_offsets()
    assert r.tolist() == [57.2, 0, 0] and a.tolist() == [0.05, 0, 0] and t.tolist() == [0, 0, 1]
    assert parse_sensors(SENSOR_FILE).known_offsets() is None
    with pytest.raises(InputError, match=r"^sensors\[2\]\.range_offset_m is not a field of a "
                       "position sensor"):
        parse_sensors([*SENSOR_FILE[:2], {**SENSOR_FILE[2], "range_offset_m": 5.0}])
    # taken off the plots as the tracks are built: range minus, azimuth minus, time minus
    n = 6
    rows = PlotRows.from_columns(
        n, t=np.arange(n, dtype=float), sensor=np.array(["R1", "ADSB"] * 3, dtype=object),
        range_m=np.where(np.arange(n) % 2, np.nan, 60_000.0),
        azimuth_deg=np.where(np.arange(n) % 2, np.nan, 10.0),
        lat_deg=np.where(np.arange(n) % 2, 46.5, np.nan),
        lon_deg=np.where(np.arange(n) % 2, 14.5, np.nan), altitude_m=np.full(n, 9_000.0),
        mode_s=np.full(n, 0xABCDEF))
    (track,) = split_aircraft(rows, s)
    tab = track.table
    radar = tab.sensor == 0
    assert tab.range_m[radar].tolist() == [60_000.0 - 57.2] * 3
    np.testing.assert_allclose(np.rad2deg(tab.azimuth_rad[radar]), 9.95)
    assert tab.t[radar].tolist() == [0.0, 2.0, 4.0]
    assert tab.t[~radar].tolist() == [0.0, 2.0, 4.0]  # ADS-B 1 s late: 1, 3, 5 -> 0, 2, 4


def test_sensor_file_json_errors():
    with pytest.raises(InputError, match="line 1 column 2"):
        parse_sensors("[x]")
    with pytest.raises(InputError, match="NaN"):
        parse_sensors('[{"id": "A", "kind": "position", "position_sigma_m": NaN}]')
    with pytest.raises(InputError, match=r"^sensors\[1\]\.id 'R1' repeats"):
        parse_sensors([SENSOR_FILE[0], {**SENSOR_FILE[1], "id": "R1"}])
    # a key twice in one object: json keeps the last, the file's reader refuses it (the
    # service does in requests; a fuzz helper found the sensor file kept the second)
    text = json.dumps(SENSOR_FILE)
    twice = text.replace('"range_error_m": 150.0', '"range_error_m": 150.0, "range_error_m": 5',
                         1)
    with pytest.raises(InputError, match=r"^sensors\[0\]\.range_error_m is given twice"):
        parse_sensors(twice)
    with pytest.raises(InputError, match=r"^reference\.lat_deg is given twice"):
        parse_sensors('{"reference": {"lat_deg": 1, "lat_deg": 2, "lon_deg": 3}, "sensors": '
                      + text + "}")
    assert parse_sensors(text).sensors[0].range_error_m == 150.0


PLOTS = st.lists(st.tuples(
    st.integers(0, 120),                                  # time (s)
    st.sampled_from(["R1", "R2", "ADSB", "NOPE"]),        # sensor
    st.sampled_from([-1, 0xA, 0xB]),                      # Mode S
    st.sampled_from([-1, 1, 2]),                          # track number
    st.booleans()),                                       # measurement fits the sensor
    min_size=1, max_size=80)


def random_rows(plots) -> PlotRows:
    n = len(plots)
    t = np.array([p[0] for p in plots], dtype=float)
    sensor = np.array([p[1] for p in plots], dtype=object)
    radar_like = np.array([(p[1] != "ADSB") == p[4] for p in plots])
    return PlotRows.from_columns(
        n, t=t, sensor=sensor, mode_s=[p[2] for p in plots], track_number=[p[3] for p in plots],
        range_m=np.where(radar_like, 50_000.0 + 100 * t, np.nan),
        azimuth_deg=np.where(radar_like, 30.0, np.nan),
        lat_deg=np.where(radar_like, np.nan, 46.3 + 1e-3 * t),
        lon_deg=np.where(radar_like, np.nan, 14.4))


@pytest.mark.parametrize("ground", [False, True])
def test_streaming_split_gives_the_same_tracks(ground):
    """split_stream over random recordings in chunks, arriving out of time order by less than
    disorder_s (5 s), gives the tracks, keys (gap pieces numbered alike), rows and problems of
    split_aircraft on the whole, while closing tracks on the way (gap_s 8 s). Random cases of
    Mode S addresses lent by sensor tracks, conflicting addresses, gaps and duplicates; with
    ``ground``, reports saying on the ground, airborne or nothing at random."""
    rng = np.random.default_rng(0)  # a seed whose cases include out-of-order pieces
    says = np.random.default_rng(1)
    closed_early = 0
    for _ in range(150):
        n = int(rng.integers(5, 120))
        rows = random_rows([(int(rng.integers(0, 121)),
                             str(rng.choice(["R1", "R2", "ADSB", "NOPE"])),
                             int(rng.choice([-1, 0xA, 0xB])), int(rng.choice([-1, 1, 2])),
                             bool(rng.random() < 0.9)) for _ in range(n)])
        if ground:
            rows = dataclasses.replace(rows, on_ground=says.choice([-1, -1, 0, 1], n).astype(
                np.int8))
        rows = rows.take(np.argsort(rows.t + rng.uniform(0.0, 5.0, n), kind="stable"))
        size = int(rng.integers(1, 12))
        closed_early += streamed_as_whole(rows, size, gap_s=8.0)[0]
    assert closed_early > 100  # tracks did come out before the end of their recording


def streamed_as_whole(rows: PlotRows, size: int, gap_s: float, case: object = None
                      ) -> tuple[int, Problems]:
    """Assert that split_stream over ``rows`` in chunks of ``size`` (disorder_s 5 s) gives
    split_aircraft's tracks, keys, rows and problems on the whole; the number of tracks that
    came out before the last chunk was read, and the problems."""
    n = len(rows)
    chunks = [rows.take(np.arange(a, min(a + size, n))) for a in range(0, n, size)]
    whole_p, stream_p = Problems(), Problems()
    whole = {tr.key: tr.rows.tolist()
             for tr in split_aircraft(rows, SENSORS, gap_s=gap_s, problems=whole_p)}
    consumed: list[int] = []
    stream, early = {}, 0
    fed = (consumed.append(k) or c for k, c in enumerate(chunks))
    for tr in split_stream(fed, SENSORS, gap_s=gap_s, disorder_s=5.0, problems=stream_p,
                           reference=recording_frame(SENSORS, rows)):
        stream[tr.key] = tr.rows.tolist()
        early += len(consumed) < len(chunks)
    assert stream == whole, case
    assert (stream_p.counts, stream_p.dropped) == (whole_p.counts, whole_p.dropped), case
    return early, whole_p


def test_streaming_split_yields_an_aircraft_once_it_has_landed():
    """Memory holds the aircraft in the air: a track comes out as soon as the recording is
    gap_s + disorder_s past its last plot, long before the recording ends."""
    early = radar_rows(np.arange(0, 100, 4), mode_s=0xA)
    late = [radar_rows(np.arange(t0, t0 + 100, 4), mode_s=0xB) for t0 in range(100, 2000, 100)]
    consumed = []

    def chunks():
        for k, c in enumerate([early, *late]):
            consumed.append(k)
            yield c

    stream = split_stream(chunks(), SENSORS, gap_s=300.0, disorder_s=60.0)
    first = next(stream)
    assert first.key == "00000A" and first.rows.tolist() == list(range(25))
    # closed once the recording passed 96 + 300 + 60 s: by the 5th chunk (t 400-496)
    assert len(consumed) == 5
    rest = list(stream)
    assert [tr.key for tr in rest] == ["00000B"] and len(rest[0].table) == 19 * 25


@settings(max_examples=60, deadline=None)
@given(PLOTS)
def test_every_row_is_in_one_track_or_counted(plots):
    """Nothing is dropped silently: each row lands in exactly one track, or is counted in the
    problems' dropped plots."""
    rows = random_rows(plots)
    n = len(rows)
    problems = Problems()
    tracks = list(split_aircraft(rows, SENSORS, problems=problems))
    used = np.concatenate([tr.rows for tr in tracks]) if tracks else np.array([], int)
    assert len(set(used.tolist())) == used.size  # no row twice
    assert used.size + sum(problems.dropped.values()) == n
    for tr in tracks:
        assert len(tr.table) == tr.rows.size >= 3
        np.testing.assert_array_equal(tr.table.t, rows.t[tr.rows])


def test_streamed_tracks_share_one_plane_set_by_the_first_position():
    """ADS-B only, the first chunk without a position: the plane is the first position plot
    of the recording for every track."""
    adsb_only = parse_sensors([SENSOR_FILE[2]])
    noise = radar_rows([0, 1, 2], sensor="NOPE", mode_s=0xC)  # no position, unknown sensor
    a = adsb_rows(np.arange(0, 40, 2), 0xA)
    b = dataclasses.replace(adsb_rows(np.arange(10, 60, 2), 0xB),
                            lat_deg=np.full(25, 47.0))
    tracks = list(split_stream([noise, a, b], adsb_only, gap_s=30.0, disorder_s=5.0))
    assert sorted(tr.key for tr in tracks) == ["00000A", "00000B"]
    assert {tr.table.frame for tr in tracks} == {LocalFrame(46.3, 14.4)}


def assert_streamed_alike(rows: PlotRows, tracks: dict, size: int) -> None:
    """split_stream over ``rows`` in chunks of ``size`` gives the tracks of the whole."""
    streamed = {tr.key: tr for tr in split_stream(
        [rows.take(np.arange(k, min(k + size, len(rows)))) for k in range(0, len(rows), size)],
        SENSORS)}
    assert sorted(streamed) == sorted(tracks)
    for key, tr in tracks.items():
        np.testing.assert_array_equal(streamed[key].rows, tr.rows)


def test_another_aircraft_under_a_key_is_told_apart():
    """A key's plots out of reach of each other at the fastest speed are aircraft apart (a
    tester's recordings: both came out as one track, 12-116 km RMS off): two aircraft
    squawking 7000 on one radar (no track number; their plots interleaved scan by scan, at
    azimuths 45 and 120 deg); R1's track 30 used again 60 s after its first aircraft's last
    plot by another 80 km away; R1's track 12 of Mode S aircraft 4CA2D1 going on to an
    aircraft without Mode S 60 km away (its address lent to those plots). The others are
    ``KEY~2`` (the larger piece, or the one with the address, keeps the key), reported; the
    same streamed."""
    scans = np.arange(0.0, 400.0, 4.8)
    rows = concat([
        radar_rows(scans, mode_3a=0o7000), radar_rows(scans + 1.0, mode_3a=0o7000,
                                                       azimuth_deg=120.0),
        radar_rows(scans[scans < 200], track_number=30, range_m=150_000.0, azimuth_deg=300.0),
        radar_rows(scans[(scans > 260) & (scans < 380)], track_number=30, range_m=70_000.0,
                   azimuth_deg=300.0),
        radar_rows(scans[scans < 250] + 2.0, mode_s=0x4CA2D1, track_number=12,
                   azimuth_deg=200.0),
        adsb_rows(np.arange(0.0, 400.0, 2.0), 0x4CA2D1),
        radar_rows(scans[scans > 310] + 2.0, track_number=12, mode_3a=0o7000,
                   range_m=120_000.0, azimuth_deg=200.0)])
    tracks, problems = split(rows)
    assert sorted(tracks) == ["4CA2D1", "4CA2D1~2", "R1:mode3a:7000", "R1:mode3a:7000~2",
                              "R1:track:30", "R1:track:30~2"]
    for key in ("R1:mode3a:7000", "R1:mode3a:7000~2"):
        az = np.rad2deg(tracks[key].table.azimuth_rad)
        assert np.ptp(az) < 1e-9 and len(tracks[key].table) == scans.size
    assert np.rad2deg(tracks["R1:mode3a:7000"].table.azimuth_rad[0]) == pytest.approx(45.0)
    later = tracks["R1:track:30~2"].table  # the smaller piece (25 plots against 42)
    assert len(tracks["R1:track:30"].table) == np.sum(scans < 200) and later.t.min() > 260
    own = tracks["4CA2D1"]
    assert (rows.mode_s[own.rows] == 0x4CA2D1).all()  # every plot with the address
    lent = tracks["4CA2D1~2"]
    assert len(lent.table) == np.sum(scans > 310) and (rows.mode_s[lent.rows] < 0).all()
    assert problems.counts["aircraft_apart"] == 3
    (entry,) = [e for e in problems.of_kind("aircraft_apart") if "4CA2D1" in e.where]
    assert "another aircraft under the same key" in entry.message and "4CA2D1~2" in entry.message
    assert_streamed_alike(rows, tracks, 37)


def test_a_few_wild_plots_stay_with_their_aircraft():
    """Fewer than 10 plots out of reach (a radar's wild plots) are no other aircraft: they stay
    in the track (the reconstruction gives them no weight), and a key whose plots all carry
    the address is not looked at."""
    scans = np.arange(0.0, 300.0, 4.8)
    wild = np.isin(np.arange(scans.size), [5, 17, 18, 40])
    far = np.where(wild, 200_000.0, 60_000.0)
    rows = concat([radar_rows(scans, track_number=5, range_m=far - 100.0 * scans),
                   radar_rows(scans + 1.0, mode_s=0xABCDEF, range_m=far - 100.0 * scans,
                              azimuth_deg=90.0)])
    tracks, problems = split(rows)
    assert sorted(tracks) == ["ABCDEF", "R1:track:5"] and "aircraft_apart" not in problems.counts
    assert all(len(tr.table) == scans.size for tr in tracks.values())


def test_a_landing_ends_the_track_and_a_take_off_starts_another():
    """An aircraft lands at 200 s, taxis, takes off at 400 s (within the 300-s gap split):
    its ADS-B says on the ground (GBS) from 200 to 400 s, its radar says nothing. The reports
    on the ground, the radar's between them too, are left out and counted (``on_ground``);
    the flight before and the one after are two tracks (one track flew an invented 12-km loop
    through the ground time in a tester's recording); the same streamed."""
    scans, ticks = np.arange(0.0, 600.0, 4.8), np.arange(0.0, 600.0, 1.0)
    radar = radar_rows(scans, mode_s=0x4CA2D1)
    adsb = adsb_rows(ticks, 0x4CA2D1)
    adsb = dataclasses.replace(adsb, on_ground=np.where((ticks >= 200) & (ticks < 400), 1, 0
                                                        ).astype(np.int8))
    both = PlotRows.concat([radar, adsb])
    rows = concat([both.take(np.argsort(both.t, kind="stable"))])  # in time, as recorded
    tracks, problems = split(rows)
    assert sorted(tracks) == ["4CA2D1", "4CA2D1#3"]
    first, second = tracks["4CA2D1"].table, tracks["4CA2D1#3"].table
    assert first.t.max() < 200.0 and second.t.min() >= 400.0
    ground = np.sum((ticks >= 200) & (ticks < 400)) + np.sum((scans > 199) & (scans < 400))
    assert problems.counts == {"on_ground": ground} and problems.dropped["on_ground"] == ground
    assert len(first) + len(second) + ground == len(rows)
    assert_streamed_alike(rows, tracks, 50)


def test_a_radars_reflections_are_no_other_aircraft():
    """A Mode A/C aircraft's track with a radar's reflections in it (one plot in six, 20 km
    further along the ray, moving with it): the reflections are out of reach of the aircraft
    and of each other's reach, 20 of them, but seen on a sixth of the scans, no aircraft: they
    stay in the track (the reconstruction gives them no weight); as ghost aircraft they came
    out 13 km off in a tester's recording."""
    scans = np.arange(0.0, 600.0, 4.8)
    ghost = np.arange(scans.size) % 6 == 3
    rows = concat([radar_rows(scans, track_number=31, range_m=np.where(ghost, 80_000.0,
                                                                       60_000.0))])
    tracks, problems = split(rows)
    assert list(tracks) == ["R1:track:31"] and len(tracks["R1:track:31"].table) == scans.size
    assert "aircraft_apart" not in problems.counts


def test_a_key_told_apart_says_its_aircrafts_problems_once():
    """A key parted is built again per aircraft: what its building said of the whole key (an
    implausible geometric height: 2,380 m from the flight level) was counted once per part
    (a reviewer's)."""
    scans = np.arange(0.0, 400.0, 4.8)
    t = np.arange(0.0, 400.0, 2.0)
    adsb = PlotRows.from_columns(t.size, t=t, sensor=np.full(t.size, "ADSB", dtype=object),
                                 lat_deg=46.3 + 1e-3 * t, lon_deg=np.full(t.size, 14.4),
                                 mode_s=np.full(t.size, 0x4CA2D1),
                                 altitude_m=np.full(t.size, 10_000.0),
                                 flight_level=np.full(t.size, 250.0))
    rows = concat([adsb, radar_rows(scans[scans < 250] + 2.0, mode_s=0x4CA2D1, track_number=12,
                                    azimuth_deg=200.0, altitude_m=250 * 30.48),
                   radar_rows(scans[scans > 310] + 2.0, track_number=12, range_m=120_000.0,
                              azimuth_deg=200.0)])
    tracks, problems = split(rows)
    assert sorted(tracks) == ["4CA2D1", "4CA2D1~2"]
    assert problems.counts["implausible_altitude"] == 1


@pytest.mark.parametrize("angle", [90.0, 30.0])
def test_two_aircraft_crossing_under_one_code_keep_their_plots(angle):
    """Two aircraft squawking 7000 on one radar (no track number; 150 m/s, noise 40 m and 0.05
    deg) cross 60 km out: each comes out with its own plots. Judged by each piece's last plot
    alone they swapped halves at 90 deg (a reviewer's); by its course over the last 30 s,
    none (at 10 deg they may still swap: a tracker's ambiguity)."""
    from solver.frames import slant_and_azimuth

    rng = np.random.default_rng(4)
    site, frame = (46.0, 14.0, 300.0), LocalFrame(46.0, 14.0)

    def radar(t, x, z):
        lat, lon = frame.to_geodetic(x, z)
        r, az, _ = slant_and_azimuth(site, lat, lon, np.full(t.size, 3000.0))
        return radar_rows(t, mode_3a=0o7000, range_m=r + rng.normal(0, 40, t.size) - 100.0 * t,
                          azimuth_deg=np.rad2deg(az) + rng.normal(0, 0.05, t.size),
                          altitude_m=3000.0)

    t = np.arange(0.0, 600.0, 4.8)
    a = np.deg2rad(angle)
    one = radar(t, np.full(t.size, 60e3), 150.0 * (t - 300.0))
    other = radar(t + 0.3, 60e3 + 150.0 * (t + 0.3 - 300.0) * np.sin(a),
                  150.0 * (t + 0.3 - 300.0) * np.cos(a))
    rows = concat([one, other])
    tracks, _ = split(rows)
    assert sorted(tracks) == ["R1:mode3a:7000", "R1:mode3a:7000~2"]
    for tr in tracks.values():
        mine = tr.rows < t.size  # the first aircraft's rows come first
        assert mine.all() or not mine.any(), (angle, mine.sum(), (~mine).sum())


def _said(t: np.ndarray, ground: np.ndarray) -> np.ndarray:
    return np.where(ground, 1, 0).astype(np.int8)


@pytest.mark.parametrize("case", ["unsaid_after_take_off", "surface_adsb_then_radar",
                                  "sensors_disagree", "one_spurious_bit"])
def test_what_the_reports_say_of_the_ground_is_voted(case):
    """A reviewer's cases, each one flight: ADS-B saying ground for 200 s and then nothing
    (CAT021 encoders leave the ground bit out in the air: the whole flight was left out);
    ADS-B saying ground for 200 s and stopping, a radar without flight status seeing the
    aircraft on (all 450 plots left out); a radar's status saying ground at every plot
    against 1-Hz ADS-B saying airborne (250 pieces); one ground bit mid-flight (two tracks).
    The reports within 15 s of a row vote (3 saying ground at least, more than say airborne);
    the same streamed."""
    ticks, scans = np.arange(0.0, 1200.0, 1.0), np.arange(0.5, 1200.0, 4.8)
    adsb = adsb_rows(ticks, 0x4CA2D1)
    radar = radar_rows(scans, mode_s=0x4CA2D1)
    n_ground = 0
    if case == "unsaid_after_take_off":
        said = np.where(ticks < 200, 1, -1).astype(np.int8)
        # on the ground while 3 ground reports lie within 15 s: to 212 s
        parts, n_ground = [dataclasses.replace(adsb, on_ground=said)], 213
    elif case == "surface_adsb_then_radar":
        adsb = adsb.take(ticks < 200)
        parts = [dataclasses.replace(adsb, on_ground=np.ones(len(adsb), np.int8)), radar]
        n_ground = len(adsb) + int(np.sum(scans <= 212.0))
    elif case == "sensors_disagree":
        parts = [dataclasses.replace(adsb, on_ground=np.zeros(len(adsb), np.int8)),
                 dataclasses.replace(radar, on_ground=np.ones(len(radar), np.int8))]
    else:
        parts = [dataclasses.replace(adsb, on_ground=_said(ticks, ticks == 600))]
    both = PlotRows.concat(parts)
    rows = concat([both.take(np.argsort(both.t, kind="stable"))])
    tracks, problems = split(rows)
    assert list(tracks) == ["4CA2D1#2" if n_ground else "4CA2D1"], (case, list(tracks))
    assert problems.counts.get("on_ground", 0) == n_ground
    assert len(next(iter(tracks.values())).table) == len(rows) - n_ground
    assert_streamed_alike(rows, tracks, 50)
