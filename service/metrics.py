"""Prometheus metrics of one app instance (own registry, so several apps can coexist)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

_LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


class Metrics:
    """Request counts and latencies, solves, solver failures, queue state."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter("trajrecon_http_requests", "HTTP requests answered.",
                                ["method", "route", "status"], registry=r)
        self.latency = Histogram("trajrecon_http_request_duration_seconds",
                                 "HTTP request latency (s).", ["method", "route"],
                                 buckets=_LATENCY_BUCKETS, registry=r)
        self.solves = Counter("trajrecon_solves", "Reconstructions run, by outcome "
                              "(ok, input_error, error).", ["method", "outcome"], registry=r)
        self.solve_seconds = Histogram("trajrecon_solve_duration_seconds",
                                       "Reconstruction time in a worker, queue included (s).",
                                       ["method"], buckets=_LATENCY_BUCKETS, registry=r)
        self.solver_failures = Counter("trajrecon_solver_failures",
                                       "Window NLP solves that failed and fell back.", registry=r)
        self.rejected = Counter("trajrecon_solves_rejected",
                                "Requests refused with 503 because the solve queue was full.",
                                registry=r)
        self.in_flight = Gauge("trajrecon_solves_in_flight",
                               "Reconstructions running or waiting for a worker.", registry=r)
        self.ready = Gauge("trajrecon_ready", "1 once the solvers are warmed up.", registry=r)
