"""A service job of many short tracks and some long ones, posted as JSON to the real server
(``python -m service`` run from the source tree ``--root``, so that two versions can be
compared; one solver worker, two job workers): the job's wall time, the bytes of its output
directory and of its figure data, and three GETs of a short and a long track's figure (the
first draws it where figures are drawn when first asked for); ``results/job_figures.md``.

    .venv/bin/python -m benchmarks.job_figures --root . --short 300 --long 50
    .venv/bin/python -m benchmarks.job_figures --root OTHER --env TRAJRECON_JOBS_TRACK_FIGURES=0
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

SENSORS = [{"id": "R1", "kind": "radar", "lat_deg": 46.0, "lon_deg": 14.0, "height_m": 300.0,
            "range_error_m": 150.0, "azimuth_error_deg": 0.24}]


def plots(rng: np.random.Generator, n: int, dt: float = 4.0) -> list[dict]:
    """A straight level flight seen by R1 (slant range, azimuth) every dt s."""
    x0, z0 = rng.uniform(-80e3, 80e3, 2)
    hd, v = rng.uniform(0, 2 * np.pi), rng.uniform(150, 250)
    t = np.arange(n) * dt + rng.uniform(0, 100)
    x, z = x0 + v * np.cos(hd) * t, z0 + v * np.sin(hd) * t
    r = np.hypot(np.hypot(x, z), 9000.0) + rng.normal(0, 50, n)
    az = np.degrees(np.arctan2(z, x)) + rng.normal(0, 0.08, n)
    return [{"t": float(a), "sensor": "R1", "range_m": float(b), "azimuth_deg": float(c) % 360,
             "altitude_m": 9300.0} for a, b, c in zip(t, r, az, strict=True)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--root", required=True)
    ap.add_argument("--short", type=int, default=300)
    ap.add_argument("--long", type=int, default=50)
    ap.add_argument("--long-plots", type=int, default=150)
    ap.add_argument("--data", default="/tmp/trajrecon-job-figures", help="the server's data "
                    "directory (emptied first)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--env", action="append", default=[], help="NAME=VALUE for the server")
    a = ap.parse_args()
    rng = np.random.default_rng(1)
    tracks = {f"S{k:05d}": plots(rng, 3) for k in range(a.short)}
    tracks |= {f"L{k:03d}": plots(rng, a.long_plots) for k in range(a.long)}
    body = {"sensors": SENSORS, "tracks": tracks}
    shutil.rmtree(a.data, ignore_errors=True)
    port = free_port()
    env = {**os.environ, "PYTHONPATH": a.root, "TRAJRECON_PORT": str(port),
           "TRAJRECON_DATA_DIR": a.data, "TRAJRECON_WORKERS": "1", "TRAJRECON_JOBS_WORKERS": "2",
           "TRAJRECON_LOG_LEVEL": "WARNING", "TRAJRECON_ACCESS_LOG": "false"}
    for kv in a.env:
        k, v = kv.split("=", 1)
        env[k] = v
    url = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "service"], cwd=a.root, env=env)
    res = {"root": a.root, "short": a.short, "long": a.long, "long_plots": a.long_plots,
           "env": a.env}
    try:
        with httpx.Client(timeout=600) as c:
            end = time.monotonic() + 180  # ready: warmed up
            while True:
                try:
                    if c.get(url + "/readyz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                assert time.monotonic() < end and proc.poll() is None
                time.sleep(0.2)
            t0 = time.monotonic()
            r = c.post(url + "/v1/jobs", json=body)
            assert r.status_code == 202, r.text
            loc = url + r.headers["location"]
            while True:
                st = c.get(loc).json()
                if st["state"] in ("done", "failed", "cancelled"):
                    break
                time.sleep(0.5)
            res["job_wall_s"] = time.monotonic() - t0
            res["state"] = st["state"]
            res["elapsed_s"] = st["elapsed_s"]
            res["tracks_done"] = st["tracks_done"]
            summ = c.get(loc + "/results/summary.json").json()
            res["reconstruct_s"] = summ.get("reconstruct_s")
            out = Path(a.data) / "jobs" / loc.rsplit("/", 1)[1] / "out"
            res["pngs_after_job"] = sum(1 for _ in out.glob("figures/*/*.png"))
            res["out_bytes"] = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
            res["figure_data_bytes"] = sum(p.stat().st_size for p in
                                           out.glob("figure_data.parquet/*") if p.is_file())
            for key in ("S00007", "L007"):
                times, status, size = [], [], []
                for _ in range(3):
                    t1 = time.perf_counter()
                    f = c.get(f"{loc}/tracks/{key}/figure.png")
                    times.append(time.perf_counter() - t1)
                    status.append(f.status_code)
                    size.append(len(f.content))
                res[f"figure_{key}_s"] = times
                res[f"figure_{key}_status"] = status
                res[f"figure_{key}_bytes"] = size
            t1 = time.perf_counter()
            z = c.get(loc + "/results/results.zip")
            res["zip_s"] = time.perf_counter() - t1
            res["zip_bytes"] = len(z.content)
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    print(json.dumps(res, indent=1))
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
