"""POST /v1/reconstructions and the operational endpoints, in process (real worker pool)."""

from __future__ import annotations

import asyncio
import copy
import json
import logging
import math
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from benchmarks.truth import SEED_LIKE_CONTROLS
from service.app import create_app
from service.convert import to_job
from service.logs import LOGGER, JsonFormatter
from service.models import ReconstructionRequest
from service.pool import Busy, SolverPool
from service.settings import Settings
from solver.estimation import SINGLE_SENSOR_NAMES
from solver.reconstruct import reconstruct

ROOT = Path(__file__).resolve().parents[1]
SEED_BATCH = json.loads((ROOT / "examples" / "seed_track.json").read_text())


def batch(t_max: float = 600.0) -> dict:
    """The committed seed-like example cut to its first ``t_max`` seconds."""
    body = copy.deepcopy(SEED_BATCH)
    body["plots"] = [p for p in body["plots"] if p["t"] <= t_max]
    return body


def wait_ready(client: TestClient, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while client.get("/readyz").status_code != 200:
        assert time.monotonic() < end, client.get("/readyz").json()
        time.sleep(0.05)


@pytest.fixture(scope="module")
def client():
    app = create_app(Settings(workers=2, max_plots=500, max_samples=20_000,
                              max_body_bytes=200_000, access_log=True))
    with TestClient(app) as c:
        first = c.get("/readyz")
        wait_ready(c)
        c.first_readyz = first  # type: ignore[attr-defined]
        yield c


def post(client: TestClient, body: dict | str | bytes):
    if isinstance(body, dict):
        return client.post("/v1/reconstructions", json=body)
    return client.post("/v1/reconstructions", content=body,
                       headers={"content-type": "application/json"})


# ------------------------------------------------------------------------------ round trip


def test_readyz_waits_for_warm_solvers(client):
    assert client.first_readyz.status_code == 503
    assert client.first_readyz.json()["status"] == "starting"
    assert client.get("/readyz").json() == {"status": "ready", "detail": ""}
    assert client.get("/healthz").json()["status"] == "ok"


def test_health_answers_head_as_get_without_a_body(client):
    """Load balancers probe with HEAD: the GET's status and headers (hand-written HEAD routes
    answered Content-Length 0 without a Content-Type), no body."""
    for path in ("/healthz", "/readyz"):
        r, get = client.head(path), client.get(path)
        assert r.status_code == get.status_code == 200, path
        assert r.content == b""
        for name in ("content-type", "content-length"):
            assert r.headers.get(name) == get.headers[name], (path, name)


def test_reconstruction_matches_in_process_solver(client):
    body = batch(600.0)
    r = post(client, body)
    assert r.status_code == 200, r.text
    out = r.json()
    job = to_job(ReconstructionRequest.model_validate(body), "sqpmethod", 500, 20_000)
    ref = reconstruct(job.plots, job.radar, job.config)

    at = out["trajectory"]["at_plots"]
    assert [p["t"] for p in at] == [p["t"] for p in body["plots"]]
    got = np.array([[p["x"], p["z"], p["vx"], p["vz"]] for p in at])
    np.testing.assert_allclose(got, ref.at_plots.states, rtol=1e-9, atol=1e-6)
    # heading clockwise from north, degrees; speed the norm of (vx, vz)
    for p in at:
        assert p["heading_deg"] == pytest.approx(
            np.rad2deg(np.arctan2(p["vz"], p["vx"])) % 360.0, abs=1e-9)
        assert p["speed"] == pytest.approx(np.hypot(p["vx"], p["vz"]), rel=1e-12)
    seg = out["trajectory"]["segments"]
    assert len(seg) == len(ref.segments)
    assert seg[0]["t_start"] == body["plots"][0]["t"]
    assert seg[-1]["t_end"] == pytest.approx(body["plots"][-1]["t"])
    assert [s["u"] for s in seg] == pytest.approx([s.u for s in ref.segments], rel=1e-9, abs=1e-12)
    samples = out["trajectory"]["samples"]
    assert np.allclose(np.diff([s["t"] for s in samples]), 1.0)
    if ref.at_plots.cov is not None:
        cov = np.array([p["cov"] for p in at])
        np.testing.assert_allclose(cov, ref.at_plots.cov, rtol=1e-9, atol=1e-9)
        assert np.allclose(cov, np.transpose(cov, (0, 2, 1)))
    d = out["diagnostics"]
    assert d["method"] == "refined" and d["criterion"] == "R2"
    assert d["windows_solved"] == ref.diagnostics.windows_solved
    assert d["extra"].keys() == ref.diagnostics.extra.keys()
    assert d["elapsed_ms"] > 0 and d["queue_ms"] >= 0


def test_the_radars_altitude_sigma_reaches_the_solver(client):
    """``radar.altitude_sigma_m`` with Mode C plots: the answer is the in-process solver's with
    that sigma, and not the one with the altitude exact (the default)."""
    body = batch(300.0)
    for p in body["plots"]:
        p["altitude_m"] = 9000.0
    exact = post(client, body).json()["trajectory"]["at_plots"]
    body["radar"]["altitude_sigma_m"] = 150.0
    r = post(client, body)
    assert r.status_code == 200, r.text
    job = to_job(ReconstructionRequest.model_validate(body), "sqpmethod", 500, 20_000)
    assert job.radar.altitude_sigma_m == 150.0
    ref = reconstruct(job.plots, job.radar, job.config)
    got = np.array([[p["x"], p["z"]] for p in r.json()["trajectory"]["at_plots"]])
    np.testing.assert_allclose(got, ref.at_plots.states[:, :2], rtol=1e-9, atol=1e-6)
    before = np.array([[p["x"], p["z"]] for p in exact])
    # 60-120 km away at 9 km the sigma adds 11-23 m to a 167-m range sigma: a small change
    assert np.abs(got - before).max() > 0.1


def test_the_sample_requests_manoeuvres_are_the_ones_it_flew(client):
    """examples/seed_track.json (19-s scans, 167 m / 0.5 deg, plots thinned in the turns):
    164 segments, and the five manoeuvres of benchmarks.truth.SEED_LIKE_CONTROLS among them,
    each within three scans of its true start and end, its heading change within 15 deg
    and its speed change within 5 m/s."""
    r = post(client, SEED_BATCH)
    assert r.status_code == 200, r.text
    found = r.json()["trajectory"]["manoeuvres"]
    ends = np.cumsum([0.0] + [d for d, _, _ in SEED_LIKE_CONTROLS])
    true = [(k, SEED_LIKE_CONTROLS[k]) for k in range(len(SEED_LIKE_CONTROLS))
            if SEED_LIKE_CONTROLS[k][1:] != (0.0, 0.0)]
    assert [(m["kind"], m["direction"]) for m in found] == [
        ("speed_change", "decrease"), ("turn", "right"), ("speed_change", "increase"),
        ("turn", "left"), ("speed_change", "decrease")]
    speed = 220.0
    for m, (k, (dur, u, w)) in zip(found, true, strict=True):
        # the request's times start at its first plot, less than a scan after the truth's
        assert abs(m["t_start"] - ends[k]) <= 3 * 19.0, (m, ends[k])
        assert abs(m["t_end"] - ends[k + 1]) <= 3 * 19.0, (m, ends[k + 1])
        if u:
            assert m["heading_change_deg"] == pytest.approx(math.degrees(u * dur / speed),
                                                            abs=15.0)
        else:
            assert m["speed_change"] == pytest.approx(w * dur, abs=5.0)
        speed += w * dur


def test_truth_is_recovered_on_a_noiseless_turn(client):
    """Degrees and frames at the edge: a noiseless constant right turn comes back where it
    flew. A convention slip (radians, counter-clockwise azimuth, swapped x/z) would put it
    kilometres away; the tolerances (20 m, 1 m/s, 0.5 deg with 100-m / 0.2-deg radar errors)
    leave the solver's own regularisation bias to the solver's tests."""
    from solver.motion import propagate, velocity

    t = 10.0 * np.arange(12)
    x, z, phi, v = propagate(60e3, -30e3, np.deg2rad(40.0), 180.0, 3.0, 0.0, t)
    body = {
        "radar": {"range_error_m": 100.0, "azimuth_error_deg": 0.2},
        "plots": [{"t": float(a), "range_m": float(np.hypot(b, c)),
                   "azimuth_deg": float(np.rad2deg(np.arctan2(c, b))) - 720.0}  # any real value
                  for a, b, c in zip(t, x, z, strict=True)],
    }
    r = post(client, body)
    assert r.status_code == 200, r.text
    at = r.json()["trajectory"]["at_plots"]
    vx, vz = velocity(phi, v)
    np.testing.assert_allclose([p["x"] for p in at], x, atol=20.0)
    np.testing.assert_allclose([p["z"] for p in at], z, atol=20.0)
    np.testing.assert_allclose([p["vx"] for p in at], vx, atol=1.0)
    np.testing.assert_allclose([p["vz"] for p in at], vz, atol=1.0)
    np.testing.assert_allclose([p["heading_deg"] for p in at], np.rad2deg(phi) % 360, atol=0.5)
    assert r.json()["diagnostics"]["method"] == "refined"


@pytest.mark.parametrize("n", [1, 2])
def test_very_short_tracks_use_the_solver_defaults(client, n):
    body = batch(100.0)
    body["plots"] = body["plots"][:n]
    r = post(client, body)
    assert r.status_code == 200, r.text
    assert len(r.json()["trajectory"]["at_plots"]) == n
    assert r.json()["diagnostics"]["warnings"]


def test_filters_run_beside_the_reconstruction(client):
    body = batch(300.0)
    body["filters"] = list(SINGLE_SENSOR_NAMES)  # fusion_*: two sensors (test_service_sensors)
    r = post(client, body)
    assert r.status_code == 200, r.text
    filters = r.json()["filters"]
    assert sorted(filters) == sorted(SINGLE_SENSOR_NAMES)
    for name, est in filters.items():
        assert [s["t"] for s in est["states"]] == [p["t"] for p in body["plots"]], name
        cov = np.array([s["cov"] for s in est["states"]])
        assert cov.shape == (len(body["plots"]), 4, 4)
    assert post(client, batch(300.0)).json()["filters"] == {}


@pytest.mark.parametrize("gate", ["default", 4.0, None])
def test_filters_report_the_plots_they_left_out(client, gate):
    """A wild plot (15 km off in range): every gating filter names it in `gated` (input
    order), the warnings say so, the states stay near the track; alpha_beta uses every plot.
    `filter_gate_sigma` null: every filter uses it, and the warnings say that (the
    reconstruction gave it no weight)."""
    body = batch(600.0)
    wild = 12
    body["plots"][wild]["range_m"] += 15_000.0
    body["filters"] = ["imm_smoother", "cv_rts", "imm", "singer", "quasi_optimal", "fuzzy",
                       "alpha_beta"]
    if gate != "default":
        body["filter_gate_sigma"] = gate
    r = post(client, body)
    assert r.status_code == 200, r.text
    out = r.json()
    assert f"given no weight: plots [{wild}]" in " ".join(out["diagnostics"]["warnings"])
    used = [w for w in out["diagnostics"]["warnings"] if "the reconstruction gave no weight" in w]
    for name, est in out["filters"].items():
        said = f"filters.{name}: used 1 plot(s) the reconstruction gave no weight as wild: [{wild}]"
        if name == "alpha_beta" or gate is None:
            assert est["gated"] == [] and said in used, (name, used)
            continue
        assert said not in used
        assert est["gated"] == [wild], name
        assert any(w.startswith(f"filters.{name}: 1 plot(s) left out") and w.endswith(f": [{wild}]")
                   for w in out["diagnostics"]["warnings"]), name
        rec = out["trajectory"]["at_plots"][wild]
        assert np.hypot(est["states"][wild]["x"] - rec["x"],
                        est["states"][wild]["z"] - rec["z"]) < 3_000.0, name


# ------------------------------------------------------------------------------ validation

BAD = batch(300.0)


def _with(path: str, value):
    body = copy.deepcopy(BAD)
    *head, last = path.split(".")
    node = body
    for key in head:
        node = node[int(key)] if key.isdigit() else node.setdefault(key, {})
    node[int(last) if last.isdigit() else last] = value
    return body


INVALID = [
    # (case, body, expected message start)
    ("duplicate t", _with("plots.5.t", BAD["plots"][4]["t"]),
     "plots[5].t is not after plots[4].t"),
    ("decreasing t", _with("plots.7.t", 1.0), "plots[7].t is not after plots[6].t"),
    ("negative range", _with("plots.3.range_m", -5.0), "plots[3].range_m must be positive"),
    ("zero range", _with("plots.0.range_m", 0.0), "plots[0].range_m must be positive"),
    ("altitude above range", _with("plots.2.altitude_m", 1e9), "plots[2].altitude_m must be"),
    ("inverted u bounds", _with("bounds.u", [7.0, -7.0]), "bounds.u is inverted or empty"),
    ("inverted v bounds", _with("bounds.v", [330.0, 30.0]), "bounds.v is inverted or empty"),
    ("three-value bounds", _with("bounds.w", [1.0, 2.0, 3.0]), "bounds.w: List should have at"),
    ("window of one plot", _with("window.plots", 1), "window.plots must be at least 2"),
    ("zero trial step", _with("window.trial_step_s", 0.0), "window.trial_step_s must be positive"),
    ("unknown filter", _with("filters", ["cv_rts", "kalmann"]), "filters[1]: Input should be"),
    ("zero filter gate", _with("filter_gate_sigma", 0.0),
     "filter_gate_sigma: Input should be greater than 0"),
    ("negative filter gate", _with("filter_gate_sigma", -6.0),
     "filter_gate_sigma: Input should be greater than 0"),
    ("string filter gate", _with("filter_gate_sigma", "off"),
     "filter_gate_sigma: Input should be a valid number"),
    ("unknown criterion", _with("criterion", "R3"), "criterion: Input should be 'R1' or 'R2'"),
    ("unknown method", _with("method", "magic"), "method: Input should be"),
    ("negative radar error", _with("radar.range_error_m", -1.0),
     "radar.range_error_m must be positive"),
    ("azimuth error in degrees", _with("radar.azimuth_error_deg", 0.0),
     "radar.azimuth_error_deg must be positive"),
    ("elevation of 90 degrees", _with("radar.max_elevation_deg", 90.0),
     "radar.max_elevation_deg must be below 90 degrees"),
    ("string for a number", _with("plots.4.range_m", "far"),
     "plots[4].range_m: Input should be a valid number"),
    ("boolean for a number", _with("plots.4.range_m", True),
     "plots[4].range_m: Input should be a valid number"),
    ("numeric string for a number", _with("radar.range_error_m", "500"),
     "radar.range_error_m: Input should be a valid number"),
    ("boolean in bounds", _with("bounds.u", [False, 7.0]), "bounds.u[0]: Input should be"),
    ("fraction for window plots", _with("window.plots", 3.5), "window.plots: Input should be"),
    ("unknown field", _with("plots.1.speed", 3.0), "plots[1].speed: Extra inputs"),
    ("no plots", _with("plots", []), "plots: List should have at least 1 item"),
    ("too many samples", _with("sample_step_s", 1e-3), "sample_step_s (0.001 s) gives more"),
    ("too many plots", {**BAD, "plots": [{"t": float(i), "range_m": 5e4, "azimuth_deg": 0.0}
                                         for i in range(501)]}, "plots has 501 plots"),
]


@pytest.mark.parametrize(("case", "body", "message"), INVALID, ids=[c[0] for c in INVALID])
def test_invalid_input_is_422_naming_the_field(client, case, body, message):
    r = post(client, body)
    assert r.status_code == 422, (case, r.text)
    assert r.json()["message"].startswith(message), r.json()
    assert r.json()["detail"]


def test_omitted_samples_are_neither_limited_nor_computed(client):
    """`omit: [samples]` lifts `max_samples`; the worker computes three samples (the cost of
    a request stays bounded), not one every `sample_step_s`."""
    body = _with("sample_step_s", 1e-3)  # 3e5 samples over the 300-s track: over the limit
    assert post(client, body).status_code == 422
    body["omit"] = ["samples"]
    job = to_job(ReconstructionRequest.model_validate(body), "sqpmethod", 500, 20_000)
    t = [p["t"] for p in body["plots"]]
    assert job.config.sample_step_s == pytest.approx((max(t) - min(t)) / 2)
    r = post(client, body)
    assert r.status_code == 200, r.text
    assert r.json()["trajectory"]["samples"] == []


def test_a_key_given_twice_is_422_naming_it(client):
    """JSON parsers keep the last of two equal keys: the earlier value would be silently
    ignored. A plot's "t" twice, a top-level field twice: 422 naming it."""
    text = json.dumps(batch(300.0))
    plot3 = json.dumps(batch(300.0)["plots"][3])
    twice = text.replace(plot3, plot3[:-1] + ', "t": 1.0}', 1)
    assert twice != text
    r = post(client, twice.encode())
    assert r.status_code == 422, r.text
    assert r.json()["message"].startswith("plots[3].t is given twice"), r.json()
    radar = json.dumps(batch(300.0)["radar"])
    r = post(client, (text[:-1] + f', "radar": {radar}}}').encode())
    assert r.status_code == 422 and r.json()["message"].startswith("radar is given twice")
    assert post(client, text.encode()).status_code == 200


def test_duplicate_key_locates_the_key_at_any_depth():
    from solver.json_keys import duplicate_key

    assert duplicate_key(b'{"a": [{"b": 1}, {"c": {"d": 1, "d": 2}}]}') == ("a", 1, "c", "d")
    assert duplicate_key(b'{"a": 1, "b": 2}') is None
    assert duplicate_key(b"{not json") is None  # the parser's own 422 says why
    deep = b'{"x": ' * 900 + b'{"k": 1, "k": 2}' + b"}" * 900  # no recursion in the search
    assert duplicate_key(deep) == (*["x"] * 900, "k")


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_numbers_are_422(client, token):
    text = json.dumps(BAD).replace('"range_m": ' + json.dumps(BAD["plots"][6]["range_m"]),
                                   f'"range_m": {token}', 1)
    assert token in text
    r = post(client, text)
    assert r.status_code == 422
    assert r.json()["message"] == "plots[6].range_m: Input should be a finite number"


@pytest.mark.parametrize("text", ["{", "[]", "null", '"plots"', "", "\xff"])
def test_malformed_json_is_422(client, text):
    r = post(client, text.encode("latin-1"))
    assert r.status_code == 422, r.text
    assert r.json()["message"]


@pytest.mark.parametrize("kind", [None, "text/plain", "application/x-www-form-urlencoded"])
def test_a_body_not_sent_as_json_is_415_naming_the_header(client, kind):
    """``curl -d @request.json`` sends ``application/x-www-form-urlencoded``: FastAPI does not
    read that as JSON, and its own message ("Input should be a valid dictionary") does not say
    why. The answer names the header and what to send; the same text as JSON is answered."""
    text = json.dumps(batch(200.0)).encode()
    r = client.post("/v1/reconstructions", content=text,
                    headers={"content-type": kind} if kind else {})
    assert r.status_code == 415, r.text
    said = f"its Content-Type is {kind!r}" if kind else "it has no Content-Type"
    assert r.json()["message"].startswith(f"the body is not read as JSON: {said}; send "
                                          "'Content-Type: application/json'"), r.text
    assert r.json()["detail"][0]["loc"] == ["headers", "content-type"]
    assert post(client, text).status_code == 200
    empty = client.post("/v1/reconstructions", content=b"",
                        headers={"content-type": "application/json"})
    assert empty.status_code == 422
    assert empty.json()["message"] == "body: is empty: the request is a JSON object in the body"


def test_the_contracts_own_example_is_answered(client):
    """spec/api.md's request, verbatim: two plots with a window of three (it was a 422,
    "window.plots (3) is longer than the track"): one window over the track, said."""
    body = {"radar": {"range_error_m": 500.0, "azimuth_error_deg": 1.5, "range_sigma_m": 166.7,
                      "azimuth_sigma_deg": 0.5, "max_altitude_m": 15000.0,
                      "max_elevation_deg": 60.0},
            "plots": [{"t": 0.0, "range_m": 81234.5, "azimuth_deg": 123.40},
                      {"t": 19.1, "range_m": 80310.2, "azimuth_deg": 124.02}],
            "bounds": {"u": [-7.0, 7.0], "w": [-2.0, 3.0], "v": [30.0, 330.0]},
            "window": {"plots": 3, "trial_step_s": 5.0}, "criterion": "R2",
            "filters": ["singer", "quasi_optimal"], "sample_step_s": 1.0}
    r = client.post("/v1/reconstructions", json=body)
    assert r.status_code == 200, r.text
    a = r.json()
    assert len(a["trajectory"]["at_plots"]) == 2 and len(a["trajectory"]["samples"]) == 21
    assert set(a["filters"]) == {"singer", "quasi_optimal"}
    assert any("two plots" in w for w in a["diagnostics"]["warnings"])
    assert "altitude_m" not in a["trajectory"]  # absent, not null, where not estimated
    r = client.post("/v1/reconstructions", json={**body, "reference": {"lat_deg": 46.0,
                                                                       "lon_deg": 14.0}})
    assert r.status_code == 422 and r.json()["message"].startswith(
        "reference applies to `sensors` only")


def test_oversize_body_is_413(client):
    body = _with("plots", [{"t": float(i), "range_m": 5e4, "azimuth_deg": 1.0}
                           for i in range(6000)])
    r = post(client, body)
    assert r.status_code == 413
    assert "200000 bytes" in r.json()["message"]

    def chunks():  # no Content-Length: the limit applies while reading
        text = json.dumps(body).encode()
        for i in range(0, len(text), 10_000):
            yield text[i:i + 10_000]

    r = client.post("/v1/reconstructions", content=chunks(),
                    headers={"content-type": "application/json"})
    assert r.status_code == 413


# ------------------------------------------------------------------------------ operations


def test_metrics_count_requests_solves_and_latency(client):
    def value(text: str, prefix: str) -> float:
        lines = [ln for ln in text.splitlines() if ln.startswith(prefix)]
        return float(lines[0].rsplit(" ", 1)[1]) if lines else 0.0

    ok = 'trajrecon_http_requests_total{method="POST",route="/v1/reconstructions",status="200"}'
    bad = 'trajrecon_http_requests_total{method="POST",route="/v1/reconstructions",status="422"}'
    solves = 'trajrecon_solves_total{method="refined",outcome="ok"}'
    lat = ('trajrecon_http_request_duration_seconds_count{method="POST",'
           'route="/v1/reconstructions"}')
    before = client.get("/metrics").text
    assert post(client, batch(200.0)).status_code == 200
    assert post(client, _with("plots.2.t", -1.0)).status_code == 422
    r = client.get("/metrics")
    assert r.headers["content-type"].startswith("text/plain")
    after = r.text
    assert value(after, ok) == value(before, ok) + 1
    assert value(after, bad) == value(before, bad) + 1
    assert value(after, solves) == value(before, solves) + 1
    assert value(after, lat) == value(before, lat) + 2
    assert value(after, "trajrecon_ready") == 1.0
    assert "trajrecon_solver_failures_total" in after


def test_every_request_is_logged_as_json_with_timing(client):
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    handler = Keep()
    LOGGER.addHandler(handler)
    try:
        r = client.get("/healthz", headers={"x-request-id": "abc123"})
    finally:
        LOGGER.removeHandler(handler)
    assert r.headers["x-request-id"] == "abc123"
    line = json.loads(JsonFormatter().format(records[-1]))
    assert line["msg"] == "request" and line["request_id"] == "abc123"
    assert line["method"] == "GET" and line["path"] == "/healthz" and line["status"] == 200
    assert 0 <= line["duration_ms"] < 1000


def test_unknown_route_is_a_json_404(client):
    r = client.get("/v2/nothing")
    assert r.status_code == 404 and r.json()["message"] == "Not Found"


def test_served_openapi_equals_the_committed_document(client):
    committed = json.loads((ROOT / "openapi" / "openapi.json").read_text())
    assert client.get("/openapi.json").json() == committed, (
        "openapi/openapi.json is stale: run .venv/bin/python -m service.openapi")


def test_settings_come_from_the_environment(monkeypatch):
    monkeypatch.setenv("TRAJRECON_PORT", "9123")
    monkeypatch.setenv("TRAJRECON_WORKERS", "3")
    monkeypatch.setenv("TRAJRECON_MAX_BODY_BYTES", "5000")
    monkeypatch.setenv("TRAJRECON_LOG_LEVEL", "DEBUG")
    monkeypatch.setenv("TRAJRECON_WARMUP_WINDOW_PLOTS", "[3, 5]")
    s = Settings()
    assert (s.port, s.workers, s.max_body_bytes, s.log_level) == (9123, 3, 5000, "DEBUG")
    assert s.warmup_window_plots == [3, 5] and s.solve_slots == 3
    monkeypatch.setenv("TRAJRECON_PORT", "-1")
    with pytest.raises(ValueError, match="port"):
        Settings()


def test_full_queue_is_refused_at_once():
    """One slot, no queue: a second solve while the first runs raises Busy (-> 503)."""
    settings = Settings(workers=1, max_concurrent_solves=1, max_queued_solves=0, warmup=False)
    body = ReconstructionRequest.model_validate(batch(200.0))
    job = to_job(body, "sqpmethod", 500, 20_000)

    async def scenario() -> None:
        from service.metrics import Metrics

        pool = SolverPool(settings, Metrics())
        pool.start()
        first = asyncio.create_task(pool.run(job))
        await asyncio.sleep(0)  # the first solve holds the only slot
        with pytest.raises(Busy):
            await pool.run(job)
        assert (await first).body is not None
        assert (await pool.run(job)).body is not None  # free again
        await pool.close()

    asyncio.run(scenario())


def test_a_request_waits_for_a_solver_at_most_max_queue_wait_s():
    """One slot held by a long solve: a queued request is refused (Busy -> 503) after
    max_queue_wait_s, not when the first solve ends; it leaves the queue; the first is
    unharmed and the slot free again afterwards."""
    import time

    settings = Settings(workers=1, max_concurrent_solves=1, warmup=False, max_queue_wait_s=0.3)
    body = ReconstructionRequest.model_validate(batch(200.0))
    job = to_job(body, "sqpmethod", 500, 20_000)
    long = to_job(ReconstructionRequest.model_validate(batch(3000.0)), "sqpmethod", 500, 20_000)

    async def scenario() -> None:
        from service.metrics import Metrics

        pool = SolverPool(settings, Metrics())
        pool.start()
        first = asyncio.create_task(pool.run(long))
        await asyncio.sleep(0)  # the long solve holds the only slot
        started = time.monotonic()
        with pytest.raises(Busy, match=r"waited 0\.3 s for a solver"):
            await pool.run(job)
        waited = time.monotonic() - started
        assert 0.3 <= waited < 1.0 and not first.done(), waited
        assert pool._pending == 1  # the refused one left the queue
        assert (await first).body is not None
        assert (await pool.run(job)).body is not None  # free again
        await pool.close()

    asyncio.run(scenario())


def test_solve_time_limit_is_a_422_and_frees_the_worker():
    settings = Settings(workers=1, warmup=False, solve_time_limit_s=0.05)
    job = to_job(ReconstructionRequest.model_validate(batch(3000.0)), "sqpmethod", 500, 20_000)

    async def scenario() -> None:
        from service.metrics import Metrics

        pool = SolverPool(settings, Metrics())
        pool.start()
        start = time.perf_counter()
        out = await pool.run(job)
        assert time.perf_counter() - start < 10
        assert out.body is None and out.error_loc == ("plots",)
        assert "solve time limit of 0.05 s" in out.error_message
        pool.settings = Settings(workers=1, warmup=False, solve_time_limit_s=0)
        small = to_job(ReconstructionRequest.model_validate(batch(100.0)), "sqpmethod", 500,
                       20_000)
        assert (await pool.run(small)).body is not None  # the same worker still serves
        await pool.close()

    asyncio.run(scenario())


def test_failed_warm_up_leaves_service_alive_but_not_ready():
    app = create_app(Settings(workers=1, warmup_window_plots=[1]))  # window of 1: invalid
    with TestClient(app) as c:
        end = time.monotonic() + 60
        while c.get("/readyz").json()["status"] == "starting":
            assert time.monotonic() < end
            time.sleep(0.05)
        r = c.get("/readyz")
        assert r.status_code == 503 and r.json()["status"] == "failed"
        assert "window.plots" in r.json()["detail"]
        assert c.get("/healthz").status_code == 200
        assert c.head("/readyz").status_code == 503 and c.head("/healthz").status_code == 200


# ------------------------------------------------------ extreme values: 200 or 422, never 5xx


def _plots_with(key: str, f) -> dict:
    body = batch(200.0)
    for i, p in enumerate(body["plots"]):
        p[key] = f(i, p)
    return body


def _radar(**kw) -> dict:
    body = batch(200.0)
    body["radar"].update(kw)
    return body


EXTREME = [
    ("range 1 mm", _plots_with("range_m", lambda i, p: 1e-3 * (1 + i)), None),
    ("range 1e9 m", _plots_with("range_m", lambda i, p: 1e9 + 1e3 * i), None),
    ("plots 1 ns apart", _plots_with("t", lambda i, p: i * 1e-9), None),
    ("all plots at one point", _plots_with("azimuth_deg", lambda i, p: 10.0), None),
    ("azimuth 1e300 deg", _plots_with("azimuth_deg", lambda i, p: 1e300 * (1 + i)), None),
    ("huge bounds", {**batch(200.0), "bounds": {"u": [-1e300, 1e300], "w": [-1e300, 1e300],
                                                "v": [1e-300, 1e300]}}, None),
    ("altitude just below range",
     _plots_with("altitude_m", lambda i, p: p["range_m"] * (1 - 1e-15)), None),
    ("range 1e300 m", _plots_with("range_m", lambda i, p: 1e300 * (1 + 1e-3 * i)), None),
    ("tiny bounds", {**batch(200.0), "bounds": {"u": [-1e-300, 1e-300], "w": [-1e-300, 1e-300],
                                                "v": [1e-300, 2e-300]}}, None),
    ("radar errors 1e300", _radar(range_error_m=1e300, azimuth_error_deg=1e300), None),
    ("radar errors 1e-300", _radar(range_error_m=1e-300, azimuth_error_deg=1e-300,
                                   range_sigma_m=None, azimuth_sigma_deg=None), None),
    ("h_max 1e300", _radar(max_altitude_m=1e300, max_elevation_deg=89.999999), None),
    ("trial step 1e-9 s", {**batch(200.0), "window": {"trial_step_s": 1e-9}}, None),
]


@pytest.mark.parametrize(
    ("case", "body"),
    [pytest.param(c, b, marks=[pytest.mark.xfail(strict=True, reason=x)] if x else [])
     for c, b, x in EXTREME],
    ids=[c[0] for c in EXTREME])
def test_extreme_values_get_200_or_422(client, case, body):
    """Physically absurd values must be refused (422) or solved (200), never a 500."""
    r = post(client, body)
    assert r.status_code in (200, 422), (case, r.status_code, r.text[:300])


def test_json_syntax_errors_name_line_and_column(client):
    text = '{\n  "radar": {"range_error_m": 500,\n  "azimuth_error_deg": 1.5,,\n}'
    r = post(client, text)
    assert r.status_code == 422
    assert r.json()["message"].startswith("body: is not valid JSON: "), r.json()
    assert "at line 3 column 28 (char 63)" in r.json()["message"], r.json()
    assert r.json()["detail"][0]["loc"] == ["body"]


def test_docs_are_served_offline(client):
    """/docs refers to no other host, and every script and style sheet it names is served."""
    import re

    page = client.get("/docs")
    assert page.status_code == 200
    urls = re.findall(r"""(?:src|href)=["']([^"']+)["']""", page.text)
    urls += re.findall(r"""url: ?["']([^"']+)["']""", page.text)
    assert urls and not [u for u in urls if "://" in u or u.startswith("//")], urls
    for url in urls:
        r = client.get(url)
        assert r.status_code == 200 and r.content, url
    assert client.get("/redoc").status_code == 404  # its script would come from a CDN


def test_late_input_errors_are_renamed_to_request_fields():
    """An input error found by the solver (in a worker, after ``to_job``) names the request's
    field, not the solver's radian one."""
    from solver.inputs import InputError

    app = create_app(Settings(workers=1, warmup=False))

    @app.get("/late")
    async def late() -> None:
        raise InputError(("plots", 3, "azimuth_rad"), "is not usable")

    with TestClient(app) as c:
        r = c.get("/late")
    assert r.status_code == 422
    assert r.json()["message"] == "plots[3].azimuth_deg is not usable"
    assert r.json()["detail"][0]["loc"] == ["plots", 3, "azimuth_deg"]


def test_metrics_label_every_route_by_its_template(client):
    """Routes outside FastAPI's own (the OpenAPI document, the docs' assets) are labelled by
    their template too, not lumped with unmatched requests; a 404 never makes a label."""
    client.get("/openapi.json")
    client.get("/docs/assets/swagger-ui.css")
    client.get("/docs/assets/no-such-file.js")
    text = client.get("/metrics").text
    assert 'route="/openapi.json",status="200"' in text
    assert 'route="/docs/assets",status="200"' in text
    assert "no-such-file" not in text


@pytest.mark.parametrize("change, loc", [
    ({"radar": {"range_error_m": 1e200, "azimuth_error_deg": 1.5}}, ["radar", "range_error_m"]),
    ({"radar": {"range_error_m": 500.0, "azimuth_error_deg": 1.5, "azimuth_sigma_deg": 1e10}},
     ["radar", "azimuth_sigma_deg"]),
    ({"bounds": {"w": [-7.0, 1e100]}}, ["bounds", "w"]),
    ({"bounds": {"u": [-1e12, 1.0]}}, ["bounds", "u"]),
    ({"bounds": {"v": [30.0, 1e7]}}, ["bounds", "v"]),
])
def test_values_no_radar_or_aircraft_has_are_422_not_500(client, change, loc):
    """An adversarial pass found these accepted and then failing in the solvers (500)."""
    r = post(client, {**batch(200.0), **change})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == loc


@pytest.mark.parametrize("body, said", [
    (b"[" * 1200 + b"]" * 1200, "is nested too deeply for the JSON parser"),
    (b'{"plots": [' + b"1" * 5001 + b"]}", "Exceeds the limit (4300 digits)"),
    (b"\xff\xfe{", "could not be decoded as UTF-8 JSON"),
])
def test_a_body_pythons_parser_refuses_is_named_for_why(client, body, said):
    """FastAPI says only 'There was an error parsing the body' when json.loads raises something
    other than its JSON errors; every such body was answered 'could not be decoded as UTF-8
    JSON' (a tester's 1200-deep nesting and 5001-digit integer). Now the reason."""
    r = client.post("/v1/reconstructions", content=body,
                    headers={"content-type": "application/json"})
    assert r.status_code == 422 and said in r.json()["message"], r.text
    assert r.json()["detail"][0]["loc"] == ["body"]
