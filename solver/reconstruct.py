"""The public entry point: plots in, reconstructed trajectory out."""

from __future__ import annotations

import time

from .config import ReconstructionConfig
from .inputs import Plots, Radar
from .results import Reconstruction


def reconstruct(plots: Plots, radar: Radar,
                config: ReconstructionConfig | None = None) -> Reconstruction:
    """Reconstruct one aircraft's trajectory from its plots.

    The sliding constant-control windows (spec section 6) give a segmentation and a first
    trajectory; with ``config.method == "refined"`` (default) one bounded full-track NLP then
    uses every plot before and after each point.
    """
    from .refine import refine
    from .sliding import reconstruct_sliding

    config = config or ReconstructionConfig()
    radar.validate()
    plots.validate()
    config.validate()
    start = time.perf_counter()
    result = reconstruct_sliding(plots, radar, config)
    if config.method == "refined" and len(plots) >= 3:
        result = refine(plots, radar, config, result)
    result.diagnostics.elapsed_ms = (time.perf_counter() - start) * 1e3
    return result
