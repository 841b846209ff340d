"""HTTP service overhead and throughput on the seed-like 19-s-scan track (examples/seed_track.json).

One run measures, interleaved so that machine load affects both alike:

1. latency of one reconstruction called in process (``solver.reconstruct`` on the validated
   job) and of the same reconstruction as ``POST /v1/reconstructions`` to a real server
   (``python -m service`` on a free loopback port): median, p95, and their ratio;
2. throughput with ``--clients`` concurrent clients (requests/s, errors).

    .venv/bin/python -m benchmarks.service_latency            # defaults: 15 rounds, 8 clients
    .venv/bin/python -m benchmarks.service_latency --rounds 30 --per-client 4 --out r.json
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
from tqdm import tqdm

from service.convert import Job, response_dict, to_job
from service.models import ReconstructionRequest, ReconstructionResponse
from solver.reconstruct import reconstruct

ROOT = Path(__file__).resolve().parents[1]
BODY = json.loads((ROOT / "examples" / "seed_track.json").read_text())


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``python -m service`` in a subprocess, ready (solvers warmed) on entry."""

    def __init__(self, workers: int):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, "TRAJRECON_PORT": str(self.port),
                    "TRAJRECON_WORKERS": str(workers),
                    "TRAJRECON_LOG_LEVEL": "WARNING", "TRAJRECON_ACCESS_LOG": "false"}

    def __enter__(self) -> Server:
        self.proc = subprocess.Popen([sys.executable, "-m", "service"], cwd=ROOT, env=self.env)
        end = time.monotonic() + 120
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError("server exited")
            try:
                if httpx.get(self.url + "/readyz", timeout=1).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            if time.monotonic() > end:
                raise RuntimeError("server not ready in 120 s")
            time.sleep(0.1)

    def __exit__(self, *exc: object) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=30)


def stats(xs: list[float]) -> dict[str, float]:
    a = np.asarray(xs) * 1e3
    return {"n": len(xs), "median_ms": float(np.median(a)),
            "p95_ms": float(np.percentile(a, 95)), "min_ms": float(a.min())}


def latency(rounds: int, workers: int) -> dict:
    """Interleaved in-process and HTTP solves of the same track."""
    job = to_job(ReconstructionRequest.model_validate(BODY), "sqpmethod", 10**6, 10**7)
    reconstruct(job.plots, job.radar, job.config)  # build and warm the in-process solvers
    local, http = [], []
    with Server(workers) as srv, httpx.Client(timeout=300) as client:
        assert client.post(srv.url + "/v1/reconstructions", json=BODY).status_code == 200
        for _ in tqdm(range(rounds), desc="latency (in-process + HTTP)"):
            t0 = time.perf_counter()
            reconstruct(job.plots, job.radar, job.config)
            local.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            r = client.post(srv.url + "/v1/reconstructions", json=BODY)
            http.append(time.perf_counter() - t0)
            if r.status_code != 200:
                raise RuntimeError(r.text)
    out = {"plots": len(job.plots), "in_process": stats(local), "http": stats(http),
           "http_layer_ms": http_layer_ms(job)}
    for k in ("median", "p95", "min"):
        out[f"overhead_ratio_{k}"] = out["http"][f"{k}_ms"] / out["in_process"][f"{k}_ms"]
    return out


def http_layer_ms(job: Job) -> dict[str, float]:
    """The service's own work per request, timed in process (load-independent breakdown):
    request parsing and validation; building, validating and serialising the answer."""
    raw = json.dumps(BODY)
    rec = reconstruct(job.plots, job.radar, job.config)
    t0 = time.perf_counter()
    to_job(ReconstructionRequest.model_validate_json(raw), "sqpmethod", 10**6, 10**7)
    t1 = time.perf_counter()
    gc.disable()  # as in service/workers.py
    body = ReconstructionResponse.model_validate(response_dict(rec, {})).model_dump_json()
    gc.enable()
    t2 = time.perf_counter()
    return {"request_ms": (t1 - t0) * 1e3, "response_ms": (t2 - t1) * 1e3,
            "response_bytes": len(body)}


def throughput(clients: int, per_client: int, workers: int) -> dict:
    """``clients`` threads, each posting ``per_client`` requests back to back."""
    codes: list[int] = []
    lock = threading.Lock()
    with Server(workers) as srv:
        bar = tqdm(total=clients * per_client, desc="throughput")

        def client_loop() -> None:
            with httpx.Client(timeout=600) as c:
                for _ in range(per_client):
                    code = c.post(srv.url + "/v1/reconstructions", json=BODY).status_code
                    with lock:
                        codes.append(code)
                        bar.update()

        threads = [threading.Thread(target=client_loop) for _ in range(clients)]
        t0 = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t0
        bar.close()
    errors = sum(c != 200 for c in codes)
    return {"workers": workers, "clients": clients,
            "requests": len(codes), "errors": errors, "wall_s": wall,
            "requests_per_s": len(codes) / wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--per-client", type=int, default=2)
    ap.add_argument("--workers", type=int, default=len(os.sched_getaffinity(0)))
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    result = {"cores": len(os.sched_getaffinity(0)), "load_avg_start": os.getloadavg(),
              "latency": latency(args.rounds, args.workers),
              "throughput": throughput(args.clients, args.per_client, args.workers)}
    result["load_avg_end"] = os.getloadavg()
    lat = result["latency"]
    print(f"\nseed-like track, {lat['plots']} plots, {result['cores']} cores, load average "
          f"{result['load_avg_start'][0]:.1f} -> {result['load_avg_end'][0]:.1f}")
    for k in ("in_process", "http"):
        s = lat[k]
        print(f"  {k:10s}  median {s['median_ms']:8.1f} ms   p95 {s['p95_ms']:8.1f} ms   "
              f"(n={s['n']})")
    print(f"  HTTP / in-process: median x{lat['overhead_ratio_median']:.3f}, "
          f"p95 x{lat['overhead_ratio_p95']:.3f}, min x{lat['overhead_ratio_min']:.3f}")
    h = lat["http_layer_ms"]
    print(f"  service work per request: request {h['request_ms']:.1f} ms, response "
          f"{h['response_ms']:.1f} ms ({h['response_bytes'] / 1e6:.2f} MB)")
    t = result["throughput"]
    print(f"  {t['clients']} concurrent clients, {t['workers']} workers: "
          f"{t['requests_per_s']:.2f} req/s over {t['requests']} requests, {t['errors']} errors")
    if args.out:
        args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
