"""Between the HTTP models (degrees, lists of objects) and ``solver`` (radians, arrays).

``to_job`` validates through the solver's own ``validate()`` methods, so every physical check
exists once; it renames the solver's radian fields back to the degree fields the client sent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.config import ReconstructionConfig
from solver.inputs import Bounds, InputError, Plots, Radar
from solver.results import Diagnostics, FilterEstimate, Reconstruction, StateSeries

from .models import ReconstructionRequest

DEFAULT_WINDOW_PLOTS: int = ReconstructionConfig().window_plots

# solver field name -> request field name
_RENAMED = {
    "azimuth_error_rad": "azimuth_error_deg",
    "azimuth_sigma_rad": "azimuth_sigma_deg",
    "max_elevation_rad": "max_elevation_deg",
    "azimuth_rad": "azimuth_deg",
}


def client_loc(loc: tuple[str | int, ...]) -> tuple[str | int, ...]:
    """The solver's field path in the request's terms (``azimuth_rad`` -> ``azimuth_deg``)."""
    return tuple(_RENAMED.get(p, p) if isinstance(p, str) else p for p in loc)


@dataclass(frozen=True)
class Job:
    """One validated reconstruction, ready to send to a worker (picklable)."""

    plots: Plots
    radar: Radar
    config: ReconstructionConfig
    filters: tuple[str, ...]


def to_job(req: ReconstructionRequest, nlp_solver: str, max_plots: int,
           max_samples: int) -> Job:
    """Validate a request into solver inputs; raise :class:`InputError` (client field names).

    Beyond the solver's checks: the service's size limits (plots, samples) and a window no
    longer than the track."""
    try:
        return _to_job(req, nlp_solver, max_plots, max_samples)
    except InputError as e:
        raise InputError(client_loc(e.loc), e.message) from None


def _to_job(req: ReconstructionRequest, nlp_solver: str, max_plots: int,
            max_samples: int) -> Job:
    n = len(req.plots)
    if n > max_plots:
        raise InputError(("plots",), f"has {n} plots; this service accepts at most {max_plots}")
    r = req.radar
    radar = Radar(
        range_error_m=r.range_error_m,
        azimuth_error_rad=np.deg2rad(r.azimuth_error_deg),
        range_sigma_m=r.range_sigma_m,
        azimuth_sigma_rad=None if r.azimuth_sigma_deg is None else np.deg2rad(r.azimuth_sigma_deg),
        max_altitude_m=r.max_altitude_m,
        max_elevation_rad=np.deg2rad(r.max_elevation_deg),
    )
    radar.validate()
    cols = np.array([(p.t, p.range_m, p.azimuth_deg) for p in req.plots], dtype=float)
    alt = None
    if any(p.altitude_m is not None for p in req.plots):
        alt = np.array([np.nan if p.altitude_m is None else p.altitude_m for p in req.plots])
    plots = Plots.from_arrays(cols[:, 0], cols[:, 1], np.deg2rad(cols[:, 2]), alt)
    b = req.bounds
    config = ReconstructionConfig(
        bounds=Bounds(u=(b.u[0], b.u[1]), w=(b.w[0], b.w[1]), v=(b.v[0], b.v[1])),
        window_plots=DEFAULT_WINDOW_PLOTS if req.window.plots is None else req.window.plots,
        trial_step_s=req.window.trial_step_s,
        criterion=req.criterion,
        sample_step_s=req.sample_step_s,
        method=req.method,
        nlp_solver=nlp_solver,  # type: ignore[arg-type]
    )
    config.validate()
    if req.window.plots is not None and req.window.plots > n:
        raise InputError(("window", "plots"),
                         f"({config.window_plots}) is longer than the track ({n} plots)")
    span = float(plots.t[-1] - plots.t[0])
    if span / config.sample_step_s >= max_samples:
        raise InputError(("sample_step_s",), f"({config.sample_step_s:g} s) gives more than "
                         f"{max_samples} samples over the {span:g}-s track; this service's "
                         "limit is max_samples")
    return Job(plots, radar, config, tuple(dict.fromkeys(req.filters)))


# ----------------------------------------------------------------------------------- results


def _states(s: StateSeries, with_heading: bool) -> list[dict]:
    """Rows of a state series; ``cov`` as nested lists (or None)."""
    cols = {"t": s.t, "x": s.x, "z": s.z, "vx": s.vx, "vz": s.vz}
    if with_heading:
        cols["heading_deg"] = np.rad2deg(s.heading)
        cols["speed"] = s.speed
    names = list(cols)
    rows = [dict(zip(names, vals, strict=True))
            for vals in np.column_stack(list(cols.values())).tolist()]
    if s.cov is not None:
        for row, c in zip(rows, np.asarray(s.cov).tolist(), strict=True):
            row["cov"] = c
    return rows


def _diagnostics(d: Diagnostics) -> dict:
    return {
        "method": d.method,
        "windows_solved": d.windows_solved,
        "trial_windows": d.trial_windows,
        "solver_failures": d.solver_failures,
        "fallbacks": d.fallbacks,
        "criterion": d.criterion,
        "criterion_values": [float(v) for v in d.criterion_values],
        "nlp_solves": len(d.nlp_solve_ms),
        "nlp_solve_ms_total": float(np.sum(d.nlp_solve_ms)) if d.nlp_solve_ms else 0.0,
        "elapsed_ms": d.elapsed_ms,
        "warnings": list(d.warnings),
        "extra": dict(d.extra),
    }


def response_dict(rec: Reconstruction, estimates: dict[str, FilterEstimate]) -> dict:
    """The JSON-ready body of a 200 (validated against ``ReconstructionResponse`` by the
    caller)."""
    segments = [
        {"t_start": s.t_start, "t_end": s.t_end, "u": s.u, "w": s.w, "x": s.x, "z": s.z,
         "heading_deg": float(np.rad2deg(s.heading) % 360.0), "speed": s.speed}
        for s in rec.segments
    ]
    return {
        "trajectory": {
            "segments": segments,
            "at_plots": _states(rec.at_plots, True),
            "samples": _states(rec.samples, True),
        },
        "filters": {name: {"states": _states(e.states, False)} for name, e in estimates.items()},
        "diagnostics": _diagnostics(rec.diagnostics),
    }
