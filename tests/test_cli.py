"""The command line end to end: an ASTERIX recording (encoded with libasterix) and a CSV plot
table in, Parquet/CSV/GeoJSON, sensor statistics, map and figures out, on a real 2-worker
Dask LocalCluster; a rerun resumes."""

from __future__ import annotations

import csv
import gc
import itertools
import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import asterix.generated as ast
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest
from asterix.base import Bits, ParsingMode
from test_io_asterix import FLIGHTS, SENSOR_FILE, encode_recording

from solver import run_settings
from solver.cli import main
from solver.io.asterix import read_recording
from solver.io.problems import Problems
from solver.io.sensors_file import parse_sensors
from solver.io.tables import FL_M, write_table


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    enc = encode_recording(tod0=86_300.0, duration=200.0)  # crosses midnight
    (d / "day.ast").write_bytes(enc.data[:-7])  # the last block truncated: reported
    (d / "sensors.json").write_text(json.dumps(SENSOR_FILE))
    return d, enc


@pytest.fixture(scope="module")
def scheduler():
    """The address of a cluster as the command line embeds (one worker process, its
    settings), for the runs whose point is not the embedded cluster: named with
    ``--scheduler`` (as a user names an existing cluster), each run saves the cluster's start
    and close (3.9 s measured). The embedded cluster is the first test's, and the SIGTERM,
    ``python -m`` and memory tests'."""
    import dask
    import distributed  # noqa: F401  (its defaults in dask's config before the set below)

    from solver.batch import dask_settings, embedded_cluster

    with dask.config.set(dask_settings()):
        cluster = embedded_cluster(1)
    with cluster:
        yield cluster.scheduler_address


def test_recording_to_tables_statistics_and_map(recording, capsys, scheduler):
    d, enc = recording
    out = d / "out"
    code = main(["reconstruct", str(d / "day.ast"), "--sensors", str(d / "sensors.json"),
                 "--out", str(out), "--workers", "2", "--no-progress", "--figures",
                 "--filters", "imm_smoother", "cv_rts", "fusion_a", "--samples", "2.5"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["tracks"] == summary["done"] == len(FLIGHTS) and summary["failed"] == 0
    assert summary["method"] == "refined"
    assert summary["filters"] == ["imm_smoother", "cv_rts", "fusion_a"]
    assert summary["problems"].get("truncated_block") == 1
    table = pq.read_table(out / "tracks.parquet")
    tracks = {name: table.column(name).to_numpy(zero_copy_only=False)
              for name in ("aircraft", "t", "time_of_day_s", "lat_deg", "lon_deg")}
    keys = tracks["aircraft"].astype(str)
    assert set(keys) == {f"{f.address:06X}" for f in FLIGHTS}
    assert table.num_rows == summary["plots"] and summary["plots"] > 0.95 * len(enc.plots)
    for k, f in enumerate(FLIGHTS):
        sel = keys == f"{f.address:06X}"
        t = tracks["t"][sel]
        assert np.diff(np.sort(t)).max() < 10.0  # through midnight without a jump
        # t from the midnight before the first plot; the recorded time of day beside it
        tods = np.array([p["tod"] for p in enc.plots if p["flight"] == k])
        np.testing.assert_allclose(np.sort(tracks["time_of_day_s"][sel]),
                                   np.sort(tods[np.isin(tods, tracks["time_of_day_s"][sel])]))
        assert (tracks["time_of_day_s"][sel] < 100).any() and t.max() > 86_400
        # exact plots: every reconstructed position within 60 m of the flight
        lat, lon, _ = f.at(t - t.min() + _first_t(enc, k))
        dy = (tracks["lat_deg"][sel] - lat) * 111_000
        dx = (tracks["lon_deg"][sel] - lon) * 111_000 * np.cos(np.deg2rad(lat))
        assert np.hypot(dx, dy).max() < 60.0
    # every plot's source is its record's byte offset: the record there, parsed by libasterix
    # alone, has the plot's time of day (and a radar plot's range)
    data = (d / "day.ast").read_bytes()
    sources = table.column("source").to_pylist()
    assert all(s.startswith("byte ") for s in sources) and len(set(sources)) == len(sources)
    for i in range(0, table.num_rows, 7):
        cat, tod, rho = _record_at(data, int(sources[i].removeprefix("byte ")))
        assert cat == (21 if table.column("sensor")[i].as_py() == "ADSB" else 48)
        assert tod == tracks["time_of_day_s"][i]
        if cat == 48:
            assert rho == pytest.approx(table.column("plot_range_m")[i].as_py(), abs=1e-6)
    lines = (out / "tracks.geojsonl").read_text().splitlines()
    assert len(lines) == len(FLIGHTS)
    feature = json.loads(lines[0])
    assert feature["geometry"]["type"] == "LineString" and len(feature["geometry"]
                                                                ["coordinates"]) > 10
    csv_rows = (out / "tracks.csv").read_text().count("\n") - 1
    assert csv_rows == table.num_rows
    # a raw recording says no date, and none was given: no UTC time
    assert table.column("time_utc").null_count == table.num_rows
    assert feature["properties"]["time_utc_start"] is None and summary["recording_date"] is None
    # straight, level flights: no manoeuvre (the job test has a turning track's)
    assert summary["manoeuvres"] == 0
    assert (out / "manoeuvres.csv").read_text().startswith('"aircraft","kind","direction"')
    sensors = {r["sensor"]: r for r in summary["sensors"]}
    assert set(sensors) == {"R1", "R2", "ADSB"}
    assert sensors["R1"]["scan_period_s"] == pytest.approx(4.0)  # from CAT034 I041
    assert sensors["R1"]["detection_rate"] > 0.95
    assert abs(sensors["R1"]["range_residual_mean_m"]) < 10  # exact plots: no bias
    assert (out / "sensors.csv").read_text().startswith('"sensor","kind"')
    assert json.loads((out / "sensors.json").read_text()) == summary["sensors"]
    # every plot against its state: the measured range as recorded (to the encoding's 1/256
    # NM), its residual small on exact plots, and the statistics are these residuals' pooled
    for sid in ("R1", "R2"):
        rows = pc.equal(table.column("sensor"), sid)
        got = table.filter(rows)
        recorded = np.array([p["range_m"] for p in enc.plots if p["sensor"] == sid])
        measured = got.column("plot_range_m").to_numpy()
        assert np.abs(measured[:, None] - recorded[None, :]).min(axis=1).max() < 1852 / 512
        dr = got.column("range_residual_m").to_numpy()
        kept = ~got.column("gated").to_numpy(zero_copy_only=False)
        assert np.abs(dr).max() < 30.0
        assert dr[kept].mean() == pytest.approx(sensors[sid]["range_residual_mean_m"], abs=1e-6)
        assert got.column("azimuth_residual_deg").null_count == 0
    adsb = table.filter(pc.equal(table.column("sensor"), "ADSB"))
    assert adsb.column("range_residual_m").null_count == adsb.num_rows
    assert np.nanmax(adsb.column("position_residual_m").to_numpy()) < 30.0
    # the ADS-B statistics along and across the track pool every track's kept plots
    kept = adsb.filter(pc.invert(adsb.column("gated")))
    for part in ("along", "cross"):
        v = kept.column(f"{part}_track_residual_m").to_numpy()
        assert v.mean() == pytest.approx(sensors["ADSB"][f"{part}_track_residual_mean_m"],
                                         abs=1e-6)
        assert v.std() == pytest.approx(sensors["ADSB"][f"{part}_track_residual_sigma_m"],
                                        rel=1e-6)
    assert (out / "sensors.png").read_bytes()[:4] == b"\x89PNG"
    # the filters asked for, beside: every plot of every track once per filter; the
    # two-sensor fusion cannot run on three sensors, which each track's warnings say
    filters = pq.read_table(out / "filters.parquet")
    assert set(filters.column("filter").to_pylist()) == {"imm_smoother", "cv_rts"}
    assert filters.num_rows == 2 * table.num_rows
    assert filters.column("gated").type == pa.bool_()  # left out as wild: none, exact plots
    assert not any(filters.column("gated").to_pylist())
    smoothed = filters.filter(pc.equal(filters.column("filter"), "imm_smoother"))
    assert np.hypot(np.asarray(smoothed.column("x")) - np.asarray(table.column("x")),
                    np.asarray(smoothed.column("z")) - np.asarray(table.column("z"))
                    ).max() < 100.0  # the same aircraft, exact plots
    ledger = [json.loads(x) for x in (out / "progress.jsonl").read_text().splitlines()]
    assert all(any(w.startswith("filters.fusion_a: fusion_a fuses exactly two")
                   for w in e["warnings"]) for e in ledger)
    # each track's line carries its reconstruction's diagnostics (and the height estimated for
    # the track, none here: the plots' flight levels give it)
    assert all(e["diagnostics"]["method"] == "refined" and e["diagnostics"]["solver_failures"]
               == 0 and e["diagnostics"]["extra"]["refine_iterations"] > 0 for e in ledger)
    assert all(e["altitude"] is None for e in ledger)
    assert table.column("h_m").null_count == table.num_rows
    _check_samples(pq.read_table(out / "samples.parquet"), table, enc, 2.5)
    assert summary["sample_step_s"] == 2.5
    assert (out / "map.png").stat().st_size > 10_000
    assert len(list((out / "figures").glob("*.png"))) == len(FLIGHTS)
    printed = capsys.readouterr().out
    assert "tracks: 2 (2 reconstructed by refined, 0 failed" in printed and "R1" in printed
    assert "ADSB: along the track " in printed

    # a rerun with other settings would mix two runs' tracks: refused, nothing touched
    code = main([str(d / "day.ast"), "--sensors", str(d / "sensors.json"), "--out", str(out),
                 "--scheduler", scheduler, "--no-progress", "--filters", "cv_rts"])
    assert code == 2 and json.loads((out / "summary.json").read_text()) == summary
    err = capsys.readouterr().err
    assert "holds a run made with filters ['imm_smoother', 'cv_rts', 'fusion_a']" in err
    # a rerun resumes: nothing redone, outputs the same (the form without the subcommand; the
    # filters in another order are the same run)
    code = main([str(d / "day.ast"), "--sensors", str(d / "sensors.json"), "--out", str(out),
                 "--scheduler", scheduler, "--no-progress", "--filters", "fusion_a", "imm_smoother",
                 "cv_rts", "--samples", "2.5"])
    again = json.loads((out / "summary.json").read_text())
    assert code == 0 and again["skipped"] == len(FLIGHTS) and again["done"] == 0
    assert pq.read_table(out / "tracks.parquet").num_rows == table.num_rows
    assert {r["sensor"]: r["plots"] for r in again["sensors"]} == {
        k: v["plots"] for k, v in sensors.items()}


def _check_samples(samples, table, enc, step: float) -> None:
    """``samples.parquet``: per aircraft, a state every ``step`` s from the first plot to the
    last (both included), on the flight (exact plots: within 60 m of the truth), the first one
    the state at the first plot, with a positive covariance and the time of day beside."""
    keys = np.asarray(samples.column("aircraft").to_pylist())
    plot_keys = np.asarray(table.column("aircraft").to_pylist())
    for k, f in enumerate(FLIGHTS):
        got = samples.filter(pc.equal(samples.column("aircraft"), f"{f.address:06X}"))
        at = table.filter(pc.equal(table.column("aircraft"), f"{f.address:06X}"))
        t, tp = got.column("t").to_numpy(), at.column("t").to_numpy()
        assert t[0] == tp.min() and t[-1] == tp.max()
        np.testing.assert_allclose(np.diff(t)[:-1], step, rtol=0, atol=1e-9)
        assert 0 < t[-1] - t[-2] <= step
        lat, lon, _ = f.at(t - t[0] + _first_t(enc, k))
        dy = (got.column("lat_deg").to_numpy() - lat) * 111_000
        dx = (got.column("lon_deg").to_numpy() - lon) * 111_000 * np.cos(np.deg2rad(lat))
        assert np.hypot(dx, dy).max() < 60.0
        first = int(np.argmin(tp))
        for name in ("x", "z", "vx", "vz", "cov_x_x", "cov_x_vz", "cov_vz_vz"):
            assert got.column(name)[0].as_py() == pytest.approx(at.column(name)[first].as_py(),
                                                                rel=1e-9, abs=1e-9), name
        assert (got.column("cov_x_x").to_numpy() > 0).all()
        np.testing.assert_allclose(got.column("time_of_day_s").to_numpy(), np.mod(t, 86_400.0))
    assert set(keys) == set(plot_keys)


def _record_at(data: bytes, at: int) -> tuple[int, float, float | None]:
    """The record at byte ``at`` of a raw ASTERIX file, parsed with libasterix alone: its
    category, time of day (s) and a CAT048 record's slant range (m)."""
    pos = 0
    while not pos + 3 <= at < pos + ((data[pos + 1] << 8) | data[pos + 2]):
        pos += (data[pos + 1] << 8) | data[pos + 2]
    cat, end = data[pos], min(len(data), pos + ((data[pos + 1] << 8) | data[pos + 2]))
    spec = {48: ast.Cat_048_1_32, 21: ast.Cat_021_2_7}[cat]
    rec, _ = spec.cv_uap.cv_record.parse(ParsingMode.StrictParsing, Bits.from_bytes(data[at:end]))
    tod = rec.get_item("140" if cat == 48 else "071").variation.content.as_quantity("s")
    rho = (rec.get_item("040").variation.get_item("RHO").variation.content.as_quantity("NM")
           * 1852.0 if cat == 48 else None)
    return cat, tod, rho


def test_plot_draws_named_aircraft_and_the_map(recording, tmp_path, capsys, scheduler):
    """`trajrecon plot`: the named aircraft's figures and the map of a finished run's tracks;
    an aircraft not in the recording, or a map without tracks, is a clear error (exit 2)."""
    d, _ = recording
    key = f"{FLIGHTS[1].address:06X}"
    out = tmp_path / "out"
    args = [str(d / "day.ast"), "--sensors", str(d / "sensors.json"), "--out", str(out)]
    assert main(["plot", *args, "--aircraft", key]) == 0
    assert (out / "figures" / f"{key}.png").stat().st_size > 20_000
    assert capsys.readouterr().out.split() == [str(out / "figures" / f"{key}.png")]
    assert main(["plot", *args, "--aircraft", key.lower()]) == 0  # an address in either case
    capsys.readouterr()
    assert main(["plot", *args, "--aircraft", key, "ABC123"]) == 2
    assert "ABC123 not in the recording" in capsys.readouterr().err
    assert main(["plot", *args, "--map"]) == 2
    assert "holds no reconstructed track" in capsys.readouterr().err
    assert main(["reconstruct", *args, "--scheduler", scheduler, "--no-progress"]) == 0
    # an unknown aircraft beside a known one and --map: the map drawn all the same, then exit
    # 2 naming it (the map was left undrawn, and nothing said so: a tester's)
    (out / "map.png").unlink()
    (out / "sensors.png").unlink()
    capsys.readouterr()
    assert main(["plot", *args, "--aircraft", key, "ABC123", "--map"]) == 2
    printed = capsys.readouterr()
    assert printed.out.split() == [str(out / "figures" / f"{key}.png"), str(out / "map.png"),
                                   str(out / "sensors.png")]
    assert "ABC123 not in the recording" in printed.err and printed.err.count("\n") == 1
    (out / "map.png").unlink()
    (out / "sensors.png").unlink()
    assert main(["plot", *args, "--map"]) == 0
    assert (out / "map.png").stat().st_size > 10_000
    assert (out / "sensors.png").stat().st_size > 10_000


def _first_t(enc, k: int) -> float:
    """Seconds from the recording's start of flight k's first plot."""
    tods = [p["tod"] for p in enc.plots if p["flight"] == k]
    t = (np.array(tods) - 86_300.0) % 86_400.0
    return float(t.min())


def test_plot_table_and_a_bad_sensor_file(recording, tmp_path, capsys, scheduler):
    d, _ = recording
    rec = read_recording(d / "day.ast", parse_sensors(SENSOR_FILE))
    write_table(rec.rows, tmp_path / "plots.csv")
    thresholds = gc.get_threshold()
    code = main([str(tmp_path / "plots.csv"), "--sensors", str(d / "sensors.json"), "--out",
                 str(tmp_path / "out"), "--scheduler", scheduler, "--no-progress", "--bounds",
                 "v=30,200"])  # the flights fly 206 and 234 m/s: held under 200
    assert code == 0
    assert gc.get_threshold() == thresholds  # the run's collector setting is undone
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["done"] == len(FLIGHTS) and summary["bounds"]["v"] == [30.0, 200.0]
    states = pq.read_table(tmp_path / "out" / "tracks.parquet")
    speed = states.column("speed").to_numpy()
    assert speed.max() <= 200.0 + 1e-3 and speed.max() > 199.0
    # a plot's source is its row of the table (data rows from 1, as the problems count them)
    table = pacsv.read_csv(tmp_path / "plots.csv").to_pydict()
    for i, source in enumerate(states.column("source").to_pylist()):
        row = int(source.removeprefix("row ")) - 1
        assert table["sensor"][row] == states.column("sensor")[i].as_py()
        assert table["time_of_day_s"][row] == states.column("time_of_day_s")[i].as_py()
        if table["sensor"][row] != "ADSB":
            assert table["range_m"][row] == states.column("plot_range_m")[i].as_py()
    # held at the bound: every track warns, and the user is told (warnings.csv has them all)
    assert summary["output"]["tracks_with_warnings"] == len(FLIGHTS)
    assert all(any("upper bound" in w for w in texts)
               for texts in summary["output"]["warnings"].values())
    printed = capsys.readouterr().out
    assert f"{len(FLIGHTS)} of {len(FLIGHTS)} track(s) reconstructed with warnings" in printed
    warned = (tmp_path / "out" / "warnings.csv").read_text().splitlines()
    assert warned[0] == "aircraft,warning" and len(warned) > len(FLIGHTS)
    code = main([str(tmp_path / "plots.csv"), "--sensors", str(d / "sensors.json"), "--out",
                 str(tmp_path / "out3"), "--no-progress", "--bounds", "v=200,30"])
    assert code == 2 and "bounds.v is inverted" in capsys.readouterr().err
    for step in ("0", "-1", "nan", "inf", "x"):  # argparse's usage error: exit 2
        with pytest.raises(SystemExit) as stop:
            main([str(tmp_path / "plots.csv"), "--sensors", str(d / "sensors.json"), "--out",
                  str(tmp_path / "out3"), "--samples", step])
        assert stop.value.code == 2
        assert f"--samples: {step!r} is not a positive number of seconds" in \
            capsys.readouterr().err
    for option, value, why in (("--workers", "-1", "is not a positive whole number"),
                               ("--workers", "0", "is not a positive whole number"),
                               ("--time-limit", "-1", "is not a number of seconds >= 0")):
        with pytest.raises(SystemExit) as stop:  # -1 workers waited for ever
            main([str(tmp_path / "plots.csv"), "--sensors", str(d / "sensors.json"), "--out",
                  str(tmp_path / "out3"), option, value])
        assert stop.value.code == 2 and f"{option}: {value!r} {why}" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([{**SENSOR_FILE[0], "lat_deg": 95.0}]))
    code = main([str(tmp_path / "plots.csv"), "--sensors", str(bad), "--out",
                 str(tmp_path / "out2"), "--no-progress"])
    assert code == 2
    assert f"sensors[0].lat_deg must be a finite number in [-90, 90] (95.0) (in {bad})" in \
        capsys.readouterr().err
    # what is not a recording, a directory as the recording or a file as --out: one line each
    text = tmp_path / "plots.txt"
    text.write_text((tmp_path / "plots.csv").read_text())
    for recording, out, message in (
            (text, tmp_path / "out4", f"recording is not an ASTERIX recording (its first bytes "
             f"{text.read_bytes()[:8].hex(' ')} are no data block header"),
            (tmp_path, tmp_path / "out4", "Is a directory"),
            (tmp_path / "plots.csv", text, f"out {text} is a file, not a directory")):
        code = main([str(recording), "--sensors", str(d / "sensors.json"), "--out", str(out),
                     "--scheduler", scheduler, "--no-progress"])
        err = capsys.readouterr().err
        assert code == 2 and message in err and "Traceback" not in err, err
    # a missing recording: said before a cluster starts (25 s of an embedded one's start
    # and close before), nothing left in --out; the corrected command then runs there
    start = time.perf_counter()
    code = main([str(tmp_path / "nope.ast"), "--sensors", str(d / "sensors.json"), "--out",
                 str(tmp_path / "out7"), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "nope.ast: No such file or directory" in err, err
    assert time.perf_counter() - start < 5.0 and not (tmp_path / "out7" / "run.json").exists()
    # what a run that stopped before any track leaves (other settings, another recording)
    # is no run to resume: the corrected command is not refused (it was, naming the files)
    left = tmp_path / "out8"
    left.mkdir()
    (left / "run.json").write_text(json.dumps(replace(run_settings.RunSettings(), method="sliding")
                                              .as_json()))
    (left / "inputs.json").write_text(json.dumps({"recording": {"name": "nope.ast"}}))
    code = main([str(tmp_path / "plots.csv"), "--sensors", str(d / "sensors.json"), "--out",
                 str(left), "--scheduler", scheduler, "--no-progress"])
    assert code == 0, capsys.readouterr().err
    assert json.loads((left / "run.json").read_text())["method"] == "refined"
    # a table of which no plot can be read: said, exit 2, and the outputs still complete
    empty = tmp_path / "empty.csv"
    empty.write_text("t,sensor,range_m,azimuth_deg\n1,NOPE,50000,10\n")
    code = main([str(empty), "--sensors", str(d / "sensors.json"), "--out",
                 str(tmp_path / "out6"), "--scheduler", scheduler, "--no-progress"])
    assert code == 2 and "no aircraft's track could be read from" in capsys.readouterr().err
    assert (tmp_path / "out6" / "tracks.csv").read_text().startswith('"aircraft","plot"')
    assert "unknown_sensor" in (tmp_path / "out6" / "problems.txt").read_text()
    # the sliding windows' settings with the refined method: refused, not stored
    code = main([str(tmp_path / "plots.csv"), "--sensors", str(d / "sensors.json"), "--out",
                 str(tmp_path / "out5"), "--window-plots", "5", "--no-progress"])
    assert code == 2 and "--window-plots set the sliding windows, which the refined method " \
        "does not use" in capsys.readouterr().err
    assert not (tmp_path / "out5" / "run.json").exists()
    # the statistics' sensors.json would overwrite the sensor file: refused, file kept
    (tmp_path / "here").mkdir()
    own = tmp_path / "here" / "sensors.json"
    own.write_text((d / "sensors.json").read_text())
    code = main(["reconstruct", str(tmp_path / "plots.csv"), "--sensors", str(own), "--out",
                 str(tmp_path / "here"), "--no-progress"])
    assert code == 2 and own.read_text() == (d / "sensors.json").read_text()
    assert "would overwrite" in capsys.readouterr().err


def test_a_table_not_in_time_order_is_sorted_not_cut(recording, tmp_path, monkeypatch):
    """Rows by aircraft (then time) or by sensor, read in batches as the command line does
    (:func:`solver.io.reading.stream`, the command line's reading): an aircraft was closed at a
    batch's end and its later rows started a new track (a tester's 60 aircraft: 70 tracks;
    here 3 for 2). Such a table is read whole and sorted, said in the problems; the tracks
    are the recording's two, with every plot. Times of day across midnight in time order are
    in order (no false alarm)."""
    import solver.io.reading as reading
    from solver.io.tables import time_disorder_s

    d, _ = recording
    (tmp_path / "long.ast").write_bytes(encode_recording(duration=600.0).data)  # > 360 s
    rows = read_recording(tmp_path / "long.ast", parse_sensors(SENSOR_FILE)).rows
    monkeypatch.setattr(reading, "STREAM_BATCH_ROWS", 200)
    keys = np.array([f"{m:06X}" for m in rows.mode_s])
    write_table(rows, tmp_path / "in_order.parquet")
    assert time_disorder_s(tmp_path / "in_order.parquet") == 0.0
    for name, order in (("in_order.parquet", None),
                        ("by_aircraft.parquet", np.lexsort((rows.t, keys))),
                        ("by_sensor.csv", np.lexsort((rows.t, rows.sensor.astype(str))))):
        if order is not None:
            write_table(rows.take(order), tmp_path / name)
        read = reading.stream(tmp_path / name, d / "sensors.json")
        tracks = list(read.tracks)
        assert sorted(t.key for t in tracks) == sorted(f"{f.address:06X}" for f in FLIGHTS)
        assert sum(len(t.table) for t in tracks) == len(rows)
        assert ("unordered_table" in read.problems.counts) == (order is not None)
    tod = tmp_path / "tod.csv"
    tod.write_text("time_of_day_s,sensor\n86390,R1\n86399.5,R1\n3.5,R1\nbad,R1\n9,R1\n")
    assert time_disorder_s(tod) == 0.0
    tod.write_text("time_of_day_s,sensor\n3.5,R1\n86390,R1\n9,R1\n100,R1\n1,R1\n")
    assert time_disorder_s(tod) == pytest.approx(99.0)


def test_the_summary_counts_the_plots_left_out(recording, tmp_path, capsys, scheduler):
    """``summary.json`` says how many plots each problem left out (``dropped``, from the
    problems' counts of what they dropped), and they add up: every data row of a table is a
    plot reconstructed or a plot left out (a row of the wrong width, a bad value, a sensor not
    in the sensor file). Printed beside the problems' counts."""
    d, _ = recording
    rows = read_recording(d / "day.ast", parse_sensors(SENSOR_FILE)).rows
    write_table(rows, tmp_path / "plots.csv")
    with open(tmp_path / "plots.csv", newline="") as f:
        table = list(csv.reader(f))
    head = table[0]
    table[5].append("surplus")                                # bad_row
    table[9][head.index("sensor")] = "R9"                     # unknown_sensor
    table[20][head.index("t")] = "soon"                       # bad_value
    with open(tmp_path / "plots.csv", "w", newline="") as f:
        csv.writer(f).writerows(table)
    code = main([str(tmp_path / "plots.csv"), "--sensors", str(d / "sensors.json"), "--out",
                 str(tmp_path / "out"), "--scheduler", scheduler, "--no-progress"])
    assert code == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["dropped"] == {"bad_row": 1, "bad_value": 1, "unknown_sensor": 1}
    assert summary["rows_in_recording"] == len(rows) - 2
    assert summary["plots"] + sum(summary["dropped"].values()) == len(rows)
    assert "bad_row 1 (1 plots left out)" in capsys.readouterr().out


def test_mode_c_is_made_geometric_by_the_aircrafts_adsb(tmp_path, capsys, scheduler):
    """An aircraft at 10 km passing 8 km abeam R1, its Mode C 250 m under its geometric height
    (a warm day), its ADS-B reporting both heights: R1's range residuals against the
    reconstruction were biased by the wrong height (about ``h dh / r``: the plots measured
    longer than the track at the pressure height gives, +112 m in the mean here) and are now
    not (measured 0.0 m); with the ADS-B's flight level only (nothing to tell the offset by)
    the bias stays, as the docs say."""
    from solver.frames import LocalFrame, slant_and_azimuth

    site = (46.0, 14.0, 300.0)
    t_adsb = np.arange(0.0, 340.0, 1.0)
    t_radar = np.arange(0.5, 340.0, 4.8)
    frame = LocalFrame(46.0, 14.0)
    geo = 10_000.0

    def at(t):
        return frame.to_geodetic(-39_000.0 + 230.0 * t, np.full(t.shape, 8_000.0))

    lat, lon = at(t_radar)
    r, az, _ = slant_and_azimuth(site, lat, lon, np.full(t_radar.shape, geo))
    fl = np.round((geo - 250.0) / (FL_M / 4)) / 4  # 25-ft Mode S altitude
    alat, alon = at(t_adsb)
    head = ["t", "sensor", "range_m", "azimuth_deg", "lat_deg", "lon_deg", "altitude_m",
            "flight_level", "mode_s"]
    radar_rows = [[f"{t:.3f}", "R1", f"{ri:.2f}", f"{np.rad2deg(ai):.5f}", "", "", "",
                   f"{fl}", "4CA2D1"] for t, ri, ai in zip(t_radar, r, az, strict=True)]
    sensors = tmp_path / "sensors.json"
    sensors.write_text(json.dumps(SENSOR_FILE))
    bias = {}
    for case, height in (("both", f"{geo}"), ("fl_only", "")):
        adsb_rows = [[f"{t:.3f}", "ADSB", "", "", f"{la:.8f}", f"{lo:.8f}", height, f"{fl}",
                      "4CA2D1"] for t, la, lo in zip(t_adsb, alat, alon, strict=True)]
        path = tmp_path / f"{case}.csv"
        with open(path, "w", newline="") as f:
            csv.writer(f).writerows([head, *sorted(radar_rows + adsb_rows,
                                                   key=lambda row: float(row[0]))])
        assert main([str(path), "--sensors", str(sensors), "--out", str(tmp_path / case),
                     "--scheduler", scheduler, "--no-progress"]) == 0
        rows = json.loads((tmp_path / case / "sensors.json").read_text())
        bias[case] = next(x for x in rows if x["sensor"] == "R1")["range_residual_mean_m"]
        moved = json.loads((tmp_path / case / "summary.json").read_text())["mode_c_offsets"]
        states = pq.read_table(tmp_path / case / "tracks.parquet").to_pydict()
        placed = np.array([h for h, sid in zip(states["plot_altitude_m"], states["sensor"],
                                               strict=True) if sid == "R1"], dtype=float)
        assert placed.size == t_radar.size  # tracks.parquet says where each plot was put
        np.testing.assert_allclose(placed, geo if case == "both" else fl * FL_M,
                                   atol=FL_M / 4)
        if case == "both":
            assert moved["tracks"] == 1 and abs(moved["median_m"] - 250.0) < FL_M / 4, moved
        else:
            assert moved is None
    assert abs(bias["both"]) < 10.0, bias
    assert bias["fl_only"] > 60.0, bias


def test_reports_on_the_ground_are_left_out_and_keep_the_radar_assessment_clean(
        tmp_path, capsys, scheduler):
    """An aircraft landing 8 km abeam R1 (70 m/s, touchdown at 200 s, braking to a 10-m/s
    taxi, parked from 300 s), noise-free plots of R1 and 1-Hz ADS-B. Rows marked
    ``on_ground`` (ADS-B's GBS, Mode S's flight status in a recording) are left out and
    counted: the flight before touchdown is reconstructed and R1's residuals are those of
    noise-free plots. The same rows unmarked are fitted as a flight at bounds.v's lowest
    speed (warned), 150-300 m off; R1's range residuals spread 79 m there (27 of its plots
    taken for wild, the ADS-B residuals 118 m RMS) until such stretches were left out of the
    statistics."""
    from solver.frames import LocalFrame, slant_and_azimuth

    site, frame, t_touch = (46.0, 14.0, 300.0), LocalFrame(46.0, 14.0), 200.0

    def at(t):
        dt = np.clip(t - t_touch, 0.0, 30.0)  # braking at 2 m/s^2, then 10 m/s to 300 s
        along = (70.0 * np.minimum(t, t_touch) + 70.0 * dt - dt**2
                 + 10.0 * np.clip(np.minimum(t, 300.0) - t_touch - 30.0, 0.0, None))
        lat, lon = frame.to_geodetic(-14_000.0 + along, np.full(t.shape, 8_000.0))
        return lat, lon, 300.0 + 3.0 * np.clip(t_touch - t, 0.0, None)

    t_radar, t_adsb = np.arange(0.5, 500.0, 4.8), np.arange(0.0, 500.0, 1.0)
    lat, lon, h = at(t_radar)
    r, az, _ = slant_and_azimuth(site, lat, lon, h)
    rows = [[f"{t:.3f}", "R1", f"{ri:.2f}", f"{np.rad2deg(ai):.5f}", "", "", f"{hi:.1f}",
             "4CA2D1", str(t >= t_touch).lower()]
            for t, ri, ai, hi in zip(t_radar, r, az, h, strict=True)]
    rows += [[f"{t:.3f}", "ADSB", "", "", f"{la:.8f}", f"{lo:.8f}", f"{hi:.1f}", "4CA2D1",
              str(t >= t_touch).lower()] for t, la, lo, hi in zip(t_adsb, *at(t_adsb),
                                                                  strict=True)]
    rows.sort(key=lambda row: float(row[0]))
    head = ["t", "sensor", "range_m", "azimuth_deg", "lat_deg", "lon_deg", "altitude_m",
            "mode_s", "on_ground"]
    sensors = tmp_path / "sensors.json"
    sensors.write_text(json.dumps(SENSOR_FILE))
    ground = int(np.sum(t_radar >= t_touch) + np.sum(t_adsb >= t_touch))
    stats = {}
    for case, width in (("marked", len(head)), ("unmarked", len(head) - 1)):
        path = tmp_path / f"{case}.csv"
        with open(path, "w", newline="") as f:
            csv.writer(f).writerows([head[:width], *[row[:width] for row in rows]])
        assert main([str(path), "--sensors", str(sensors), "--out", str(tmp_path / case),
                     "--scheduler", scheduler, "--no-progress"]) == 0
        summary = json.loads((tmp_path / case / "summary.json").read_text())
        stats[case] = {x["sensor"]: x for x in json.loads(
            (tmp_path / case / "sensors.json").read_text())}
        if case == "marked":
            assert summary["dropped"] == {"on_ground": ground}
            assert summary["plots"] == len(rows) - ground
            states = pq.read_table(tmp_path / case / "tracks.parquet").to_pydict()
            assert max(states["t"]) < t_touch
    marked, unmarked = stats["marked"], stats["unmarked"]
    assert marked["R1"]["range_residual_sigma_m"] < 1.0, marked["R1"]
    assert marked["ADSB"]["position_residual_rms_m"] < 1.0, marked["ADSB"]
    # unmarked, the track runs on through the taxi at bounds.v's lowest speed, warned; the
    # statistics leave that stretch out (solver.refine.gate.misfit_stretches), counted as
    # plots where the track is no reference, not as the radar's wild plots
    assert unmarked["R1"]["plots_no_reference"] >= np.sum(t_radar >= t_touch), unmarked["R1"]
    assert unmarked["R1"]["plots_wild"] < 5, unmarked["R1"]
    assert unmarked["R1"]["range_residual_sigma_m"] < 1.0, unmarked["R1"]
    with open(tmp_path / "unmarked" / "warnings.csv", newline="") as f:
        assert any("speed at its lower bound" in w["warning"] for w in csv.DictReader(f))
    # sensors.png pools the plots sensors.json does (it took the gated ones alone: 0 wild and
    # a 97.5-m sigma in the figure where the table said 27 wild and 79.1 m)
    from solver.assessment import sensor_residuals

    r1 = next(x for x in sensor_residuals(tmp_path / "unmarked") if x.sensor == "R1")
    assert unmarked["R1"]["plots_wild"] == r1.wild
    assert unmarked["R1"]["plots_no_reference"] == r1.no_reference > 0
    mean, sigma, _, _ = r1.bias_sigma()
    assert mean == pytest.approx(unmarked["R1"]["range_residual_mean_m"], abs=1e-6)
    assert sigma == pytest.approx(unmarked["R1"]["range_residual_sigma_m"], abs=1e-6)
    assert "on_ground" in capsys.readouterr().out


def test_another_aircraft_under_a_reused_track_number_is_told_apart(
        tmp_path, capsys, scheduler):
    """R1's track 12 is Mode S aircraft 4CA2D1 (its ADS-B throughout) until R1 loses it at
    250 s; from 310 s R1 gives track 12 to an aircraft squawking 7000 without Mode S, 60 km
    away (a tester's recording; noise-free plots here). The track lent its address to those
    plots: they came out in the Mode S aircraft's track, given no weight, and R1's range bias
    read -47 km (sigma 45 km). Now that aircraft comes out apart (``4CA2D1~2``, reported).
    Under one key of the user's own (never told apart) the plots out of reach are given no
    weight, said so, and left out of R1's statistics."""
    from solver.frames import LocalFrame, slant_and_azimuth

    site, frame = (46.0, 14.0, 300.0), LocalFrame(46.0, 14.0)

    def at(t, x0, z0, h, vx, vz):
        lat, lon = frame.to_geodetic(x0 + vx * t, z0 + vz * t)
        return lat, lon, np.full(t.shape, h)

    own = (-30e3, -20e3, 9000.0, 150.0, 180.0)
    other = (30e3, 10e3, 5000.0, -100.0, -100.0)
    t1, t2, ta = np.arange(0.3, 250.0, 4.8), np.arange(310.3, 600.0, 4.8), np.arange(0.0, 600.0)
    rows = []
    for t, flight, code, address in ((t1, own, "", "4CA2D1"), (t2, other, "7000", "")):
        r, az, _ = slant_and_azimuth(site, *at(t, *flight))
        rows += [[f"{ti:.3f}", "R1", f"{ri:.2f}", f"{np.rad2deg(ai):.6f}", "", "", address,
                  code, "12"] for ti, ri, ai in zip(t, r, az, strict=True)]
    lat, lon, _ = at(ta, *own)
    rows += [[f"{ti:.3f}", "ADSB", "", "", f"{la:.8f}", f"{lo:.8f}", "4CA2D1", "", ""]
             for ti, la, lo in zip(ta, lat, lon, strict=True)]
    rows.sort(key=lambda row: float(row[0]))
    head = ["t", "sensor", "range_m", "azimuth_deg", "lat_deg", "lon_deg", "mode_s", "mode_3a",
            "track_number", "aircraft"]
    sensors = tmp_path / "sensors.json"
    sensors.write_text(json.dumps(SENSOR_FILE))
    r1 = {}
    for case, key in (("keys", ""), ("user", "A1")):
        path = tmp_path / f"{case}.csv"
        with open(path, "w", newline="") as f:
            csv.writer(f).writerows([head, *[[*row, key] for row in rows]])
        out = tmp_path / case
        assert main([str(path), "--sensors", str(sensors), "--out", str(out), "--scheduler",
                     scheduler, "--no-progress"]) == 0
        summary = json.loads((out / "summary.json").read_text())
        r1[case] = {x["sensor"]: x for x in summary["sensors"]}["R1"]
        with open(out / "warnings.csv", newline="") as f:
            warned = [w["warning"] for w in csv.DictReader(f)]
        states = pq.read_table(out / "tracks.parquet", columns=["aircraft"]).to_pydict()
        if case == "keys":
            assert summary["problems"].get("aircraft_apart") == 1
            assert sorted(set(states["aircraft"])) == ["4CA2D1", "4CA2D1~2"]
            assert states["aircraft"].count("4CA2D1~2") == t2.size
            assert r1[case]["plots_wild"] == 0
        else:
            assert set(states["aircraft"]) == {"A1"}
            assert r1[case]["plots_wild"] == t2.size
            assert any(f"{t2.size} plot(s) out of reach" in w and "another aircraft" in w
                       for w in warned), warned
        assert r1[case]["plots"] == t1.size + t2.size
        assert abs(r1[case]["range_residual_mean_m"]) < 5.0, r1[case]
        assert r1[case]["range_residual_sigma_m"] < 5.0, r1[case]


def test_known_offsets_reach_the_tracks_a_radar_sees_alone(tmp_path, capsys, scheduler):
    """R1 reports ranges 150 m long and azimuths 0.2 deg clockwise. A run with its
    ``estimate_bias`` finds them on the aircraft ADS-B also sees, but the aircraft R1 sees
    alone (no Mode S: a track number) keeps them (175 m at 50 km: not observable alone; a
    walkthrough helper). Given back as the sensor file's known offsets they are taken off
    every R1 plot: the lone track within 25 m of the truth (noise-free plots: measured
    0.001 m; 190 m before)."""
    from solver.frames import LocalFrame, slant_and_azimuth

    site = (46.0, 14.0, 300.0)
    frame = LocalFrame(46.0, 14.0)
    t_radar = np.arange(0.5, 300.0, 4.8)
    t_adsb = np.arange(0.0, 300.0, 1.0)
    geo = 9_000.0
    flights = {"A": (-30_000.0, 40_000.0, 200.0, 0.0), "B": (20_000.0, -45_000.0, 0.0, 210.0)}

    def at(name, t):
        x0, z0, vx, vz = flights[name]
        return frame.to_geodetic(x0 + vx * t, z0 + vz * t)

    head = ["t", "sensor", "range_m", "azimuth_deg", "lat_deg", "lon_deg", "altitude_m",
            "mode_s", "track_number"]
    rows = []
    for name in flights:
        lat, lon = at(name, t_radar)
        r, az, _ = slant_and_azimuth(site, lat, lon, np.full(t_radar.shape, geo))
        rows += [[f"{t:.3f}", "R1", f"{ri + 150.0:.2f}", f"{np.rad2deg(ai) + 0.2:.5f}", "", "",
                  f"{geo}", "4CA2D1" if name == "A" else "", "" if name == "A" else "7"]
                 for t, ri, ai in zip(t_radar, r, az, strict=True)]
    lat, lon = at("A", t_adsb)
    rows += [[f"{t:.3f}", "ADSB", "", "", f"{la:.8f}", f"{lo:.8f}", f"{geo}", "4CA2D1", ""]
             for t, la, lo in zip(t_adsb, lat, lon, strict=True)]
    table = tmp_path / "plots.csv"
    with open(table, "w", newline="") as f:
        csv.writer(f).writerows([head, *sorted(rows, key=lambda row: float(row[0]))])
    r1 = {"id": "R1", "kind": "radar", "lat_deg": 46.0, "lon_deg": 14.0, "height_m": 300.0,
          "range_error_m": 150.0, "azimuth_error_deg": 0.24}
    adsb = {"id": "ADSB", "kind": "position", "position_sigma_m": 30.0}
    err = {}
    for run, entry in (("estimated", {**r1, "estimate_bias": True}), ("known", None)):
        if entry is None:  # the first run's estimates, given back as known offsets
            found = next(x for x in json.loads((tmp_path / "estimated" / "sensors.json")
                                               .read_text()) if x["sensor"] == "R1")
            entry = {**r1, "range_offset_m": found["range_bias_m"],
                     "azimuth_offset_deg": found["azimuth_bias_deg"]}
            assert abs(found["range_bias_m"] - 150.0) < 15.0, found
            assert abs(found["azimuth_bias_deg"] - 0.2) < 0.02, found
        sensors = tmp_path / f"{run}.json"
        sensors.write_text(json.dumps([entry, adsb]))
        capsys.readouterr()
        assert main([str(table), "--sensors", str(sensors), "--out", str(tmp_path / run),
                     "--scheduler", scheduler, "--no-progress"]) == 0
        if run == "estimated":
            assert "add them to its sensor-file entry's range_offset_m" in capsys.readouterr().out
        states = pq.read_table(tmp_path / run / "tracks.parquet").to_pydict()
        lone = np.array([a == "R1:track:7" for a in states["aircraft"]])
        t = np.array(states["t"])[lone]
        lat, lon = at("B", t)
        x, z = frame.to_plane(np.array(states["lat_deg"])[lone],
                              np.array(states["lon_deg"])[lone])
        tx, tz = frame.to_plane(lat, lon)
        err[run] = float(np.sqrt(np.mean((x - tx) ** 2 + (z - tz) ** 2)))
    assert err["estimated"] > 150.0 and err["known"] < 25.0, err


def test_date_gives_the_captures_utc_times_and_overrides_the_captures_own(
        recording, tmp_path, capsys, scheduler):
    """The recording across midnight as raw ASTERIX with ``--date`` and as a pcap capture
    stamped by a right clock without it: the same ``time_utc`` in tracks.parquet (each row's
    ``t`` on 2023-11-14, Python's datetime as the reference: those past midnight on the 15th),
    in tracks.csv (ISO 8601 ending in Z), the GeoJSON lines and manoeuvres.csv's header; the
    capture with another ``--date`` is timed on it, a ``date_override`` problem naming both in
    problems.txt and the summary (it exited 2: a host clock whole days off could not be
    corrected)."""
    import datetime as dt

    from test_io_asterix import CAPTURE_DAY, pcap

    d, enc = recording
    (tmp_path / "day.ast").write_bytes(b"".join(enc.blocks))
    (tmp_path / "day.pcap").write_bytes(pcap(enc.blocks))
    got = {}
    for name, extra in (("day.ast", ["--date", CAPTURE_DAY]), ("day.pcap", [])):
        out = tmp_path / f"out-{name}"
        assert main([str(tmp_path / name), "--sensors", str(d / "sensors.json"), "--out",
                     str(out), "--scheduler", scheduler, "--no-progress", *extra]) == 0
        table = pq.read_table(out / "tracks.parquet").sort_by([("aircraft", "ascending"),
                                                              ("t", "ascending")])
        assert table.schema.field("time_utc").type == pa.timestamp("us", tz="UTC")
        utc = table.column("time_utc").to_pylist()
        midnight = dt.datetime(2023, 11, 14, tzinfo=dt.UTC)
        assert utc == [midnight + dt.timedelta(seconds=t) for t in table.column("t").to_pylist()]
        assert utc[0].date() == dt.date(2023, 11, 14) and utc[-1].date() == dt.date(2023, 11, 15)
        with open(out / "tracks.csv", newline="") as f:
            text = [r["time_utc"] for r in csv.DictReader(f)]
        assert sorted(text) == sorted(u.strftime("%Y-%m-%dT%H:%M:%S.%fZ") for u in utc)
        feature = json.loads((out / "tracks.geojsonl").read_text().splitlines()[0])
        props = feature["properties"]
        assert props["time_utc_start"] == (midnight + dt.timedelta(seconds=props["t_start"])
                                           ).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
        assert (out / "manoeuvres.csv").read_text().splitlines()[0].endswith(
            '"time_utc_start","time_utc_end"')
        assert json.loads((out / "summary.json").read_text())["recording_date"] == CAPTURE_DAY
        got[name] = (table.column("aircraft").to_pylist(), utc)
    assert got["day.ast"] == got["day.pcap"]
    capsys.readouterr()
    out = tmp_path / "other-day"
    assert main([str(tmp_path / "day.pcap"), "--sensors", str(d / "sensors.json"), "--out",
                 str(out), "--scheduler", scheduler, "--no-progress",
                 "--date", "2023-11-15"]) == 0
    assert "date_override 1" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["recording_date"] == "2023-11-15" and summary["problems"] == {
        "date_override": 1}
    assert ("date_override at date: the date given, 2023-11-15, overrides 2023-11-14 (from its "
            "capture's packet times)") in (out / "problems.txt").read_text()
    utc = pq.read_table(out / "tracks.parquet").sort_by([("aircraft", "ascending"),
                                                         ("t", "ascending")]).column("time_utc")
    assert utc.to_pylist() == [u + dt.timedelta(days=1) for u in got["day.pcap"][1]]
    with pytest.raises(SystemExit):  # argparse: not a calendar day
        main([str(tmp_path / "day.ast"), "--sensors", str(d / "sensors.json"), "--out",
              str(tmp_path / "bad"), "--date", "2023-02-29"])
    assert "'2023-02-29' is not a date YYYY-MM-DD" in capsys.readouterr().err


def test_a_recording_not_in_time_order_is_sorted_not_split(recording, tmp_path, monkeypatch):
    """Two ASTERIX recordings concatenated (``cat later.ast earlier.ast``, raw and as a pcap
    capture), streamed in small units as the command line does: each aircraft came out in
    overlapping pieces (10 tracks for 2, nothing reported; a fuzz helper). The sampled times
    show the backward jump: read whole and sorted, said in the problems, the two tracks with
    every plot. A recording in time order across midnight (the fixture's) is streamed with no
    alarm; a stream that still gets plots late (the sampling bypassed) counts each one."""
    from test_io_asterix import SENSORS, pcap

    import solver.io.reading as reading
    from solver.io.asterix import iter_recording, time_disorder_s
    from solver.io.split import split_stream

    d, _ = recording
    blocks = encode_recording(duration=1200.0).blocks
    half = len(blocks) // 2
    swapped = blocks[half:] + blocks[:half]
    (tmp_path / "cat.ast").write_bytes(b"".join(swapped))
    (tmp_path / "cat.pcap").write_bytes(pcap(swapped))
    monkeypatch.setattr(reading, "STREAM_CHUNK_BYTES", 4096)
    n = len(read_recording(tmp_path / "cat.ast", SENSORS).rows)
    for name in ("cat.ast", "cat.pcap"):
        assert 600 < time_disorder_s(tmp_path / name, SENSORS, every_bytes=4096) < 1200
        read = reading.stream(tmp_path / name, d / "sensors.json")
        tracks = list(read.tracks)
        assert sorted(t.key for t in tracks) == sorted(f"{f.address:06X}" for f in FLIGHTS)
        assert sum(len(t.table) for t in tracks) == n
        assert all(np.all(np.diff(t.table.t) > 0) for t in tracks)
        assert "unordered_recording" in read.problems.counts
        assert "late_plots" not in read.problems.counts
    assert time_disorder_s(d / "day.ast", SENSORS, every_bytes=64) == 0.0
    read = reading.stream(d / "day.ast", d / "sensors.json")
    assert len(list(read.tracks)) == 2 and "unordered_recording" not in read.problems.counts
    problems = Problems()
    late = list(split_stream((p.rows for p in iter_recording(tmp_path / "cat.ast", SENSORS,
                                                             chunk_bytes=4096)),
                             SENSORS, problems=problems))
    assert len(late) > 2
    first_half = sum(1 for p in encode_recording(duration=1200.0).plots if p["tod"] < 36_600)
    assert problems.counts["late_plots"] == first_half
    assert problems.of_kind("late_plots")[0].where.startswith("byte ")


@pytest.mark.parametrize("detected", [0.95, 0.7, 0.5, 0.35, 0.2])
def test_scan_period_from_a_track_that_misses_scans(detected):
    """A 4-s radar detecting a share of its scans (times jittered by 50 ms, a few split
    plots): the period is 4 s within 1 %, and the sensor statistics' detection rate is the
    share (its split plots counted: 1/40 more; the median interval gave 5 s at half the scans
    missed, 8 s at 60 %)."""
    from solver.io.scans import scan_step
    from solver.plots import PlotTable
    from solver.sensor_stats import SensorStats, sensor_spans

    rng = np.random.default_rng(int(detected * 100))
    t = np.arange(0.0, 3000.0, 4.0) + rng.normal(0, 0.05, 750)
    t = t[rng.random(750) < detected]
    t = np.sort(np.concatenate([t, t[::40] + 0.3]))  # split plots
    period = scan_step(np.diff(t))
    assert period == pytest.approx(4.0, rel=0.01)
    sensors = parse_sensors(SENSOR_FILE)
    radar = sensors.sensors[0]
    table = PlotTable.build([radar], t, np.zeros(t.size, int), range_m=np.full(t.size, 5e4),
                            azimuth_rad=np.zeros(t.size))
    spans = sensor_spans(table)[radar.id]
    assert spans["median_step_s"] == period
    stats = SensorStats(sensors, {})
    stats.add([{"id": radar.id, "kind": "radar", "plots": t.size, "plots_gated": 0, **spans,
                "range_residual_mean_m": 0.0, "range_residual_rms_m": 50.0,
                "azimuth_residual_mean_rad": 0.0, "azimuth_residual_rms_rad": 1e-3,
                "position_residual_rms_m": None, "range_bias_m": None,
                "azimuth_bias_rad": None, "time_bias_s": None}])
    row = {r["sensor"]: r for r in stats.rows()}[radar.id]
    assert row["detection_rate"] == pytest.approx(detected * (1 + 1 / 40), abs=0.03)


@pytest.mark.parametrize("detected", [0.9, 0.5])
def test_a_hole_in_coverage_is_no_missed_detection(detected):
    """A 4-s radar detecting a share of its scans, and the same with 150 s out of its coverage
    in the middle of the track (the aircraft beyond range while ADS-B follows it): the hole
    counted apart (``coverage_holes``, ``coverage_hole_s``), the detection rate the share in
    both (the hole, counted as 37 missed scans, read 0.85 for 0.9, 0.47 for 0.5); runs of
    misses the rate explains are no holes (none in 20 tracks without one)."""
    from solver.plots import PlotTable
    from solver.sensor_stats import SensorStats, sensor_spans

    sensors = parse_sensors(SENSOR_FILE)
    radar = sensors.sensors[0]
    rng = np.random.default_rng(int(detected * 10))

    def row(t: np.ndarray) -> dict:
        table = PlotTable.build([radar], t, np.zeros(t.size, int),
                                range_m=np.full(t.size, 5e4), azimuth_rad=np.zeros(t.size))
        stats = SensorStats(sensors, {})
        stats.add([{"id": radar.id, "kind": "radar", "plots": t.size, "plots_gated": 0,
                    **sensor_spans(table)[radar.id], "range_residual_mean_m": 0.0,
                    "range_residual_rms_m": 50.0, "azimuth_residual_mean_rad": 0.0,
                    "azimuth_residual_rms_rad": 1e-3, "position_residual_rms_m": None,
                    "range_bias_m": None, "azimuth_bias_rad": None, "time_bias_s": None}])
        return {r["sensor"]: r for r in stats.rows()}[radar.id]

    scans = np.arange(0.0, 3000.0, 4.0)
    for _ in range(20):
        t = scans[rng.random(scans.size) < detected]
        whole = row(t)
        assert whole["coverage_holes"] == 0 and whole["coverage_hole_s"] == 0.0
        assert whole["detection_rate"] == pytest.approx(t.size / (t[-1] - t[0] + 4.0) * 4.0)
    seen = t[(t < 1400.0) | (t > 1550.0)]
    holed = row(seen)
    assert holed["coverage_holes"] == 1 and 150.0 <= holed["coverage_hole_s"] <= 180.0
    assert holed["detection_rate"] == pytest.approx(detected, abs=0.05)
    # split plots (a second plot in 40 % of the scans) are no more detections: no hole (a
    # reviewer's 0.6 radar read holes in 205 of 300 tracks)
    for _ in range(20):
        t = scans[rng.random(scans.size) < detected]
        split = np.sort(np.concatenate([t, t[rng.random(t.size) < 0.4] + 0.3]))
        assert row(split)["coverage_holes"] == 0


def test_python_m_submits_the_importable_task(recording, tmp_path, monkeypatch):
    """``python -m solver.cli`` runs the module as ``__main__``; its task must still be
    ``solver.track_task.assess_track``, pickled by reference (a ``__main__`` function is
    pickled by value, and so is every result's class): the worker then imports
    ``solver.track_task``, and not the command line's module."""
    from distributed import Client, LocalCluster

    d, _ = recording
    root = Path(__file__).resolve().parent.parent
    monkeypatch.setenv("TRAJRECON_COMPILE", "0")  # the worker interprets: same results
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster, Client(cluster) as client:
        assert not any(client.run(lambda: "solver.track_task" in sys.modules).values())
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            [str(root), *filter(None, [os.environ.get("PYTHONPATH")])])}
        done = subprocess.run(
            [sys.executable, "-m", "solver.cli", str(d / "day.ast"), "--sensors",
             str(d / "sensors.json"), "--out", str(tmp_path / "out"), "--scheduler",
             cluster.scheduler_address, "--no-progress"], cwd=root, env=env,
            capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        assert all(client.run(lambda: "solver.track_task" in sys.modules).values())
        assert not any(client.run(lambda: "solver.cli" in sys.modules).values())
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["done"] == len(FLIGHTS)


def test_key_groups_select_what_a_scan_per_key_selects():
    from solver.outputs import _key_groups

    rng = np.random.default_rng(16)
    keys = np.array([f"{v:06X}" for v in rng.integers(0, 7, 500)], dtype=object)
    expected = [(k, np.flatnonzero(keys == k)) for k in dict.fromkeys(keys.tolist())]
    got = list(_key_groups(keys))
    assert [k for k, _ in got] == [k for k, _ in expected]
    for (_, a), (_, b) in zip(got, expected, strict=True):
        assert np.array_equal(a, b)
    assert list(_key_groups(keys[:0])) == []


def test_sigterm_closes_the_cluster_and_the_same_command_resumes(tmp_path):
    """A batch scheduler's or a container's stop (SIGTERM to the command line alone): the
    embedded cluster is closed (no worker process left, no leaked semaphore), the exit status
    is 143 and the message names the finished tracks kept; the same command then does the
    rest, every track once. The stop comes after the first commit, mid-run or (on a fast
    machine, all tracks in one commit) while the outputs are written: the same checks hold."""
    import signal
    import time

    import psutil
    from test_io_asterix import Flight

    flights = tuple(Flight(0x400000 + k, 2_000.0 * k, -1_500.0 * k, 180.0 - 5 * k, 60.0,
                           300.0 + k, (110 + k, 210 + k)) for k in range(8))
    enc = encode_recording(duration=150.0, flights=flights)
    (tmp_path / "day.ast").write_bytes(enc.data)
    (tmp_path / "sensors.json").write_text(json.dumps(SENSOR_FILE))
    out = tmp_path / "out"
    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(root), *filter(None, [os.environ.get("PYTHONPATH")])])}
    cmd = [sys.executable, "-m", "solver.cli", str(tmp_path / "day.ast"), "--sensors",
           str(tmp_path / "sensors.json"), "--out", str(out), "--workers", "1", "--no-progress"]

    def ledger() -> list[str]:
        path = out / "progress.jsonl"
        text = path.read_text() if path.exists() else ""
        return [json.loads(line)["aircraft"] for line in text.splitlines() if line.endswith("}")]

    proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        waited = time.monotonic() + 180
        while not ledger():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < waited, "no track finished in 180 s"
            time.sleep(0.05)
        children = psutil.Process(proc.pid).children(recursive=True)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    kept = ledger()  # all of them when the stop came after the last commit (tracks are
    assert 1 <= len(kept) <= len(flights)  # committed every 5 s): then it stopped the outputs
    assert f"stopped by SIGTERM; {len(kept)} finished tracks are kept in {out}" in err
    assert "leaked" not in err and "Traceback" not in err, err
    assert "CancelledError" not in err, err  # the workers' line per cancelled track
    assert children, "the embedded cluster's processes"
    _, alive = psutil.wait_procs(children, timeout=10)
    assert not alive, alive

    assert main(cmd[3:]) == 0  # the same command, in this process
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["skipped"], summary["done"]) == (len(kept), len(flights) - len(kept))
    assert sorted(ledger()) == sorted(f"{f.address:06X}" for f in flights)


def test_named_aircraft_alone_are_reconstructed(recording, tmp_path, capsys, scheduler):
    """`--aircraft`: only the named tracks (a Mode S address in either case); a name the
    recording does not hold: the others written, exit status 2 naming it."""
    d, _ = recording
    key = f"{FLIGHTS[1].address:06X}"
    args = [str(d / "day.ast"), "--sensors", str(d / "sensors.json"), "--scheduler", scheduler,
            "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "one"), "--aircraft", key.lower()]) == 0
    summary = json.loads((tmp_path / "one" / "summary.json").read_text())
    assert summary["tracks"] == summary["done"] == 1 and summary["aircraft"] == [key]
    assert summary["aircraft_not_found"] == []
    keys = set(pq.read_table(tmp_path / "one" / "tracks.parquet").column("aircraft").to_pylist())
    assert keys == {key}
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "two"), "--aircraft", key, "ABC123"]) == 2
    assert "not in the recording" in capsys.readouterr().err
    summary = json.loads((tmp_path / "two" / "summary.json").read_text())
    assert summary["done"] == 1 and summary["aircraft_not_found"] == ["ABC123"]


def test_sliding_windows_reconstruct_the_recording(recording, tmp_path, capsys, scheduler):
    """`--method sliding`: the seed's windows over every sensor's plots of each aircraft (two
    radars and ADS-B on the earth, across midnight): every track within 60 m of its flight
    (exact plots), no covariance, the method in the summary and each track's diagnostics."""
    d, enc = recording
    out = tmp_path / "sliding"
    args = [str(d / "day.ast"), "--sensors", str(d / "sensors.json"), "--scheduler", scheduler,
            "--no-progress", "--out", str(out), "--method", "sliding"]
    assert main([*args, "--window-plots", "4", "--criterion", "R1"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "sliding" and summary["done"] == len(FLIGHTS)
    assert summary["window"] == {"plots": 4, "trial_step_s": 5.0} and summary["criterion"] == "R1"
    assert f"({len(FLIGHTS)} reconstructed by sliding, 0 failed" in capsys.readouterr().out
    table = pq.read_table(out / "tracks.parquet")
    assert np.isnan(table.column("cov_x_x").to_numpy(zero_copy_only=False)).all()
    keys = table.column("aircraft").to_numpy(zero_copy_only=False).astype(str)
    t_all = table.column("t").to_numpy()
    for k, f in enumerate(FLIGHTS):
        sel = keys == f"{f.address:06X}"
        t = t_all[sel]
        lat, lon, _ = f.at(t - t.min() + _first_t(enc, k))
        dy = (table.column("lat_deg").to_numpy()[sel] - lat) * 111_000
        dx = (table.column("lon_deg").to_numpy()[sel] - lon) * 111_000 * np.cos(
            np.deg2rad(lat))
        assert np.hypot(dx, dy).max() < 60.0
    lines = [json.loads(x) for x in (out / "progress.jsonl").read_text().splitlines()]
    assert {x["diagnostics"]["method"] for x in lines if "diagnostics" in x} == {"sliding"}
    assert {x["diagnostics"]["criterion"] for x in lines if "diagnostics" in x} == {"R1"}
    # a rerun resumes only the same windows; bad ones are named
    capsys.readouterr()
    assert main([*args, "--window-plots", "3", "--criterion", "R1"]) == 2
    assert "window {'plots': 4" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "bad"), "--window-plots", "1"]) == 2
    assert "window.plots" in capsys.readouterr().err


def test_a_selection_takes_a_keys_later_pieces():
    from types import SimpleNamespace

    from solver.io.reading import Selection

    chosen = Selection(["4ca2d1", "R1:track:101"])
    names = ["4CA2D1", "3C6DD4", "4CA2D1#2", "4CA2D12", "R1:track:101#3", "R1:track:1011"]
    got = [t.key for t in chosen.filter(iter(SimpleNamespace(key=k, members=())
                                             for k in names))]
    assert got == ["4CA2D1", "4CA2D1#2", "R1:track:101#3"]
    assert chosen.missing() == []
    assert Selection(["ABC123"]).missing() == ["ABC123"]
    assert list(Selection(None).filter(iter(names))) == names


def test_sensor_statistics_pool_a_position_sensors_time_offset():
    """A position sensor's per-track time offsets (its latency) pool to their median; it has
    no range or azimuth offset."""
    from solver.sensor_stats import SensorStats

    stats = SensorStats(parse_sensors(SENSOR_FILE), {})
    for k, lag in enumerate((0.9, 1.1, 1.0)):
        stats.add([{"id": "ADSB", "kind": "position", "plots": 50, "plots_gated": 0,
                    "range_residual_mean_m": None, "position_residual_rms_m": 20.0,
                    "range_bias_m": None, "azimuth_bias_rad": None, "time_bias_s": lag,
                    "span_s": 250.0, "median_step_s": 5.0 + k}])
    row = {r["sensor"]: r for r in stats.rows()}["ADSB"]
    assert row["time_bias_s"] == pytest.approx(1.0)
    assert row["range_bias_m"] is None and row["azimuth_bias_deg"] is None


def test_a_sensors_offsets_pool_by_precision_against_one_time_reference():
    """A tester's recording: R1's offsets pooled as the plain median of its tracks' (a track
    whose offsets are barely observable, +-184 m, counting as much as a +-7 m one), without a
    sigma; and its time offset mixed two references, the ADS-B's on tracks with ADS-B not
    estimating (-0.56 s: the radar against the ADS-B's latency) and the radars' mean on tracks
    of two radars alone (-0.19 s). Now a median weighted by the inverse variances, with its
    sigma, the time from the tracks with a sensor that kept its own where there are any."""
    from solver.sensor_stats import SensorStats, pooled_offsets, weighted_median

    spec = [{**SENSOR_FILE[0], "estimate_bias": True}, {**SENSOR_FILE[1], "estimate_bias": True},
            SENSOR_FILE[2]]
    stats = SensorStats(parse_sensors(spec), {})

    def report(sid, rng_m, rng_sd, t_s, adsb):
        r1 = {"id": sid, "kind": "radar", "plots": 100, "plots_gated": 0,
              "range_residual_mean_m": None, "position_residual_rms_m": None,
              "range_bias_m": rng_m, "range_bias_sigma_m": rng_sd,
              "azimuth_bias_rad": np.deg2rad(0.05), "azimuth_bias_sigma_rad": np.deg2rad(0.01),
              "time_bias_s": t_s, "time_bias_sigma_s": 0.05, "span_s": 400.0}
        return [r1] + ([{"id": "ADSB", "kind": "position", "plots": 80, "plots_gated": 0,
                         "range_residual_mean_m": None, "position_residual_rms_m": 20.0,
                         "range_bias_m": None, "azimuth_bias_rad": None,
                         "time_bias_s": None}] if adsb else [])

    for k in range(3):  # precise, with ADS-B: the radar against the ADS-B's time
        stats.add(report("R1", 120.0 + k, 7.0, -0.55 + 0.01 * k, True))
    for v in (300.0, -60.0, 250.0, 0.0):  # two radars alone: vague offsets (within their
        stats.add(report("R1", v, 184.0, -0.19, False))  # sigmas), time against their mean
    row = {r["sensor"]: r for r in stats.rows()}["R1"]
    assert row["range_bias_m"] == 121.0 and row["offset_tracks"] == 7
    assert row["range_bias_sigma_m"] == pytest.approx(1.2533 / np.sqrt(
        3 / 7.0**2 + 4 / 184.0**2), rel=1e-9)
    assert row["time_bias_s"] == pytest.approx(-0.54)  # the ADS-B tracks' alone
    assert row["time_bias_sigma_s"] == pytest.approx(1.2533 * 0.05 / np.sqrt(3))
    # tracks scattered beyond their sigmas (each aircraft's ADS-B latency its own: a tester's
    # radar had a reduced chi-square of 10.7 and a time sigma 3x small): scaled by its root
    scattered = np.array([[1, np.nan, np.nan, t, np.nan, np.nan, 0.02]
                          for t in (-0.40, -0.55, -0.70, -0.50)])
    got = pooled_offsets(scattered, radar=False)
    t = scattered[:, 3]
    chi2 = np.sum((t - t.mean()) ** 2 / 0.02**2) / 3
    assert chi2 > 10
    assert got["time_bias_sigma_s"] == pytest.approx(1.2533 * 0.02 / 2 * np.sqrt(chi2))
    assert row["time_bias_reference"] == "the sensors not estimating their offsets"
    assert row["azimuth_bias_deg"] == pytest.approx(0.05)
    # one or two tracks: their weighted mean (the lower median of two read 100 for 100 and
    # 120, a reviewer's); an even count of equal weights: the middle two's midpoint
    two = np.array([[1, 100.0, 0.0, -0.5, 10.0, 1e-3, 0.05], [1, 120.0, 0.0, -0.6, 10.0, 1e-3,
                                                                0.05]])
    got = pooled_offsets(two, radar=True)
    assert got["range_bias_m"] == pytest.approx(110.0)
    # 10 / sqrt(2), times sqrt(2): the two lie 2 of their sigmas apart (chi-square 2)
    assert got["range_bias_sigma_m"] == pytest.approx(10.0)
    assert got["time_bias_s"] == pytest.approx(-0.55)
    assert weighted_median(np.array([0.0, 10.0, 20.0, 30.0]), np.ones(4)) == 15.0
    assert weighted_median(np.array([0.0, 10.0, 20.0]), np.array([1.0, 1.0, 3.0])) == 20.0


def test_a_rerun_reports_the_tracks_earlier_runs_failed(recording, tmp_path, capsys, scheduler):
    """A resumed run keeps earlier failures in view: exit status 1 and their reasons until
    `--retry-failed` redoes them; `output` in summary.json is the whole directory's state."""
    d, _ = recording
    key = f"{FLIGHTS[0].address:06X}"
    args = [str(d / "day.ast"), "--sensors", str(d / "sensors.json"), "--out",
            str(tmp_path / "out"), "--scheduler", scheduler, "--no-progress", "--aircraft", key]
    assert main([*args, "--time-limit", "0.001"]) == 1
    capsys.readouterr()
    assert main(args) == 1  # nothing redone: the failure stays
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert (summary["failed"], summary["skipped"]) == (0, 1)
    assert summary["output"]["tracks_failed"] == 1
    assert summary["output"]["failures"][key].startswith("DeadlineExceeded")
    assert "1 track(s) failed in an earlier run and were not retried" in capsys.readouterr().out
    assert main([*args, "--retry-failed"]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert (summary["output"]["tracks_done"], summary["output"]["tracks_failed"]) == (1, 0)
    assert summary["output"]["plots_done"] == summary["plots"] > 0


def test_the_filters_gate_is_set_and_kept_with_the_run(recording, tmp_path, capsys, scheduler):
    """`--filter-gate`: a radar plot 15 km off is left out by the gated `cv_rts` (named in
    filters.parquet's `gated` and the track's warnings) and used by `alpha_beta`, which has no
    gate; `off` makes `cv_rts` use it too, and the warnings name every filter that used a plot
    the reconstruction gave no weight. The gate is kept in run.json: a rerun with another is
    refused; a bad value is a usage error."""
    d, _ = recording
    rows = read_recording(d / "day.ast", parse_sensors(SENSOR_FILE)).rows
    key = f"{FLIGHTS[1].address:06X}"
    mine = np.flatnonzero((rows.mode_s == FLIGHTS[1].address) & (rows.sensor == "R1"))
    wild = mine[len(mine) // 2]
    rows.range_m[wild] += 15_000.0
    write_table(rows, tmp_path / "plots.csv")
    args = [str(tmp_path / "plots.csv"), "--sensors", str(d / "sensors.json"), "--scheduler",
            scheduler, "--no-progress", "--aircraft", key, "--filters", "cv_rts", "alpha_beta"]

    def run(out: str, *more: str) -> tuple[dict[str, list[int]], list[str], dict]:
        assert main([*args, "--out", str(tmp_path / out), *more]) == 0
        states = pq.read_table(tmp_path / out / "tracks.parquet")
        at = int(np.flatnonzero(np.asarray(states.column("source").to_pylist())
                                == f"row {wild + 1}")[0])
        assert states.column("gated")[at].as_py() is True  # the reconstruction: no weight
        filters = pq.read_table(tmp_path / out / "filters.parquet").to_pydict()
        gated = {name: [p for f, p, g in zip(filters["filter"], filters["plot"],
                                              filters["gated"], strict=True) if f == name and g]
                 for name in ("cv_rts", "alpha_beta")}
        with open(tmp_path / out / "warnings.csv", newline="") as f:
            warned = [w for _, w in csv.reader(f) if w.startswith("filters.")]
        return gated, warned, {
            "at": at, "run": json.loads((tmp_path / out / "run.json").read_text())}

    gated, warned, got = run("default")
    assert gated == {"cv_rts": [got["at"]], "alpha_beta": []}
    assert got["run"]["filter_gate_sigma"] == 6.0
    assert [w.split(":")[0] for w in warned] == ["filters.cv_rts", "filters.alpha_beta"]
    assert "1 plot(s) left out" in warned[0] and "used 1 plot(s)" in warned[1]
    gated, warned, got = run("off", "--filter-gate", "off")
    assert gated == {"cv_rts": [], "alpha_beta": []}
    assert got["run"]["filter_gate_sigma"] is None
    assert sorted(w.split(":")[0] for w in warned) == ["filters.alpha_beta", "filters.cv_rts"]
    assert all(f"used 1 plot(s) the reconstruction gave no weight as wild: [{got['at']}]" in w
               for w in warned)
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "off"), "--filter-gate", "4"]) == 2
    assert "filter_gate_sigma None (asked: 4.0)" in capsys.readouterr().err
    for bad in ("0", "-1", "nan", "inf", "x"):  # argparse's usage error: exit 2
        with pytest.raises(SystemExit) as stop:
            main([*args, "--out", str(tmp_path / "bad"), "--filter-gate", bad])
        assert stop.value.code == 2
        assert f"{bad!r} is not a positive number of sigmas or off" in capsys.readouterr().err


def test_a_rerun_on_another_recording_is_refused(recording, tmp_path, capsys, scheduler,
                                                monkeypatch):
    """A rerun resumes by aircraft key: into an --out made from another recording (the same
    Mode S addresses, other flights) it kept the old tracks as the new recording's, exit 0
    (a fuzz helper). The inputs are kept in inputs.json; other files are refused, naming them;
    the same files resume; other software is refused."""
    d, _ = recording
    other = tmp_path / "other.ast"
    other.write_bytes(encode_recording(tod0=50_000.0, duration=60.0).data)
    out = tmp_path / "out"
    args = ["--sensors", str(d / "sensors.json"), "--out", str(out), "--scheduler", scheduler,
            "--no-progress"]
    assert main([str(d / "day.ast"), *args]) == 0
    kept = json.loads((out / "inputs.json").read_text())
    assert kept["recording"]["name"] == "day.ast" and kept["recording"]["bytes"] > 0
    capsys.readouterr()
    assert main([str(other), *args]) == 2
    assert "holds a run made from other inputs (the recording differs" in capsys.readouterr().err
    assert main([str(d / "day.ast"), *args]) == 0  # the same files: resumed
    assert "finished before" in capsys.readouterr().out
    # another version of the solver (an upgrade between the runs): its tracks would differ
    # from the finished ones (a walkthrough helper: up to 8.7 m), so it is refused too
    assert kept["software"] == run_settings.software()
    upgraded = {**run_settings.software(), "solver_sha256": "0" * 64}
    monkeypatch.setattr(run_settings, "software", lambda: upgraded)
    assert main([str(d / "day.ast"), *args]) == 2
    err = capsys.readouterr().err
    assert "(the software (version and solver sources) differs from inputs.json's)" in err


def test_odd_tables_and_sensor_files_get_a_line_not_a_traceback(recording, tmp_path, capsys,
                                                                 scheduler):
    """Files a fuzz helper found ending in a traceback (exit 1): CR-only line ends and two
    unknown columns of one name are read; a non-Parquet `.parquet`, two `t` columns, a binary
    `sensor` column that is no UTF-8, a Latin-1 sensor file are one line naming the problem,
    exit 2."""
    d, _ = recording
    rows = read_recording(d / "day.ast", parse_sensors(SENSOR_FILE)).rows
    write_table(rows, tmp_path / "good.csv")
    lines = (tmp_path / "good.csv").read_text().splitlines()
    (tmp_path / "cr.csv").write_text("\r".join(lines) + "\r")
    (tmp_path / "dup.csv").write_text("\n".join(
        [lines[0] + ",callsign,callsign"] + [ln + ",X,Y" for ln in lines[1:]]) + "\n")
    (tmp_path / "not.parquet").write_bytes(b"hello")
    good = rows.to_arrow()
    pq.write_table(pa.Table.from_arrays([*good.columns, good.column("t")],
                                        names=[*good.column_names, "t"]),
                   tmp_path / "twice.parquet")
    i = good.column_names.index("sensor")
    pq.write_table(good.set_column(i, "sensor", pa.array([b"\xff\xfe"] * good.num_rows,
                                                         pa.binary())),
                   tmp_path / "binary.parquet")
    latin1 = tmp_path / "latin1.json"
    latin1.write_bytes(json.dumps(SENSOR_FILE).replace('"R1"', '"R\\u00e91"')
                       .encode().replace(b"\\u00e9", "\u00e9".encode("latin-1")))
    sensors = str(d / "sensors.json")
    cases = [("cr.csv", sensors, 0, None), ("dup.csv", sensors, 0, None),
             ("not.parquet", sensors, 2, "is not a readable Parquet file"),
             ("twice.parquet", sensors, 2, "t appears twice in the header"),
             ("binary.parquet", sensors, 2, "sensor has type binary, expected text"),
             ("good.csv", str(latin1), 2, "is not UTF-8 text")]
    for name, sensor_file, code, said in cases:
        capsys.readouterr()
        got = main([str(tmp_path / name), "--sensors", sensor_file, "--out",
                    str(tmp_path / f"out-{name}"), "--scheduler", scheduler, "--no-progress"])
        err = capsys.readouterr().err
        assert got == code, (name, err)
        assert said is None or said in err, (name, err)
    done = json.loads((tmp_path / "out-cr.csv" / "summary.json").read_text())
    assert done["plots"] == rows.t.size


def test_samples_are_capped_per_track_with_a_warning(recording, tmp_path, capsys, scheduler):
    """``--samples 0.001`` asked 2.6 M samples of a tester's 44-min track (a MemoryError, exit
    1; 0.01 wrote 43 MB for it): the command line had no cap, where the service has
    ``max_samples``. Now every track over the shared cap keeps none, each with a warning
    (counted in the summary, listed in warnings.csv), and the tracks themselves are done."""
    from solver.config import MAX_SAMPLES

    d, _ = recording
    out = tmp_path / "out"
    assert main([str(d / "day.ast"), "--sensors", str(d / "sensors.json"), "--out", str(out),
                 "--scheduler", scheduler, "--no-progress", "--samples", "0.001"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["done"] == summary["tracks"] > 0 and summary["failures"] == {}
    assert summary["output"]["tracks_with_warnings"] == summary["tracks"]
    warned = list(csv.DictReader((out / "warnings.csv").open()))
    capped = [w for w in warned if w["warning"].startswith("samples: none kept")]
    assert sorted(w["aircraft"] for w in capped) == sorted(
        pq.read_table(out / "tracks.parquet").column("aircraft").unique().to_pylist())
    assert all(f"the limit is {MAX_SAMPLES}" in w["warning"] for w in capped)
    samples = out / "samples.parquet"
    assert not samples.exists() or pq.read_table(samples).num_rows == 0


def _compressed(data: bytes) -> dict[str, bytes]:
    """``data`` as each compressed file a recording may come in (zstd: the zstd tool's frame of
    b"abc", Python 3.11 has no zstd; only its first bytes matter)."""
    import bz2
    import gzip
    import io
    import lzma
    import zipfile

    z = io.BytesIO()
    with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as f:
        f.writestr("day.ast", data)
    return {"gzip": gzip.compress(data), "bzip2": bz2.compress(data), "xz": lzma.compress(data),
            "zip": z.getvalue(), "zstd": bytes.fromhex("28b52ffd0458190000616263990977ad")}


def test_a_compressed_recording_is_refused_naming_its_compression(recording, tmp_path, capsys):
    """A gzipped plot table or capture was decoded as raw ASTERIX (gzip's 1f 8b read as a
    CAT031 header): 459 made-up problems and "no aircraft's track could be read" (a
    tester's). Every compression, of an ASTERIX file or a table, under a compressed name or a
    table's: one line naming it, by ``reconstruct`` (before a cluster starts) and ``plot``;
    the files uncompressed are read (the other tests)."""
    d, _ = recording
    table = b"t,sensor,lat_deg,lon_deg\n0,ADSB,48.1,16.5\n"
    for kind, packed in _compressed((d / "day.ast").read_bytes()).items():
        for name, data in (("day.ast.x", packed), ("plots.csv",
                                                    _compressed(table)[kind])):
            path = tmp_path / f"{kind}-{name}"
            path.write_bytes(data)
            common = [str(path), "--sensors", str(d / "sensors.json"), "--out",
                      str(tmp_path / "out")]
            for args in (["reconstruct", *common, "--no-progress"],
                         ["plot", *common, "--aircraft", "ABC123"]):
                code = main(args)
                err = capsys.readouterr().err
                assert code == 2 and err.count("\n") == 1, (kind, name, args[0], err)
                assert f"recording is compressed with {kind}: decompress it first" in err, err


def test_keys_a_file_name_cannot_tell_apart_get_a_figure_each(recording, tmp_path, capsys,
                                                              scheduler):
    """Keys ``AB 1`` and ``AB/1`` are two tracks, but both figures were ``figures/AB_1.png``,
    one over the other (a tester's): a key that is no safe file name gets a short hash of
    itself beside its readable form (``reconstruct --figures``; ``plot`` names by the same
    function); a Mode S address stays its own name."""
    from solver.track_task import track_file_name

    d, _ = recording
    rec = read_recording(d / "day.ast", parse_sensors(SENSOR_FILE))
    write_table(rec.rows, tmp_path / "plots.csv")
    table = pacsv.read_csv(tmp_path / "plots.csv")
    names = {f"{f.address:06X}": n for f, n in zip(FLIGHTS, ("AB 1", "AB/1"), strict=False)}
    keep = pc.is_in(table.column("mode_s"), pa.array(list(names)))
    table = table.filter(keep)
    table = table.set_column(table.column_names.index("aircraft"), "aircraft", pa.array(
        [names[k] for k in table.column("mode_s").to_pylist()]))
    pacsv.write_csv(table, tmp_path / "keys.csv")
    out = tmp_path / "out"
    args = [str(tmp_path / "keys.csv"), "--sensors", str(d / "sensors.json"), "--out", str(out)]
    assert main([*args, "--scheduler", scheduler, "--no-progress", "--figures"]) == 0
    files = {track_file_name(k) + ".png" for k in ("AB 1", "AB/1")}
    assert len(files) == 2 and all(f.startswith("AB_1-") for f in files)
    assert {p.name for p in (out / "figures").iterdir()} == files
    assert track_file_name("3C6DD4") == "3C6DD4" and track_file_name("a.b_c-1") == "a.b_c-1"
    made = track_file_name("AB 1")  # a safe key of a made name's form is made a name too
    assert track_file_name(made) != made

def test_a_gap_piece_and_another_aircraft_get_their_own_figure_and_selection():
    """``KEY#2`` (a piece after a time gap) and ``KEY~2`` (another aircraft under the key) both
    became the file name ``KEY_2`` (one figure over the other), and ``--aircraft 4ca2d1~2``
    matched nothing (a reviewer's)."""
    from solver.io.reading import normal_key
    from solver.track_task import track_file_name

    names = {track_file_name(k) for k in ("R1:track:30", "R1:track:30#2", "R1:track:30~2")}
    assert len(names) == 3
    assert normal_key("4ca2d1~2") == "4CA2D1~2" and normal_key("4ca2d1#2") == "4CA2D1#2"


def test_a_track_across_the_antimeridian_is_cut_there_in_the_geojson():
    """A tester's Fiji track drew a 359.997-deg step across the whole world (RFC 7946,
    3.1.9: cut the line there). Both ways round, the parts meet at +-180 deg at the latitude
    between the two points; a track that does not cross stays one LineString."""
    from solver.outputs import line_geometry

    east = [[179.8, -17.0], [179.9, -17.0], [-179.9, -16.8], [-179.8, -16.8]]
    g = line_geometry(east)
    assert g["type"] == "MultiLineString"
    assert g["coordinates"] == [[[179.8, -17.0], [179.9, -17.0], [180.0, -16.9]],
                                [[-180.0, -16.9], [-179.9, -16.8], [-179.8, -16.8]]]
    west = line_geometry([[-179.95, 52.0], [179.85, 52.4], [-179.9, 52.5], [-179.7, 52.6]])
    assert [len(p) for p in west["coordinates"]] == [2, 3, 3]  # across and back
    assert west["coordinates"][0][-1] == [-180.0, 52.1]  # a quarter of the way
    assert west["coordinates"][1][0] == [180.0, 52.1]
    for part in west["coordinates"]:
        lons = [p[0] for p in part]
        assert max(abs(a - b) for a, b in itertools.pairwise(lons)) < 180.0
    near = [[14.0, 46.0], [14.1, 46.1], [14.3, 46.0]]
    assert line_geometry(near) == {"type": "LineString", "coordinates": near}


def test_mode_ac_aircraft_seen_by_two_radars_are_one_track_each(tmp_path, capsys, scheduler):
    """Issue 16 end to end: an ASTERIX recording (libasterix) of three aircraft without Mode
    S, all squawking 7000 at FL 50 (two 3 km apart in parallel, one crossing them), each seen
    by R1 and R2 under their own track numbers: three tracks (not six), each reconstructed
    from both radars' plots, the associations counted in the summary, and each radar's
    statistics from the three tracks, every one of which holds both radars' plots."""
    from test_io_association import recording, three_aircraft

    from solver.io.asterix import encode_rows
    from solver.sensor_stats import iter_stats
    from solver.track_task import track_file_name

    rows = recording(three_aircraft())
    (tmp_path / "modeac.ast").write_bytes(encode_rows(rows, parse_sensors(SENSOR_FILE)))
    (tmp_path / "sensors.json").write_text(json.dumps(SENSOR_FILE))
    out = tmp_path / "out"
    assert main([str(tmp_path / "modeac.ast"), "--sensors", str(tmp_path / "sensors.json"),
                 "--out", str(out), "--scheduler", scheduler, "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["problems"] == {"tracks_associated": 3}
    states = pq.read_table(out / "tracks.parquet", columns=["aircraft"]).to_pydict()
    assert sorted(set(states["aircraft"])) == ["R1:track:11", "R1:track:12", "R1:track:13"]
    per_track = list(iter_stats(out / "sensor_stats.jsonl"))
    assert len(per_track) == 3
    for reports in per_track:
        assert {r["id"]: r["plots"] > 0 for r in reports} == {"R1": True, "R2": True}
    sensors = {x["sensor"]: x for x in summary["sensors"]}
    for s in ("R1", "R2"):
        assert sensors[s]["tracks"] == 3
        assert sensors[s]["plots"] == int(np.sum(rows.sensor == s))
        assert sensors[s]["plots_wild"] == 0
        assert sensors[s]["range_residual_sigma_m"] < 100.0, sensors[s]  # noise 50 m
    # `plot` finds an associated track by the key R2 gave it, as `reconstruct --aircraft` does
    # (it matched the output's key only: exit 2, "not in the recording": a reviewer's)
    args = ["plot", str(tmp_path / "modeac.ast"), "--sensors", str(tmp_path / "sensors.json"),
            "--out", str(out)]
    assert main([*args, "--aircraft", "R2:track:42"]) == 0  # the crossing aircraft
    assert [p.name for p in (out / "figures").glob("*.png")] == [
        f"{track_file_name('R1:track:13')}.png"]
    assert main([*args, "--aircraft", "R2:track:99"]) == 2
