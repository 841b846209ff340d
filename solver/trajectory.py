"""Evaluate a piecewise-constant-control trajectory (a list of segments) at arbitrary times."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .inputs import FloatArray
from .motion import propagate, velocity
from .results import Segment, StateSeries


def segment_arrays(segments: Sequence[Segment]) -> dict[str, FloatArray]:
    """Columns ``t_start, x, z, heading, speed, u, w`` of the segments as arrays."""
    names = ("t_start", "x", "z", "heading", "speed", "u", "w")
    return {k: np.array([getattr(s, k) for s in segments], dtype=float) for k in names}


def evaluate(segments: Sequence[Segment], t: FloatArray) -> StateSeries:
    """States at times ``t`` (any order): each time uses the last segment starting at or before
    it (the first segment for earlier times, the last one for later times), propagated in
    closed form from that segment's start."""
    t = np.asarray(t, dtype=float)
    if not segments:
        raise ValueError("no segments to evaluate")
    s = segment_arrays(segments)
    k = np.clip(np.searchsorted(s["t_start"], t, side="right") - 1, 0, len(segments) - 1)
    x, z, phi, v = propagate(s["x"][k], s["z"][k], s["heading"][k], s["speed"][k],
                             s["u"][k], s["w"][k], t - s["t_start"][k])
    vx, vz = velocity(phi, v)
    return StateSeries(t.copy(), x, z, vx, vz)


def sample_times(t_first: float, t_last: float, step: float) -> FloatArray:
    """Regular grid from ``t_first`` with spacing ``step``, ``t_last`` always included."""
    n = int(np.floor((t_last - t_first) / step + 1e-9))
    grid = t_first + step * np.arange(n + 1)
    if t_last - grid[-1] > 1e-9 * max(1.0, abs(t_last)):
        grid = np.append(grid, t_last)
    else:
        grid[-1] = t_last
    return grid
