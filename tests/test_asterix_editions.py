"""ASTERIX of other editions (solver.io.asterix ``editions=``, the command line's ``--edition``,
run.json): recordings ENCODED here with libasterix, CAT021 reports in 0.26 (older ADS-B ground
stations: time of day I030, position I130 at 180/2^25 deg, I131 the signal amplitude) and the
same reports in 2.7, beside CAT048 1.32 of a radar; CAT048 1.27 against 1.32. Read as their
edition they give the same plots; read as another, the decoder reports it and keeps no
garbage."""

from __future__ import annotations

import json

import asterix.generated as ast
import numpy as np
import pytest
from test_io_asterix import (
    C048,
    CODES,
    FLIGHTS,
    SENSOR_FILE,
    SENSORS,
    SITES,
    cat048,
)

from solver.cli import main
from solver.frames import slant_and_azimuth
from solver.inputs import InputError
from solver.io.asterix import (
    DEFAULT_EDITIONS,
    EDITIONS,
    decode_blocks,
    edition_choices,
    editions_named,
    parse_edition,
    read_recording,
)
from solver.run_settings import RUN_FILE, RunSettings, keep, stored

C021_026, C021_027 = ast.Cat_021_0_26, ast.Cat_021_2_7
LSB_026_DEG = 180.0 / 2**25  # I021/130 of 0.24-0.26 (2.7's I131: 180/2^30, a divisor of it)
GEO_FT = 250.0  # the geometric height above the flight level's pressure altitude (6.25-ft grid)


def _i040(edition: str, rab: int = 0, gbs: int = 0) -> tuple:
    if edition == "0.26":  # one octet pair: DCR GBS SIM TST RAB SAA SPI spare | ATP ARC spare
        return (("DCR", 0), ("GBS", gbs), ("SIM", 0), ("TST", 0), ("RAB", rab), ("SAA", 0),
                ("SPI", 0), 0, ("ATP", 1), ("ARC", 1), 0)
    return ((("ATP", 0), ("ARC", 0), ("RC", 0), ("RAB", rab), None),
            (("DCR", 0), ("GBS", gbs), ("SIM", 0), ("TST", 0), ("SAA", 0), ("CL", 0), None))


def adsb(edition: str, tod: float, lat: float, lon: float, fl: float, address: int,
         mode_3a: str, rab: int = 0) -> object:
    """A CAT021 report of the ADS-B ground station in ``edition`` (0.26 or 2.7): the same
    time, position (on 0.26's grid), flight level, geometric height, address, Mode 3/A."""
    sac, sic = CODES["ADSB"]
    items: dict = {"010": (("SAC", sac), ("SIC", sic)), "040": _i040(edition, rab),
                   "145": (fl, "FL"), "140": (fl * 100.0 + GEO_FT, "ft"), "080": address}
    pos = (("LAT", (lat, "°")), ("LON", (lon, "°")))
    if edition == "0.26":
        items |= {"030": (tod, "s"), "130": pos, "131": 200,  # I131: signal amplitude
                  "070": (0, 0, 0, 0, ("MODE3A", mode_3a))}
        return C021_026.cv_record.create(items)
    items |= {"071": (tod, "s"), "131": pos, "070": (0, ("MODE3A", mode_3a))}
    return C021_027.cv_record.create(items)


def recording(edition: str, duration: float = 80.0, tod0: float = 36_000.0) -> bytes:
    """ADS-B reports of both flights every 2 s (CAT021 in ``edition``, a block each) and radar
    R1's scans every 4 s (CAT048 1.32, the same in every recording)."""
    cat = {"0.26": C021_026, "2.7": C021_027}[edition]
    blocks = []
    for k, t in enumerate(np.arange(0.0, duration, 2.0)):
        tod = tod0 + float(t)
        for f in FLIGHTS:
            lat, lon, h = (float(v[0]) for v in f.at(np.array([t])))
            lat, lon = (round(v / LSB_026_DEG) * LSB_026_DEG for v in (lat, lon))
            blocks.append(cat.create([adsb(edition, tod, lat, lon, f.fl, f.address,
                                           f.mode_3a)]).unparse().to_bytes())
            if k % 2 == 0:  # the radar sees the aircraft 0.5 s later
                lat, lon, h = (float(v[0]) for v in f.at(np.array([t + 0.5])))
                r, az, _ = slant_and_azimuth(SITES["R1"], lat, lon, h)
                blocks.append(C048.create([cat048(
                    "R1", tod + 0.5, float(r) / 1852.0, float(np.rad2deg(az)), f.fl,
                    f.address, f.track_numbers[0], f.mode_3a)]).unparse().to_bytes())
    return b"".join(blocks)


PLOT_COLUMNS = ("time_of_day_s", "range_m", "azimuth_deg", "lat_deg", "lon_deg", "altitude_m",
                "flight_level", "mode_s", "mode_3a", "track_number", "on_ground")


def assert_same_plots(a, b) -> None:
    assert len(a) == len(b) > 0
    assert a.sensor.tolist() == b.sensor.tolist()
    for name in PLOT_COLUMNS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


# ---------------------------------------------------------------------------------- decoding


def test_cat021_0_26_read_as_0_26_gives_the_plots_of_the_same_reports_in_2_7():
    """CAT021 0.26 reports decoded with ``editions={21: Cat_021_0_26}`` give the plots the same
    reports in 2.7 give by default: times (I030 against I071), positions (I130 against I131,
    on 0.26's grid), geometric heights and flight levels, addresses, Mode 3/A (0.26's I070 has
    V/G/L flags), on-ground bits; 0.26's I131 (signal amplitude) is no position. A field
    monitor's report (RAB) is left out in both."""
    old, new = recording("0.26"), recording("2.7")
    monitor = {e: c.create([adsb(e, 36_001.0, 46.0, 14.0, 0.0, 0xABCDEF, "7777", rab=1)])
               .unparse().to_bytes() for e, c in (("0.26", C021_026), ("2.7", C021_027))}
    a = read_recording(old + monitor["0.26"], SENSORS, editions={21: C021_026})
    b = read_recording(new + monitor["2.7"], SENSORS)
    assert a.problems.counts == b.problems.counts == {"not_aircraft": 1}
    assert_same_plots(a.rows, b.rows)
    adsb_rows = a.rows.sensor == "ADSB"
    assert adsb_rows.sum() == 2 * 40 and a.blocks == {21: 81, 48: 40}
    fl = a.rows.flight_level[adsb_rows]
    np.testing.assert_array_equal(a.rows.altitude_m[adsb_rows], (fl * 100 + GEO_FT) * 0.3048)
    assert set(a.rows.mode_s[adsb_rows].tolist()) == {f.address for f in FLIGHTS}
    assert set(a.rows.mode_3a[adsb_rows].tolist()) == {int(f.mode_3a, 8) for f in FLIGHTS}
    # the same through the names the command line and jobs give
    named = read_recording(old, SENSORS, editions=editions_named({21: "0.26"}))
    assert_same_plots(named.rows, read_recording(new, SENSORS).rows)


@pytest.mark.parametrize("edition", ["0.23", "0.24", "0.25", "0.26"])
def test_every_0_2x_edition_reads_its_position_at_its_resolution(edition):
    """0.23's I130 is 24-bit (180/2^23 deg), 0.24-0.26's 32-bit (180/2^25): the LSB is
    libasterix's for the edition."""
    spec = EDITIONS[21][edition]
    lsb = 180.0 / 2**23 if edition == "0.23" else LSB_026_DEG
    lat, lon = 46.123456789, 14.987654321
    sac, sic = CODES["ADSB"]
    record = spec.cv_record.create({"010": (("SAC", sac), ("SIC", sic)), "030": (100.0, "s"),
                                    "130": (("LAT", (lat, "°")), ("LON", (lon, "°"))),
                                    "145": (350.0, "FL"), "080": 0x4CA2D1})
    rec = decode_blocks(spec.create([record]).unparse().to_bytes(), SENSORS,
                        editions={21: spec})
    assert not rec.problems, rec.problems.summary()
    assert abs(rec.rows.lat_deg[0] - lat) <= lsb / 2 and abs(rec.rows.lon_deg[0] - lon) <= lsb / 2
    assert rec.rows.time_of_day_s[0] == 100.0 and rec.rows.flight_level[0] == 350.0
    assert rec.rows.mode_s[0] == 0x4CA2D1


def test_another_editions_cat021_is_reported_and_no_garbage_plot_kept():
    """CAT021 0.26 read as 2.7 (the default): each record parsed as 2.7 gave a row with its
    time up to 10 h and its position up to 25,000 km off, beside a ``bad_record`` per block.
    Now the blocks' rows are left out with one ``other_edition`` problem naming the choices;
    the radar's plots are read. The other way (2.7 read as 0.26) alike. One damaged block
    among sound ones is damage, not another edition: its rows before the damage are kept."""
    old, new = recording("0.26"), recording("2.7")
    for data, editions, read_as in ((old, None, "2.7"), (new, {21: C021_026}, "0.26")):
        rec = read_recording(data, SENSORS, editions=editions)
        assert rec.problems.counts.get("other_edition") == 1, rec.problems.counts
        assert rec.problems.counts.get("bad_record", 0) >= 40
        (problem,) = rec.problems.of_kind("other_edition")
        assert f"80 of 80 CAT021 data blocks do not parse to their end as CAT021 {read_as}" \
            in problem.message
        assert "0.23, 0.24, 0.25, 0.26, 2.1" in problem.message and "--edition 21=" in \
            problem.message
        assert set(rec.rows.sensor.tolist()) == {"R1"}  # no ADS-B plot, garbage or not
        radar = read_recording(new, SENSORS).rows
        assert_same_plots(rec.rows, radar.take(np.flatnonzero(radar.sensor == "R1")))
    # damage: one 2.7 block of two records, the second cut short
    two = C021_027.create([adsb("2.7", 10.0 + k, 46.0, 14.0, 100.0, 0x4CA2D1, "1234")
                           for k in range(2)]).unparse().to_bytes()
    cut = bytes([21]) + len(two[:-4]).to_bytes(2, "big") + two[3:-4]
    rec = read_recording(new + cut, SENSORS)
    assert "other_edition" not in rec.problems.counts and rec.problems.counts["bad_record"] == 1
    assert len(rec.rows) == len(read_recording(new, SENSORS).rows) + 1


def test_cat048_1_27_and_1_32_read_each_other():
    """CAT048's UAP is the same from 1.27 to 1.32: 1.27 data read as 1.32 (the default) give
    their plots. libasterix's 1.27-1.31 take I090's FL unsigned (1.32: two's complement): a
    negative FL read through 1.27 (4095.75 FL silently before) is a ``bad_value``, no
    altitude. 1.32's I020 third octet (1.31 on) is no 1.27 record: reported, nothing kept."""
    c127 = EDITIONS[48]["1.27"]

    def rec(spec, k: int, fl: float, i020: tuple | None = None):
        items = {"010": (("SAC", 25), ("SIC", 201)), "140": (100.0 + k, "s"),
                 "040": (("RHO", (30.0, "NM")), ("THETA", (10.0, "°"))), "220": 0xABCDEF,
                 "090": (0, 0, ("FL", (fl, "FL")))}
        return spec.cv_record.create(items | ({"020": i020} if i020 else {}))

    old = b"".join(c127.create([rec(c127, k, fl)]).unparse().to_bytes()
                   for k, fl in enumerate((350.0, 0.0, 10.25)))
    a, b = (decode_blocks(old, SENSORS, editions=e) for e in ({48: c127}, None))
    assert not a.problems and not b.problems
    assert_same_plots(a.rows, b.rows)
    assert a.rows.flight_level.tolist() == [350.0, 0.0, 10.25]
    new = b"".join(C048.create([rec(C048, k, fl)]).unparse().to_bytes()
                   for k, fl in enumerate((350.0, -0.25, -4.5)))
    assert decode_blocks(new, SENSORS).rows.flight_level.tolist() == [350.0, -0.25, -4.5]
    through = decode_blocks(new, SENSORS, editions={48: c127})
    assert through.rows.flight_level[0] == 350.0 and np.isnan(through.rows.flight_level[1:]).all()
    assert np.isnan(through.rows.altitude_m[1:]).all()
    assert through.problems.counts == {"bad_value": 2}
    (first,) = through.problems.of_kind("bad_value")  # one per sensor, counted
    assert "reads 4095.75 FL through CAT048 1.27" in first.message
    i020 = ((("TYP", 2), ("SIM", 0), ("RDP", 0), ("SPI", 0), ("RAB", 0), None),
            (("TST", 0), ("ERR", 0), ("XPP", 0), ("ME", 0), ("MI", 0), ("FOEFRI", 0), None),
            (("ADSB", (("EP", 1), ("VAL", 1))), ("SCN", (("EP", 0), ("VAL", 0))),
             ("PAI", (("EP", 0), ("VAL", 0))), 0, None))
    data = b"".join(C048.create([rec(C048, k, 100.0, i020)]).unparse().to_bytes()
                    for k in range(4))
    assert len(decode_blocks(data, SENSORS).rows) == 4
    wrong = decode_blocks(data, SENSORS, editions={48: c127})
    assert len(wrong.rows) == 0 and wrong.problems.counts["bad_record"] == 4


def test_editions_are_named_and_checked_against_libasterix():
    assert parse_edition("21=0.26") == parse_edition("CAT021=0.26") == (21, "0.26")
    assert parse_edition(" 48 = 1.27 ") == (48, "1.27")
    assert list(EDITIONS[21]) == ["0.23", "0.24", "0.25", "0.26", "2.1", "2.2", "2.3", "2.4",
                                  "2.5", "2.6", "2.7"]
    assert list(EDITIONS[48]) == ["1.27", "1.28", "1.29", "1.30", "1.31", "1.32"]
    assert editions_named({}) == DEFAULT_EDITIONS
    assert editions_named({21: "0.26"})[21] is C021_026
    for text, says in (("21=0.27", "no CAT021 edition '0.27'"), ("62=1.19", "CAT062 is not "
                       "decoded"), ("21", "give CATEGORY=EDITION"), ("x=1", "give CATEGORY")):
        with pytest.raises(ValueError) as e:
            parse_edition(text)
        assert says in str(e.value) and edition_choices() in str(e.value)


def test_run_settings_keep_the_editions_and_a_rerun_with_others_is_refused(tmp_path):
    chosen = RunSettings(editions=((21, "0.26"), (48, "1.32")))
    assert chosen.editions == ((21, "0.26"),)  # the default edition named: the default run
    assert RunSettings(editions=((21, "2.7"),)) == RunSettings()
    assert chosen.asterix_editions()[21] is C021_026 and RunSettings().asterix_editions() is None
    keep(tmp_path, chosen)
    assert json.loads((tmp_path / RUN_FILE).read_text())["editions"] == {"21": "0.26"}
    assert stored(tmp_path) == chosen
    (tmp_path / "progress.jsonl").write_text(json.dumps({"aircraft": "A"}) + "\n")
    for other in (RunSettings(), RunSettings(editions=((21, "0.25"),))):
        with pytest.raises(InputError) as e:
            keep(tmp_path, other)
        assert "holds a run made with editions {'21': '0.26'}" in str(e.value)
    # a run.json written before editions were kept: the defaults
    doc = json.loads((tmp_path / RUN_FILE).read_text())
    del doc["editions"]
    assert RunSettings.from_json(doc) == RunSettings()
    for bad, says in ((((21, "0.27"),), "no CAT021 edition '0.27'"),
                      (((21, "0.26"), (21, "0.25")), "CAT021 is given two editions")):
        with pytest.raises(InputError) as e:
            RunSettings(editions=bad)
        assert e.value.loc == ("editions",) and says in str(e.value)


# ---------------------------------------------------------------------------------- command line


@pytest.fixture(scope="module")
def scheduler():
    """A cluster as the command line embeds (one worker), named with ``--scheduler``."""
    import dask
    import distributed  # noqa: F401  (its defaults in dask's config before the set below)

    from solver.batch import dask_settings, embedded_cluster

    with dask.config.set(dask_settings()):
        cluster = embedded_cluster(1)
    with cluster:
        yield cluster.scheduler_address


def _run(tmp_path, data: bytes, out: str, scheduler: str, *more: str) -> int:
    (tmp_path / f"{out}.ast").write_bytes(data)
    (tmp_path / "sensors.json").write_text(json.dumps(SENSOR_FILE))
    return main(["reconstruct", str(tmp_path / f"{out}.ast"), "--sensors",
                 str(tmp_path / "sensors.json"), "--out", str(tmp_path / out), "--scheduler",
                 scheduler, "--no-progress", *more])


def _tracks_csv(path) -> list[list[str]]:
    """tracks.csv without its ``source`` column (the records' byte offsets differ), by
    aircraft and plot (the tracks are written as they finish)."""
    lines = [line.split(",") for line in path.read_text().splitlines()]
    col = lines[0].index('"source"')
    assert lines[0][:2] == ['"aircraft"', '"plot"']
    return [line[:col] + line[col + 1:]
            for line in lines[:1] + sorted(lines[1:], key=lambda s: (s[0], int(s[1])))]


def test_command_line_edition_reads_0_26_as_the_default_reads_2_7(tmp_path, capsys, scheduler):
    """``--edition 21=0.26`` on the 0.26 recording gives the tracks (every column but the
    byte offsets) the 2.7 recording gives by default, and keeps the edition in run.json; a
    rerun with other editions is refused; the default on the 0.26 recording reads no ADS-B
    plot and says why (problems.txt); usage errors list the choices."""
    assert _run(tmp_path, recording("2.7"), "new", scheduler) == 0
    assert _run(tmp_path, recording("0.26"), "old", scheduler, "--edition", "21=0.26") == 0
    new, old = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("new", "old"))
    assert old["tracks"] == new["tracks"] == len(FLIGHTS) and old["plots"] == new["plots"]
    assert old["problems"] == new["problems"] == {}
    assert _tracks_csv(tmp_path / "old" / "tracks.csv") == _tracks_csv(
        tmp_path / "new" / "tracks.csv")
    assert {r["sensor"]: r["plots"] for r in old["sensors"] if r["plots"]} == {"R1": 40,
                                                                              "ADSB": 80}
    assert json.loads((tmp_path / "old" / RUN_FILE).read_text())["editions"] == {"21": "0.26"}
    assert json.loads((tmp_path / "new" / RUN_FILE).read_text())["editions"] == {}
    capsys.readouterr()
    # the same --out without the edition: another run, refused
    assert _run(tmp_path, recording("0.26"), "old", scheduler) == 2
    assert "holds a run made with editions {'21': '0.26'} (asked: {})" in capsys.readouterr().err
    # the default on the 0.26 recording: the radar's tracks alone, the ADS-B left out, said
    assert _run(tmp_path, recording("0.26"), "default", scheduler) == 0
    summary = json.loads((tmp_path / "default" / "summary.json").read_text())
    assert summary["problems"]["other_edition"] == 1
    assert {r["sensor"] for r in summary["sensors"] if r["plots"]} == {"R1"}
    assert "--edition 21=EDITION" in (tmp_path / "default" / "problems.txt").read_text()
    for bad, says in (("21=0.27", "libasterix has no CAT021 edition '0.27'"),
                      ("62=1.19", "CAT062 is not decoded"), ("0.26", "give CATEGORY=EDITION")):
        with pytest.raises(SystemExit) as e:
            _run(tmp_path, b"", "bad", scheduler, "--edition", bad)
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert "argument --edition" in err and says in err and "CAT021 0.23, 0.24" in err
    assert not (tmp_path / "bad").exists()
