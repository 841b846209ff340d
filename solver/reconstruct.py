"""The public entry point: plots in, reconstructed trajectory out."""

from __future__ import annotations

import time

from .config import ReconstructionConfig
from .inputs import Plots, Radar
from .results import Reconstruction


def reconstruct(plots: Plots, radar: Radar,
                config: ReconstructionConfig | None = None) -> Reconstruction:
    """Reconstruct one aircraft's trajectory from its plots.

    ``config.method == "sliding"``: the seed's sliding constant-control windows (spec section
    6). ``"refined"`` (default): one bounded full-track NLP that uses every plot before and
    after each point (``solver.refine``); tracks of fewer than 3 plots always take the sliding
    path, which defines their behaviour.
    """
    from .refine import refine
    from .sliding import reconstruct_sliding

    config = config or ReconstructionConfig()
    radar.validate()
    plots.validate()
    config.validate()
    start = time.perf_counter()
    if config.method == "refined" and len(plots) >= 3:
        initial = (reconstruct_sliding(plots, radar, config)
                   if config.refine.init == "sliding" else None)
        result = refine(plots, radar, config, initial)
    else:
        result = reconstruct_sliding(plots, radar, config)
    result.diagnostics.elapsed_ms = (time.perf_counter() - start) * 1e3
    return result
