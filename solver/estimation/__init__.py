"""Recursive state estimators ("filtered state estimates", spec filters.md).

``run_filter(name, plots, radar, **params)`` runs one estimator on the plots and returns the
state ``(x, z, vx, vz)`` with its covariance at every plot (input order); ``run_filters`` runs
several. Measurement noise is the radar's ``sigma_r`` / ``sigma_psi``; a plot with a known
altitude is used with its ground range ``sqrt(r^2 - h^2)``. Any step size works (missed plots);
one or two plots give a defined (broad) estimate.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from ..inputs import Plots, Radar
from ..results import FilterEstimate
from .alpha_beta import run_alpha_beta
from .common import SIGMA_V0, estimate
from .cv_rts import run_cv_rts
from .fuzzy import run_fuzzy
from .imm import run_imm
from .measurements import PolarPlots
from .quasi_optimal import run_quasi_optimal
from .singer import run_singer

FILTER_NAMES: tuple[str, ...] = ("singer", "quasi_optimal", "fuzzy", "alpha_beta", "cv_rts", "imm")

_RUNNERS: dict[str, Callable[..., FilterEstimate]] = {
    "singer": run_singer,
    "quasi_optimal": run_quasi_optimal,
    "fuzzy": run_fuzzy,
    "alpha_beta": run_alpha_beta,
    "cv_rts": run_cv_rts,
    "imm": run_imm,
}


def _fallback(name: str, meas: PolarPlots, reason: str) -> FilterEstimate:
    """Plot points with their converted covariance and an unknown velocity; variances beyond
    the float range (absurd radar sigmas) are capped at 1e300."""
    n = len(meas)
    s = np.zeros((n, 4))
    s[:, :2] = meas.points()
    P = np.zeros((n, 4, 4))
    with np.errstate(all="ignore"):
        P[:, :2, :2] = meas.converted_cov()
    P[:, 2, 2] = P[:, 3, 3] = SIGMA_V0**2
    P = np.clip(np.nan_to_num(P, nan=0.0, posinf=1e300, neginf=-1e300), -1e300, 1e300)
    return estimate(name, meas.t, s, P, warning=reason)


def run_filter(name: str, plots: Plots, radar: Radar, **params: Any) -> FilterEstimate:
    """Run estimator ``name`` (one of :data:`FILTER_NAMES`) with optional tuning ``params``.

    Raises ``KeyError`` for an unknown name and ``ValueError``/``TypeError`` for bad parameters.
    Never returns non-finite numbers: if the recursion breaks down numerically, the plot points
    with their measurement covariance are returned and ``info["warning"]`` says why.
    """
    if name not in _RUNNERS:
        raise KeyError(f"unknown filter {name!r}; choose from {', '.join(FILTER_NAMES)}")
    meas = PolarPlots.from_plots(plots, radar)
    try:
        with np.errstate(all="ignore"):
            est = _RUNNERS[name](meas, **params)
    except np.linalg.LinAlgError as exc:
        return _fallback(name, meas, f"numerical failure: {exc}")
    st = est.states
    assert st.cov is not None
    if not (np.all(np.isfinite(st.states)) and np.all(np.isfinite(st.cov))):
        return _fallback(name, meas, "non-finite estimate replaced by the plot points")
    return est


def run_filters(names: Iterable[str], plots: Plots, radar: Radar) -> dict[str, FilterEstimate]:
    """Run each named estimator with its defaults."""
    return {name: run_filter(name, plots, radar) for name in names}


__all__ = ["FILTER_NAMES", "run_filter", "run_filters"]
