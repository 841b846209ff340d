"""A job survives a restart of the real server (``python -m service``): killed with SIGKILL
mid-job and started again on the same data directory, it resumes and ends with every track
present exactly once, the tracks finished before the kill kept (not redone)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import time
from collections import Counter
from pathlib import Path

import httpx
import pyarrow.parquet as pq
from procs import start_service, stop
from test_io_asterix import SENSOR_FILE, Flight, encode_recording

ROOT = Path(__file__).resolve().parents[1]
FLIGHTS = tuple(Flight(0x500000 + k, 4_000.0 * k, -15_000.0 + 5_000.0 * k, 190.0,
                       40.0 - 15 * k, 320.0, (120 + k, 220 + k)) for k in range(6))


def start(data_dir: Path) -> tuple[subprocess.Popen, str]:
    # a session of its own: whatever the killed server leaves behind is ended with it
    return start_service({"TRAJRECON_WORKERS": "1", "TRAJRECON_WARMUP": "false",
                          "TRAJRECON_LOG_LEVEL": "WARNING", "TRAJRECON_ACCESS_LOG": "false",
                          "TRAJRECON_DATA_DIR": str(data_dir), "TRAJRECON_JOBS_WORKERS": "1",
                          "TRAJRECON_JOBS_TRACK_FIGURES": "false"}, start_new_session=True)


def poll(url: str, until, timeout: float = 120.0) -> dict:
    end = time.monotonic() + timeout
    while True:
        status = httpx.get(url, timeout=10).json()
        if until(status):
            return status
        assert time.monotonic() < end, status
        time.sleep(0.1)


def test_a_job_survives_a_killed_server(tmp_path):
    data = tmp_path / "data"
    first, url = start(data)
    try:
        r = httpx.post(url + "/v1/jobs", timeout=30, files={
            "recording": ("day.ast", encode_recording(duration=120.0, flights=FLIGHTS).data),
            "sensors": ("sensors.json", json.dumps(SENSOR_FILE))})
        assert r.status_code == 202, r.text
        job = url + r.headers["location"]
        before = poll(job, lambda s: s["tracks_done"] >= 1)
        done_before = {t["aircraft"]: t for t in httpx.get(job + "/tracks").json()
                       if t["status"] == "done"}
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=10)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(first.pid, signal.SIGKILL)  # the dead server's workers, if any
    assert before["state"] == "running" and before["tracks_total"] == len(FLIGHTS)
    assert 1 <= len(done_before) < len(FLIGHTS), "killed too late to be mid-job"

    second, url = start(data)
    try:
        job = url + r.headers["location"]
        status = poll(job, lambda s: s["state"] != "running" and s["state"] != "queued")
        tracks = httpx.get(job + "/tracks").json()
        table = pq.read_table(
            io.BytesIO(httpx.get(job + "/results/tracks.parquet").content))
    finally:
        stop(second)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(second.pid, signal.SIGKILL)
    assert status["state"] == "done", status
    assert status["runs"] == 2  # resumed, not restarted from nothing
    assert status["tracks_total"] == status["tracks_done"] == len(FLIGHTS)
    assert sorted(t["aircraft"] for t in tracks) == sorted(f"{f.address:06X}"
                                                           for f in FLIGHTS)
    for key, t in done_before.items():  # finished before the kill: kept, not redone
        again = next(x for x in tracks if x["aircraft"] == key)
        assert again["status"] == "done" and again["elapsed_s"] == t["elapsed_s"]
    # every track exactly once: in the results and in the commit log
    pairs = Counter(zip(table.column("aircraft").to_pylist(), table.column("plot").to_pylist(),
                        strict=True))
    assert set(pairs.values()) == {1} and len(pairs) == status["plots"]
    assert Counter(a for a, _ in pairs) == {t["aircraft"]: t["plots"] for t in tracks}
    ledger = (data / "jobs" / r.json()["id"] / "out" / "progress.jsonl").read_text()
    keys = Counter(json.loads(line)["aircraft"] for line in ledger.splitlines())
    assert set(keys.values()) == {1} and len(keys) == len(FLIGHTS)
