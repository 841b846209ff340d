"""The public entry point: plots in, reconstructed trajectory out."""

from __future__ import annotations

import logging
import time

import numpy as np

from .config import ReconstructionConfig
from .inputs import Plots, Radar
from .results import Reconstruction

log = logging.getLogger(__name__)


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
    result = None
    if config.method == "refined" and len(plots) >= 3:
        initial = (reconstruct_sliding(plots, radar, config)
                   if config.refine.init == "sliding" else None)
        try:
            result = refine(plots, radar, config, initial)
        except (ArithmeticError, ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
            if "KeyboardInterrupt" in str(exc):
                # CasADi reports a signal handler's exception (Ctrl-C, a time limit) this way:
                # an interruption, not a numerical failure
                raise KeyboardInterrupt(str(exc)) from exc
            # degrade to the seed's method rather than fail the request
            log.warning("refinement failed (%s); falling back to the sliding windows", exc)
            result = reconstruct_sliding(plots, radar, config)
            result.diagnostics.solver_failures += 1
            result.diagnostics.fallbacks += 1
            result.diagnostics.warnings.append(
                f"refinement failed ({type(exc).__name__}: {exc}); sliding-window result")
    if result is None:
        result = reconstruct_sliding(plots, radar, config)
    result.diagnostics.elapsed_ms = (time.perf_counter() - start) * 1e3
    return result
