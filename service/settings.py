"""Service configuration from environment variables (prefix ``TRAJRECON_``).

Every setting has an embedded default, so ``python -m service`` runs with no environment at all.
Example: ``TRAJRECON_PORT=9000 TRAJRECON_WORKERS=4 python -m service``.
"""

from __future__ import annotations

import os
from functools import cache
from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from solver.config import MAX_SAMPLES


def _cores() -> int:
    """CPUs this process may run on (the affinity mask, not the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


class Settings(BaseSettings):
    """Runtime settings; each field maps to ``TRAJRECON_<NAME>`` (case-insensitive)."""

    model_config = SettingsConfigDict(env_prefix="TRAJRECON_", extra="ignore")

    host: str = Field("127.0.0.1", description="Interface to listen on (0.0.0.0 in Docker).")
    port: int = Field(8000, ge=0, le=65535, description="TCP port.")
    workers: int = Field(default_factory=_cores, ge=1,
                         description="Solver worker processes (default: the usable cores).")
    worker_niceness: int = Field(5, ge=0, le=19, description="CPU niceness added to worker "
                                 "processes, so the HTTP event loop keeps answering when "
                                 "solves saturate the cores.")
    worker_memory_mb: int = Field(
        0, ge=0, description="Address-space limit of each solver worker (MiB) applied after "
        "its warm-up; a solve that needs more is answered 422. 0 = none (the kernel's OOM "
        "killer may then end a worker: its solve is retried once, then answered 422).")
    max_concurrent_solves: int | None = Field(
        None, ge=1, description="Solves running at once (default: the number of workers).")
    max_queued_solves: int = Field(
        32, ge=0, description="Requests allowed to wait for a solver slot; beyond this the "
        "service answers 503 with Retry-After.")
    max_queue_wait_s: float = Field(
        120.0, ge=0, description="Longest a request waits for a solver slot (s); beyond this the "
        "service answers 503 with Retry-After. 0 = as long as it takes.")
    retry_after_s: int = Field(2, ge=1, description="Retry-After value of a 503 (s).")
    max_body_bytes: int = Field(2_000_000, ge=1024, description="Largest accepted request "
                                "body (bytes); larger bodies get 413.")
    max_plots: int = Field(20_000, ge=1, description="Most plots accepted in one request.")
    max_nodes: int = Field(50_000, ge=16, description="Most node intervals of a refinement "
                           "(every plot, gaps cut to refine.max_node_step_s): long gaps cost "
                           "nodes, so a small body can ask for hours of work; beyond: 422.")
    max_samples: int = Field(MAX_SAMPLES, ge=1, description="Most regular samples in one answer "
                             "(track duration / sample_step_s).")
    solve_time_limit_s: float = Field(
        300.0, ge=0, description="Longest one reconstruction may run in a worker (s); longer "
        "ones are stopped and answered 422. 0 = no limit.")
    nlp_solver: Literal["sqpmethod", "ipopt"] = Field(
        "sqpmethod", description="CasADi plugin for the window NLPs.")
    warmup: bool = Field(True, description="Build and warm the CasADi solvers in every worker "
                         "before /readyz reports ready.")
    warmup_window_plots: list[int] = Field(
        [3], description="Window sizes to warm up (JSON list, e.g. [3,4,5]).")
    request_timeout_s: float = Field(
        30.0, gt=0, description="Time a client has to send a request's headers once connected "
        "(or after the previous answer), and longest pause within its body; beyond: 408 and the "
        "connection is closed.")
    max_connections: int = Field(1000, ge=1, description="Open client connections at most; "
                                 "a connection beyond is answered 503 and closed.")
    keep_alive_s: int = Field(5, ge=1, description="Idle time after an answer before a "
                              "keep-alive connection is closed (s).")
    shutdown_timeout_s: int = Field(
        10, ge=1, description="On SIGTERM, time open requests get to finish before they are "
        "cancelled and the workers stopped (s).")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "INFO", description="Level of the JSON logs on stderr.")
    access_log: bool = Field(True, description="Log every request (method, path, status, ms).")
    data_dir: Path | None = Field(
        None, description="Directory of the durable job store (SQLite database, job inputs and "
        "results). Default: $XDG_STATE_HOME/trajrecon (~/.local/state/trajrecon), else "
        "./trajrecon-data.")
    dask_scheduler: str | None = Field(
        None, description="Address of an existing Dask scheduler that runs the jobs' tracks "
        "(default: an embedded LocalCluster, started with the first job).")
    jobs_workers: int = Field(default_factory=_cores, ge=1, description="Worker processes of "
                              "the embedded Dask cluster for jobs (default: the usable cores).")
    jobs_max_running: int = Field(1, ge=1, description="Jobs running at once; later ones wait "
                                  "in the queue.")
    jobs_max_queued: int = Field(16, ge=0, description="Jobs allowed to wait beyond the running "
                                 "ones; beyond this POST /v1/jobs answers 503 with Retry-After.")
    jobs_max_upload_bytes: int = Field(1 << 30, ge=1024, description="Largest accepted job "
                                       "upload (bytes); larger ones get 413.")
    jobs_max_json_bytes: int = Field(
        32 << 20, ge=1024, description="Largest accepted JSON body of tracks (bytes; at most "
        "jobs_max_upload_bytes); larger ones get 413. Validating JSON takes about 14 times its "
        "size in the server's memory (a 99-MB body: 1.5 GB); send more plots as a CSV or "
        "Parquet table.")
    jobs_json_bytes_in_flight: int = Field(
        64 << 20, ge=1024, description="JSON bodies of tracks received and checked at once "
        "(bytes, each counted by its Content-Length, a body without one as "
        "jobs_max_json_bytes); a body beyond gets 503 with Retry-After (one body alone is "
        "always let in). At about 14 times its size in memory, the default holds that near "
        "0.9 GB: 6 bodies of 30 MB received at once had taken the service from 0.9 to 2.7 GB.")
    jobs_answer_builds: int = Field(
        2, ge=1, description="Job answers built at once (GET /v1/jobs/{id}/tracks/{key} and "
        "pages of GET /v1/jobs/{id}/tracks: Python work holding the interpreter lock, 3.3 s "
        "for a 19.6-MB track); later ones wait (without a thread), so /healthz stays fast: 20 "
        "built at once had held it up to 10.8 s.")
    jobs_answer_waiting: int = Field(
        64, ge=0, description="Job answers allowed to wait for a build slot; beyond this they "
        "get 503 with Retry-After.")
    jobs_max_tracks: int = Field(50_000, ge=1, description="Most tracks one job may hold: a "
                                 "recording read into more fails at once with the reason, a "
                                 "JSON body of more gets 422 (a job's cost is then bounded by "
                                 "this times jobs_track_time_limit_s).")
    jobs_track_time_limit_s: float = Field(300.0, ge=0, description="Longest one track of a "
                                           "job may be solved (s); then it fails. 0 = none.")
    jobs_track_figures: bool = Field(True, description="Keep what each job track's figure is "
                                     "drawn from (its plots' error ellipses and the "
                                     "reconstruction's samples: about 1 KB for a three-plot "
                                     "track), so that GET /v1/jobs/{id}/tracks/{key}/figure.png "
                                     "draws it when first asked for; off: no track figures.")
    jobs_figure_draws: int = Field(2, ge=1, description="Job track figures being drawn (when "
                                   "first asked for: 0.3-0.8 s each, one at a time in the "
                                   "service's threads) or waiting to be, at once; a figure "
                                   "asked for beyond this is answered 503 with Retry-After.")

    @property
    def solve_slots(self) -> int:
        """Solves allowed to run at once."""
        return self.max_concurrent_solves or self.workers


@cache
def get_settings() -> Settings:
    """The process-wide settings, read once from the environment."""
    return Settings()
