"""The filters' validation gate: a plot far from the filter's prediction is not used.

A recorded track has wild plots (false plots, reflections, a split plot's ghost, a garbled
range). Unguarded, one such plot pulls a Kalman filter by its gain and a smoother carries the
error both ways: with 1 % of the plots 3-20 km off (ssr profile, four dev tracks) the IMM
smoother's RMS error went from 52 to 500 m, the causal IMM's from 92 to 673 m, while the
reconstruction, which gates its own (:mod:`solver.refine.gate`), stayed at 52 m.

The rule (:func:`gated_pass`): a plot whose normalised innovation squared exceeds ``gate^2``
(``nu^T S^-1 nu`` of the update, the smallest over an IMM's modes; the sum over a plot's two
coordinates in the per-coordinate filters) is not used: the state there is the prediction. When
the next plot is far too, either the plot before them, which the filter used, was a wild one
that passed the gate and pulled the filter off (then, with it left out, all the far plots are
within the gate: it is left out instead), or they are left out too, up to :data:`MAX_GATED_RUN`
in a row. One more is not a few wild plots but an aircraft that is not where the filter thinks
(after a long gap, a manoeuvre the model cannot follow): the run's first plot is used. The filter
then runs again from the plot decided. So a track is never lost, only its isolated far plots
are left out. Every plot left out is reported (``info["gated"]``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

GATE_SIGMA = 6.0
"""Default gate (sigmas of the normalised innovation). On the dev plots (seeds 100-101, six
ADS-B tracks and the seed-like track, three profiles) the CV and Singer filters' largest
normalised innovations are 4.8-6.1 sigma (19-s scans in turns); 6 sigma leaves out about one
plot in 10^4 there, for a Gaussian 2-d innovation one in 7 * 10^7."""
MAX_GATED_RUN = 2
"""At most this many plots in a row are left out (module docstring)."""

Step = Callable[[int, np.ndarray, bool], np.ndarray]
"""``step(k, lanes, use) -> nis``: filter step ``k`` (from the state after plot ``k - 1`` to the
state after plot ``k``) of the given lanes (independent filters run side by side), with the
plot's update (``use``) or without it (the prediction); returns the lanes' normalised innovations
squared (only read after ``use=True``)."""


def check_gate(gate: float | None) -> None:
    """``ValueError`` unless ``gate`` is None (no gate) or a positive finite number."""
    if gate is not None and (isinstance(gate, bool) or not isinstance(gate, int | float)
                             or not 0 < gate < np.inf):
        raise ValueError(f"gate must be a positive number of sigmas or None, not {gate!r}")


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
    fixed = np.zeros((n, lanes), dtype=bool)  # decided for good: used, or left out if gated
    running = False  # some lane's run is under way (run > 0)
    one = lanes == 1
    for k in range(1, n):
        nis = step(k, every, True)
        # most steps: nothing else to do (one lane: a float's test, no array)
        if not (nis[0] > limit if one else (far := np.asarray(nis) > limit).any()):
            if running:
                run[:] = 0
                running = False
            continue
        if one:
            far = np.ones(1, dtype=bool)
        running = True
        run[~far] = 0
        first = far & (run == 0)  # a lane's first far plot: left out
        if first.any():
            step(k, every[first], False)
            gated[k, first] = True
            run[first] = 1
        for b in np.flatnonzero(far & ~first):
            _resolve(int(b), k, step, limit, run, gated, fixed)
    return gated


def _resolve(b: int, k: int, step: Step, limit: float, run: np.ndarray, gated: np.ndarray,
             fixed: np.ndarray) -> None:
    """Lane ``b``'s plot ``k`` is far again after ``run[b]`` far plots left out (its state at
    ``k`` has the update). Either the plot before that run, which the lane used, was a wild one
    that passed the gate and pulled it off: then with that plot left out every plot of the run
    and ``k`` is within the gate, and that plot is left out for good. Or ``k`` is left out too,
    up to :data:`MAX_GATED_RUN` in a row; one more and the aircraft is elsewhere (after a gap, a
    manoeuvre the model cannot follow): the run's first plot is used for good. Then the lane is
    filtered again up to ``k``, each far plot decided the same way; every return fixes one more
    decision, so this ends."""
    lane = np.array([b])

    def far(j: int) -> bool:  # the step with the plot's update; is the plot far?
        return float(np.asarray(step(j, lane, True))[0]) > limit

    j = k
    while True:  # decide the far plot j (the states before j are final)
        r = int(run[b])
        j0 = j - r  # the run's first plot
        before = j0 - 1
        wild_before = False
        if r and before >= 1 and not fixed[before, b]:
            step(before, lane, False)
            wild_before = not any(far(i) for i in range(j0, j + 1))  # stops at a far plot
            if wild_before:
                fixed[before, b] = gated[before, b] = True
                gated[j0:j + 1, b] = False
                run[b] = 0
                j += 1
            else:  # back as it was, j with its update
                step(before, lane, True)
                for i in range(j0, j):
                    step(i, lane, False)
                far(j)
        if not wild_before:
            if r < MAX_GATED_RUN:
                step(j, lane, False)
                gated[j, b] = True
                run[b] += 1
                j += 1
            else:
                fixed[j0, b] = True
                gated[j0:j + 1, b] = False
                run[b] = 0
                step(j0, lane, True)
                j = j0 + 1
        while j <= k:
            if fixed[j, b]:
                step(j, lane, not gated[j, b])
                run[b] = 0
            elif far(j):
                break
            else:
                run[b] = 0
            j += 1
        else:
            return
