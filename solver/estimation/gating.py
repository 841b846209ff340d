"""The filters' validation gate: a plot far from the filter's prediction is not used.

A recorded track has wild plots (false plots, reflections, a split plot's ghost, a garbled
range). Unguarded, one such plot pulls a Kalman filter by its gain and a smoother carries the
error both ways: with 1 % of the plots 3-20 km off (ssr profile, four dev tracks) the IMM
smoother's RMS error went from 52 to 500 m, the causal IMM's from 92 to 673 m, while the
reconstruction, which gates its own (:mod:`solver.refine.gate`), stayed at 52 m.

The rule (:func:`gated_pass`): a plot whose normalised innovation squared exceeds ``gate^2``
(``nu^T S^-1 nu`` of the update, the smallest over an IMM's modes; the sum over a plot's two
coordinates in the per-coordinate filters) is far. The recording is there to look ahead: a far
plot is left out (the state there is the prediction) when the next plot is likelier under the
prediction made without it than under the one made with it (its predictive likelihood: the
normalised innovation alone favours the longer prediction's wider spread); else the track is
there (a turn the model follows late, a hold, genuine plots after a wild one that pulled the
filter off) and it is used. Gating on the distance alone left out genuine plots of 19-s scans in
turns, two at a time, and a Singer or fuzzy filter coasting through a 6 m/s^2 turn ended 12-24 %
worse on the clean held-out plots of the seed000 profile. More than :data:`MAX_GATED_RUN` far
plots left out in a row are not wild plots but an aircraft that is elsewhere: the run's first
plot is used and the filter runs again from there, so a track is never lost. Every plot left out
is reported (``info["gated"]``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..config import FILTER_GATE_SIGMA
from ..config import check_filter_gate as check_gate
from ..results import listed

GATE_SIGMA = FILTER_GATE_SIGMA
"""Default gate (sigmas): :data:`solver.config.FILTER_GATE_SIGMA`, where its measured reason is."""
MAX_GATED_RUN = 2
"""At most this many plots in a row are left out (module docstring)."""

Step = Callable[[int, np.ndarray, bool], np.ndarray]
"""``step(k, lanes, use) -> (2, len(lanes))``: filter step ``k`` (from the state after plot
``k - 1`` to the state after plot ``k``) of the given lanes (independent filters run side by
side), with the plot's update (``use``) or without it (the prediction); returns per lane the
plot's normalised innovation squared and its deviance ``-2 log`` of the predictive likelihood
(up to a constant; ``nis + log det S`` for one Gaussian); read only after ``use=True``."""


def gated_pass(n: int, lanes: int, step: Step, gate: float | None) -> np.ndarray:
    """Run steps ``1 .. n-1`` of ``lanes`` independent filters with the gate (module docstring);
    returns ``(n, lanes)``, True where a lane left the plot out. ``gate=None``: every plot is used.
    """
    check_gate(gate)
    gated = np.zeros((n, lanes), dtype=bool)
    every = np.arange(lanes)
    if gate is None:
        for k in range(1, n):
            step(k, every, True)
        return gated
    limit = float(gate) ** 2
    run = np.zeros(lanes, dtype=int)
    used = np.zeros((n, lanes), dtype=bool)  # the first plot of a run too long: used for good
    running = False  # some lane's run is under way (run > 0)
    one = lanes == 1
    for k in range(1, n):
        nis = step(k, every, True)
        # most steps: nothing else to do (one lane: a float's test, no array)
        if not (nis[0, 0] > limit if one else (far := np.asarray(nis)[0] > limit).any()):
            if running:
                run[:] = 0
                running = False
            continue
        if one:
            far = np.ones(1, dtype=bool)
        run[~far] = 0
        for b in np.flatnonzero(far):
            _decide(int(b), k, n, step, limit, run, gated, used)
        running = bool(run.any())
    return gated


def _decide(b: int, k: int, n: int, step: Step, limit: float, run: np.ndarray,
            gated: np.ndarray, used: np.ndarray) -> None:
    """Lane ``b``'s plot ``k`` is far (its state at ``k`` has the update): used if the next
    plot is likelier under the lane's prediction with it than without it (an aircraft that
    turned, or that a wild plot before had pulled the filter from: the plots that follow agree),
    else left out (a wild plot: the next agrees with the prediction without it). One far plot
    more than :data:`MAX_GATED_RUN` left out in a row: the run's first plot is used for good and
    the lane filtered again from there up to ``k``, each far plot decided the same way (each
    return fixes one more plot, so this ends)."""
    lane = np.array([b])

    def nis_at(j: int) -> float:
        return float(np.asarray(step(j, lane, True))[0, 0])

    def deviance_at(j: int) -> float:
        return float(np.asarray(step(j, lane, True))[1, 0])

    j = k
    while True:  # decide the far plot j (its state has the update; those before are final)
        if used[j, b]:
            run[b] = 0
        elif j + 1 < n and not deviance_at(j + 1) > _without(j, lane, step, deviance_at):
            step(j, lane, True)  # the next plot is no likelier without it: used
            run[b] = 0
        elif run[b] < MAX_GATED_RUN:
            step(j, lane, False)
            gated[j, b] = True
            run[b] += 1
        else:  # the aircraft is elsewhere: the run's first plot is used, and on from there
            j = j - int(run[b])
            used[j, b] = True
            gated[j:k + 1, b] = False
            run[b] = 0
            step(j, lane, True)
        j += 1
        while j <= k:  # on to the next far plot up to k
            if not used[j, b] and nis_at(j) > limit:
                break
            run[b] = 0
            j += 1
        else:
            return


def _without(j: int, lane: np.ndarray, step: Step, deviance_at: Callable[[int], float]
             ) -> float:
    """The next plot's deviance with plot ``j`` left out (the state at ``j`` is then the
    prediction)."""
    step(j, lane, False)
    return deviance_at(j + 1)


def gate_warnings(gated: dict[str, list[int]], no_weight: np.ndarray) -> list[str]:
    """The operator's lines about the filters' gates: per filter the plots it left out
    (``gated``: plot indexes by filter name), and those the reconstruction gave no weight as
    wild (``no_weight``, :attr:`solver.results.Reconstruction.no_weight`) that it used; each
    filter gates by its own rule, some by none (a tester read the reconstruction's 'given no
    weight' as true of the filters, whose states were 55-248 km off there)."""
    wild = np.asarray(no_weight, dtype=int)
    out = []
    for name, left_out in gated.items():
        if left_out:
            out.append(f"filters.{name}: {len(left_out)} plot(s) left out, far from the "
                       f"filter's prediction (wild plots?): {listed(left_out, 10)}")
        used = np.setdiff1d(wild, left_out).tolist()
        if used:
            out.append(f"filters.{name}: used {len(used)} plot(s) the reconstruction gave no "
                       f"weight as wild: {listed(used, 10)}")
    return out
