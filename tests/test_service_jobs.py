"""Jobs (``/v1/jobs``) in process: the app with its real job runner, SQLite store and a real
one-worker Dask LocalCluster (shared by this module's jobs). An ASTERIX recording encoded with
libasterix runs to done with every track once; a JSON body of tracks too; cancel, the 413 and
503 limits, and bad inputs (422 naming the part or field, a recording that cannot be read
accepted and failed with the reason)."""

from __future__ import annotations

import copy
import csv
import io
import json
import os
import re
import shutil
import time
import zipfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient
from test_io_asterix import (
    C048,
    FLIGHTS,
    SENSOR_FILE,
    Flight,
    cat048,
    dpkt_frame,
    encode_recording,
    pcapng_section,
)

from service.admission import Crowded
from service.app import create_app
from service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
UPLOAD_LIMIT = 200_000
MANY = tuple(Flight(0x400000 + k, 5_000.0 * k, -20_000.0 + 4_000.0 * k, 180.0, 60.0 - 20 * k,
                    300.0, (110 + k, 210 + k)) for k in range(6))


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    settings = Settings(workers=1, warmup=False, access_log=False, log_level="WARNING",
                        data_dir=tmp_path_factory.mktemp("jobs"), jobs_workers=1,
                        jobs_max_running=1, jobs_max_queued=1,
                        jobs_max_upload_bytes=UPLOAD_LIMIT)
    with TestClient(create_app(settings)) as c:
        yield c


def upload(client: TestClient, data: bytes, name: str = "day.ast", sensors=SENSOR_FILE):
    return client.post("/v1/jobs", files={"recording": (name, data),
                                          "sensors": ("sensors.json", json.dumps(sensors))})


def wait(client: TestClient, location: str, states=("done", "failed", "cancelled"),
         timeout: float = 120.0) -> dict:
    end = time.monotonic() + timeout
    while True:
        status = client.get(location).json()
        if status["state"] in states:
            return status
        assert time.monotonic() < end, status
        time.sleep(0.2)


def json_tracks(enc) -> tuple[list[dict], dict[str, list[dict]]]:
    """A recording's sensors (without ASTERIX codes) and its two flights as a JSON body's
    tracks "A" and "B"."""
    sensors = [{k: v for k, v in s.items() if k not in ("sac", "sic")} for s in SENSOR_FILE]
    tracks: dict[str, list[dict]] = {"A": [], "B": []}
    for p in enc.plots:
        plot = {"t": p["tod"], "sensor": p["sensor"]}
        plot |= ({"range_m": p["range_m"], "azimuth_deg": p["azimuth_deg"]} if "range_m" in p
                 else {"lat_deg": p["lat"], "lon_deg": p["lon"]})
        tracks["AB"[p["flight"]]].append(plot)
    return sensors, tracks


def test_pcapng_capture_job_runs_to_done(client):
    """A pcapng capture (Wireshark's format; the file name says nothing) is a recording: every
    track done once; a packet cut by the snap length is counted, the rest read."""
    from dpkt.pcapng import EnhancedPacketBlockLE

    enc = encode_recording(duration=60.0)
    blocks = [bytearray(bytes(EnhancedPacketBlockLE(pkt_data=dpkt_frame(x, 1))))
              for x in enc.blocks]
    blocks[2][24:28] = (len(dpkt_frame(enc.blocks[2], 1)) + 10).to_bytes(4, "little")  # pkt_len
    data = pcapng_section(True, [1], []) + b"".join(blocks)
    r = upload(client, bytes(data), name="capture")
    assert r.status_code == 202, r.text
    status = wait(client, r.headers["location"])
    assert status["state"] == "done", status
    assert status["tracks_total"] == status["tracks_done"] == len(FLIGHTS)
    assert status["problems"]["counts"] == {"truncated_packet": 1}
    assert status["plots"] == status["plots_done"] == status["rows"] > 0.95 * len(enc.plots)


def test_job_date_gives_utc_times_overrides_a_captures_and_a_contradicting_one_fails(client):
    """`options.date` on a raw recording (which says no date): every state's `time_utc` is its
    `t` on that day (Python's datetime as the reference), the segments' and samples' too, and
    the status says the date; a pcap capture whose packet times give 2023-11-14, with a date of
    the 15th, is timed on the 15th with a `date_override` problem naming both (a host clock
    may be whole days off: it failed, the right date could not be given); a table whose
    `timestamp` says the 9th, with the 10th, fails at once naming both dates."""
    import datetime as dt

    from test_io_asterix import CAPTURE_DAY, pcap

    enc = encode_recording(duration=30.0)
    r = client.post("/v1/jobs", files={"recording": ("day.ast", enc.data),
                                       "sensors": ("sensors.json", json.dumps(SENSOR_FILE))},
                    data={"options": json.dumps({"date": CAPTURE_DAY, "sample_step_s": 10.0,
                                                 "filters": ["singer"]})})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    status = wait(client, loc)
    assert status["state"] == "done" and status["options"]["date"] == CAPTURE_DAY, status
    midnight = dt.datetime(2023, 11, 14, tzinfo=dt.UTC)

    def iso(t: float) -> str:
        return (midnight + dt.timedelta(seconds=t)).strftime("%Y-%m-%dT%H:%M:%S.%fZ")

    body = client.get(f"{loc}/tracks/{FLIGHTS[0].address:06X}").json()["trajectory"]
    assert body["at_plots"] and all(s["time_utc"] == iso(s["t"]) for s in body["at_plots"])
    assert body["samples"] and all(s["time_utc"] == iso(s["t"]) for s in body["samples"])
    assert all(g["time_utc_start"] == iso(g["t_start"]) and g["time_utc_end"] == iso(g["t_end"])
               for g in body["segments"])
    assert body["at_plots"][0]["time_utc"].startswith("2023-11-14T10:00:")
    # the filters' states too (they had no time_utc), and segments.parquet's ends (it had none)
    states = client.get(f"{loc}/tracks/{FLIGHTS[0].address:06X}").json()["filters"]["singer"][
        "states"]
    assert states and all(s["time_utc"] == iso(s["t"]) for s in states)
    segments = pq.read_table(io.BytesIO(client.get(loc + "/results/segments.parquet").content))
    for end in ("start", "end"):
        assert segments.schema.field(f"time_utc_{end}").type == pa.timestamp("us", tz="UTC")
        assert segments.column(f"time_utc_{end}").to_pylist() == [
            midnight + dt.timedelta(seconds=t) for t in segments.column(f"t_{end}").to_pylist()]
    summary = json.loads(client.get(loc + "/results/summary.json").content)
    assert summary["recording_date"] == CAPTURE_DAY

    r = client.post("/v1/jobs", files={"recording": ("day.pcap", pcap(enc.blocks)),
                                       "sensors": ("sensors.json", json.dumps(SENSOR_FILE))},
                    data={"options": json.dumps({"date": "2023-11-15"})})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    status = wait(client, loc)
    assert status["state"] == "done", status
    assert status["problems"]["counts"] == {"date_override": 1}, status["problems"]
    assert ("date_override at date: the date given, 2023-11-15, overrides 2023-11-14 (from "
            "its capture's packet times)") in status["problems"]["examples"][0]
    summary = json.loads(client.get(loc + "/results/summary.json").content)
    assert summary["recording_date"] == "2023-11-15"
    assert summary["problems"] == {"date_override": 1}
    body = client.get(f"{loc}/tracks/{FLIGHTS[0].address:06X}").json()["trajectory"]
    assert body["at_plots"][0]["time_utc"].startswith("2023-11-15T10:00:")

    table = ("timestamp,sensor,range_m,azimuth_deg\n2024-03-09T10:00:00Z,R1,50000,10\n"
             "2024-03-09T10:00:04Z,R1,50100,10\n")
    r = client.post("/v1/jobs", files={"recording": ("day.csv", table.encode()),
                                       "sensors": ("sensors.json", json.dumps(SENSOR_FILE))},
                    data={"options": json.dumps({"date": "2024-03-10"})})
    assert r.status_code == 202, r.text
    status = wait(client, r.headers["location"])
    assert status["state"] == "failed", status
    assert status["error"].startswith("options.date 2024-03-10 contradicts the recording's "
                                      "own date 2024-03-09 (from its timestamp column)"
                                      ), status


def test_an_ioss_recording_job_runs_to_done(client):
    """An IOSS (FINAL) recording (frames of a recorder around the data blocks; named .ff) is a
    recording: every plot read, every track done once."""
    from test_io_framing import framed

    enc = encode_recording(duration=60.0)
    r = upload(client, framed(enc.blocks, 2), name="day.ff")
    assert r.status_code == 202, r.text
    status = wait(client, r.headers["location"])
    assert status["state"] == "done", status
    assert status["tracks_total"] == status["tracks_done"] == len(FLIGHTS)
    assert status["problems"]["counts"] == {}
    assert status["plots"] == status["plots_done"] == status["rows"] == len(enc.plots)


def test_asterix_recording_job_runs_to_done_with_every_track_once(client):
    enc = encode_recording(duration=60.0)
    r = upload(client, enc.data[:-7])  # the last block truncated: a problem, not fatal
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["state"] == "queued" and r.headers["location"] == f"/v1/jobs/{job['id']}"
    status = wait(client, r.headers["location"])
    loc = r.headers["location"]
    assert status["state"] == "done", status
    keys = {f"{f.address:06X}" for f in FLIGHTS}
    assert status["tracks_total"] == status["tracks_done"] == len(FLIGHTS)
    assert status["tracks_failed"] == 0 and status["error"] is None
    assert status["problems"]["counts"] == {"truncated_block": 1}
    assert status["plots"] == status["plots_done"] == status["rows"] > 0.95 * len(enc.plots)
    assert status["runs"] == 1 and status["elapsed_s"] > 0 and status["finished"]

    tracks = client.get(loc + "/tracks").json()
    assert {t["aircraft"] for t in tracks} == keys and len(tracks) == len(FLIGHTS)
    assert all(t["status"] == "done" and t["error"] is None for t in tracks)
    # paged: the same tracks in the same order (a tester's 300,000 made one 29-MB answer)
    pages = [client.get(loc + f"/tracks?offset={k}&limit=1") for k in range(len(tracks))]
    assert [p.json()[0] for p in pages] == tracks
    assert {p.headers["x-total-count"] for p in pages} == {str(len(tracks))}
    assert client.get(loc + f"/tracks?offset={len(tracks)}").json() == []
    assert client.get(loc + "/tracks?limit=10001").status_code == 422

    table = pq.read_table(io.BytesIO(client.get(loc + "/results/tracks.parquet").content))
    pairs = list(zip(table.column("aircraft").to_pylist(), table.column("plot").to_pylist(),
                     strict=True))
    assert len(pairs) == len(set(pairs)) == status["plots"]  # every plot of every track once
    for t in tracks:
        assert sum(a == t["aircraft"] for a, _ in pairs) == t["plots"]

    for k, f in enumerate(FLIGHTS):
        key = f"{f.address:06X}"
        one = client.get(f"{loc}/tracks/{key}")
        assert one.status_code == 200, one.text
        body = one.json()
        states = body["trajectory"]["at_plots"]
        plots = next(t["plots"] for t in tracks if t["aircraft"] == key)
        assert len(states) == plots and [s["plot"] for s in states] == list(range(plots))
        assert body["trajectory"]["segments"] and {s["id"] for s in body["sensors"]} == {
            "R1", "R2", "ADSB"}
        assert body["trajectory"]["manoeuvres"] == []  # straight and level: none
        t = np.array([s["t"] for s in states])
        lat, lon, _ = f.at(t - t.min() + _first_t(enc, k))
        dy = (np.array([s["lat_deg"] for s in states]) - lat) * 111_000
        dx = (np.array([s["lon_deg"] for s in states]) - lon) * 111_000 * np.cos(
            np.deg2rad(lat))
        assert np.hypot(dx, dy).max() < 60.0  # exact plots: the flight within 60 m
        for s in states:  # each plot against its state, as tracks.parquet has it
            named = "range_residual_m" if s["sensor"] != "ADSB" else "position_residual_m"
            assert abs(s[named]) < 30.0 and s["gated"] is False, s
            assert ("azimuth_residual_deg" in s) == (s["sensor"] != "ADSB")
            if s["sensor"] == "ADSB":  # the distance split along and across the track
                assert np.hypot(s["along_track_residual_m"], s["cross_track_residual_m"]) == \
                    pytest.approx(s["position_residual_m"], rel=1e-9)
        figure = client.get(f"{loc}/tracks/{key}/figure.png")
        assert figure.headers["content-type"] == "image/png"
        assert figure.content[:8] == b"\x89PNG\r\n\x1a\n"

    assert client.get(loc + "/map.png").content[:4] == b"\x89PNG"
    assert client.get(loc + "/sensors.png").content[:4] == b"\x89PNG"
    sensors = {s["sensor"]: s for s in client.get(loc + "/sensors").json()}
    assert set(sensors) == {"R1", "R2", "ADSB"} and sensors["R1"]["scan_period_s"] == 4.0
    archive = zipfile.ZipFile(io.BytesIO(client.get(loc + "/results/results.zip").content))
    assert {"tracks.parquet", "segments.parquet", "tracks.csv", "tracks.geojsonl",
            "manoeuvres.csv", "sensors.json", "sensors.csv", "summary.json", "problems.txt",
            "map.png", "sensors.png"} <= set(archive.namelist())
    # the command line's summary fields too (a walkthrough helper found them missing)
    summary = json.loads(archive.read("summary.json"))
    assert [s["sensor"] for s in summary["sensors"]] == ["R1", "R2", "ADSB"]
    assert summary["csv_rows"] == summary["plots"] and summary["geojson_tracks"] == len(keys)
    assert summary["manoeuvres"] == 0
    assert archive.read("sensors.csv").decode().splitlines()[0].startswith('"sensor","kind",')
    lines = client.get(loc + "/results/tracks.geojsonl").text.splitlines()
    assert sorted(json.loads(x)["properties"]["aircraft"] for x in lines) == sorted(keys)
    assert client.get(f"{loc}/tracks/NOPE").status_code == 404
    assert client.get(loc + "/results/nope.txt").status_code == 404
    assert client.get(f"{loc}/tracks/{next(iter(keys))}").json()["filters"] == {}
    nofilters = client.get(loc + "/results/filters.parquet")
    assert nofilters.status_code == 404 and "asked for no filters" in nofilters.json()["message"]

    # a finished job is removed with its data
    assert client.delete(loc).status_code == 204
    assert client.get(loc).status_code == 404
    assert client.get(loc + "/tracks").status_code == 404


def _first_t(enc, k: int) -> float:
    return min(p["tod"] for p in enc.plots if p["flight"] == k) - 36_000.0


def test_json_tracks_job(client):
    enc = encode_recording(duration=40.0)
    tracks: dict[str, list[dict]] = {"A": [], "B/2#x": []}
    for p in enc.plots:
        plot = {"t": p["tod"], "sensor": p["sensor"]}
        if "range_m" in p:
            plot |= {"range_m": p["range_m"], "azimuth_deg": p["azimuth_deg"]}
        else:
            plot |= {"lat_deg": p["lat"], "lon_deg": p["lon"]}
        tracks[("A", "B/2#x")[p["flight"]]].append(plot)
    sensors = [{k: v for k, v in s.items() if k not in ("sac", "sic")} for s in SENSOR_FILE]
    tracks["short"] = tracks["A"][:2]  # too short: reported, not dropped silently
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks})
    assert r.status_code == 202, r.text
    status = wait(client, r.headers["location"])
    assert status["state"] == "done" and status["kind"] == "tracks", status
    assert status["tracks_total"] == status["tracks_done"] == 2
    assert status["problems"]["counts"] == {"short_track": 1}
    listed = client.get(r.headers["location"] + "/tracks").json()
    assert [(t["aircraft"], t["plots"]) for t in listed] == [("A", len(tracks["A"])),
                                                            ("B/2#x", len(tracks["B/2#x"]))]
    # any key is addressable: "/" as is (or %2F), "#" percent-encoded
    for path in ("B/2%23x", "B%2F2%23x"):
        one = client.get(f"{r.headers['location']}/tracks/{path}")
        assert one.status_code == 200 and one.json()["aircraft"] == "B/2#x"
        assert len(one.json()["trajectory"]["at_plots"]) == len(tracks["B/2#x"])
    # each state names its plot in the body: the same time and sensor there, every plot once
    at_plots = one.json()["trajectory"]["at_plots"]
    named = [int(s["source"].removeprefix("tracks.B/2#x[").removesuffix("]")) for s in at_plots]
    assert sorted(named) == list(range(len(tracks["B/2#x"])))
    for state, j in zip(at_plots, named, strict=True):
        assert (state["t"], state["sensor"]) == (tracks["B/2#x"][j]["t"],
                                                 tracks["B/2#x"][j]["sensor"])
    figure = client.get(f"{r.headers['location']}/tracks/B/2%23x/figure.png")
    assert figure.status_code == 200 and figure.content[:4] == b"\x89PNG"


def test_a_json_job_takes_the_sensor_files_own_list(client):
    """The sensor file's sensors with their ASTERIX `sac`/`sic` (recordings.md): the same list
    serves an upload and a JSON body (it was a 422, "sensors[0].radar.sac: Extra inputs are
    not permitted"); a code out of range is still named."""
    enc = encode_recording(duration=40.0)
    _, tracks = json_tracks(enc)
    r = client.post("/v1/jobs", json={"sensors": SENSOR_FILE, "tracks": tracks})
    assert r.status_code == 202, r.text
    assert wait(client, r.headers["location"])["state"] == "done"
    bad = copy.deepcopy(SENSOR_FILE)
    bad[0]["sac"] = 256
    r = client.post("/v1/jobs", json={"sensors": bad, "tracks": tracks})
    assert r.status_code == 422 and r.json()["message"].startswith("sensors[0].sac: "), r.text


def test_job_options_run_the_filters_on_every_track(client):
    """`filters` and `sample_step_s` (JSON body; `options` part of an upload): each track's
    answer carries every filter's state at its plots and the regular samples, the same as the
    single-track endpoint's for those plots (an independent path: one request, no job, no
    Parquet); `filters.parquet` and `samples.parquet` hold them all; the bounds reach the
    reconstruction (a speed cap the flight is held under). A step that would give a track
    more than `max_samples` keeps none, with the track's warning."""
    enc = encode_recording(duration=40.0)
    sensors, tracks = json_tracks(enc)
    names = ["imm_smoother", "cv_rts"]
    bounds = {"u": [-7.0, 7.0], "w": [-2.0, 3.0], "v": [30.0, 150.0]}  # the flights fly 206 and 234
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks, "bounds": bounds,
                                      "filters": [*names, "cv_rts"],  # asked twice: run once
                                      "sample_step_s": 5.0, "filter_gate_sigma": 4.0})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    status = wait(client, loc)
    assert status["state"] == "done" and status["tracks_done"] == 2, status
    assert status["options"] == {"bounds": bounds, "filters": names,  # what it runs with
                                 "sample_step_s": 5.0, "aircraft": None,
                                 "method": "refined", "criterion": "R2",
                                 "window": {"plots": 3, "trial_step_s": 5.0},
                                 "filter_gate_sigma": 4.0, "editions": {}, "date": None}
    for key, plots in tracks.items():
        body = client.get(f"{loc}/tracks/{key}").json()
        assert set(body["filters"]) == set(names)
        assert max(s["speed"] for s in body["trajectory"]["at_plots"]) <= 150.0 + 1e-3
        single = client.post("/v1/reconstructions", json={
            "sensors": sensors, "plots": plots, "filters": names, "sample_step_s": 5.0,
            "bounds": bounds, "filter_gate_sigma": 4.0})
        assert single.status_code == 200, single.text
        # the single-track answer's diagnostics and estimated altitude
        got, want = body["diagnostics"], single.json()["diagnostics"]
        for field in ("method", "windows_solved", "solver_failures", "criterion", "nlp_solves"):
            assert got[field] == want[field], field
        np.testing.assert_allclose(got["criterion_values"], want["criterion_values"], rtol=1e-9)
        assert set(got["extra"]) == set(want["extra"]) and got["extra"]["refine_nodes"] > 0
        assert got["extra"]["refine_iterations"] == want["extra"]["refine_iterations"]
        assert got["task_ms"] >= got["elapsed_ms"] > 0 and got["filters_ms"] > 0
        alt, alt_want = body["trajectory"].get("altitude_m"), single.json()["trajectory"].get(
            "altitude_m")
        assert (alt is None) == (alt_want is None)
        if alt is not None:
            assert alt == pytest.approx(alt_want, abs=1e-6)
        got, want = body["trajectory"]["samples"], single.json()["trajectory"]["samples"]
        assert len(got) == len(want) > 5 and got[0]["t"] == plots[0]["t"]
        assert got[-1]["t"] == max(p["t"] for p in plots)
        for field in ("t", "x", "z", "vx", "vz", "lat_deg", "lon_deg", "speed", "heading_deg"):
            np.testing.assert_allclose([s[field] for s in got], [s[field] for s in want],
                                       rtol=0, atol=1e-6, err_msg=f"{key} samples {field}")
        np.testing.assert_allclose(np.array([s["cov"] for s in got]),
                                   np.array([s["cov"] for s in want]), rtol=1e-9)
        for name in names:
            got, want = body["filters"][name]["states"], single.json()["filters"][name]["states"]
            assert len(got) == len(want) == len(plots)
            for field in ("t", "x", "z", "vx", "vz", "lat_deg", "lon_deg"):
                np.testing.assert_allclose([s[field] for s in got], [s[field] for s in want],
                                           rtol=0, atol=1e-6, err_msg=f"{key} {name} {field}")
            np.testing.assert_allclose(np.array([s["cov"] for s in got]),
                                       np.array([s["cov"] for s in want]), rtol=1e-9)
            assert body["filters"][name]["gated"] == single.json()["filters"][name]["gated"]
    table = pq.read_table(io.BytesIO(client.get(loc + "/results/filters.parquet").content))
    assert table.num_rows == len(names) * sum(len(p) for p in tracks.values())
    assert sorted(set(table.column("filter").to_pylist())) == sorted(names)
    # ?omit=: the single-track request's parts to leave out (a bad one: 422 naming it)
    key = next(iter(tracks))
    lean = client.get(f"{loc}/tracks/{key}", params={"omit": ["samples", "covariances"]})
    assert lean.status_code == 200 and lean.json()["trajectory"]["samples"] == []
    assert all(s["cov"] is None for s in lean.json()["trajectory"]["at_plots"])
    assert all(s["cov"] is None for f in lean.json()["filters"].values() for s in f["states"])
    bad = client.get(f"{loc}/tracks/{key}", params={"omit": "plots"})
    assert bad.status_code == 422 and "omit" in bad.json()["message"], bad.text
    sampled = pq.read_table(io.BytesIO(client.get(loc + "/results/samples.parquet").content))
    assert sampled.num_rows == sum(len(client.get(f"{loc}/tracks/{k}").json()["trajectory"]
                                       ["samples"]) for k in tracks)
    summary = json.loads(client.get(loc + "/results/summary.json").content)
    assert summary["filters"] == names and summary["sample_step_s"] == 5.0
    assert summary["method"] == "refined"
    # held under the speed cap, every track warns: counted, and all of it in warnings.csv
    assert summary["tracks_with_warnings"] == len(tracks) == len(summary["warnings"])
    warned = client.get(loc + "/results/warnings.csv").text.splitlines()
    assert warned[0] == "aircraft,warning"
    assert {line.split(",")[0] for line in warned[1:]} == set(tracks)
    assert any("upper bound" in line for line in warned)
    archive = zipfile.ZipFile(io.BytesIO(client.get(loc + "/results/results.zip").content))
    assert {"filters.parquet", "samples.parquet"} <= set(archive.namelist())

    # an upload's `options` part: the recording's tracks carry the filter too; a step that
    # would give more than max_samples (100,000) samples keeps none, saying so
    options = json.dumps({"filters": ["imm_smoother"], "sample_step_s": 1e-4})
    r = client.post("/v1/jobs", files={"recording": ("day.ast", enc.data),
                                       "sensors": ("sensors.json", json.dumps(SENSOR_FILE))},
                    data={"options": options})
    assert r.status_code == 202, r.text
    up = r.headers["location"]
    done = wait(client, up)
    assert done["state"] == "done" and done["options"] == {
        "bounds": {"u": [-7.0, 7.0], "w": [-2.0, 3.0], "v": [30.0, 330.0]},
        "filters": ["imm_smoother"], "sample_step_s": 1e-4, "aircraft": None,
        "method": "refined", "criterion": "R2", "window": {"plots": 3, "trial_step_s": 5.0},
        "filter_gate_sigma": 6.0, "editions": {}, "date": None}
    for t in client.get(up + "/tracks").json():
        body = client.get(f"{up}/tracks/{t['aircraft']}").json()
        assert list(body["filters"]) == ["imm_smoother"]
        assert len(body["filters"]["imm_smoother"]["states"]) == t["plots"]
        assert body["trajectory"]["samples"] == []
        assert any(re.match(r"samples: none kept: sample_step_s 0\.0001 gives \d{6,} samples "
                            r"over the .*-s track, the limit is 100000 \(max_samples\)", w)
                   for w in body["diagnostics"]["warnings"])
    missing = client.get(up + "/results/samples.parquet")
    assert missing.status_code == 404 and "no track kept any" in missing.json()["message"]

    # `aircraft`: only the named (a Mode S address in either case); a name the recording does
    # not hold is the job's problem
    key = f"{FLIGHTS[1].address:06X}"
    r = client.post("/v1/jobs", files={"recording": ("day.ast", enc.data),
                                       "sensors": ("sensors.json", json.dumps(SENSOR_FILE))},
                    data={"options": json.dumps({"aircraft": [key.lower(), "ABC123"]})})
    assert r.status_code == 202, r.text
    one = r.headers["location"]
    done = wait(client, one)
    assert done["state"] == "done" and done["tracks_total"] == done["tracks_done"] == 1
    assert done["options"]["aircraft"] == [key.lower(), "ABC123"]
    assert done["problems"]["counts"] == {"aircraft_not_found": 1}
    assert "ABC123 is not in the recording" in done["problems"]["examples"][0]
    assert [t["aircraft"] for t in client.get(one + "/tracks").json()] == [key]
    for job in (loc, up, one):
        assert client.delete(job).status_code == 204


def test_a_jobs_filter_gate_reaches_every_track(client):
    """`filter_gate_sigma` null in a job's options: the filters use a radar plot 15 km off,
    which the reconstruction gave no weight, and the track's warnings say so; with the default
    gate `cv_rts` leaves it out. The options echo the gate."""
    enc = encode_recording(duration=40.0)
    sensors, tracks = json_tracks(enc)
    radar = [i for i, p in enumerate(tracks["A"]) if "range_m" in p]
    wild = radar[len(radar) // 2]
    tracks["A"][wild]["range_m"] += 15_000.0
    for gate in (None, "default"):
        body = {"sensors": sensors, "tracks": {"A": tracks["A"]}, "filters": ["cv_rts"]}
        if gate is None:
            body["filter_gate_sigma"] = None
        r = client.post("/v1/jobs", json=body)
        assert r.status_code == 202, r.text
        status = wait(client, r.headers["location"])
        assert status["state"] == "done", status
        assert status["options"]["filter_gate_sigma"] == (None if gate is None else 6.0)
        track = client.get(r.headers["location"] + "/tracks/A").json()
        plot = next(i for i, s in enumerate(track["trajectory"]["at_plots"])
                    if s["source"] == f"tracks.A[{wild}]")
        assert track["trajectory"]["at_plots"][plot]["gated"] is True
        assert track["filters"]["cv_rts"]["gated"] == ([] if gate is None else [plot])
        used = [w for w in track["diagnostics"]["warnings"]
                if w.startswith("filters.cv_rts: used 1 plot(s) the reconstruction gave no")]
        assert len(used) == (gate is None), track["diagnostics"]["warnings"]
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks,
                                      "filter_gate_sigma": 0})
    assert r.status_code == 422 and r.json()["message"].startswith("filter_gate_sigma: "), r.text


def test_a_jobs_method_is_the_single_track_method(client):
    """`method: sliding` with its `window` and `criterion` (JSON body; an upload's
    `options`): every track is the seed's sliding windows, the same as the single-track
    endpoint's `sliding` answer with those settings for its plots (segments and states), not
    the refined default."""
    enc = encode_recording(duration=30.0)
    sensors, tracks = json_tracks(enc)
    windows = {"window": {"plots": 4, "trial_step_s": 3.0}, "criterion": "R1"}
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks,
                                      "method": "sliding", **windows})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    status = wait(client, loc)
    assert status["state"] == "done" and status["tracks_done"] == 2, status
    assert status["options"]["method"] == "sliding"
    assert {k: status["options"][k] for k in windows} == windows
    for key, plots in tracks.items():
        body = client.get(f"{loc}/tracks/{key}").json()
        want = {m: client.post("/v1/reconstructions", json={
            "sensors": sensors, "plots": plots, "method": m, **windows}).json()
            for m in ("sliding", "refined")}
        assert body["diagnostics"]["criterion"] == "R1"
        assert body["diagnostics"]["method"] == "sliding"
        assert body["diagnostics"]["windows_solved"] == want["sliding"]["diagnostics"][
            "windows_solved"] > 0
        got = body["trajectory"]["at_plots"]
        for field in ("x", "z", "vx", "vz"):
            np.testing.assert_allclose([s[field] for s in got], [
                s[field] for s in want["sliding"]["trajectory"]["at_plots"]], rtol=0,
                atol=1e-6, err_msg=f"{key} {field}")
        refined = np.array([s["x"] for s in want["refined"]["trajectory"]["at_plots"]])
        assert np.abs(np.array([s["x"] for s in got]) - refined).max() > 1e-3
        assert [s["u"] for s in body["trajectory"]["segments"]] == pytest.approx(
            [s["u"] for s in want["sliding"]["trajectory"]["segments"]], abs=1e-9)
    summary = json.loads(client.get(loc + "/results/summary.json").content)
    assert summary["method"] == "sliding"
    r = client.post("/v1/jobs", files={"recording": ("day.ast", enc.data),
                                       "sensors": ("sensors.json", json.dumps(SENSOR_FILE))},
                    data={"options": json.dumps({"method": "sliding"})})
    assert r.status_code == 202, r.text
    up = wait(client, r.headers["location"])
    assert up["state"] == "done" and up["options"]["method"] == "sliding"
    for t in client.get(r.headers["location"] + "/tracks").json():
        body = client.get(f"{r.headers['location']}/tracks/{t['aircraft']}").json()
        assert body["diagnostics"]["method"] == "sliding"
    for job in (loc, r.headers["location"]):
        assert client.delete(job).status_code == 204


def test_cancel_and_the_concurrent_job_limit(client):
    data = encode_recording(duration=300.0, flights=MANY).data  # ~10 s of solving
    first = upload(client, data)
    second = upload(client, data)
    assert first.status_code == second.status_code == 202
    busy = upload(client, data)  # one running and one queued: the limit
    assert busy.status_code == 503 and busy.headers["retry-after"]
    assert busy.json()["message"].startswith("too many jobs")

    queued = client.delete(second.headers["location"])
    assert queued.status_code == 200 and queued.json()["state"] == "cancelled"
    end = time.monotonic() + 120  # mid-run: tracks done, others in flight
    while (running := client.get(first.headers["location"]).json())["tracks_done"] < 1:
        assert time.monotonic() < end, running
        time.sleep(0.1)
    assert running["state"] == "running"
    cancelled = client.delete(first.headers["location"]).json()
    assert cancelled["state"] == "cancelled" and cancelled["error"]
    time.sleep(2.0)  # nothing of a cancelled job goes on
    later = client.get(first.headers["location"]).json()
    assert later["state"] == "cancelled" and later["tracks_done"] < len(MANY)
    assert later["tracks_done"] == cancelled["tracks_done"]
    assert later["tracks_failed"] == 0  # the stop is not recorded as the tracks' failure
    # its finished tracks' whole-job results (a walkthrough helper found them 409, readable
    # only one by one); the unfinished ones listed as cancelled, not pending for good
    loc = first.headers["location"]
    end = time.monotonic() + 60
    while (summary := client.get(loc + "/results/summary.json")).status_code != 200:
        assert summary.status_code == 409 and time.monotonic() < end, summary.text
        time.sleep(0.2)
    summary = summary.json()
    assert summary["cancelled"] and summary["done"] == later["tracks_done"]
    assert summary["not_reconstructed"] == later["tracks_total"] - later["tracks_done"] > 0
    listed = client.get(loc + "/tracks").json()
    assert {t["status"] for t in listed} == {"done", "cancelled"}
    assert sum(t["status"] == "done" for t in listed) == later["tracks_done"]
    assert client.get(loc + "/map.png").status_code == 200
    assert client.get(loc + "/sensors").status_code == 200
    csv_rows = client.get(loc + "/results/tracks.csv").text.count("\n") - 1
    assert csv_rows == later["plots_done"]
    assert client.get(second.headers["location"] + "/tracks").json() == []
    assert client.get(second.headers["location"] + "/map.png").status_code == 409  # none done
    # the jobs, newest first (a lost id found again), by state too
    jobs = client.get("/v1/jobs").json()
    assert [j["id"] for j in jobs[:2]] == [r.headers["location"].rsplit("/", 1)[1]
                                           for r in (second, first)]
    assert {j["state"] for j in client.get("/v1/jobs", params={"state": "cancelled"}).json()
            } == {"cancelled"}
    assert len(client.get("/v1/jobs", params={"limit": 1}).json()) == 1
    assert client.get("/v1/jobs", params={"limit": 0}).status_code == 422
    assert client.get("/v1/jobs", params={"state": "lost"}).status_code == 422
    for r in (first, second):  # deleting a finished (cancelled) job removes it
        assert client.delete(r.headers["location"]).status_code == 204
        assert client.get(r.headers["location"]).status_code == 404
    assert upload(client, b"\x00" * 10, name="x.csv").status_code == 202  # room again


def test_delete_of_a_running_job_answers_at_once_and_the_job_stops(client):
    """DELETE of a running job waited for the job's thread to write the whole-job outputs of
    its finished tracks: 1.4-2.4 s here, 1.8-5.9 s for a tester, whose httpx client's default
    5-s timeout ran out. It answers at once now (its counts final), the outputs follow in the
    background, and the job's work stops: no track more, the runner's thread lets go of it,
    the Dask worker idles."""
    import os

    import psutil

    runner = client.app.state.jobs
    r = upload(client, encode_recording(duration=300.0, flights=MANY).data)
    assert r.status_code == 202, r.text
    loc, job_id = r.headers["location"], r.json()["id"]
    end = time.monotonic() + 120
    while (running := client.get(loc).json())["tracks_done"] < 1:
        assert time.monotonic() < end, running
        time.sleep(0.1)
    assert running["state"] == "running"
    began = time.monotonic()
    cancelled = client.delete(loc)
    took = time.monotonic() - began
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    assert took < 1.0, f"DELETE took {took:.2f} s"
    done = cancelled.json()["tracks_done"]
    assert 1 <= done < len(MANY)

    end = time.monotonic() + 60
    while job_id in runner._running:  # the outputs written, the thread free for the next job
        assert time.monotonic() < end, "the cancelled job's thread did not let go"
        time.sleep(0.1)
    workers = [psutil.Process(pid) for pid in runner._dask().run(os.getpid).values()]

    def cpu_s() -> float:
        return sum(p.cpu_times().user + p.cpu_times().system for p in workers)

    end = time.monotonic() + 60  # a track in flight runs to its end on its worker, no other
    while True:
        before = cpu_s()
        time.sleep(1.0)
        if cpu_s() - before < 0.2:
            break
        assert time.monotonic() < end, "the worker is still busy with the cancelled job"
    later = client.get(loc).json()
    assert later["state"] == "cancelled" and later["tracks_done"] == done, later
    assert later["tracks_failed"] == 0
    summary = client.get(loc + "/results/summary.json")
    assert summary.status_code == 200 and summary.json()["cancelled"], summary.text
    assert summary.json()["done"] == done
    assert client.delete(loc).status_code == 204


def _store_settings(client, tmp_path) -> Settings:
    """A second service's settings on its own data directory and this module's cluster."""
    return Settings(workers=1, warmup=False, access_log=False, log_level="WARNING",
                    data_dir=tmp_path, dask_scheduler=client.app.state.jobs.dask_address,
                    jobs_track_figures=False)


def _upload_until_a_track_is_done(service) -> tuple[str, dict]:
    """Upload a 600-s recording of MANY aircraft; its job's location and status once a track
    is done (tracks are committed in batches of up to a second: of 300-s tracks, all six were
    once committed in the first, and the job ended before the stop its test meant to make)."""
    loc = upload(service, encode_recording(duration=600.0, flights=MANY).data).headers[
        "location"]
    end = time.monotonic() + 120
    while (before := service.get(loc).json())["tracks_done"] < 1:
        assert time.monotonic() < end, before
        time.sleep(0.1)
    return loc, before


def test_a_service_stopped_right_after_a_delete_keeps_the_job_cancelled(client, tmp_path):
    """DELETE no longer waits for a cancelled job's whole-job outputs: a service stopped just
    after it (as on SIGTERM) still writes them, and the next service on the data directory
    has the job cancelled (not resumed), with the finished tracks of the DELETE's answer
    readable and the whole-job results of them."""
    settings = _store_settings(client, tmp_path)
    with TestClient(create_app(settings)) as first:
        loc, _ = _upload_until_a_track_is_done(first)
        cancelled = first.delete(loc).json()
    assert cancelled["state"] == "cancelled" and 1 <= cancelled["tracks_done"] < len(MANY)
    with TestClient(create_app(settings)) as second:
        time.sleep(1.0)  # a job queued again would be claimed by now
        status = second.get(loc).json()
        assert status["state"] == "cancelled" and status["runs"] == 1, status
        assert status["tracks_done"] == cancelled["tracks_done"]
        listed = second.get(loc + "/tracks").json()
        done = [t["aircraft"] for t in listed if t["status"] == "done"]
        assert len(done) == cancelled["tracks_done"]
        assert {t["status"] for t in listed} == {"done", "cancelled"}
        for key in done:
            assert second.get(f"{loc}/tracks/{key}").status_code == 200
        # its figures were off (jobs_track_figures): nothing kept to draw them from
        nofigure = second.get(f"{loc}/tracks/{done[0]}/figure.png")
        assert nofigure.status_code == 404, nofigure.text
        assert nofigure.json()["message"].startswith(f"no figure of track {done[0]!r}")
        summary = second.get(loc + "/results/summary.json")
        assert summary.status_code == 200 and summary.json()["done"] == len(done)
        assert second.delete(loc).status_code == 204


def test_a_jobs_sensors_carry_every_field_of_its_sensors_json(client):
    """`GET /v1/jobs/{id}/sensors` is the job's `results/sensors.json`, every field (the
    response model dropped the sigma estimates, the coverage holes and `plots_no_reference`,
    which the file and the command line's carry): the same keys in the same order and the
    same values, and the model lists the command line's columns, so a later one cannot be
    dropped silently. The job's `summary.json` has the command line's rate fields."""
    from service.job_models import SensorSummaryOut
    from solver.sensor_stats import SENSOR_COLUMNS

    assert list(SensorSummaryOut.model_fields) == list(SENSOR_COLUMNS)
    sensors, tracks = json_tracks(encode_recording(duration=40.0))
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    assert wait(client, loc)["state"] == "done"
    got = client.get(loc + "/sensors").json()
    want = client.get(loc + "/results/sensors.json").json()
    assert [list(s) for s in got] == [list(s) for s in want] and len(got) == 3
    assert got == want
    radar = next(s for s in got if s["sensor"] == "R1")
    assert radar["range_sigma_estimate_m"] > 0 and radar["azimuth_sigma_estimate_deg"] > 0
    assert radar["coverage_holes"] == 0 and radar["coverage_hole_s"] == 0.0
    adsb = next(s for s in got if s["sensor"] == "ADSB")
    assert adsb["position_sigma_estimate_m"] > 0
    summary = client.get(loc + "/results/summary.json").json()
    assert summary["plots_per_s"] == pytest.approx(summary["plots"] / summary["reconstruct_s"])
    assert summary["elapsed_s"] > summary["reconstruct_s"] > 0
    assert client.delete(loc).status_code == 204


def test_a_jobs_track_has_no_altitude_where_the_single_answer_has_none(client):
    """`trajectory.altitude_m` and `altitude_sigma_m` are absent unless the altitude was
    estimated from several radars (sensors.md), as in `POST /v1/reconstructions`'s answer
    for the same plots; a job's track had them null."""
    enc = encode_recording(duration=40.0)
    sensors, tracks = json_tracks(enc)
    radar = [{**sensors[0], "id": "R"}]
    alone = [p | {"sensor": "R"} for p in tracks["A"] if p["sensor"] == sensors[0]["id"]]
    cases = {"ALONE": (radar, alone), **{k: (sensors, v) for k, v in tracks.items()}}
    estimated = {}
    for key, (sens, plots) in cases.items():
        r = client.post("/v1/jobs", json={"sensors": sens, "tracks": {key: plots}})
        assert r.status_code == 202, r.text
        loc = r.headers["location"]
        assert wait(client, loc)["state"] == "done"
        got = client.get(f"{loc}/tracks/{key}").json()["trajectory"]
        single = client.post("/v1/reconstructions", json={"sensors": sens, "plots": plots})
        assert single.status_code == 200, single.text
        want = single.json()["trajectory"]
        for name in ("altitude_m", "altitude_sigma_m"):
            assert (name in got) == (name in want), (key, name)
            assert got.get(name, 0.0) == pytest.approx(want.get(name, 0.0), abs=1e-6)
        estimated[key] = "altitude_m" in got
        assert client.delete(loc).status_code == 204
    assert estimated["ALONE"] is False, estimated


def test_a_jobs_track_with_flight_levels_is_the_single_answer(client):
    """Every plot field a single request takes reaches a JSON job's track: `flight_level`
    was dropped (a tester's Mode C track: 655 m RMS as a job, 49.6 m as a single request).
    The radars' Mode C reads 250 m low (flight level only), the ADS-B gives the geometric
    height and its flight level: the job's track has the single answer's states and
    warnings, and its `summary.json` the +250 m offset (it was null)."""
    from dataclasses import fields

    from service.models import PlotIn
    from solver.io.tables import PlotRows

    assert set(PlotIn.model_fields) <= {f.name for f in fields(PlotRows)}
    low = 250.0 / 30.48  # flight levels
    enc = encode_recording(duration=40.0)
    sensors, tracks = json_tracks(enc)
    plots = []
    for p, fl in zip(tracks["A"], (q["fl"] for q in enc.plots if q["flight"] == 0),
                     strict=True):
        plots.append(p | ({"flight_level": fl - low} if "range_m" in p else
                          {"altitude_m": fl * 30.48, "flight_level": fl - low}))
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {"A": plots}})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    assert wait(client, loc)["state"] == "done"
    track = client.get(f"{loc}/tracks/A").json()
    got = track["trajectory"]["at_plots"]
    single = client.post("/v1/reconstructions", json={"sensors": sensors, "plots": plots})
    assert single.status_code == 200, single.text
    want = single.json()
    assert any("made geometric by the aircraft's ADS-B: +250.0 m" in w
               for w in want["diagnostics"]["warnings"]), want["diagnostics"]["warnings"]
    # the same words in the job's track (it had none: the offset only in summary.json)
    assert track["diagnostics"]["warnings"] == want["diagnostics"]["warnings"]
    assert len(got) == len(want["trajectory"]["at_plots"]) == len(plots)
    for field in ("t", "x", "z", "vx", "vz", "lat_deg", "lon_deg"):
        np.testing.assert_allclose([s[field] for s in got],
                                   [s[field] for s in want["trajectory"]["at_plots"]],
                                   rtol=0, atol=1e-6, err_msg=field)
    offsets = client.get(loc + "/results/summary.json").json()["mode_c_offsets"]
    assert offsets is not None and offsets["tracks"] == 1, offsets
    assert offsets["median_m"] == pytest.approx(250.0, abs=0.01)
    assert client.delete(loc).status_code == 204


def test_upload_over_the_limit_is_413(client):
    r = upload(client, b"\x30" * (UPLOAD_LIMIT + 1))
    assert r.status_code == 413
    assert "upload limit of 200000 bytes" in r.json()["message"]

    def chunks():  # no Content-Length: counted while streaming
        for _ in range(30):
            yield b"x" * 10_000

    r = client.post("/v1/jobs", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413 and r.json()["detail"] == []


def test_a_json_body_of_tracks_has_its_own_smaller_limit(tmp_path):
    """A JSON body is validated in memory, about 14 times its size (a tester's 99-MB body took
    the server to 1.5 GB, under the 1-GiB upload limit): it has its own limit, and the 413 says
    to send a table instead; an upload of the same size is not held to it."""
    settings = Settings(workers=1, warmup=False, access_log=False, log_level="WARNING",
                        data_dir=tmp_path, jobs_max_upload_bytes=200_000,
                        jobs_max_json_bytes=50_000)
    with TestClient(create_app(settings)) as c:
        r = c.post("/v1/jobs", content=b" " * 60_000, headers={"content-type": "application/json"})
        assert r.status_code == 413, r.text
        assert "limit of 50000 bytes for a JSON body" in r.json()["message"]
        assert "CSV or Parquet" in r.json()["message"]
        assert upload(c, b"\x00" * 60_000, name="x.csv").status_code == 202


@pytest.mark.parametrize(("files", "field"), [
    ({"sensors": ("s.json", json.dumps(SENSOR_FILE))}, "recording"),
    ({"recording": ("r.ast", b"\x30\x00\x03")}, "sensors"),
    ({"recording": ("r.ast", b"\x30\x00\x03"), "sensors": ("s.json", "[{\"id\": \"R1\"}]")},
     "sensors[0].kind"),
    ({"recording": ("r.ast", b"\x30\x00\x03"),
      "sensors": ("s.json", json.dumps([{**SENSOR_FILE[0], "range_error_m": -1.0}]))},
     "sensors[0].range_error_m"),
    ({"recording": ("r.ast", b""), "sensors": ("s.json", json.dumps(SENSOR_FILE))},
     "recording"),
    # JSON of any layout and name: a compact one was accepted, then failed as a CSV table
    *(({"recording": (name, text), "sensors": ("s.json", json.dumps(SENSOR_FILE))},
       "recording is not an ASTERIX recording (its first bytes ")
      for name in ("r.ast", "x.json", "recording", "t.csv")
      for text in (json.dumps({"sensors": SENSOR_FILE}).encode(),
                   json.dumps(SENSOR_FILE, indent=2).encode(),
                   b"\xef\xbb\xbf\n " + json.dumps({"sensors": SENSOR_FILE}).encode())),
    ({"recording": ("r.ast", b"\x30"), "sensors": ("s.json", json.dumps(SENSOR_FILE)),
      "extra": ("e", b"1")}, "extra"),
    *(({"recording": ("r.ast", b"\x30\x00\x03"), "sensors": ("s.json", json.dumps(SENSOR_FILE)),
        "options": ("o.json", text)}, field) for text, field in (
        ('{"filters": ["singer", "nope"]}', "options.filters[1]"),
        ('{"bounds": {"v": [300.0, 30.0]}}', "options.bounds.v"),
        ('{"filters": ["singer"], "colour": 1}', "options.colour"),
        ('{"sample_step_s": 0}', "options.sample_step_s"),
        ('{"method": "kalman"}', "options.method"),
        ('{"window": {"plots": 1}}', "options.window.plots"),
        ('{"window": {"trial_step_s": 0}}', "options.window.trial_step_s"),
        # accepted, then every track failed alike (a tester's): the single request's bound
        ('{"window": {"trial_step_s": 1e-9}}', "options.window.trial_step_s"),
        ('{"criterion": "R3"}', "options.criterion"),
        ('{"aircraft": []}', "options.aircraft"),
        ('{"aircraft": [""]}', "options.aircraft[0]"),
        ('{"editions": {"21": "0.27"}}', "options.editions: Value error, '21=0.27': "
         "libasterix has no CAT021 edition '0.27'; the choices: CAT021 0.23, 0.24"),
        ('{"editions": {"62": "1.19"}}', "options.editions.62"),
        ('{"editions": ["21=0.26"]}', "options.editions"),
        ('{"date": "2023-02-29"}', "options.date: Value error, '2023-02-29' is not a date"),
        ('{"date": "14.11.2023"}', "options.date"),
        ('{"date": 20231114}', "options.date"),
        ('{"filters": [', "options is not valid JSON"))),
])
def test_bad_upload_is_422_naming_the_part(client, files, field):
    r = client.post("/v1/jobs", files=files)
    assert r.status_code == 422, r.text
    assert r.json()["message"].startswith(field), r.json()


def test_bad_json_tracks_are_422_naming_the_field(client):
    sensors = [{k: v for k, v in SENSOR_FILE[0].items() if k not in ("sac", "sic")}]
    plot = {"t": 0.0, "sensor": "R1", "range_m": 1000.0, "azimuth_deg": 10.0}
    cases = [
        ({"sensors": sensors, "tracks": {"A": [plot, {**plot, "sensor": "X"}]}},
         "tracks.A[1].sensor"),
        ({"sensors": sensors, "tracks": {"A": [plot, {"t": 1.0, "sensor": "R1",
                                                      "range_m": 1.0}]}},
         "tracks.A[1].azimuth_deg"),
        ({"sensors": sensors, "tracks": {}}, "tracks"),
        ({"sensors": sensors}, "tracks"),
        ({"sensors": sensors, "tracks": {"A": [{**plot, "range_m": "far"}]}},
         "tracks.A[0].range_m"),
        ({"sensors": sensors, "tracks": {"A": [plot]}, "bounds": {"v": [300.0, 30.0]}},
         "bounds.v"),
        ({"sensors": sensors, "tracks": {"A": [plot]}, "filters": ["kalman"]},
         "filters[0]"),
        ({"sensors": sensors, "tracks": {"A": [plot]}, "sample_step_s": -1.0},
         "sample_step_s"),
        ({"sensors": sensors, "tracks": {"A": [plot]}, "method": "imm"}, "method"),
        ({"sensors": sensors, "tracks": {"A": [plot]}, "window": {"plots": 1}},
         "window.plots"),
        ({"sensors": sensors, "tracks": {"A": [plot]}, "window": {"trial_step_s": 1e-9}},
         "window.trial_step_s"),
    ]
    for body, field in cases:
        r = client.post("/v1/jobs", json=body)
        assert r.status_code == 422, (body, r.text)
        assert r.json()["message"].startswith(field), (field, r.json()["message"])
    # a track name twice: the earlier track would have been silently lost
    text = json.dumps({"sensors": sensors, "tracks": {"A": [plot], "B": [plot]}})
    r = client.post("/v1/jobs", content=text.replace('"B"', '"A"').encode(),
                    headers={"content-type": "application/json"})
    assert r.status_code == 422 and r.json()["message"].startswith("tracks.A is given twice")
    r = client.post("/v1/jobs", content=b"{not json", headers={"content-type":
                                                                "application/json"})
    assert r.status_code == 422 and "not valid JSON" in r.json()["message"]
    # the position said once (it was "... at line 1 column 2 at line 1 column 1 (char 0)")
    assert r.json()["message"] == ("body: is not valid JSON: key must be a string at line 1 "
                                   "column 2"), r.text
    r = client.post("/v1/jobs", content=b" ", headers={"content-type": "application/json"})
    assert r.json()["message"] == "body: is empty: the request is a JSON object in the body"
    r = client.post("/v1/jobs", content=b"x", headers={"content-type": "text/plain"})
    assert r.status_code == 415


def test_json_tracks_plots_are_checked_as_a_single_tracks(client):
    """A bad plot of a JSON track is a 422 naming it by its track and its index there, in the
    single-track endpoint's words for the same plots (the job would leave it out, reported at
    a row of all tracks joined); an empty track is a 422 too, and a default plane at a pole
    names the radar it comes from."""
    sensors, tracks = json_tracks(encode_recording(duration=60.0))
    radar = next(i for i, p in enumerate(tracks["B"]) if i > 5 and "range_m" in p)
    adsb = next(i for i, p in enumerate(tracks["B"]) if i > 5 and "lat_deg" in p)
    cases = [
        (lambda b: b[radar].update(range_m=-5.0), f"tracks.B[{radar}].range_m must be positive"),
        (lambda b: b[adsb].update(lat_deg=95.0), f"tracks.B[{adsb}].lat_deg must be a finite"),
        (lambda b: b.insert(radar + 1, dict(b[radar])),
         f"tracks.B[{radar + 1}].t is not after tracks.B[{radar}].t"),
    ]
    for change, message in cases:
        plots = copy.deepcopy(tracks["B"])
        change(plots)
        r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {**tracks, "B": plots}})
        assert r.status_code == 422, r.text
        assert r.json()["message"].startswith(message), r.json()
        single = client.post("/v1/reconstructions", json={"sensors": sensors, "plots": plots})
        assert single.status_code == 422, single.text
        assert r.json()["message"] == single.json()["message"].replace("plots[", "tracks.B[")
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {**tracks, "A": []}})
    assert r.status_code == 422 and r.json()["message"].startswith("tracks.A has no plots")
    pole = [{**sensors[0], "lat_deg": 90.0}, *sensors[1:]]
    r = client.post("/v1/jobs", json={"sensors": pole, "tracks": tracks})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["sensors", 0, "lat_deg"]
    assert "defaults to the first radar's site" in r.json()["message"]


@pytest.mark.parametrize("twice", ["recording", "sensors", "options"])
def test_a_part_given_twice_is_422(client, twice):
    """Not the last one silently."""
    parts = {"recording": ("a.ast", b"\x30\x00\x03"),
             "sensors": ("s.json", json.dumps(SENSOR_FILE)), "options": ("o.json", "{}")}
    r = client.post("/v1/jobs", files=[*parts.items(), (twice, parts[twice])])
    assert r.status_code == 422, r.text
    assert r.json()["message"].startswith(f"{twice} is given twice"), r.json()


def test_a_jobs_track_is_found_in_another_case_when_only_one_matches(client):
    """`/tracks/4ca2d1` is the track `4CA2D1` (as `options.aircraft` takes it); an exact key
    comes first, and keys that differ only in case are not guessed between."""
    sensors, tracks = json_tracks(encode_recording(duration=40.0))
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {
        "4CA2D1": tracks["A"], "ab": tracks["B"], "AB": tracks["B"]}})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    assert wait(client, loc)["state"] == "done"
    for path, key in (("4ca2d1", "4CA2D1"), ("4Ca2d1", "4CA2D1"), ("ab", "ab"), ("AB", "AB")):
        one = client.get(f"{loc}/tracks/{path}")
        assert one.status_code == 200 and one.json()["aircraft"] == key, (path, one.text)
    figure = client.get(f"{loc}/tracks/4ca2d1/figure.png")
    assert figure.status_code == 200 and figure.content[:4] == b"\x89PNG"
    r = client.get(f"{loc}/tracks/Ab")
    assert r.status_code == 404 and "2 tracks differ from it only in case" in r.json()["message"]
    assert client.get(f"{loc}/tracks/Ab/figure.png").status_code == 404
    assert client.delete(loc).status_code == 204


def test_a_failed_jobs_error_names_no_server_path(client):
    r = upload(client, b"not a Parquet file", name="day.parquet")
    assert r.status_code == 202
    status = wait(client, r.headers["location"])
    assert status["state"] == "failed" and "'recording.parquet'" in status["error"], status
    assert str(client.app.state.jobs.root) not in status["error"], status


def test_unreadable_recording_is_accepted_and_fails_with_the_reason(client):
    r = upload(client, b"a,b\n1,2\n", name="plots.csv")
    assert r.status_code == 202
    status = wait(client, r.headers["location"])
    assert status["state"] == "failed", status
    # columns of its own are read past; what it lacks is named, with what it has
    assert status["error"].startswith("t is missing: the table needs a `t`, a "
                                      "`time_of_day_s` or a `timestamp` column (columns: a, "
                                      "b)"), status
    assert client.get(r.headers["location"] + "/results/tracks.csv").status_code == 409

    # bytes that are no recording at all (random, a JSON file sent as the recording): refused
    # at the upload naming the part, as the command line does (a new user's JSON file was
    # accepted and failed as "unknown_category at byte 0: CAT123 ...")
    garbage = bytes(np.random.default_rng(7).integers(0, 256, 5000, dtype=np.uint8))
    for data, name in ((garbage, "noise.bin"), (json.dumps(SENSOR_FILE).encode(), "r.json")):
        r = upload(client, data, name=name)
        assert r.status_code == 422, r.text
        assert r.json()["message"].startswith("recording is not an ASTERIX recording (its "
                                              "first bytes "), r.json()
    # a recording whose blocks hold no plot (every record of a SAC/SIC not in the sensor
    # file): accepted, failed with the reason; what was read is there to see
    alien = b"".join(C048.create([cat048("R1", 100.0 + k, 30.0, 10.0, 350.0, 0x4CA2D1, 7,
                                         code=(9, 9))]).unparse().to_bytes() for k in range(5))
    r = upload(client, alien, name="alien.ast")
    assert r.status_code == 202, r.text
    status = wait(client, r.headers["location"])
    assert status["state"] == "failed" and status["rows"] == 0, status
    assert status["error"].startswith("no plot could be read from the recording ("), status
    assert status["problems"]["total"] >= 1 and "byte 3" in status["problems"]["examples"][0]
    # what was read is there to see (the status shows a few examples): 409 before
    problems = client.get(r.headers["location"] + "/results/problems.txt")
    assert problems.status_code == 200 and "byte 3" in problems.text
    summary = client.get(r.headers["location"] + "/results/summary.json").json()
    assert summary["error"] == status["error"] and summary["tracks"] == 0
    # all of it as a zip (a 500 every time: the job had no export directory; a tester's)
    got = client.get(r.headers["location"] + "/results/results.zip")
    assert got.status_code == 200, got.text
    with zipfile.ZipFile(io.BytesIO(got.content)) as z:
        assert {"summary.json", "problems.txt"} <= set(z.namelist())
        assert json.loads(z.read("summary.json"))["error"] == status["error"]


def test_a_file_sent_while_its_job_is_deleted_is_sent_whole_and_one_gone_is_404(
        client, tmp_path, monkeypatch):
    """A DELETE racing reads unlinked a figure, a Parquet part or the zip while it was sent:
    500s (a hostile-client tester's). A file is sent from the file opened before the answer
    (its descriptor closed after); one gone before it is opened is a 404 when its job was
    deleted meanwhile (a 500 when the job is still there: a missing file is then a fault); a
    job being deleted is not found."""
    import asyncio

    from service.routes_jobs import _file

    path = tmp_path / "big.bin"
    data = np.random.default_rng(1).integers(0, 256, 300_000, np.uint8).tobytes()
    path.write_bytes(data)
    answer = _file(path, "application/octet-stream", "big.bin")
    path.unlink()
    sent: list[dict] = []

    async def receive() -> dict:  # the client stays (the answer listens for it leaving)
        await asyncio.sleep(3600)
        return {"type": "http.disconnect"}

    async def send(message: dict) -> None:
        sent.append(message)

    scope = {"type": "http", "method": "GET", "headers": [], "path": "/x"}
    asyncio.run(answer(scope, receive, send))
    assert b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body") \
        == data
    with pytest.raises(OSError):
        os.fstat(answer.fd)  # closed

    loc = upload(client, encode_recording(duration=60.0).data).headers["location"]
    assert wait(client, loc)["state"] == "done"
    runner = client.app.state.jobs
    job_id = loc.rsplit("/", 1)[1]

    def deleted_meanwhile(job: str, name: str):
        runner._deleting.add(job)
        return tmp_path / "gone.csv"

    monkeypatch.setattr(runner, "result_file", deleted_meanwhile)
    try:
        gone = client.get(loc + "/results/tracks.csv")
    finally:
        runner._deleting.discard(job_id)
    assert gone.status_code == 404 and "deleted" in gone.json()["message"], gone.text
    monkeypatch.setattr(runner, "result_file", lambda job, name: tmp_path / "gone.csv")
    assert client.get(loc + "/results/tracks.csv").status_code == 500
    monkeypatch.undo()
    runner._deleting.add(job_id)
    try:
        assert client.get(loc).status_code == 404
        assert client.get(loc + "/tracks/" + f"{FLIGHTS[0].address:06X}").status_code == 404
    finally:
        runner._deleting.discard(job_id)
    assert client.delete(loc).status_code == 204


def test_a_client_gone_mid_upload_is_499_not_an_error(client):
    """A client that closes its connection mid-upload was logged as an unhandled error and
    counted a 500 (a hostile-client tester's: 6 of 6); the single-track route answers 499."""
    import asyncio

    boundary = "xyz"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"recording\"; "
            'filename="day.ast"\r\nContent-Type: application/octet-stream\r\n\r\n').encode()
    messages = [{"type": "http.request", "body": head + bytes(50_000), "more_body": True},
                {"type": "http.disconnect"}]
    sent: list[dict] = []

    async def receive() -> dict:
        return messages.pop(0) if messages else {"type": "http.disconnect"}

    async def send(message: dict) -> None:
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
             "method": "POST", "scheme": "http", "path": "/v1/jobs", "raw_path": b"/v1/jobs",
             "query_string": b"", "root_path": "", "client": ("127.0.0.1", 5000),
             "server": ("127.0.0.1", 8000), "state": {},
             "headers": [(b"host", b"testserver"), (b"content-length", b"150000"),
                         (b"content-type", f"multipart/form-data; boundary={boundary}".encode())]}
    asyncio.run(client.app(scope, receive, send))
    starts = [m for m in sent if m["type"] == "http.response.start"]
    assert [m["status"] for m in starts] == [499], sent


def test_the_embedded_job_cluster_runs_nicer_than_the_single_track_workers(client):
    """A job is background work: its workers ran at niceness 0 beside the single-track
    workers' 5, and a 500-plot request took 590-665 ms during a job instead of 170 (a
    tester's)."""
    import os

    from service.jobs import JOBS_EXTRA_NICENESS

    runner = client.app.state.jobs
    mine = os.nice(0)
    nice = runner._dask().run(os.nice, 0)
    want = mine + min(19, runner.settings.worker_niceness + JOBS_EXTRA_NICENESS)
    assert nice and set(nice.values()) == {min(19, want)}, nice


def test_unknown_job_is_404(client):
    for method, path in (("GET", "/v1/jobs/nope"), ("GET", "/v1/jobs/nope/tracks"),
                         ("DELETE", "/v1/jobs/nope"), ("GET", "/v1/jobs/nope/map.png")):
        r = client.request(method, path)
        assert r.status_code == 404 and r.json()["message"] == "job nope not found"


def test_a_jobs_options_take_the_single_requests_bounds(client):
    """A job's trial step of 1e-9 s was accepted (202) and then failed every track with the
    same error: it is the single request's 422 at the same field, from the same bound."""
    sensors, tracks = json_tracks(encode_recording(duration=20.0))
    window = {"plots": 3, "trial_step_s": 1e-9}
    job = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks,
                                        "method": "sliding", "window": window})
    single = client.post("/v1/reconstructions", json={"sensors": sensors, "plots": tracks["A"],
                                                      "method": "sliding", "window": window})
    assert job.status_code == single.status_code == 422, (job.text, single.text)
    assert job.json()["message"] == single.json()["message"], (job.json(), single.json())
    assert job.json()["message"].startswith("window.trial_step_s must be at least 0.0078125 s")


def test_long_path_values_are_not_echoed_whole(client):
    """A 100-KB job id came back whole in its 404 message (60,000 characters here: the test
    client's longest URL is 65,536)."""
    long = "x" * 60_000
    job = client.post("/v1/jobs", json=dict(zip(("sensors", "tracks"), json_tracks(
        encode_recording(duration=20.0)), strict=True))).headers["location"]
    for path in (f"/v1/jobs/{long}", f"/v1/jobs/{long}/tracks", f"{job}/tracks/{long}",
                 f"{job}/results/{long}", f"/v1/jobs/{long}/tracks/A/figure.png"):
        r = client.get(path)
        assert r.status_code == 404, (path[:60], r.status_code)
        assert len(r.content) < 400 and "(60000 characters)" in r.json()["message"], r.text
    wait(client, job)
    client.delete(job)


def test_head_answers_like_get_without_the_body(client):
    """HEAD on a GET route (a job's status, tracks, results, figures) was a 405: it answers the
    GET's status and headers, Content-Length included, with no body; a file is not sent."""
    sensors, tracks = json_tracks(encode_recording(duration=20.0))
    job = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks}).headers["location"]
    assert wait(client, job)["state"] == "done"
    for path in (job, f"{job}/tracks", f"{job}/tracks/A", f"{job}/tracks/A/figure.png",
                 f"{job}/map.png", f"{job}/results/summary.json", f"{job}/results/results.zip",
                 f"{job}/sensors", "/v1/jobs/nope", f"{job}/results/nope"):
        for encoding in ("identity", "gzip"):
            head = client.head(path, headers={"accept-encoding": encoding})
            get = client.get(path, headers={"accept-encoding": encoding})
            assert head.status_code == get.status_code, (path, head.status_code)
            assert head.content == b"", path
            same = ("content-type", "content-length", "content-encoding", "x-total-count")
            assert [head.headers.get(k) for k in same] == [get.headers.get(k) for k in same], (
                path, encoding)
    assert client.head(f"{job}/results/results.zip").headers["content-length"] == str(
        len(client.get(f"{job}/results/results.zip").content))
    assert client.head("/v1/reconstructions").status_code == 405  # POST only
    assert client.head("/healthz").status_code == 200
    client.delete(job)


@pytest.fixture(scope="module")
def lean(tmp_path_factory):
    """An app of one build slot and none to wait in, a JSON budget of 1 KiB and a queue of
    one job."""
    settings = Settings(workers=1, warmup=False, access_log=False, log_level="WARNING",
                        data_dir=tmp_path_factory.mktemp("lean"), jobs_max_running=1,
                        jobs_workers=1, jobs_max_queued=0, jobs_answer_builds=1,
                        jobs_answer_waiting=0,
                        jobs_json_bytes_in_flight=1024)
    with TestClient(create_app(settings)) as c:
        yield c


def test_large_answers_beyond_the_build_slots_are_503(lean):
    """Job answers are built at most ``jobs_answer_builds`` at once (20 built at once held
    /healthz up to 10.8 s); beyond those and the waiting places: 503 with Retry-After."""
    slots = lean.app.state.answer_slots
    lean.portal.call(slots.acquire)  # an answer being built
    try:
        for path in ("/v1/jobs/nope/tracks", "/v1/jobs/nope/tracks/A"):
            r = lean.get(path)
            assert r.status_code == 503 and r.headers["retry-after"] == "2", r.text
            assert r.json()["message"].startswith("too many large answers at once: 1 large "
                                                  "answers are being built and 0 wait")
        assert lean.get("/healthz").status_code == 200
    finally:
        lean.portal.call(slots.release)
    assert lean.get("/v1/jobs/nope/tracks").status_code == 404
    assert (slots.building, slots.waiting) == (0, 0)


def test_json_bodies_beyond_their_byte_budget_or_the_queue_are_503(lean):
    """JSON bodies in flight are bounded in bytes (6 of 30 MB at once took the service from
    0.9 to 2.7 GB), and a body being received holds a place in the queue (the room check
    counted committed jobs only): beyond either, 503 with Retry-After before reading it; one
    body alone is let in whatever its size."""
    sensors, tracks = json_tracks(encode_recording(duration=20.0))
    body = {"sensors": sensors, "tracks": tracks}
    assert len(json.dumps(body)) > 1024
    budget = lean.app.state.json_bytes
    budget.reserve(1000)  # a body being received
    try:
        r = lean.post("/v1/jobs", json=body)
        assert r.status_code == 503 and r.headers["retry-after"] == "2", r.text
        assert r.json()["message"].startswith("too many JSON bodies at once: 1000 bytes of "
                                              "JSON bodies of tracks are being received")
    finally:
        budget.release(1000)
    runner = lean.app.state.jobs
    with runner.receiving():  # the queue's one place taken by a post being received
        r = lean.post("/v1/jobs", json=body)
        assert r.status_code == 503, r.text
        assert "0 jobs are queued or running and 1 more are being received" in r.text
    r = lean.post("/v1/jobs", json=body)
    assert r.status_code == 202, r.text
    assert budget.taken == 0 and runner._receiving == 0
    lean.delete(r.headers["location"])
    budget.reserve(2000)  # one body alone over the budget: a post holding none still enters
    try:
        budget.reserve(0)
        with pytest.raises(Crowded):
            budget.reserve(1)
    finally:
        budget.release(2000)


def test_a_named_dask_scheduler_runs_the_jobs(client, tmp_path):
    """``dask_scheduler``: the tracks run on that cluster (here the first app's, which stays
    up when this app closes its client)."""
    address = client.app.state.jobs.dask_address
    assert address is not None  # the jobs above started the embedded cluster
    settings = Settings(workers=1, warmup=False, access_log=False, log_level="WARNING",
                        data_dir=tmp_path, dask_scheduler=address, jobs_track_figures=False)
    enc = encode_recording(duration=40.0)
    with TestClient(create_app(settings)) as other:
        r = upload(other, enc.data)
        assert r.status_code == 202
        status = wait(other, r.headers["location"])
        assert status["state"] == "done" and status["tracks_done"] == len(FLIGHTS), status
        jobs = other.app.state.jobs
        assert jobs.dask_address == address and jobs._cluster is None  # no cluster of its own
    assert client.get("/healthz").status_code == 200
    r = upload(client, enc.data)  # the first app's cluster still serves
    assert wait(client, r.headers["location"])["state"] == "done"


def test_a_job_that_reconstructs_no_track_is_failed_with_its_outputs(client, tmp_path):
    """A job that ran to its end without one track reconstructed is ``failed``, not ``done``:
    every track over its time limit (the reason of the first, the tracks' reasons at /tracks),
    or no track long enough to try. Its summary and problems stay readable."""
    address = client.app.state.jobs.dask_address
    assert address is not None
    settings = Settings(workers=1, warmup=False, access_log=False, log_level="WARNING",
                        data_dir=tmp_path, dask_scheduler=address, jobs_track_figures=False,
                        jobs_track_time_limit_s=1e-4)
    enc = encode_recording(duration=40.0)
    with TestClient(create_app(settings)) as other:
        r = upload(other, enc.data)
        assert r.status_code == 202
        loc = r.headers["location"]
        status = wait(other, loc)
        assert status["state"] == "failed", status
        assert (status["tracks_total"], status["tracks_done"], status["tracks_failed"]) == (
            len(FLIGHTS), 0, len(FLIGHTS))
        assert status["error"].startswith(f"every one of the {len(FLIGHTS)} tracks failed ("), \
            status
        assert "DeadlineExceeded" in status["error"] and "see /tracks" in status["error"]
        listed = other.get(f"{loc}/tracks").json()
        assert all(t["status"] == "failed" and "DeadlineExceeded" in t["error"] for t in listed)
        summary = other.get(f"{loc}/results/summary.json")
        assert summary.status_code == 200, summary.text
        assert (summary.json()["done"], summary.json()["failed"]) == (0, len(FLIGHTS))
        assert set(summary.json()["failures"]) == {t["aircraft"] for t in listed}
        r = other.get(f"{loc}/results/tracks.parquet")
        assert r.status_code == 404 and "no track was reconstructed" in r.json()["message"]
        assert other.get(f"{loc}/map.png").status_code == 404

        sensors, tracks = json_tracks(enc)
        r = other.post("/v1/jobs", json={"sensors": sensors,
                                         "tracks": {k: v[:2] for k, v in tracks.items()}})
        assert r.status_code == 202, r.text
        status = wait(other, r.headers["location"])
        assert status["state"] == "failed" and status["tracks_total"] == 0, status
        assert status["error"].startswith("no aircraft's track could be read from the "
                                          "job's input (short_track"), status
        assert status["problems"]["counts"] == {"short_track": 2}
        problems = other.get(r.headers["location"] + "/results/problems.txt")
        assert problems.status_code == 200 and "short_track: 2" in problems.text


def test_a_second_service_on_the_same_data_dir_is_refused(client):
    """Two services would run the same jobs into the same directories: the second one's jobs
    answer 503 naming the reason (single tracks still served)."""
    settings = Settings(workers=1, warmup=False, access_log=False, log_level="WARNING",
                        data_dir=client.app.state.jobs.root)
    with TestClient(create_app(settings)) as other:
        r = other.get("/v1/jobs/x")
        assert r.status_code == 503 and "another service uses the data directory" in r.json()[
            "message"]
        assert other.get("/healthz").status_code == 200
    assert client.get("/v1/jobs/x").status_code == 404  # the first one serves on


def test_a_cancelled_jobs_outputs_cut_by_a_kill_are_written_by_the_next_service(client,
                                                                                  tmp_path):
    """A service killed after a DELETE and before the cancelled job's whole-job outputs
    (their files removed here, as a kill leaves them: the summary is written last, whole)
    left its results 409 for good; the next service on the data directory writes them."""
    settings = _store_settings(client, tmp_path)
    with TestClient(create_app(settings)) as first:
        loc, _ = _upload_until_a_track_is_done(first)
        cancelled = first.delete(loc).json()
        out = tmp_path / "jobs" / cancelled["id"] / "out"
    written = {p.name: p.read_bytes() for p in (out / "export").iterdir()}
    assert "tracks.parquet" in written
    for name in ("summary.json", "sensors.json", "map.png"):
        (out / name).unlink()
    shutil.rmtree(out / "export")
    with TestClient(create_app(settings)) as second:
        end = time.monotonic() + 60
        while (summary := second.get(loc + "/results/summary.json")).status_code == 409:
            assert time.monotonic() < end, "the cut outputs were not written again"
            time.sleep(0.1)
        assert summary.status_code == 200, summary.text
        assert summary.json()["cancelled"] and summary.json()["done"] == cancelled["tracks_done"]
        assert second.get(loc).json()["state"] == "cancelled"
        assert second.get(loc + "/map.png").status_code == 200
        assert second.get(loc + "/sensors").status_code == 200
        assert second.get(loc + "/results/tracks.parquet").content == written["tracks.parquet"]
        assert second.delete(loc).status_code == 204


def test_a_job_of_more_tracks_than_the_limit_fails_at_once_or_is_refused(client, tmp_path):
    """A job's cost is bounded by jobs_max_tracks times the track time limit (a tester's
    30,000 three-plot tracks held the only job slot for 6.7 hours): a recording read into more
    tracks fails at once with the reason; a JSON body of more is a 422."""
    settings = _store_settings(client, tmp_path).model_copy(update={"jobs_max_tracks": 5})
    with TestClient(create_app(settings)) as small:
        loc = upload(small, encode_recording(duration=60.0, flights=MANY).data).headers[
            "location"]
        status = wait(small, loc)
        assert status["state"] == "failed", status
        assert status["error"].startswith("the recording holds 6 tracks, more than this "
                                          "service's 5 a job"), status
        sensors = [{k: v for k, v in s.items() if k not in ("sac", "sic")} for s in SENSOR_FILE]
        plot = {"t": 0.0, "sensor": sensors[0]["id"], "range_m": 5e4, "azimuth_deg": 10.0}
        r = small.post("/v1/jobs", json={"sensors": sensors,
                                         "tracks": {f"K{k}": [plot] * 3 for k in range(6)}})
        assert r.status_code == 422 and "at most 5" in r.json()["message"], r.text


def test_a_stopped_service_resumes_its_running_job(client, tmp_path):
    """A service stopped mid-job (its lifespan's end, as on SIGTERM) leaves the job running in
    its store; the next service on the data directory resumes it: no track failed by the
    stop, every track once. (Both on this module's cluster, through ``dask_scheduler``.)"""
    settings = _store_settings(client, tmp_path)
    with TestClient(create_app(settings)) as first:
        loc, before = _upload_until_a_track_is_done(first)
    with TestClient(create_app(settings)) as second:
        assert second.get(loc).json()["state"] in ("queued", "running")
        status = wait(second, loc)
        tracks = second.get(loc + "/tracks").json()
        table = pq.read_table(io.BytesIO(second.get(loc + "/results/tracks.parquet").content))
    assert before["state"] == "running" and before["tracks_done"] < len(MANY)
    assert status["state"] == "done" and status["runs"] == 2, status
    assert status["tracks_done"] == len(MANY) and status["tracks_failed"] == 0
    pairs = list(zip(table.column("aircraft").to_pylist(), table.column("plot").to_pylist(),
                     strict=True))
    assert len(pairs) == len(set(pairs)) == sum(t["plots"] for t in tracks)


def test_a_jobs_track_has_the_manoeuvres_of_the_single_track_answer(client):
    """The seed-like sample track (examples/seed_track.json) as a job's JSON track on the
    earth: its `trajectory.manoeuvres` (read back from `segments.parquet`) are those of
    `POST /v1/reconstructions` for the same sensor and plots, and `manoeuvres.csv` lists them
    with latitude and longitude."""
    seed = json.loads((ROOT / "examples" / "seed_track.json").read_text())
    sensors = [{"id": "R", "kind": "radar", "lat_deg": 46.0, "lon_deg": 14.0, "height_m": 0.0,
                "range_error_m": seed["radar"]["range_error_m"],
                "azimuth_error_deg": seed["radar"]["azimuth_error_deg"]}]
    plots = [{"sensor": "R", **p} for p in seed["plots"]]
    want = client.post("/v1/reconstructions", json={"sensors": sensors, "plots": plots})
    assert want.status_code == 200, want.text
    expected = want.json()["trajectory"]["manoeuvres"]
    assert [(m["kind"], m["direction"]) for m in expected] == [
        ("speed_change", "decrease"), ("turn", "right"), ("speed_change", "increase"),
        ("turn", "left"), ("speed_change", "decrease")]
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {"SEED": plots}})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    assert wait(client, loc)["state"] == "done"
    got = client.get(f"{loc}/tracks/SEED").json()["trajectory"]["manoeuvres"]
    assert len(got) == len(expected)
    for g, e in zip(got, expected, strict=True):
        # beside the single answer's fields, a job's UTC times: null, a JSON track has no date
        assert g.pop("time_utc_start") is None and g.pop("time_utc_end") is None
        assert g == {k: v if isinstance(v, str) else pytest.approx(v, rel=1e-9, abs=1e-6)
                     for k, v in e.items()}
    segments = pq.read_table(io.BytesIO(client.get(loc + "/results/segments.parquet").content))
    assert segments.num_rows and all(segments.column(f"time_utc_{end}").null_count
                                     == segments.num_rows for end in ("start", "end"))
    table = list(csv.DictReader(io.StringIO(client.get(loc + "/results/manoeuvres.csv").text)))
    assert [(m["aircraft"], m["kind"], m["direction"]) for m in table] == [
        ("SEED", e["kind"], e["direction"]) for e in expected]
    for m, e in zip(table, expected, strict=True):
        assert float(m["t_start"]) == pytest.approx(e["t_start"])
        # the plane is centred on the radar: 1 deg of latitude is 111 km north
        assert float(m["lat_start_deg"]) == pytest.approx(46.0 + e["x_start"] / 111_200,
                                                          abs=0.02)
    assert client.delete(loc).status_code == 204


def test_a_full_disk_neither_stops_the_runner_nor_gives_a_500(client, monkeypatch):
    """The store failing to write (SQLite's 'database or disk is full', as on a tester's 3-MB
    tmpfs): the runner's thread died on it, leaving later jobs queued or running until a
    restart, and DELETE answered 500. Now the runner retries and runs the job; DELETE answers
    503 with Retry-After, and again, once the store writes, 204."""
    import sqlite3

    import service.jobs as jobs_module

    full = sqlite3.OperationalError("database or disk is full")
    real_claim, real_delete = jobs_module.JobStore.claim, jobs_module.JobStore.delete
    fails = {"claim": 1, "delete": 1}

    def claim(self):
        if fails["claim"]:
            fails["claim"] -= 1
            raise full
        return real_claim(self)

    def delete(self, job_id):
        if fails["delete"]:
            fails["delete"] -= 1
            raise full
        return real_delete(self, job_id)

    monkeypatch.setattr(jobs_module, "STORE_RETRY_S", 0.2)
    monkeypatch.setattr(jobs_module.JobStore, "claim", claim)
    monkeypatch.setattr(jobs_module.JobStore, "delete", delete)
    sensors, tracks = json_tracks(encode_recording(duration=40.0))
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {"A": tracks["A"]}})
    assert r.status_code == 202, r.text
    status = wait(client, r.headers["location"], timeout=60.0)
    assert status["state"] == "done" and fails["claim"] == 0, status
    gone = client.delete(r.headers["location"])
    assert gone.status_code == 503 and "Retry-After" in gone.headers, gone.text
    assert "job store cannot be written" in gone.json()["message"]
    assert client.delete(r.headers["location"]).status_code == 204
    assert client.get(r.headers["location"]).status_code == 404


@pytest.mark.parametrize("key", ["A" * 201, "A\x00B", "tab\there"])
def test_a_json_track_key_is_a_printable_name_of_at_most_200_characters(client, key):
    """A tester's 100,000-character key and a key with NUL were accepted and the job ran: the
    keys name the tracks in every answer and file, like the aircraft option (200 characters)."""
    sensors = [{k: v for k, v in s.items() if k not in ("sac", "sic")} for s in SENSOR_FILE]
    plot = {"t": 0.0, "sensor": sensors[0]["id"], "range_m": 5e4, "azimuth_deg": 10.0}
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {key: [plot] * 3}})
    assert r.status_code == 422, r.text
    assert "at most 200 printable characters" in r.json()["message"]


def test_a_json_track_key_may_not_end_like_the_figures_path(client):
    """`t/figure.png` was accepted, but its URL is the figure of a track `t` (404): no answer
    could ever be read. Refused at submission."""
    sensors = [{k: v for k, v in s.items() if k not in ("sac", "sic")} for s in SENSOR_FILE]
    plot = {"t": 0.0, "sensor": sensors[0]["id"], "range_m": 5e4, "azimuth_deg": 10.0}
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {"t/figure.png": [plot] * 3}})
    assert r.status_code == 422, r.text
    assert r.json()["message"] == ("tracks.t/figure.png is not a track name: it may not end in "
                                   "/figure.png (the track figure's path)"), r.json()


@pytest.mark.parametrize("key", ["A#2", "A~2"])
def test_a_json_track_key_may_not_look_like_a_piece(client, key):
    """`A#2` names key `A`'s piece after a time gap: a track so named merged with it (a fuzz
    helper, through a table); `A~2` another aircraft found under key `A`: a track so named
    was accepted, then all its plots dropped as bad values "at row N" (a tester's). Refused
    at submission."""
    sensors = [{k: v for k, v in s.items() if k not in ("sac", "sic")} for s in SENSOR_FILE]
    plot = {"t": 0.0, "sensor": sensors[0]["id"], "range_m": 5e4, "azimuth_deg": 10.0}
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {key: [plot] * 3}})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["tracks", key], r.json()
    assert "may not end in #<number> or ~<number>" in r.json()["message"], r.json()


@pytest.mark.parametrize(("key", "said"), [("B1 ", "white space"), (" B1", "white space"),
                                           ("B1\t", "printable"), (".", "path segments"),
                                           ("..", "path segments"), ("a/../b", "path segments"),
                                           ("x/./y", "path segments"), ("../b", "path segments")])
def test_a_json_track_key_with_edge_spaces_or_a_dot_segment_is_refused(client, key, said):
    """`B1 ` was stored as `B1` and merged with the track of that name, 10 plots 70 km apart
    fitted as one, no problem reported; `..` is resolved away by clients (a hostile-client
    tester's). Refused at submission, naming the key."""
    sensors = [{k: v for k, v in s.items() if k not in ("sac", "sic")} for s in SENSOR_FILE]
    plot = {"t": 0.0, "sensor": sensors[0]["id"], "range_m": 5e4, "azimuth_deg": 10.0}
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {"B1": [plot] * 3,
                                                                     key: [plot] * 3}})
    assert r.status_code == 422, r.text
    assert said in r.json()["message"] and r.json()["detail"][0]["loc"] == ["tracks", key]
    three = [{**plot, "t": float(k), "range_m": 5e4 + 200.0 * k} for k in range(3)]
    ok = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {"a/b..c": three}})
    assert ok.status_code == 202, ok.text  # dots inside a segment are a name
    client.delete(ok.headers["location"])


def test_a_job_resumed_by_other_software_redoes_its_finished_tracks(client, monkeypatch):
    """A job the service resumes after an upgrade (its record running again at a start) kept
    the old version's finished tracks beside the new ones' (the command line refuses such a
    rerun; a review helper found the service's resume unchecked). The finished tracks are
    removed and redone, and the status says so; the same software resumes as ever."""
    import service.jobs as jobs_module

    r = upload(client, encode_recording().data)
    assert r.status_code == 202
    loc = r.headers["location"]
    first = wait(client, loc)
    assert first["state"] == "done" and first["tracks_done"] == first["tracks_total"] > 0
    runner = client.app.state.jobs
    job_id = loc.rsplit("/", 1)[1]
    kept = json.loads((runner.job_dir(job_id) / "out" / "software.json").read_text())
    assert kept == jobs_module.software()
    upgraded = {**kept, "solver_sha256": "f" * 64}
    monkeypatch.setattr(jobs_module, "software", lambda: upgraded)
    progress = runner.job_dir(job_id) / "out" / "progress.jsonl"
    old_lines = progress.read_text().splitlines()
    with runner._db()._tx() as db:  # as a start finds a job its stop left running
        db.execute("UPDATE jobs SET state = 'queued' WHERE id = ?", (job_id,))
    with runner._wake:
        runner._wake.notify()
    end = time.monotonic() + 120
    while (again := client.get(loc).json())["runs"] == first["runs"] or again["state"] != "done":
        assert time.monotonic() < end, again
        time.sleep(0.2)
    assert again["tracks_done"] == first["tracks_done"] and again["tracks_failed"] == 0
    assert again["problems"]["counts"].get("software_changed") == 1, again["problems"]
    said = next(e for e in again["problems"]["examples"] if "software_changed" in e)
    assert f"its {first['tracks_done']} finished track(s) were redone" in said
    new_lines = progress.read_text().splitlines()  # every track solved again, once
    assert len(new_lines) == len(old_lines) and not set(new_lines) & set(old_lines)
    assert json.loads((runner.job_dir(job_id) / "out" / "software.json").read_text()) \
        == upgraded
    assert client.delete(loc).status_code == 204


def test_a_recordings_cat021_edition_is_a_job_option(client):
    """`options.editions` `{"21": "0.26"}`: a recording whose CAT021 is of edition 0.26 gives
    the tracks (every state at every plot) the same reports in 2.7 give by default, and the
    job's options echo it; without it, the ADS-B reports are an `other_edition` problem and
    the radar's tracks alone are made."""
    from test_asterix_editions import recording

    jobs = {}
    for name, data, options in (("new", recording("2.7"), None),
                                ("old", recording("0.26"), {"editions": {"21": "0.26"}}),
                                ("default", recording("0.26"), {})):
        r = client.post("/v1/jobs", files={"recording": ("day.ast", data),
                                           "sensors": ("sensors.json", json.dumps(SENSOR_FILE))},
                        data={} if options is None else {"options": json.dumps(options)})
        assert r.status_code == 202, r.text
        jobs[name] = (r.headers["location"], wait(client, r.headers["location"]))
    (new_loc, new), (old_loc, old), (_, default) = jobs.values()
    assert old["state"] == new["state"] == "done" and old["problems"]["counts"] == {}
    assert old["options"]["editions"] == {"21": "0.26"} and new["options"]["editions"] == {}
    assert old["rows"] == new["rows"] == 120 and old["tracks_done"] == len(FLIGHTS)
    for t in client.get(new_loc + "/tracks").json():
        a, b = (client.get(f"{loc}/tracks/{t['aircraft']}").json()["trajectory"]["at_plots"]
                for loc in (old_loc, new_loc))
        assert len(a) == len(b) == t["plots"]
        for field in ("t", "lat_deg", "lon_deg", "speed", "sensor"):
            assert [s[field] for s in a] == [s[field] for s in b], field
    assert default["state"] == "done" and default["rows"] == 40, default
    assert default["problems"]["counts"]["other_edition"] == 1
    assert default["problems"]["dropped"]["other_edition"] == 80
    for loc, _ in jobs.values():
        assert client.delete(loc).status_code == 204


def _job_figure_dir(client, loc: str) -> Path:
    return client.app.state.jobs.job_dir(loc.rsplit("/", 1)[1]) / "out" / "figures"


def test_a_jobs_track_figure_is_drawn_when_first_asked_for_from_what_the_job_stored(
        client, monkeypatch):
    """A job drew every track's figure on its workers (0.8 s a figure against 63 ms to solve a
    three-plot track: a tester's 30,000 short tracks spent most of 6.7 h on figures nobody
    asked for). Now none is drawn while the job runs; the first GET draws the figure from the
    job's stored rows and keeps it, later ones answer the kept file (no drawing). The figure
    shows what the one drawn from the job's own reconstruction shows (its drawn data, as
    test_figures compares them, there also with the samples kept in samples.parquet).
    results.zip holds no track figure."""
    from test_figures import difference, drawn

    from solver.figures import draw_track_figure, track_figure
    from solver.reconstruct import reconstruct

    runner = client.app.state.jobs
    sensors, tracks = json_tracks(encode_recording(duration=40.0))
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks})
    assert r.status_code == 202, r.text
    loc, job_id = r.headers["location"], r.json()["id"]
    assert wait(client, loc)["state"] == "done"
    assert not _job_figure_dir(client, loc).exists()  # nothing drawn during the job
    settings = runner.options(job_id)
    loaded, chosen = runner._load(job_id, settings)
    track = next(t for t in chosen if t.key == "A")
    data, times_of_day, date = runner.figure_data(job_id, "A")
    assert (times_of_day, date) == (loaded.times_of_day, loaded.date)
    lazy = drawn(draw_track_figure(data, "A", times_of_day))
    live = drawn(track_figure(track.table, reconstruct(track.table, config=settings.config()),
                              "A", loaded.times_of_day))
    assert difference(lazy, live) is None, difference(lazy, live)
    first = client.get(f"{loc}/tracks/A/figure.png")
    assert first.status_code == 200 and first.content[:8] == b"\x89PNG\r\n\x1a\n"
    (kept,) = _job_figure_dir(client, loc).glob("*/A.png")
    assert kept.read_bytes() == first.content
    stamp = kept.stat().st_mtime_ns

    def no_drawing(*args):
        raise AssertionError("drawn again")

    with monkeypatch.context() as m:
        m.setattr(runner, "draw_figure", no_drawing)
        again = client.get(f"{loc}/tracks/a/figure.png")  # another case: the same track
    assert again.status_code == 200 and again.content == first.content
    assert kept.stat().st_mtime_ns == stamp
    names = zipfile.ZipFile(io.BytesIO(client.get(loc + "/results/results.zip").content)
                            ).namelist()
    assert {n for n in names if n.endswith(".png")} == {"map.png", "sensors.png"}, names
    assert client.delete(loc).status_code == 204


def test_track_figures_drawn_at_once_are_bounded_and_each_drawn_once(client, monkeypatch):
    """At most `jobs_figure_draws` figures are drawn at once (in threads, off the event loop):
    a figure asked for beyond is 503 with Retry-After (a drawn one is still answered); asked
    for again while it is drawn, it is drawn once and both answered from it."""
    import asyncio
    import threading

    from service.job_figures import Busy, TrackFigures

    runner = client.app.state.jobs
    sensors, tracks = json_tracks(encode_recording(duration=40.0))
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks})
    loc, job_id = r.headers["location"], r.json()["id"]
    assert wait(client, loc)["state"] == "done"
    draw, release, calls = runner.draw_figure, threading.Event(), []

    def held(job: str, key: str):
        calls.append(key)
        assert release.wait(30)
        return draw(job, key)

    monkeypatch.setattr(runner, "draw_figure", held)

    async def scenario():
        figures = TrackFigures(runner, max_draws=1)
        first = asyncio.ensure_future(figures.path(job_id, "A"))
        while not calls:  # its drawing started
            await asyncio.sleep(0.01)
        second = asyncio.ensure_future(figures.path(job_id, "A"))
        await asyncio.sleep(0.05)
        with pytest.raises(Busy, match=r"1 figures are being drawn \(the limit is 1"):
            await figures.path(job_id, "B")
        release.set()
        return await first, await second, figures.drawing

    a, b, drawing = asyncio.run(scenario())
    assert a == b and a.is_file() and calls == ["A"] and drawing == 0
    figures = client.app.state.job_figures
    monkeypatch.setattr(figures, "drawing", figures.max_draws)  # every slot taken
    busy = client.get(f"{loc}/tracks/B/figure.png")
    assert busy.status_code == 503 and busy.headers["retry-after"] == "2", busy.text
    assert "too many figures being drawn" in busy.json()["message"]
    assert client.get(f"{loc}/tracks/A/figure.png").status_code == 200  # kept
    assert calls == ["A"]
    release = threading.Event()  # ``held`` now waits on this one

    async def cancelled():  # a request cancelled while its figure is drawn: the thread runs
        figures = TrackFigures(runner, max_draws=1)  # on, and so its slot stays taken
        asking = asyncio.ensure_future(figures.path(job_id, "B"))
        while calls == ["A"]:
            await asyncio.sleep(0.01)
        asking.cancel()
        with pytest.raises(asyncio.CancelledError):
            await asking
        taken = figures.drawing
        release.set()
        while figures.drawing:
            await asyncio.sleep(0.01)
        return taken, figures._pending

    assert asyncio.run(cancelled()) == (1, {})
    assert client.delete(loc).status_code == 204


def test_a_track_figure_asked_for_as_its_job_is_deleted_is_the_deleted_404(client, monkeypatch):
    """A figure request whose job is deleted before its drawing reads the job's data is the
    job-deleted 404 (it was "its job kept nothing to draw it from ... jobs_track_figures":
    the data of a deleted job read as none kept)."""
    runner = client.app.state.jobs
    sensors, tracks = json_tracks(encode_recording(duration=20.0))
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks})
    loc, job_id = r.headers["location"], r.json()["id"]
    assert wait(client, loc)["state"] == "done"
    cached = runner.figure

    def deleted_meanwhile(job: str, key: str):
        got = cached(job, key)  # not drawn yet: None
        assert runner.cancel(job) is None  # the finished job removed with its data
        return got

    monkeypatch.setattr(runner, "figure", deleted_meanwhile)
    gone = client.get(f"{loc}/tracks/A/figure.png")
    assert gone.status_code == 404, gone.text
    assert "deleted" in gone.json()["message"] and "kept nothing" not in gone.text, gone.text
    assert not runner.job_dir(job_id).exists()


def test_a_track_figure_of_a_running_job_and_one_drawn_while_its_job_is_deleted(
        client, monkeypatch):
    """A done track's figure is drawn while its job still runs; an unknown key is a 404
    naming it, a pending track a 409. A figure drawn while a DELETE removes its (finished)
    job is a 404 saying so, never a 500, and nothing of the job is left on disk."""
    runner = client.app.state.jobs
    loc, _ = _upload_until_a_track_is_done(client)
    job_id = loc.rsplit("/", 1)[1]
    done = next(t["aircraft"] for t in client.get(loc + "/tracks").json()
                if t["status"] == "done")
    figure = client.get(f"{loc}/tracks/{done}/figure.png")
    assert figure.status_code == 200 and figure.content[:4] == b"\x89PNG"
    assert client.get(loc).json()["state"] == "running"  # it was drawn while the job ran
    pending = [t["aircraft"] for t in client.get(loc + "/tracks").json()
               if t["status"] == "pending"]
    if pending:
        r = client.get(f"{loc}/tracks/{pending[-1]}/figure.png")
        assert r.status_code == 409 and "pending" in r.json()["message"], r.text
    missing = client.get(f"{loc}/tracks/NOPE/figure.png")
    assert missing.status_code == 404 and "'NOPE'" in missing.json()["message"]
    assert client.delete(loc).status_code == 200  # cancelled
    end = time.monotonic() + 60
    while job_id in runner._running:  # its outputs written: a DELETE now removes it
        assert time.monotonic() < end
        time.sleep(0.1)
    shutil.rmtree(_job_figure_dir(client, loc))  # the figure to be drawn again
    read = runner.figure_data

    def deleted_meanwhile(job: str, key: str):
        got = read(job, key)
        assert runner.cancel(job) is None  # the finished job removed with its data
        return got

    monkeypatch.setattr(runner, "figure_data", deleted_meanwhile)
    gone = client.get(f"{loc}/tracks/{done}/figure.png")
    assert gone.status_code == 404 and "deleted" in gone.json()["message"], gone.text
    assert not runner.job_dir(job_id).exists()


def test_a_compressed_recording_is_refused_at_the_upload(client):
    """A gzipped table or capture was taken as raw ASTERIX (gzip's 1f 8b a CAT031 header) and
    read into made-up problems (a tester's, through the reader the command line shares): a
    422 naming the compression, under a compressed name or a table's."""
    import gzip

    data = gzip.compress(b"t,sensor,lat_deg,lon_deg\n0,ADSB,48.1,16.5\n")
    for name in ("plots.csv.gz", "plots.csv", "day.ast"):
        r = upload(client, data, name=name)
        assert r.status_code == 422, (name, r.text)
        assert r.json()["message"].startswith("recording is compressed with gzip: decompress "
                                              "it first"), r.json()


def test_a_json_job_takes_plots_west_of_the_antimeridian(client):
    """A JSON job's plots are checked as the single request's and read as a table's: one
    longitude limit, [-360, 360], so -180.0006 is taken by both (it was a 422 here and a
    bad_value in a table, while 180.0006 was taken), the answer's longitudes in [-180, 180)."""
    lons = [-179.99 - 0.002 * i for i in range(10)]  # 92 m/s west at 65.5 N, past -180
    sensors = [{"id": "ADSB", "kind": "position", "position_sigma_m": 30.0}]
    tracks = {"W": [{"t": float(i), "sensor": "ADSB", "lat_deg": 65.5, "lon_deg": lon,
                     "altitude_m": 10_000.0} for i, lon in enumerate(lons)]}
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks})
    assert r.status_code == 202, r.text
    status = wait(client, r.headers["location"])
    assert status["state"] == "done" and status["tracks_done"] == 1, status
    assert status["problems"]["counts"] == {}, status
    at_plots = client.get(r.headers["location"] + "/tracks/W").json()["trajectory"]["at_plots"]
    got = np.array([s["lon_deg"] for s in at_plots])
    assert len(got) == 10 and np.all((got >= -180.0) & (got < 180.0))
    assert np.all(np.abs((got - np.array(lons) + 180.0) % 360.0 - 180.0) < 0.002)
