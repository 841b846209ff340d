"""Recursive state estimators ("filtered state estimates", spec filters.md).

``run_filter(name, table_or_plots, radar=None, **params)`` runs one estimator on the plots (a
:class:`~solver.plots.PlotTable` of one or several sensors, or the single radar's ``Plots`` with
its ``Radar``) and returns the state ``(x, z, vx, vz)`` with its covariance at every plot (input
order); ``run_filters`` runs several. Several sensors: every plot at its own time with its own
sensor's model (:class:`~.measurements.SensorPlots`). Measurement noise is the radar's
``sigma_r`` / ``sigma_psi``; a plot with a known altitude is used with its ground range
``sqrt(r^2 - h^2)``. Any step size works (missed plots);
one or two plots give a defined (broad) estimate.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterable
from dataclasses import fields, replace
from typing import Any

import numpy as np

from ..inputs import Plots, Radar
from ..plots import PlotTable
from ..results import FilterEstimate
from .alpha_beta import run_alpha_beta
from .common import SIGMA_V0, estimate
from .cv_rts import run_cv_rts
from .fusion import run_fusion_a, run_fusion_b, run_fusion_c
from .fuzzy import run_fuzzy
from .gating import GATE_SIGMA, check_gate
from .imm import run_imm
from .imm_smoother import run_imm_smoother
from .measurements import PolarPlots, SensorPlots
from .quasi_optimal import run_quasi_optimal
from .singer import run_singer

FILTER_NAMES: tuple[str, ...] = ("singer", "quasi_optimal", "fuzzy", "alpha_beta", "cv_rts", "imm",
                                 "imm_smoother", "fusion_a", "fusion_b", "fusion_c")

_RUNNERS: dict[str, Callable[..., FilterEstimate]] = {
    "singer": run_singer,
    "quasi_optimal": run_quasi_optimal,
    "fuzzy": run_fuzzy,
    "alpha_beta": run_alpha_beta,
    "cv_rts": run_cv_rts,
    "imm": run_imm,
    "imm_smoother": run_imm_smoother,
    "fusion_a": run_fusion_a,
    "fusion_b": run_fusion_b,
    "fusion_c": run_fusion_c,
}
FUSION_NAMES: tuple[str, ...] = ("fusion_a", "fusion_b", "fusion_c")
"""Seed 004's fusion variants: defined for exactly two sensors (``ValueError`` otherwise)."""
SINGLE_SENSOR_NAMES: tuple[str, ...] = tuple(n for n in FILTER_NAMES if n not in FUSION_NAMES)
"""The filters that run on any number of sensors, one included."""
GATING_NAMES: tuple[str, ...] = tuple(n for n in FILTER_NAMES
                                     if "gate" in inspect.signature(_RUNNERS[n]).parameters)
"""The filters with the validation gate (:mod:`.gating`); ``alpha_beta`` and the fusion
variants (seed 004's fits) use every plot."""
_PER_MEASUREMENT = frozenset({"nis", "gains", "gain_level", "gated"})
"""``info`` arrays that describe each measurement (not the state after it)."""


def measurement_set(data: PlotTable | Plots, radar: Radar | None = None
                    ) -> PolarPlots | SensorPlots:
    """The filters' measurements: ``PolarPlots`` for the single radar at the origin of a flat
    plane (``(plots, radar)`` or a legacy table: today's filters unchanged), else
    ``SensorPlots`` in time order."""
    if isinstance(data, PlotTable):
        if radar is not None:
            raise TypeError("give the radar inside the PlotTable, not beside it")
        if data.is_legacy:
            return PolarPlots.from_plots(*data.legacy())
        return SensorPlots.from_table(data)
    if radar is None:
        raise TypeError("plots need their radar: run_filter(name, plots, radar)")
    return PolarPlots.from_plots(data, radar)


def _in_table_order(est: FilterEstimate, meas: SensorPlots) -> FilterEstimate:
    """Time-ordered output of a runner to table rows; plots at one instant all get the state
    after the last of them (per-measurement diagnostics keep their own values)."""
    n = len(meas)
    inv = np.empty(n, dtype=int)
    inv[meas.rows] = np.arange(n)
    sel = meas.same_instant()[inv]
    st = est.states
    assert st.cov is not None
    info = {k: (v[inv] if k in _PER_MEASUREMENT else v[sel])
            if isinstance(v, np.ndarray) and v.shape[:1] == (n,) else v
            for k, v in est.info.items()}
    return estimate(est.name, meas.t[inv], st.states[sel], st.cov[sel], **info)


def _fallback(name: str, meas: PolarPlots | SensorPlots, reason: str) -> FilterEstimate:
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


START_PLOTS = 2
"""The filters start from their first two plots (the state from one, the velocity's spread from
the next), which their gate cannot judge: a wild first or second plot (8 km and 2 deg off, the
turning track of ``tests/test_estimation_gating.py``) was used and pulled the start, and the
smoothers carried it on: the IMM smoother's RMS error at the genuine plots went from 129 to
261 m (first plot wild) and 315 m (second), the CV smoother's from 184 to 301 and 328 m. From the
third plot on the gate leaves an 8-km plot out (every gating filter, two seeds)."""
REVERSED_PLOTS = 10
"""How many first plots the gating filters run backwards over to judge the first
:data:`START_PLOTS` (:func:`_from_a_sound_start`)."""
_VELOCITY_SIGN = np.array([1.0, 1.0, -1.0, -1.0])
START_JUDGE = "imm"
"""The filter run backwards to judge the first plots, whichever filter runs: the causal IMM
(its coordinated-turn modes follow a turn). Each filter judging its own start took the first
plot of a standard-rate turn (3 deg/s) on 19-s scans for wild in 19-20 of 20 runs (the CV,
Singer, fuzzy, quasi-optimal filters and the IMM smoother; a review helper), and its state
2 km off; the IMM judges none of them (nor of 25-30 m/s^2 turns on 4.8-s scans). Left: starts
in a 25-30 m/s^2 turn, or braking at 8 m/s^2, on 19-s scans are still taken for wild (all and
9-13 of 20 runs)."""


def _from_a_sound_start(name: str, meas: PolarPlots | SensorPlots, params: dict[str, Any]
                        ) -> FilterEstimate:
    """Run a filter, its first :data:`START_PLOTS` plots judged by a gate run backwards:
    :data:`START_JUDGE` over the first :data:`REVERSED_PLOTS` plots in reverse (times
    mirrored, so they grow) reaches them with a converged state, and what its gate leaves out
    of them (the rule of :mod:`.gating`, the filter's gate) is left out of the forward run
    too. Their states are the backward run's (velocity turned back: no causal estimate exists
    without them), marked ``gated``, their other diagnostics the forward run's at its first
    plot. Filters without a gate, a
    gate of None, and fewer plots than :data:`REVERSED_PLOTS` run as they are."""
    run = _RUNNERS[name]
    n = len(meas)
    if name not in GATING_NAMES or params.get("gate", GATE_SIGMA) is None or n < REVERSED_PLOTS:
        return run(meas, **params)
    back = np.arange(REVERSED_PLOTS)[::-1]
    backward = _RUNNERS[START_JUDGE](_take(meas, back, meas.t[back[0]] - meas.t[back]),
                                     **gate_param(START_JUDGE, params.get("gate", GATE_SIGMA)))
    wild = np.flatnonzero(np.asarray(backward.info["gated"])[::-1][:START_PLOTS])
    if not wild.size:
        return run(meas, **params)
    keep = np.setdiff1d(np.arange(n), wild)
    forward = run(_take(meas, keep, meas.t[keep]), **params)
    st, bst = forward.states, backward.states
    assert st.cov is not None and bst.cov is not None
    states, cov = np.empty((n, 4)), np.empty((n, 4, 4))
    states[keep], cov[keep] = st.states, st.cov
    states[wild] = bst.states[::-1][wild] * _VELOCITY_SIGN
    cov[wild] = bst.cov[::-1][wild] * np.outer(_VELOCITY_SIGN, _VELOCITY_SIGN)
    info: dict[str, Any] = {}
    for key, value in forward.info.items():
        if not (isinstance(value, np.ndarray) and value.shape[:1] == (len(keep),)):
            info[key] = value
            continue
        out = np.empty((n, *value.shape[1:]), dtype=value.dtype)
        out[keep] = value
        out[wild] = value[0]
        info[key] = out
    info["gated"][wild] = True
    if "nis" in info and "nis" in backward.info:
        info["nis"][wild] = np.asarray(backward.info["nis"])[::-1][wild]
    return estimate(forward.name, meas.t, states, cov, **info)


def _take(meas: PolarPlots | SensorPlots, idx: np.ndarray, t: np.ndarray
          ) -> PolarPlots | SensorPlots:
    """The measurements ``idx`` (in that order) at times ``t``."""
    n = len(meas)
    taken = {f.name: getattr(meas, f.name)[idx] for f in fields(meas)
             if isinstance(getattr(meas, f.name), np.ndarray)
             and getattr(meas, f.name).shape[:1] == (n,)}
    return replace(meas, **{**taken, "t": np.asarray(t, dtype=float)})


def run_filter(name: str, data: PlotTable | Plots, radar: Radar | None = None,
               **params: Any) -> FilterEstimate:
    """Run estimator ``name`` (one of :data:`FILTER_NAMES`) with optional tuning ``params`` on
    a :class:`PlotTable` or on ``(plots, radar)``; one state per plot in input (table) order.

    Raises ``KeyError`` for an unknown name and ``ValueError``/``TypeError`` for bad parameters
    (and for the fusion variants on other than two sensors). Never returns non-finite numbers:
    if the recursion breaks down numerically, the plot points with their measurement covariance
    are returned and ``info["warning"]`` says why.
    """
    if name not in _RUNNERS:
        raise KeyError(f"unknown filter {name!r}; choose from {', '.join(FILTER_NAMES)}")
    meas = measurement_set(data, radar)
    k = _plane_scale(data, meas)
    if k != 1.0 and isinstance(meas, SensorPlots):  # run on the ground's scale (its noise)
        meas = replace(meas, centre=meas.centre / k, cov=meas.cov / k**2)
    try:
        with np.errstate(all="ignore"):
            est = _from_a_sound_start(name, meas, params)
        st = est.states
        assert st.cov is not None
        if not (np.all(np.isfinite(st.states)) and np.all(np.isfinite(st.cov))):
            est = _fallback(name, meas, "non-finite estimate replaced by the plot points")
    except np.linalg.LinAlgError as exc:
        est = _fallback(name, meas, f"numerical failure: {exc}")
    est = _in_table_order(est, meas) if isinstance(meas, SensorPlots) else est
    return est if k == 1.0 else _scaled(est, k)


def _plane_scale(data: PlotTable | Plots, meas: PolarPlots | SensorPlots) -> float:
    """The plane's median scale at the plots of a table on the earth (1 on a flat plane). The
    filters' process noise (accelerations) and start spreads are ground quantities, while the
    plots' fixes are plane metres (their scale times the ground's): run in plane metres far
    from the reference (scale 1.122 at 4,300 km) the states' sigmas grew 1.09 times where
    ``x``, ``z`` grew 1.122 times (a tester's). Scaled by the median, the filter runs on the
    ground's scale and its answer is mapped back exactly (a similarity of the plane)."""
    if not (isinstance(data, PlotTable) and data.frame is not None
            and isinstance(meas, SensorPlots) and len(meas) and not meas.polar.any()):
        return 1.0
    with np.errstate(all="ignore"):
        k = float(np.median(data.frame.scale(meas.centre[:, 0], meas.centre[:, 1])))
    return k if np.isfinite(k) and k > 0 else 1.0


def _scaled(est: FilterEstimate, k: float) -> FilterEstimate:
    """``est`` with its positions and velocities times ``k``, covariances times ``k^2``
    (``info["filtered"]``, the filtered states of a smoother, too)."""
    st = est.states
    assert st.cov is not None
    info = dict(est.info)
    if isinstance(info.get("filtered"), np.ndarray):
        info["filtered"] = np.asarray(info["filtered"]) * k
    return estimate(est.name, st.t, st.states * k, st.cov * k**2, **info)


def run_filters(names: Iterable[str], data: PlotTable | Plots, radar: Radar | None = None, *,
                gate: float | None = GATE_SIGMA) -> dict[str, FilterEstimate]:
    """Run each named estimator with its defaults, those of :data:`GATING_NAMES` with the
    validation gate ``gate`` (sigmas; None: every plot used)."""
    check_gate(gate)
    return {name: run_filter(name, data, radar, **gate_param(name, gate)) for name in names}


def gate_param(name: str, gate: float | None) -> dict[str, float | None]:
    """``{"gate": gate}`` for a filter of :data:`GATING_NAMES`, else nothing."""
    return {"gate": gate} if name in GATING_NAMES else {}


__all__ = ["FILTER_NAMES", "FUSION_NAMES", "GATE_SIGMA", "GATING_NAMES", "SINGLE_SENSOR_NAMES",
           "gate_param", "measurement_set", "run_filter", "run_filters"]
