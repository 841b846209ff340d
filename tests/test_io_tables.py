"""The documented plot table (solver.io.tables): CSV and Parquet round trips, missing columns
named, bad values reported by row while the rest is read, time of day unwrapped."""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from test_io_asterix import SENSORS, encode_recording

from solver.inputs import InputError
from solver.io.asterix import read_recording
from solver.io.problems import Problems
from solver.io.tables import (
    PlotRows,
    counts_from_midnight,
    iter_table,
    read_csv,
    read_table,
    unwrap_time_of_day,
    write_table,
)

COLUMNS = ("t", "time_of_day_s", "range_m", "azimuth_deg", "lat_deg", "lon_deg",
           "altitude_m", "flight_level", "mode_s", "mode_3a", "track_number")


def assert_rows_equal(a: PlotRows, b: PlotRows) -> None:
    assert len(a) == len(b)
    for name in COLUMNS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.sensor.tolist() == b.sensor.tolist()
    assert a.aircraft.tolist() == b.aircraft.tolist()


def decoded() -> PlotRows:
    rows = read_recording(encode_recording(tod0=86_390.0).data, SENSORS).rows
    aircraft = np.array(["" if i % 5 else f"user-{i}" for i in range(len(rows))], dtype=object)
    return PlotRows.from_columns(len(rows), **{n: getattr(rows, n) for n in COLUMNS},
                                 sensor=rows.sensor, aircraft=aircraft)


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_round_trip(tmp_path, suffix):
    rows = decoded()
    assert rows.mode_3a.max() == 0o7000 and (rows.track_number >= 0).any()
    path = tmp_path / f"plots{suffix}"
    write_table(rows, path)
    back, problems = read_table(path)
    assert not problems, problems.summary()
    assert back.origin.tolist() == list(range(1, len(rows) + 1))
    assert_rows_equal(back, rows)


def test_csv_text_format(tmp_path):
    """Mode S in hex, Mode 3/A in octal with leading zeros, empty cells for missing values."""
    rows = PlotRows.from_columns(1, t=[1.5], sensor=np.array(["R1"], dtype=object),
                                 range_m=[1000.0], azimuth_deg=[90.0], mode_s=[0x00A1B2],
                                 mode_3a=[0o0123])
    write_table(rows, tmp_path / "p.csv")
    with open(tmp_path / "p.csv", newline="") as f:
        (record,) = csv.DictReader(f)
    assert record["mode_s"] == "00A1B2" and record["mode_3a"] == "0123"
    assert record["lat_deg"] == "" and record["track_number"] == ""


def test_missing_columns_are_named():
    with pytest.raises(InputError, match=r"^sensor is missing"):
        read_csv(b"t,range_m,azimuth_deg\n1,2,3\n")
    with pytest.raises(InputError, match=r"^azimuth_deg is missing \(it goes with `range_m`\)"):
        read_csv(b"t,sensor,range_m\n1,R1,3\n")
    with pytest.raises(InputError, match=r"^t is missing"):
        read_csv(b"sensor,range_m,azimuth_deg\nR1,2,3\n")
    with pytest.raises(InputError, match=r"^range_m is missing"):
        read_csv(b"t,sensor\n1,R1\n")
    with pytest.raises(InputError, match=r"^t is missing.*\(columns: time, sensor"):
        read_csv(b"time,sensor,range_m,azimuth_deg\n1,R1,2,3\n")  # named as the file has them


def test_a_users_own_columns_are_read_past_and_reported_once():
    data = b"t,sensor,range_m,azimuth_deg,speed,comment\n1,R1,2,3,4,a\n2,R1,2,3,5,b\n"
    rows, problems = read_csv(data)
    assert len(rows) == 2 and problems.counts == {"unknown_column": 2}
    assert [e.message.split(" is not")[0] for e in problems.entries] == ["`speed`", "`comment`"]
    with pytest.raises(InputError, match=r"^speed is not a column"):
        read_csv(data, strict=True)


def test_missing_column_in_parquet_is_named(tmp_path):
    path = tmp_path / "p.parquet"
    pq.write_table(pa.table({"t": [1.0], "sensor": ["R1"], "lat_deg": [46.0]}), path)
    with pytest.raises(InputError, match=r"^lon_deg is missing"):
        read_table(path)


def test_bad_values_are_reported_by_row_and_the_rest_is_read():
    data = (b"time_of_day_s,sensor,range_m,azimuth_deg,lat_deg,lon_deg,mode_s,mode_3a\n"
            b"86399,R1,50000,10,,,4CA2D1,7000\n"
            b"86399.5,R1,fifty,10,,,4CA2D1,7000\n"      # row 2: not a number
            b"0.5,ADSB,,,46.1,14.2,4CA2D1,\n"
            b"1.0,R1,50100,10,46,14,,\n"                # row 4: radar and position
            b"1.5,,50200,10,,,,\n"                      # row 5: no sensor
            b"2.0,R1,50300,10,,,XYZ,7000\n"             # row 6: bad Mode S
            b"2.5,R1,50400,10,,,,8000\n"                # row 7: not octal
            b"3.0,R1,50500,,,,,\n"                      # row 8: range without azimuth
            b"4.0,R1,50600,11,,,,\n")
    rows, problems = read_csv(data)
    assert problems.counts == {"bad_value": 6} and problems.dropped == {"bad_value": 6}
    where = {p.where: p.message for p in problems.entries}
    assert where == {
        "row 2 (line 3)": "range_m: 'fifty' is not a number",
        "row 4 (line 5)": "lat_deg: a row is either a radar plot (range_m, azimuth_deg) or a "
                          "position plot (lat_deg, lon_deg), not both",
        "row 5 (line 6)": "sensor: is missing",
        "row 6 (line 7)": "mode_s: 'XYZ' is not a 24-bit hex address (4CA2D1)",
        "row 7 (line 8)": "mode_3a: '8000' is not 4 octal digits (7000)",
        "row 8 (line 9)": "azimuth_deg: is missing (the row has `range_m`)"}
    assert rows.origin.tolist() == [1, 3, 9]
    # the time of day wraps at midnight: t grows across it
    np.testing.assert_array_equal(rows.t, [86399.0, 86400.5, 86404.0])
    np.testing.assert_array_equal(rows.time_of_day_s, [86399.0, 0.5, 4.0])
    assert rows.mode_s.tolist() == [0x4CA2D1, 0x4CA2D1, -1]
    assert rows.mode_3a.tolist() == [0o7000, -1, -1]


def test_strict_raises_at_the_first_bad_row():
    with pytest.raises(InputError, match=r"^rows\[2\]\.range_m 'x' is not a number"):
        read_csv(b"t,sensor,range_m,azimuth_deg\n1,R1,5,6\n2,R1,x,6\n", strict=True)


def test_flight_level_gives_pressure_altitude():
    rows, _ = read_csv(b"t,sensor,range_m,azimuth_deg,flight_level,altitude_m\n"
                       b"1,R1,5000,6,350,\n2,R1,5000,6,350,9000\n3,R1,5000,6,,\n")
    np.testing.assert_array_equal(rows.altitude_m[:2], [350 * 30.48, 9000.0])
    assert np.isnan(rows.altitude_m[2])


def test_unwrap_time_of_day():
    tod = np.array([86398.0, 86399.5, 0.5, 86399.9, 1.0, 43000.0, 86000.0, 100.0])
    np.testing.assert_array_equal(
        unwrap_time_of_day(tod),
        [86398.0, 86399.5, 86400.5, 86399.9, 86401.0, 86400 + 43000.0, 86400 + 86000.0,
         2 * 86400 + 100.0])


def test_counts_from_midnight():
    """ASTERIX rows and a table timed by its time of day count ``t`` from a UTC midnight
    (across midnight, a late report before it too); a table with its own ``t`` does not,
    nor one whose times of day are partly missing; an empty table does not."""
    assert counts_from_midnight(decoded())
    by_tod, _ = read_csv(b"time_of_day_s,sensor,range_m,azimuth_deg\n86399.5,R1,5000,6\n"
                         b"0.5,R1,5000,6\n86399.9,R1,5000,6\n")
    np.testing.assert_array_equal(by_tod.t, [86399.5, 86400.5, 86399.9])
    assert counts_from_midnight(by_tod)
    own_t, _ = read_csv(b"t,time_of_day_s,sensor,range_m,azimuth_deg\n"
                        b"10,36000,R1,5000,6\n14,36004,R1,5000,6\n")
    assert not counts_from_midnight(own_t)
    no_tod, _ = read_csv(b"t,sensor,range_m,azimuth_deg\n36000,R1,5000,6\n")
    assert not counts_from_midnight(no_tod)
    assert not counts_from_midnight(dataclasses.replace(by_tod, time_of_day_s=np.array(
        [86399.5, np.nan, 86399.9])))
    assert not counts_from_midnight(by_tod.take(np.array([], dtype=int)))


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_reading_in_batches_gives_the_table(tmp_path, suffix):
    """iter_table's batches: the rows, row numbers, times (unwrapped across midnight and
    across batches) and problems of read_table."""
    from solver.io.tables import iter_table

    rows = decoded()
    rows = PlotRows.concat([rows] * 3)  # 300+ rows
    rows = dataclasses.replace(rows, t=np.full(len(rows), np.nan))  # times of day only
    table = rows.to_arrow().drop_columns(["t"])
    bad = table.column("range_m").to_pylist()
    bad[40] = -5.0  # a bad value in a later batch
    table = table.set_column(table.column_names.index("range_m"), "range_m",
                             pa.array(bad, pa.float64()))
    path = tmp_path / f"plots{suffix}"
    (pq.write_table if suffix == ".parquet" else pacsv_write)(table, path)
    whole, whole_p = read_table(path)
    batched_p = Problems()
    parts = list(iter_table(path, batch_rows=20, problems=batched_p))
    assert len(parts) > 3
    back = PlotRows.concat(parts)
    assert_rows_equal(back, whole)
    assert back.origin.tolist() == whole.origin.tolist()
    assert [str(p) for p in batched_p.entries] == [str(p) for p in whole_p.entries]
    assert whole_p.entries[0].where.startswith("row 41")
    assert whole.t.max() > 86_400


def pacsv_write(table: pa.Table, path) -> None:
    import pyarrow.csv as pacsv

    pacsv.write_csv(table, path)


def test_unwrap_time_of_day_vectorised_equals_value_by_value():
    """The vectorised unwrap gives what unwrapping one value after the other gives: random
    recordings across midnight, jumps of about 12 h (ties), NaN and infinite values, with and
    without the time before the first value."""
    from solver.io.tables import _unwrap_loop

    rng = np.random.default_rng(16)
    for trial in range(2000):
        n = int(rng.integers(0, 30))
        if trial % 3 == 0:
            tod = np.mod(np.cumsum(rng.exponential(3000.0, n)) + rng.uniform(0, 86400), 86400)
        elif trial % 3 == 1:
            tod = np.round(rng.uniform(0, 86400, n) * 128) / 128
        else:
            tod = rng.choice([0.0, 1.0, 21600.0, 43199.5, 43200.0, 43200.5, 86399.0], n)
        u = rng.random(n)
        tod[u < 0.1] = np.nan
        tod[(u > 0.1) & (u < 0.13)] = np.inf
        tod[(u > 0.13) & (u < 0.15)] = -np.inf
        previous = (np.nan, float(rng.uniform(0, 3 * 86400)), 43200.0, np.inf)[trial % 4]
        with np.errstate(invalid="ignore"):
            np.testing.assert_array_equal(unwrap_time_of_day(tod, previous),
                                          _unwrap_loop(tod, previous))


def test_a_users_key_that_looks_like_a_piece_is_a_counted_bad_value():
    """`A#2` names key `A`'s piece after a 300-s gap (solver.io.split): a user's key of that
    form was merged with another aircraft's piece, or made a traceback when it came in a later
    batch (a fuzz helper). Its rows are bad values, named and counted; `B#x` is a key."""
    text = (b"t,sensor,range_m,azimuth_deg,aircraft\n"
            b"0,R1,5000,6,A\n1,R1,5000,6,A#2\n2,R1,5000,6,B#x\n")
    rows, problems = read_csv(text)
    assert rows.aircraft.tolist() == ["A", "B#x"]
    assert problems.counts == {"bad_value": 1} and problems.dropped == {"bad_value": 1}
    assert "aircraft: ends in #<number>" in problems.summary()


def test_a_parquet_integer_column_written_as_float_is_read_as_integers(tmp_path):
    """pandas writes an integer column with missing values as float64, NaN where missing:
    such a Parquet ``mode_s`` refused every row (a fuzz helper). Whole numbers are the
    integers they are (``mode_s`` the address, ``mode_3a`` its octal digits, as an integer
    column gives them), NaN is missing; a fraction or a value beyond 2^53 is a counted
    bad value of its row only."""
    nan = np.nan
    table = pa.table({
        "t": [1.0, 2.0, 3.0, 4.0, 5.0],
        "sensor": ["R1"] * 5,
        "range_m": [1e4] * 5,
        "azimuth_deg": [10.0] * 5,
        "mode_s": pa.array([0x4CA2D1, nan, 0x4CA2D1 + 0.5, 0x3C6DD4, 1e300], pa.float64()),
        "mode_3a": pa.array([7000.0, 1234.0, nan, 7000.0, 7000.0], pa.float64()),
        "track_number": pa.array([12.0, nan, 12.0, 7.0, 7.0], pa.float64()),
    })
    pq.write_table(table, tmp_path / "pandas.parquet")
    rows, problems = read_table(tmp_path / "pandas.parquet")
    assert rows.origin.tolist() == [1, 2, 4]
    assert rows.mode_s.tolist() == [0x4CA2D1, -1, 0x3C6DD4]
    assert rows.mode_3a.tolist() == [0o7000, 0o1234, 0o7000]
    assert rows.track_number.tolist() == [12, -1, 7]
    assert problems.counts == {"bad_value": 2}
    assert [e.where for e in problems.entries] == ["row 3", "row 5"]
    assert all("mode_s: must be a 24-bit hex address" in e.message for e in problems.entries)


ODD_CSV = (b"t,sensor,range_m,azimuth_deg,comment\n"
           b"1,R1,1000,10,ok\n"
           b"2,R1,1000,10,a,b\n"             # row 2: a field too many
           b"3,R\xe9,1000,10,x\n"            # row 3: a Latin-1 sensor name
           b"4,R1,1000,10,Z\xfcrich\n"       # row 4: Latin-1 in a column read past: fine
           b"\"5\",R1,1000,10,\"two\nlines\"\n"
           b"6,R1,1000\n"                    # row 6 (line 8): fields missing
           b"7,R1,xx,10,\n"                  # row 7 (line 9): a bad value
           b"8,R1,1000,10,\n")


def test_a_row_of_the_wrong_width_or_not_utf8_is_skipped_and_the_rest_read(tmp_path):
    """One CSV row with a field too many or too few, or a byte that is not UTF-8 in a column
    read, refused the whole table (Arrow's reader; a fuzz helper). Such a row is now a
    counted problem (``bad_row``, ``bad_value``) naming its row and line, and every later row
    keeps its number and line (also after a quoted newline), whole and in batches; the
    reader's time-order check reads past it too; ``strict`` raises at it."""
    from solver.io.tables import iter_table, time_disorder_s

    path = tmp_path / "odd.csv"
    path.write_bytes(ODD_CSV)
    for got in (read_csv(ODD_CSV), read_table(path)):
        rows, problems = got
        assert rows.origin.tolist() == [1, 4, 5, 8] and rows.t.tolist() == [1, 4, 5, 8]
        assert problems.counts == {"bad_row": 2, "unknown_column": 1, "bad_value": 2}
        assert [str(e).split(":")[0] for e in problems.entries if e.kind != "unknown_column"] \
            == ["bad_row at row 2 (line 3)", "bad_row at row 6 (line 8)",
                "bad_value at row 3 (line 4)", "bad_value at row 7 (line 9)"]
        assert "has 6 field(s), the header 5" in problems.entries[0].message
        assert problems.dropped["bad_row"] == 2
    lines = ["t,sensor,range_m,azimuth_deg"] + [
        f"{i},R1,1000,10" + (",x" if i in (700, 2999, 3000) else "") for i in range(3000, 0, -1)]
    path.write_text("\n".join(lines) + "\n")
    problems = Problems()
    parts = list(iter_table(path, batch_rows=100, problems=problems))
    assert len(parts) > 5
    origin = [o for p in parts for o in p.origin.tolist()]
    assert origin == [r for r in range(1, 3001) if r not in (1, 2, 2301)]
    assert [e.where for e in problems.entries] == ["row 1 (line 2)", "row 2 (line 3)",
                                                   "row 2301 (line 2302)"]
    assert time_disorder_s(path) == pytest.approx(2999 - 1 - 1)  # rows 3 ... 2998 down
    with pytest.raises(InputError, match="has 6 field"):
        read_csv(ODD_CSV, strict=True)


def test_a_latin1_header_and_a_long_field_before_a_short_row(tmp_path):
    """Two tracebacks a review helper found: a header line that is not UTF-8 (now an error
    naming the file's header and the byte), and a field longer than the csv module's default
    limit (128 KiB) before a row of the wrong width, which the row numbering reads with it
    (now read: the short row skipped and counted)."""
    path = tmp_path / "latin1.csv"
    path.write_bytes("t,sensor,range_m,azimuth_deg,comment\u00e9\n1,R1,1000,10,x\n"
                     .encode("latin-1"))
    for read in (read_table, lambda p: list(iter_table(p))):
        with pytest.raises(InputError, match=r"header line that is not UTF-8 text \(byte 36\)"):
            read(path)
    long = "x" * 200_000
    path = tmp_path / "long.csv"
    path.write_text(f"t,sensor,range_m,azimuth_deg,comment\n1,R1,1000,10,{long}\n2,R1,1000\n"
                    "3,R1,1000,10,y\n")
    for rows, problems in (read_table(path),):
        assert rows.origin.tolist() == [1, 3] and problems.counts.get("bad_row") == 1
    problems = Problems()
    assert [r.origin.tolist() for r in iter_table(path, problems=problems)] == [[1, 3]]
    assert problems.counts.get("bad_row") == 1


def test_a_bad_value_after_a_quoted_newline_or_a_blank_line_names_its_line(tmp_path):
    """With no row skipped the lines were ``row + 1``: one early after a value spanning two
    lines or a blank line (a review helper). A problem's line is now the csv reader's (read
    only when a problem needs it), whole and in batches; the rows keep their numbers."""
    for text, where in (('t,sensor,range_m,azimuth_deg,aircraft\n1,R1,5e4,10,\n2,R1,5e4,10,'
                         '"two\nlines"\n3,R1,abc,10,\n4,R1,5e4,10,\n', "row 3 (line 5)"),
                        ("t,sensor,range_m,azimuth_deg\n1,R1,5e4,10\n\n3,R1,abc,10\n",
                         "row 2 (line 4)")):
        path = tmp_path / "t.csv"
        path.write_text(text)
        rows, problems = read_table(path)
        assert [e.where for e in problems.entries] == [where]
        batched = Problems()
        parts = list(iter_table(path, batch_rows=1, problems=batched))
        assert [e.where for e in batched.entries] == [where]
        assert [o for p in parts for o in p.origin.tolist()] == rows.origin.tolist()


def test_on_ground_is_read_and_written(tmp_path):
    """``on_ground``: ``true``, ``1`` (any case) on the ground, ``false``, ``0`` airborne,
    empty not said; another word is a bad value of its row. Parquet: a boolean column with
    nulls, or integers (2 is no boolean). Written back (CSV, Parquet), the same."""
    text = ("t,sensor,range_m,azimuth_deg,on_ground\n"
            "1,R1,1000,10,false\n2,R1,1000,10,TRUE\n3,R1,1000,10,\n4,R1,1000,10,1\n"
            "5,R1,1000,10,0\n6,R1,1000,10,maybe\n7,R1,1000,10, True \n")
    rows, problems = read_csv(text.encode(), problems=Problems())
    assert rows.t.tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 7.0]
    assert rows.on_ground.tolist() == [0, 1, -1, 1, 0, 1]
    assert problems.counts == {"bad_value": 1}
    (bad,) = problems.of_kind("bad_value")
    assert bad.where == "row 6 (line 7)" and "on_ground" in bad.message and "maybe" in bad.message
    for suffix in (".csv", ".parquet"):
        write_table(rows, tmp_path / f"back{suffix}")
        back, problems = read_table(tmp_path / f"back{suffix}")
        assert back.on_ground.tolist() == rows.on_ground.tolist() and not problems
    table = pa.table({"t": [1.0, 2.0, 3.0], "sensor": ["R1"] * 3, "range_m": [1e3] * 3,
                      "azimuth_deg": [10.0] * 3})
    path = tmp_path / "plots.parquet"
    pq.write_table(table.append_column("on_ground", pa.array([True, None, False])), path)
    rows, problems = read_table(path)
    assert rows.on_ground.tolist() == [1, -1, 0] and not problems
    pq.write_table(table.append_column("on_ground", pa.array([0, 1, 2])), path)
    rows, problems = read_table(path)
    assert rows.on_ground.tolist() == [0, 1] and problems.counts == {"bad_value": 1}
    assert problems.of_kind("bad_value")[0].where == "row 3"
    # as pandas writes a column of None, and one of 0.0 / 1.0 with NaN (a reviewer's: the
    # whole table refused)
    for column, said in ((pa.nulls(3), [-1, -1, -1]), (pa.array([1.0, np.nan, 0.0]),
                                                       [1, -1, 0])):
        pq.write_table(table.append_column("on_ground", column), path)
        rows, problems = read_table(path)
        assert rows.on_ground.tolist() == said and not problems


def test_longitudes_either_side_of_the_antimeridian_are_read_and_wrapped(tmp_path):
    """-180.0006 (a fix a hair west of the antimeridian) was a bad value while 180.0006 and
    359.9 were accepted (a tester's): [-360, 360] is accepted and wrapped to [-180, 180),
    a longitude already there kept bit for bit, beyond +-360 refused naming the range."""
    lons = [179.9994, -180.0006, 180.0006, 359.9, -359.9, -180.0, 360.0, -360.5, 360.5]
    path = tmp_path / "lon.csv"
    path.write_text("t,sensor,lat_deg,lon_deg\n" + "".join(
        f"{i},ADSB,65.5,{lon!r}\n" for i, lon in enumerate(lons)))
    rows, problems = read_table(path)
    want = [179.9994, 179.9994, -179.9994, -0.1, 0.1, -180.0, 0.0]
    np.testing.assert_allclose(rows.lon_deg, want, rtol=0, atol=1e-9)
    assert rows.lon_deg[0] == 179.9994 and rows.lon_deg[5] == -180.0
    assert np.all((rows.lon_deg >= -180.0) & (rows.lon_deg < 180.0))
    assert problems.counts == {"bad_value": 2}
    assert "lon_deg: must be in [-360, 360]" in problems.summary()
