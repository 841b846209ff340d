"""Inputs a fuzz run of a real server found answered with a 5xx, a track stored broken, or a
422 naming a field the client did not send (each test names its finding). Every one is now a
200 or a 4xx naming the field, and a job's track is never stored with a NaN."""

from __future__ import annotations

import copy
import json
import math
import re
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from test_io_asterix import SENSOR_FILE, encode_recording
from test_service_sensors import _body

from service.app import create_app
from service.settings import Settings
from solver import batch
from solver.config import MAX_FILTER_GATE_SIGMA
from solver.results import non_finite_part

ROOT = Path(__file__).resolve().parents[1]
SEED = json.loads((ROOT / "examples" / "seed_track.json").read_text())


def seed(n: int = 14) -> dict:
    body = copy.deepcopy(SEED)
    body["plots"] = body["plots"][:n]
    body["omit"] = ["samples"]
    return body


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    settings = Settings(workers=1, warmup=False, access_log=False, log_level="WARNING",
                        max_plots=2000, max_body_bytes=1_000_000,
                        data_dir=tmp_path_factory.mktemp("jobs"), jobs_workers=1,
                        jobs_track_figures=False)
    with TestClient(create_app(settings)) as c:
        end = time.monotonic() + 120
        while c.get("/readyz").status_code != 200:
            assert time.monotonic() < end
            time.sleep(0.1)
        yield c


def wait(client: TestClient, location: str) -> dict:
    end = time.monotonic() + 120
    while (status := client.get(location).json())["state"] not in ("done", "failed"):
        assert time.monotonic() < end, status
        time.sleep(0.2)
    return status


def assert_422(r, loc: list, start: str) -> None:
    assert r.status_code == 422, r.text[:400]
    assert r.json()["detail"][0]["loc"][-len(loc):] == loc, r.json()
    assert r.json()["message"].startswith(start), r.json()["message"]


@pytest.mark.parametrize("gate", [1.4e154, 1e300, MAX_FILTER_GATE_SIGMA * 1.01])
def test_a_gate_beyond_its_limit_is_422_not_an_overflow(client, gate):
    """F1: 1.4e154 overflowed the gate's square inside the filter (a 500; in a job every
    track's filters failed); the field's upper limit is checked first."""
    body = seed() | {"filters": ["singer"], "filter_gate_sigma": gate}
    assert_422(client.post("/v1/reconstructions", json=body), ["filter_gate_sigma"],
               "filter_gate_sigma: Input should be less than or equal to 1000000")
    sensors = [{"id": "R", "kind": "radar", "range_error_m": 500.0, "azimuth_error_deg": 1.5}]
    tracks = {"A": [{"sensor": "R", **{k: p[k] for k in ("t", "range_m", "azimuth_deg")}}
                    for p in seed()["plots"]]}
    assert_422(client.post("/v1/jobs", json={"sensors": sensors, "tracks": tracks,
                                             "filter_gate_sigma": gate}),
               ["filter_gate_sigma"], "filter_gate_sigma: Input should be less than")
    widest = client.post("/v1/reconstructions", json=body | {
        "filter_gate_sigma": MAX_FILTER_GATE_SIGMA})
    assert widest.status_code == 200 and widest.json()["filters"]["singer"]["gated"] == []


@pytest.mark.parametrize("method", ["sliding", "refined"])
def test_a_vanishing_range_is_answered(client, method):
    """F2, F3: a range of 1e-200 m (sliding: the screening smoother's numerical fallback has no
    `gated`, a KeyError) or 5e-324 m (refined: 0 weight x an infinite residual made the
    criterion NaN, a failed response validation): a 200 with finite numbers, the plot given
    no weight."""
    body = seed() | {"method": method}
    body["plots"][3]["range_m"] = 1e-200 if method == "sliding" else 5e-324
    r = client.post("/v1/reconstructions", json=body)
    assert r.status_code == 200, r.text[:400]
    out = r.json()
    assert all(math.isfinite(v) for v in out["diagnostics"]["criterion_values"])
    if method == "refined":
        assert any("given no weight" in w and w.endswith("plots [3]")
                   for w in out["diagnostics"]["warnings"])


def test_a_job_track_with_a_vanishing_range_is_stored_readable(client):
    """F6: the same plot in a job: the track was stored with a NaN criterion and every read of
    it answered 500; now it reads as the single request answers."""
    sensors = [{"id": "R", "kind": "radar", "lat_deg": 46.0, "lon_deg": 14.0,
                "range_error_m": 500.0, "azimuth_error_deg": 1.5}]
    plots = [{"sensor": "R", **{k: p[k] for k in ("t", "range_m", "azimuth_deg")}}
             for p in seed()["plots"]]
    plots[3]["range_m"] = 5e-324
    r = client.post("/v1/jobs", json={"sensors": sensors, "tracks": {"A": plots}})
    assert r.status_code == 202, r.text
    assert wait(client, r.headers["location"])["state"] == "done"
    track = client.get(r.headers["location"] + "/tracks/A")
    assert track.status_code == 200, track.text[:300]
    assert track.json()["trajectory"]["at_plots"][3]["gated"] is True


def test_a_non_finite_result_fails_its_track_instead_of_being_stored(monkeypatch):
    """The guard behind F6: whatever makes a result non-finite, the track fails naming the
    part, and nothing of it is stored."""
    from solver import reconstruct as module
    from solver.io.asterix import read_recording
    from solver.io.sensors_file import parse_sensors
    from solver.io.split import split_aircraft

    sensors = parse_sensors(SENSOR_FILE)
    rows = read_recording(encode_recording(duration=40.0).data, sensors).rows
    table = next(iter(split_aircraft(rows, sensors))).table
    real = module.reconstruct

    def poisoned(*args, **kwargs):
        rec = real(*args, **kwargs)
        assert non_finite_part(rec) is None
        rec.diagnostics.criterion_values = [float("nan")]
        return rec

    monkeypatch.setattr(module, "reconstruct", poisoned)
    out = batch.solve_track("A", table)
    assert out.status == "failed" and out.states is None
    assert "diagnostics.criterion_values holds NaN or infinity" in out.error


def test_a_tiny_altitude_sigma_is_422(client):
    """F4: a radar's `altitude_sigma_m` of 1e-300 m (with Mode C plots) made the covariance
    smoother's matrix singular (a 500); like a position sensor's, it is 0 or at least 1 mm."""
    body = _body(mode_c=True)
    body["sensors"][1]["altitude_sigma_m"] = 1e-300
    assert_422(client.post("/v1/reconstructions", json=body),
               ["sensors", 1, "altitude_sigma_m"], "sensors[1].altitude_sigma_m must be 0")
    body["sensors"][1]["altitude_sigma_m"] = 1e-3
    assert client.post("/v1/reconstructions", json=body).status_code == 200


def test_an_id_given_to_two_kinds_of_sensor_is_named(client):
    """F7: a position sensor with a radar's id was blamed on the first plot's missing
    `lat_deg`; the repeated id is the error."""
    body = _body()
    body["sensors"][2]["id"] = "LJLJ"
    assert_422(client.post("/v1/reconstructions", json=body), ["sensors", 2, "id"],
               "sensors[2].id 'LJLJ' repeats sensors[0].id")


def test_a_far_idle_radar_is_named_not_the_unsent_reference(client):
    """F8: without `reference` the plane sits at the first radar's site; an idle radar listed
    first, 19,600 km from the plots, was reported as `reference` (never sent)."""
    body = _body()
    del body["reference"]
    body["sensors"].insert(0, {"id": "FAR", "kind": "radar", "lat_deg": -45.0,
                               "lon_deg": -160.0, "range_error_m": 150.0,
                               "azimuth_error_deg": 0.24})
    r = client.post("/v1/reconstructions", json=body)
    assert_422(r, ["sensors", 0], "sensors[0] lies 19639 km from the data")
    assert r.json()["message"].endswith("the plane's `reference` defaults to the first "
                                        "radar's site")


def test_times_spanning_more_than_a_float_are_named_as_the_plots(client):
    """F9: t from -1e308 to 1e308 (each finite, their span not) was blamed on
    `sample_step_s`, which the client did not send."""
    body = seed(3) | {"method": "sliding"}
    for p, t in zip(body["plots"], (-1e308, 0.0, 1e308), strict=True):
        p["t"] = t
    assert_422(client.post("/v1/reconstructions", json=body), ["plots"],
               "plots span from t = -1e+308 to 1e+308 s, more than a float holds")


def test_an_uploads_sensor_file_nested_too_deeply_is_422(client):
    """F5: 3,000 levels of nesting in the `sensors` part hit a RecursionError in the JSON
    parser (a 500 that also dropped the connection)."""
    r = client.post("/v1/jobs", files={
        "recording": ("day.ast", encode_recording(duration=40.0).data),
        "sensors": ("sensors.json", "[" * 3000 + "]" * 3000)})
    assert r.status_code == 422, r.text[:300]
    assert "sensors" in r.json()["message"] and "nested too deeply" in r.json()["message"]
    ok = client.post("/v1/jobs", files={
        "recording": ("day.ast", encode_recording(duration=40.0).data),
        "sensors": ("sensors.json", json.dumps(SENSOR_FILE))})
    assert ok.status_code == 202 and wait(client, ok.headers["location"])["state"] == "done"


def test_a_radar_without_a_site(client):
    """A radar without `lat_deg`/`lon_deg` sits at `reference`: in a job's JSON body it was
    refused for a `height_m` the client never sent (the model's default 0 reached the sensor
    file's check); a `height_m` the client does send without a site is named, in the single
    request too (it was silently ignored there)."""
    sensors = [{"id": "R", "kind": "radar", "range_error_m": 500.0, "azimuth_error_deg": 1.5}]
    tracks = {"A": [{"sensor": "R", **{k: p[k] for k in ("t", "range_m", "azimuth_deg")}}
                    for p in seed()["plots"]]}
    body = {"sensors": sensors, "tracks": tracks, "reference": {"lat_deg": 46.0,
                                                               "lon_deg": 14.0}}
    r = client.post("/v1/jobs", json=body)
    assert r.status_code == 202, r.text
    assert wait(client, r.headers["location"])["tracks_done"] == 1
    high = copy.deepcopy(body)
    high["sensors"][0]["height_m"] = 500.0
    assert_422(client.post("/v1/jobs", json=high), ["sensors", 0, "height_m"],
               "sensors[0].height_m needs lat_deg and lon_deg")
    single = _body()
    single["sensors"][0] = {k: v for k, v in single["sensors"][0].items()
                            if k not in ("lat_deg", "lon_deg")}
    assert_422(client.post("/v1/reconstructions", json=single), ["sensors", 0, "height_m"],
               "sensors[0].height_m needs lat_deg and lon_deg")
    del single["sensors"][0]["height_m"]
    assert client.post("/v1/reconstructions", json=single).status_code == 200


def test_a_sensor_file_whose_first_radar_is_at_a_pole_is_refused_at_once(client):
    """The plane's default tangent point is the first radar's site: at a pole there is no
    plane. An upload was accepted (202) and its job failed naming `reference`, which the file
    did not have; now the upload is a 422 at that radar's `lat_deg` (with a `reference` in the
    file, accepted)."""
    polar = copy.deepcopy(SENSOR_FILE)
    polar[0]["lat_deg"] = 90.0
    r = client.post("/v1/jobs", files={
        "recording": ("day.ast", encode_recording(duration=40.0).data),
        "sensors": ("sensors.json", json.dumps(polar))})
    assert_422(r, ["sensors", 0, "lat_deg"], "sensors[0].lat_deg must be within 89.9 degrees")
    assert "give the file a `reference` away from the pole" in r.json()["message"]
    with_reference = {"sensors": polar, "reference": {"lat_deg": 46.0, "lon_deg": 14.5}}
    from solver.io.sensors_file import parse_sensors

    assert parse_sensors(json.dumps(with_reference)).reference is not None


def test_a_far_reference_names_the_data_it_is_far_from(client):
    """A `reference` 19,600 km from the track: the 422 names what it is measured against (it
    said "a sensor's site or a position plot")."""
    body = _body()
    body["reference"] = {"lat_deg": -45.0, "lon_deg": -160.0}
    r = client.post("/v1/reconstructions", json=body)
    assert_422(r, ["reference"], "reference lies")
    assert "km from the data (the site of sensor 'SSR2')" in r.json()["message"], r.json()
    body["sensors"] = body["sensors"][2:]  # ADS-B alone: its first plot
    body["plots"] = [p for p in body["plots"] if p["sensor"] == "ADSB"]
    r = client.post("/v1/reconstructions", json=body)
    assert_422(r, ["reference"], "reference lies")
    named = re.search(r"km from the data \(plots\[(\d+)\]\)", r.json()["message"])
    assert named and int(named[1]) < len(body["plots"]), r.json()
