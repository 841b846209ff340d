"""Mode C pressure altitudes made geometric by the aircraft's ADS-B (solver.io.altitudes): the
offset from reports that carry both, or from a geometric height near a pressure altitude in
time; followed as it drifts; nothing moved without pairs; into the tracks the reader builds."""

from __future__ import annotations

import numpy as np
import pytest

from solver.io.altitudes import MIN_PAIRS, geometric_altitudes
from solver.io.problems import Problems
from solver.io.sensors_file import parse_sensors
from solver.io.split import split_aircraft
from solver.io.tables import FL_M, PlotRows

QUARTER_FL_M = FL_M / 4  # Mode S and CAT021 I145 report flight levels in 1/4 FL (25 ft)


def flight(offset_m, n_adsb: int = 300, climb_m_s: float = 0.0, radar_every: int = 5):
    """A track of ADS-B reports every second (geometric height, and the barometric flight
    level ``offset_m`` lower, quantised to 25 ft) and radar plots between them with the Mode C
    flight level; returns times, altitudes (radar rows: the pressure altitude), flight
    levels, which rows are ADS-B and the true geometric heights."""
    t_adsb = np.arange(n_adsb, dtype=float)
    t_radar = np.arange(0.4, n_adsb, radar_every, dtype=float)
    t = np.concatenate([t_adsb, t_radar])
    order = np.argsort(t, kind="stable")
    t = t[order]
    adsb = np.concatenate([np.ones(t_adsb.size, bool), np.zeros(t_radar.size, bool)])[order]
    geo = 10_000.0 + climb_m_s * t
    off = np.broadcast_to(np.asarray(offset_m(t) if callable(offset_m) else offset_m), t.shape)
    fl = np.round((geo - off) / QUARTER_FL_M) * QUARTER_FL_M / FL_M
    alt = np.where(adsb, geo, fl * FL_M)
    return t, alt, fl, adsb, geo


SENSORS = parse_sensors([
    {"id": "R1", "kind": "radar", "lat_deg": 46.0, "lon_deg": 14.0, "height_m": 300.0,
     "range_error_m": 150.0, "azimuth_error_deg": 0.24},
    {"id": "ADSB", "kind": "position", "position_sigma_m": 30.0}])


def one_aircraft(t, alt, fl, adsb) -> PlotRows:
    """One aircraft's rows (Mode S 4CA2D1): R1's plots and its ADS-B reports."""
    n = t.size
    return PlotRows.from_columns(
        n, t=t, sensor=np.where(adsb, "ADSB", "R1").astype(object),
        range_m=np.where(adsb, np.nan, 60_000.0), azimuth_deg=np.where(adsb, np.nan, 10.0),
        lat_deg=np.where(adsb, 46.5, np.nan), lon_deg=np.where(adsb, 14.1, np.nan),
        altitude_m=alt, flight_level=fl, mode_s=np.full(n, 0x4CA2D1))


def test_reports_with_both_heights_give_the_offset():
    """ADS-B with geometric height and flight level: every Mode C altitude moved by the
    offset, to the geometric height within the 25-ft quantisation (7.6 m); the ADS-B heights
    untouched."""
    t, alt, fl, adsb, geo = flight(250.0)
    got = geometric_altitudes(t, alt, fl, adsb)
    assert got.corrected == np.count_nonzero(~adsb) and got.pairs == np.count_nonzero(adsb)
    assert got.median_m == pytest.approx(250.0, abs=QUARTER_FL_M)
    assert np.abs(got.altitude_m - geo)[~adsb].max() < QUARTER_FL_M
    np.testing.assert_array_equal(got.altitude_m[adsb], alt[adsb])
    assert np.abs(alt - geo)[~adsb].min() > 240.0  # what they were


def test_a_geometric_height_pairs_with_a_mode_c_altitude_near_in_time():
    """ADS-B with its geometric height only (no I145): each radar plot's Mode C pairs with the
    heights interpolated around it; climbing at 15 m/s, the offset is still found."""
    t, alt, fl, adsb, geo = flight(-180.0, climb_m_s=15.0)
    fl = np.where(adsb, np.nan, fl)
    got = geometric_altitudes(t, alt, fl, adsb)
    assert got.pairs == np.count_nonzero(~adsb) and got.corrected == got.pairs
    assert np.abs(got.altitude_m - geo)[~adsb].max() < QUARTER_FL_M


def test_a_drifting_offset_is_followed():
    """The offset grows from 100 to 300 m over 10 minutes (a climb through warm air): the
    running median follows it (within 12 m everywhere), where one offset would be 100 m off
    at the ends."""
    t, alt, fl, adsb, geo = flight(lambda t: 100.0 + t / 3.0, n_adsb=600)
    got = geometric_altitudes(t, alt, fl, adsb)
    err = np.abs(got.altitude_m - geo)[~adsb]
    assert err.max() < 12.0, err.max()
    single = alt[~adsb] + got.median_m - geo[~adsb]
    assert np.abs(single).max() > 90.0


def test_nothing_is_moved_without_pairs():
    """No ADS-B, ADS-B with its flight level only, fewer than MIN_PAIRS pairs, or radar rows
    whose altitude is not their flight level's (a 3-D radar's height): left as they are."""
    t, alt, fl, adsb, _ = flight(250.0)
    radar = ~adsb
    alone = geometric_altitudes(t[radar], alt[radar], fl[radar], adsb[radar])  # no ADS-B
    assert alone.corrected == 0 and alone.median_m is None
    np.testing.assert_array_equal(alone.altitude_m, alt[radar])
    fl_only = np.where(adsb, fl * FL_M, alt)  # ADS-B with its flight level only
    got = geometric_altitudes(t, fl_only, fl, adsb)
    assert got.corrected == 0 and got.median_m is None
    np.testing.assert_array_equal(got.altitude_m, fl_only)
    few = np.flatnonzero(adsb)[MIN_PAIRS - 1:]
    keep = np.setdiff1d(np.arange(t.size), few)
    got = geometric_altitudes(t[keep], alt[keep], fl[keep], adsb[keep])
    assert got.pairs == MIN_PAIRS - 1 and got.corrected == 0
    np.testing.assert_array_equal(got.altitude_m, alt[keep])
    own = np.where(radar, alt + 500.0, alt)  # radar rows with a height of their own
    got = geometric_altitudes(t, own, fl, adsb)
    assert got.corrected == 0
    np.testing.assert_array_equal(got.altitude_m, own)


def test_the_reader_builds_tracks_with_geometric_heights():
    """:func:`split_aircraft`: one aircraft's radar rows reach the table at their geometric
    height, and the track says by how much they were moved."""
    t, alt, fl, adsb, geo = flight(250.0)
    rows = one_aircraft(t, alt, fl, adsb)
    (track,) = split_aircraft(rows, SENSORS)
    assert track.pressure_offset_m == pytest.approx(250.0, abs=QUARTER_FL_M)
    h = track.table.altitude_m[track.table.radar_rows()]
    assert np.abs(h - geo[~adsb]).max() < QUARTER_FL_M
    (plain,) = split_aircraft(rows.take(~adsb), SENSORS)
    assert plain.pressure_offset_m is None


def test_a_bad_geometric_height_is_not_used_and_is_reported():
    """ADS-B reporting a geometric height of 0 m at 9-10 km beside a right flight level: the
    offset it gives (-10 km) is no atmosphere's; every Mode C of the aircraft was moved to 0 m
    (a review helper). Pairs more than MAX_OFFSET_M apart are not used and counted: nothing
    moved, and the reader reports it; a few bad ones among good ones are outvoted."""
    t, alt, fl, adsb, geo = flight(200.0)
    bad = np.where(adsb, 0.0, alt)
    got = geometric_altitudes(t, bad, fl, adsb)
    assert got.corrected == 0 and got.rejected == np.count_nonzero(adsb)
    np.testing.assert_array_equal(got.altitude_m, bad)
    some = alt.copy()
    some[np.flatnonzero(adsb)[::10]] = 0.0  # one report in ten
    got = geometric_altitudes(t, some, fl, adsb)
    assert got.rejected == np.flatnonzero(adsb)[::10].size
    assert np.abs(got.altitude_m - geo)[~adsb].max() < QUARTER_FL_M
    problems = Problems()
    (track,) = split_aircraft(one_aircraft(t, bad, fl, adsb), SENSORS, problems=problems)
    assert track.pressure_offset_m is None
    assert problems.counts == {"implausible_altitude": 1}
    assert problems.entries[0].where == "aircraft 4CA2D1"
