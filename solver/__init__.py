"""Pure computation: radar trajectory reconstruction and recursive filters (no web imports)."""

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
