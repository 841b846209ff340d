"""A recording's date and UTC times (solver.io.dates): captures encoded with libasterix and
stamped here as a live capture would be (classic pcap; pcapng with its own time units), a
recording across midnight, a clock that disagrees, a plot table's timestamp column, a date
given that contradicts the recording's own. The reference times are Python's ``datetime``
(the code under test uses numpy / Arrow)."""

from __future__ import annotations

import datetime as dt
import io

import numpy as np
import pyarrow as pa
import pytest
from test_io_asterix import (
    CAPTURE_DAY,
    CAPTURE_MIDNIGHT_S,
    SENSORS,
    capture_times,
    dpkt_frame,
    encode_recording,
    pcap,
)

from solver.inputs import InputError
from solver.io.asterix import read_recording
from solver.io.dates import CLOCK_TOLERANCE_S, iso_utc, parse_date, utc_times
from solver.io.reading import recording_date
from solver.io.tables import read_csv

MIDNIGHT = dt.datetime(2023, 11, 14, tzinfo=dt.UTC)
assert MIDNIGHT.timestamp() == CAPTURE_MIDNIGHT_S and str(MIDNIGHT.date()) == CAPTURE_DAY


def expected_utc(tods: list[float], day: dt.datetime) -> list[dt.datetime]:
    """Each report's UTC time: its time of day on ``day``, the day after once the times of
    day wrapped past midnight (they are in time order and span less than a day)."""
    out, after = [], False
    for k, tod in enumerate(tods):
        after = after or (k > 0 and tod < tods[k - 1] - 43_200)
        out.append(day + dt.timedelta(days=int(after), seconds=tod))
    return out


def test_pcap_capture_across_midnight_gives_utc_times_on_both_days():
    """A capture of 23:58:20-00:01:40 stamped by a clock that is right: the date is the
    midnight before the first report's, every row's UTC time is its report's (to 1 us),
    those after midnight on the next day; the same with the recording cut into small units
    (the first decides, the others agree) and with packet times 20 s late (within the
    tolerance)."""
    enc = encode_recording(tod0=86_300.0, duration=200.0)
    times = capture_times(enc.blocks)
    assert times[0] < CAPTURE_MIDNIGHT_S + 86_400 < times[-1]  # the packets cross midnight
    for chunk, late in ((1 << 20, 0.0), (512, 0.0), (1 << 20, 20.0)):
        rec = read_recording(pcap(enc.blocks, times=[p + late for p in times]), SENSORS,
                             chunk_bytes=chunk)
        assert not rec.problems, rec.problems.summary()
        assert rec.rows.date == CAPTURE_DAY
        got = utc_times(rec.rows.t, rec.rows.date).to_pylist()
        want = expected_utc([p["tod"] for p in enc.plots], MIDNIGHT)
        assert sorted(got) == sorted(want)  # rows by sensor, plots by time: as sets
        assert {g.date() for g in got} == {dt.date(2023, 11, 14), dt.date(2023, 11, 15)}
        row_tods = rec.rows.time_of_day_s
        for g, tod in zip(got, row_tods.tolist(), strict=True):
            assert (g - g.replace(hour=0, minute=0, second=0, microsecond=0)).total_seconds() \
                == pytest.approx(tod, abs=1e-6)


def test_a_dated_recording_written_as_a_table_reads_back_with_its_date(tmp_path):
    """A capture's rows across midnight written as a plot table (CSV, Parquet) carry a
    timestamp column beside t and time_of_day_s: read back, the same t, time of day and date
    (nothing of the date lost on the way)."""
    from solver.io.tables import read_table, write_table

    enc = encode_recording(tod0=86_390.0, duration=20.0)
    rows = read_recording(pcap(enc.blocks), SENSORS).rows
    assert rows.date == CAPTURE_DAY
    for name in ("rows.csv", "rows.parquet"):
        write_table(rows, tmp_path / name)
        back, problems = read_table(tmp_path / name)
        assert not problems, problems.summary()
        assert back.date == CAPTURE_DAY
        np.testing.assert_allclose(back.t, rows.t, atol=1e-6)
        np.testing.assert_allclose(back.time_of_day_s, rows.time_of_day_s, atol=1e-6)
    text = (tmp_path / "rows.csv").read_text().splitlines()
    assert text[0].startswith('"t","time_of_day_s","timestamp"')
    assert ',"2023-11-14T23:59:50.296875Z",' in text[1]


def test_pcapng_time_units_and_offset():
    """pcapng packet times in the interface's units (if_tsresol 10^-9) plus its if_tsoffset:
    the capture's date comes out, and every packet's time is dpkt's reader's."""
    from dpkt import pcap as dpkt_pcap
    from dpkt import pcapng as ng

    from solver.io.pcap import iter_udp_packets
    from solver.io.problems import Problems

    enc = encode_recording(tod0=36_000.0, duration=20.0)
    times = capture_times(enc.blocks)
    offset = 1_000_000  # s, in the interface's if_tsoffset
    idb = ng.InterfaceDescriptionBlockLE(linktype=1, snaplen=65535, opts=[
        ng.PcapngOptionLE(code=ng.PCAPNG_OPT_IF_TSRESOL, data=bytes([9])),
        ng.PcapngOptionLE(code=ng.PCAPNG_OPT_IF_TSOFFSET,
                          data=offset.to_bytes(8, "little", signed=True)),
        ng.PcapngOptionLE(code=ng.PCAPNG_OPT_ENDOFOPT)])
    blocks = [bytes(ng.SectionHeaderBlockLE()), bytes(idb)]
    for payload, when in zip(enc.blocks, times, strict=True):
        ns = round((when - offset) * 1e9)
        blocks.append(bytes(ng.EnhancedPacketBlockLE(
            iface_id=0, pkt_data=dpkt_frame(payload, 1), ts_high=ns >> 32,
            ts_low=ns & 0xFFFFFFFF)))
    data = b"".join(blocks)
    rec = read_recording(data, SENSORS)
    assert not rec.problems, rec.problems.summary()
    assert rec.rows.date == CAPTURE_DAY
    # the packet times as dpkt's own readers give them (its pcapng reader: the first
    # interface's units and offset), classic pcap in nanoseconds, big-endian, too
    classic = pcap(enc.blocks, times=times, nanoseconds=True, big_endian=True)
    for capture, reader in ((data, ng.Reader), (classic, dpkt_pcap.Reader)):
        got = [w for _, _, w in iter_udp_packets(capture, Problems())]
        want = [float(ts) for ts, _ in reader(io.BytesIO(capture))]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
        np.testing.assert_allclose(got, times, rtol=0, atol=1e-6)
    assert utc_times(rec.rows.t[:1], rec.rows.date).to_pylist()[0] == \
        MIDNIGHT + dt.timedelta(seconds=float(rec.rows.time_of_day_s[0]))


def test_a_clock_that_disagrees_is_reported_and_gives_no_date():
    """Packet times an hour off (a replayed capture): every report is a clock_disagreement,
    and there is no date; one packet 2 h off among right ones: that packet's reports are
    counted, the date stands; 1 s beyond the tolerance is reported, at it is not."""
    enc = encode_recording(tod0=36_000.0, duration=40.0)
    times = capture_times(enc.blocks)
    rec = read_recording(pcap(enc.blocks, times=[p + 3600.0 for p in times]), SENSORS)
    assert rec.rows.date is None
    assert rec.problems.counts == {"clock_disagreement": len(rec.rows) + 1}  # + "no date"
    assert any(e.where == "capture" for e in rec.problems.of_kind("clock_disagreement"))
    one_off = list(times)
    one_off[5] += 7200.0
    rec = read_recording(pcap(enc.blocks, times=one_off), SENSORS)
    assert rec.rows.date == CAPTURE_DAY
    n5 = len(read_recording(enc.blocks[5], SENSORS).rows)
    assert rec.problems.counts == {"clock_disagreement": n5}
    for shift, reported in ((CLOCK_TOLERANCE_S + 1.0, True), (CLOCK_TOLERANCE_S - 1.0, False)):
        # each packet stamped at its first report's time: its later reports are a little
        # earlier than the packet (within the 1/128-s grid); shifted back, all are off by more
        rec = read_recording(pcap(enc.blocks, times=[p - shift for p in times]), SENSORS)
        assert ("clock_disagreement" in rec.problems.counts) == reported
        assert (rec.rows.date is None) == reported


def test_a_streamed_capture_whose_first_unit_has_no_plot_dates_its_tracks(tmp_path,
                                                                         monkeypatch):
    """Streamed in 512-byte units as the command line reads, a capture that starts with 1 KB
    of CAT034 service messages (no plot): the date is known when the first track comes out
    (the command line hands it to every track's task then), and a date given that differs
    overrides it, reported (``date_override``) before any track."""
    import json

    from test_io_asterix import SENSOR_FILE

    import solver.io.reading as reading

    monkeypatch.setattr(reading, "STREAM_CHUNK_BYTES", 512)
    enc = encode_recording(tod0=36_000.0, duration=20.0)
    service = [b for b in enc.blocks if b[0] == 34][:1] * 100
    assert sum(map(len, service)) > 1024
    payloads = service + enc.blocks
    path = tmp_path / "day.pcap"
    path.write_bytes(pcap(payloads))
    (tmp_path / "sensors.json").write_text(json.dumps(SENSOR_FILE))
    read = reading.stream(path, tmp_path / "sensors.json")
    assert read.date == CAPTURE_DAY
    assert len(list(read.tracks)) == 2 and not read.problems
    read = reading.stream(path, tmp_path / "sensors.json", date="2023-11-13")
    assert read.date == "2023-11-13" and read.problems.counts == {"date_override": 1}
    assert "2023-11-13, overrides 2023-11-14" in str(read.problems.entries[0])


def test_a_capture_clock_whole_days_off_yields_to_the_date_given(tmp_path):
    """A capturing host's clock with the right time of day but 3 days ahead: the capture's
    date is 3 days late and no clock_disagreement can show it (the check is modulo a day).
    The right date given overrides it (it was refused as contradicting the capture's own),
    reported as ``date_override`` naming both dates; a table's ``timestamp`` still refuses
    a date that contradicts it (test_table_timestamps_across_midnight_and_a_given_date)."""
    import json

    from test_io_asterix import SENSOR_FILE

    import solver.io.reading as reading

    enc = encode_recording(tod0=36_000.0, duration=20.0)
    times = [p + 3 * 86_400.0 for p in capture_times(enc.blocks)]
    path = tmp_path / "day.pcap"
    path.write_bytes(pcap(enc.blocks, times=times))
    (tmp_path / "sensors.json").write_text(json.dumps(SENSOR_FILE))
    rec = read_recording(path, SENSORS)
    assert rec.rows.date == "2023-11-17" and not rec.problems
    assert recording_date(rec.rows, None, True) == "2023-11-17"  # nothing tells it wrong
    loaded = reading.load(path, tmp_path / "sensors.json", date=CAPTURE_DAY)
    assert loaded.date == CAPTURE_DAY
    assert loaded.problems.counts == {"date_override": 1}
    entry = loaded.problems.entries[0]
    assert (entry.kind, entry.where) == ("date_override", "date")
    assert ("the date given, 2023-11-14, overrides 2023-11-17 (from its capture's packet "
            "times)") in entry.message and "3 days (ahead)" in entry.message
    assert utc_times(loaded.rows.t[:1], loaded.date).to_pylist()[0] == \
        MIDNIGHT + dt.timedelta(seconds=float(loaded.rows.time_of_day_s[0]))


def test_table_timestamps_across_midnight_and_a_given_date():
    """A table timed by ISO 8601 text (Z, an offset, none: UTC) and epoch seconds: t from the
    midnight before the first row, growing across midnight, its date; the UTC times are the
    timestamps. A date given that contradicts it is an error naming both; one that agrees, or
    one given for ASTERIX times of day without a date, is taken; one given for a table's own
    t (any epoch) is refused."""
    stamps = ["2024-03-09T23:59:58.5Z", "2024-03-10T00:59:59+01:00", "2024-03-10 00:00:01",
              str(dt.datetime(2024, 3, 10, 0, 0, 4, tzinfo=dt.UTC).timestamp())]
    csv = "timestamp,sensor,range_m,azimuth_deg\n" + "".join(
        f"{s},R1,50000,{10 + k}\n" for k, s in enumerate(stamps))
    rows, problems = read_csv(csv.encode())
    assert not problems, problems.summary()
    np.testing.assert_allclose(rows.t, [86_398.5, 86_399.0, 86_401.0, 86_404.0])
    np.testing.assert_allclose(rows.time_of_day_s, [86_398.5, 86_399.0, 1.0, 4.0])
    assert rows.date == "2024-03-09"
    want = ["2024-03-09T23:59:58.500000Z", "2024-03-09T23:59:59.000000Z",
            "2024-03-10T00:00:01.000000Z", "2024-03-10T00:00:04.000000Z"]
    assert iso_utc(utc_times(rows.t, rows.date)).to_pylist() == want
    assert recording_date(rows, None, True) == "2024-03-09"
    assert recording_date(rows, "2024-03-09", True) == "2024-03-09"
    with pytest.raises(InputError, match=r"2024-03-10 contradicts the recording's own date "
                       r"2024-03-09 \(from its timestamp column\)") as e:
        recording_date(rows, "2024-03-10", True)
    assert e.value.loc == ("date",)
    asterix = read_recording(encode_recording().data, SENSORS).rows  # no date of its own
    assert asterix.date is None and recording_date(asterix, "2024-03-09", True) == "2024-03-09"
    own_t, _ = read_csv(b"t,sensor,range_m,azimuth_deg\n5,R1,50000,10\n")
    with pytest.raises(InputError, match="counts from no UTC midnight"):
        recording_date(own_t, "2024-03-09", False)


def test_table_timestamps_with_rfc3339_lower_case_t_and_z():
    """RFC 3339 allows ``t`` and ``z`` in lower case: read as ``T`` and ``Z`` (a lower-case
    ``z`` was a bad value, "not a time", though its regex took it as zoned)."""
    csv = ("timestamp,sensor,range_m,azimuth_deg\n2024-03-09T10:00:00z,R1,50000,10\n"
           "2024-03-09t10:00:01.5Z,R1,50000,11\n2024-03-09t05:00:02-05:00,R1,50000,12\n"
           "2024-03-09t10:00:03,R1,50000,13\n")
    rows, problems = read_csv(csv.encode())
    assert not problems, problems.summary()
    assert rows.date == "2024-03-09"
    np.testing.assert_allclose(rows.t, [36_000.0, 36_001.5, 36_002.0, 36_003.0])


def test_table_timestamp_column_checks():
    """A bad timestamp is a bad value of its row; a t or time_of_day_s beside the timestamp
    that disagrees with it too; a Parquet timestamp column (naive: UTC) is read as such."""
    csv = ("timestamp,t,time_of_day_s,sensor,range_m,azimuth_deg\n"
           "2024-03-09T10:00:00Z,36000,36000,R1,50000,10\n"
           "yesterday,,,R1,50000,11\n"
           "2024-03-09T10:00:04Z,36004,36005,R1,50000,12\n"
           "2024-03-09T10:00:08Z,8,,R1,50000,13\n"
           "99,,,R1,50000,13\n")
    rows, problems = read_csv(csv.encode())
    assert list(rows.origin) == [1]
    where = sorted((e.where, e.message.split(":")[0]) for e in problems.of_kind("bad_value"))
    assert where == [("row 2 (line 3)", "timestamp"), ("row 3 (line 4)", "time_of_day_s"),
                     ("row 4 (line 5)", "t"), ("row 5 (line 6)", "timestamp")]
    from solver.io.tables import rows_from_arrow

    table = pa.table({"timestamp": pa.array(np.array(["2024-03-09T10:00:00", "2024-03-09T10:00:04"],
                                                     dtype="datetime64[ms]")),
                      "sensor": ["R1", "R1"], "range_m": [5e4, 5e4], "azimuth_deg": [1.0, 2.0]})
    rows, problems = rows_from_arrow(table)
    assert not problems and rows.date == "2024-03-09"
    np.testing.assert_array_equal(rows.t, [36_000.0, 36_004.0])


def test_parse_date():
    assert parse_date(" 2024-02-29 ") == "2024-02-29"
    for bad in ("2023-02-29", "2024-3-9", "09.03.2024", "2024-03-09T00:00", ""):
        with pytest.raises(InputError, match="is not a date YYYY-MM-DD"):
            parse_date(bad)
