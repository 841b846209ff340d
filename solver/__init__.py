"""Pure computation: radar trajectory reconstruction and recursive filters (no web imports)."""

import os

# CasADi's IPOPT loads a bundled OpenMP BLAS whose second thread only spins on these small banded
# KKT systems: measured on a 1458-plot track, the same 1.35 s wall time with 2.6 s of CPU
# (1.2 s of it system time) against 1.3 s with one thread. Read when IPOPT is first loaded, so
# setting it here (unless the caller chose) halves the CPU of every solve.
os.environ.setdefault("OMP_NUM_THREADS", "1")

from .inputs import Bounds, InputError, Plots, Radar
from .results import Diagnostics, FilterEstimate, Reconstruction, Segment, StateSeries

__all__ = [
    "Bounds",
    "Diagnostics",
    "FilterEstimate",
    "InputError",
    "Plots",
    "Radar",
    "Reconstruction",
    "Segment",
    "StateSeries",
]
