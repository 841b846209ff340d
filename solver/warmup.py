"""Warming a process up before its first real track: imports, compiled functions, a solver.

A fresh process pays for its first reconstruction what later ones do not: the imports, the
motion model compiled to machine code (:mod:`solver.compiled`) and the first block solvers.
Measured on the first track of the benchmark recording (515 plots, three sensors) in a fresh
process: 2.97 s cold, 0.59 s after :func:`warm_refinement` (which took 2.64 s), 0.42 s warm.
Building every solver of the ladder instead (:func:`solver.refine.build_solvers`) took 5.3 s
and still left 1.38 s for that track: the solvers are cheap, the compiling is not. Since the
compiled objects are cached per machine (:func:`solver.compiled.cache_dir`), only a machine's
first process compiles: a fresh process's :func:`warm_refinement` then takes about 0.8 s
(4.6 s compiling).
"""

from __future__ import annotations

import time

import numpy as np

from .config import ReconstructionConfig
from .inputs import Plots, Radar
from .motion import propagate


def synthetic_track(n: int) -> tuple[Plots, Radar]:
    """``n`` noiseless plots every 10 s of a 200 m/s aircraft turning at 2 m/s^2."""
    t = 10.0 * np.arange(n)
    x, z, _, _ = propagate(50e3, 20e3, 0.5, 200.0, 2.0, 0.2, t)
    radar = Radar(range_error_m=300.0, azimuth_error_rad=np.deg2rad(0.5))
    return Plots.from_arrays(t, np.hypot(x, z), np.arctan2(z, x)), radar


WARM_PLOTS = 30
"""Plots of :func:`warm_refinement`'s track: enough for the refinement (not the sliding
windows' minimum only), small enough to take a tenth of a second once compiled."""


_warmed: set[str] = set()  # the methods this process has warmed up


def warm_refinement(config: ReconstructionConfig | None = None) -> float:
    """Reconstruct :func:`synthetic_track` (``WARM_PLOTS`` plots) with ``config`` (default:
    the default method), once per method and process; returns the seconds it took (0.0 when
    done before). A Dask task: ``solver.batch`` runs one on every worker as a run's first
    work, so a long-lived cluster (the service's jobs) pays it once per worker, not per run."""
    from .reconstruct import reconstruct

    config = config or ReconstructionConfig()
    if config.method in _warmed:
        return 0.0
    start = time.perf_counter()
    plots, radar = synthetic_track(WARM_PLOTS)
    reconstruct(plots, radar, config)
    _warmed.add(config.method)
    return time.perf_counter() - start
