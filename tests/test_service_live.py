"""The real server (``python -m service`` on a free loopback port): a client generated from the
committed OpenAPI document and responsiveness while solving (the fuzz run of the API is in
test_service_fuzz.py)."""

from __future__ import annotations

import copy
import importlib
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
from procs import start_service, stop
from test_service_sensors import _body as two_sensor_body

ROOT = Path(__file__).resolve().parents[1]
OPENAPI = ROOT / "openapi" / "openapi.json"
SEED_BATCH = json.loads((ROOT / "examples" / "seed_track.json").read_text())
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def server():
    """``python -m service`` exactly as the README runs it, configured by environment."""
    proc, url = start_service({"TRAJRECON_WORKERS": "2", "TRAJRECON_LOG_LEVEL": "WARNING",
                               "TRAJRECON_MAX_PLOTS": "400"}, timeout=90,
                              stderr=subprocess.PIPE)
    try:
        yield url
    finally:
        stop(proc)


def test_generated_client_round_trip(server, tmp_path):
    """openapi-python-client -> pip install -> a full reconstruction and a 422 through it."""
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    subprocess.run([BIN / "openapi-python-client", "generate", "--path", str(OPENAPI),
                    "--meta", "setup", "--output-path", str(tmp_path / "client")],
                   check=True, cwd=tmp_path, env=env, capture_output=True)
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target",
                    str(tmp_path / "site"), str(tmp_path / "client")],
                   check=True, env=env, capture_output=True)
    sys.path.insert(0, str(tmp_path / "site"))
    try:
        pkg = "radar_trajectory_reconstruction_client"
        client_mod = importlib.import_module(pkg)
        api = importlib.import_module(f"{pkg}.api.reconstruction.create_reconstruction")
        models = importlib.import_module(f"{pkg}.models")

        plots = [p for p in SEED_BATCH["plots"] if p["t"] <= 500.0]
        request = models.ReconstructionRequest(
            radar=models.RadarIn(**SEED_BATCH["radar"]),
            plots=[models.PlotIn(**p) for p in plots],
            window=models.WindowIn(plots=3, trial_step_s=5.0),
            filters=[models.ReconstructionRequestFiltersItem("cv_rts")],
        )
        with client_mod.Client(base_url=server, timeout=httpx.Timeout(60.0)) as client:
            res = api.sync_detailed(client=client, body=request)
            assert res.status_code == 200, res.content
            out = res.parsed
            assert isinstance(out, models.ReconstructionResponse)
            assert [s.t for s in out.trajectory.at_plots] == [p["t"] for p in plots]
            assert out.trajectory.segments[0].t_start == plots[0]["t"]
            assert len(out.filters["cv_rts"].states) == len(plots)
            assert out.diagnostics.method == "refined" and out.diagnostics.elapsed_ms > 0
            # reference: the same body posted as plain JSON gives the same answer
            raw = httpx.post(server + "/v1/reconstructions", json=request.to_dict(), timeout=60)
            assert raw.json()["trajectory"]["at_plots"] == [
                s.to_dict() for s in out.trajectory.at_plots]

            bad = copy.deepcopy(request)
            bad.plots[4].t = bad.plots[2].t
            res = api.sync_detailed(client=client, body=bad)
            assert res.status_code == 422
            assert isinstance(res.parsed, models.ErrorResponse)
            assert res.parsed.message.startswith("plots[4].t is not after plots[3].t")

            # several sensors on the earth through the generated models (sensors.md)
            body = two_sensor_body()
            two = models.ReconstructionRequest.from_dict(body)
            assert two.to_dict()["sensors"] == body["sensors"]
            res = api.sync_detailed(client=client, body=two)
            assert res.status_code == 200, res.content
            out = res.parsed
            assert [s.id for s in out.sensors] == ["LJLJ", "SSR2", "ADSB"]
            assert len(out.trajectory.at_plots) == len(body["plots"])
            first = out.trajectory.at_plots[0]
            assert 45 < first.lat_deg < 47 and 13 < first.lon_deg < 16
            assert out.trajectory.altitude_m > 9000
            raw = httpx.post(server + "/v1/reconstructions", json=two.to_dict(), timeout=60)
            assert raw.json()["sensors"] == [s.to_dict() for s in out.sensors]
    finally:
        sys.path.remove(str(tmp_path / "site"))


def in_flight(url: str) -> float:
    text = httpx.get(url + "/metrics", timeout=5).text
    line = next(ln for ln in text.splitlines() if ln.startswith("trajrecon_solves_in_flight "))
    return float(line.split()[1])


def test_healthz_answers_while_every_worker_solves(server):
    """Four whole-track solves keep both workers busy; /healthz still answers at once (a
    blocked event loop would hold it for a whole solve)."""
    results: list[int] = []

    def solve() -> None:
        r = httpx.post(server + "/v1/reconstructions", json=SEED_BATCH, timeout=120)
        results.append(r.status_code)

    threads = [threading.Thread(target=solve) for _ in range(4)]
    for t in threads:
        t.start()
    end = time.monotonic() + 10
    while in_flight(server) < 2:
        assert time.monotonic() < end, "the solves never started"
        time.sleep(0.01)
    latencies = []
    for _ in range(10):
        start = time.perf_counter()
        assert httpx.get(server + "/healthz", timeout=5).status_code == 200
        latencies.append(time.perf_counter() - start)
    assert in_flight(server) >= 1, "the solves ended before the measurement did"
    for t in threads:
        t.join()
    assert results == [200] * 4
    latencies.sort()
    assert latencies[5] < 0.25 and latencies[-1] < 1.0, latencies
