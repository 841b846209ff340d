"""Settings of one reconstruction (every value has a documented default)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from .inputs import Bounds, InputError

Criterion = Literal["R1", "R2"]
Method = Literal["refined", "sliding"]
NlpSolver = Literal["sqpmethod", "ipopt"]
MIN_BLOCK_NODES, MAX_BLOCK_NODES = 16, 2048  # block solver sizes (solver.refine.LADDER)
FILTER_GATE_SIGMA = 6.0
"""Default validation gate of the recursive filters (sigmas of the normalised innovation,
:mod:`solver.estimation.gating`). On the dev plots (seeds 100-101, the seven
benchmark tracks, three profiles; ``python -m benchmarks.gating``) 4 sigma catches a few more
false plots (1-11 % lower RMS error with 1 % false plots in seed000, the same elsewhere) and
leaves no genuine plot out where the radar's sigmas are right; but declared sigmas half the true
ones (an operator's sigmas are seldom exact) made it leave out up to 33 genuine plots per 1,000
and cost up to 9.4 % RMS on clean plots, where 6 sigma left out at most 1.6 per 1,000 and cost
at most 1 %. Looking ahead keeps far genuine plots (turns) either way."""

MAX_SAMPLES = 100_000
"""Most regular samples one track keeps (its span / ``sample_step_s``): a track that would
have more keeps none, with a warning (:func:`solver.batch.solve_track`); the
default of the command line and of the service's ``max_samples`` setting. A tester's 2,511-plot,
44-min track with ``--samples 0.001`` (2.6 M samples) ended in a MemoryError while Dask pickled
its result, and ``--samples 0.01`` wrote 43 MB for it; at 0.0262 s (99,930 samples) 19 MB."""

MIN_TRIAL_STEP_S = 1 / 128
"""The finest spacing of the sliding windows' trial start points (s): the time stamps of a
recording are no finer (ASTERIX I140: 1/128 s), so no switch time lies between two closer
trial starts. A 1e-9-s step asked 2e10 trial starts of a 19-s window; a job took it and then
failed every track with the same error (a hostile-client tester's)."""


MAX_FILTER_GATE_SIGMA = 1e6
"""The widest gate accepted (sigmas): wider is no gate (None); 1.4e154 overflowed its square."""


def check_filter_gate(gate: float | None) -> None:
    """``ValueError`` unless ``gate`` is None (no gate) or a positive number of at most
    :data:`MAX_FILTER_GATE_SIGMA`."""
    if gate is not None and (isinstance(gate, bool) or not isinstance(gate, int | float)
                             or not 0 < gate <= MAX_FILTER_GATE_SIGMA):
        raise ValueError(f"gate must be a positive number of sigmas up to "
                         f"{MAX_FILTER_GATE_SIGMA:g}, or None (no gate), not {gate!r}")


@dataclass(frozen=True)
class RefineSettings:
    """Tuning of the full-track NLP (``solver.refine``); defaults chosen on the benchmark dev set
    (``python -m benchmarks.tune refine [--grid]``, table in ``benchmarks/results/tuning.md``:
    no other point of the sweeps is better on every radar profile).

    ``max_node_step_s``: longest interval between control nodes (gaps are subdivided; on the
    19-s-scan profile 5, 10 and 20 s gave the same accuracy, 20 s at a quarter of the nodes).
    ``switch_penalty_u`` / ``switch_penalty_w``: L1 weight per m/s^2 of control change, in criterion
    (chi-square) units (``w``: 5 -> 1.25 measured 1-2 % better on seed000 and ssr and 5 % with
    altitude, seed001 unchanged, on both dev seeds 100 and 101). ``level_penalty_u`` /
    ``level_penalty_w``: weight per (m/s^2 s) of ``|u|``, ``|w|`` (aircraft fly mostly straight at
    constant speed), smoothed over ``level_smoothing`` m/s^2 (``sqrt(u^2 + eps^2)``; a trade of
    accuracy for iterations, dev seeds 100-103, 7 tracks: 0.02 gave RMS 356.6 m against 358.5 m
    on seed000 for 80 % more iterations; 0.1 gave 360.8 / 319.2 / 73.21 / 49.28 m against
    358.5 / 317.5 / 73.10 / 49.11 m (seed000 / seed001 / ssr / ssr with altitude) for 19-22 %
    fewer; at 0.01-0.02 with both level weights 0.07-0.14 none beat the defaults by more than
    0.7 %, seed000's 356.1 m at 0.01 and 0.1, for 2.2 times the iterations).
    ``level_relief_u`` (m/s^2): at each node the ``|u|`` weight is divided by
    ``1 + (u0 / level_relief_u)^2``, ``u0`` the start's lateral acceleration there (adaptive
    weights from a pilot estimate, after Zou 2006: a constant weight flattens the turns it should
    only keep out of the straight legs); 0: a constant weight.
    Chosen on dev seeds 100 and 101 (7 tracks; 1, 1.5, 2 and 3 m/s^2, exponents 1 and 2 tried):
    RMS position seed000 370.9 -> 363.0 m, seed001 326.1 -> 317.0 m, ssr 74.8 -> 75.0 m, ssr with
    altitude 47.6 -> 47.9 m, the same iterations (2 m/s^2: 363.7 / 318.0 / 74.9 / 47.8 m; 3:
    365.4 / 320.0 / 74.9 / 47.8 m); halving ``level_penalty_u`` instead gave 367.4 / 321.6 /
    75.3 m. ``huber_delta``: pseudo-Huber
    threshold in sigmas (None: plain least squares); ``outlier_gate``: plots further than this many
    sigmas from the first solution get no weight in the second (None: keep all), as long as they
    are at most ``outlier_max_share`` of the plots and the speed does not sit at a bound (else
    they are not wild plots but a track that the bounds or the radar's sigmas do not fit: then
    none is rejected, and a warning says so).
    ``block_nodes`` / ``overlap_nodes``: block length and overlap for long tracks (the cut leaves
    half the overlap as look-ahead: 256 kept seams within 0.3 m of the one-block solution; short
    look-aheads cost accuracy: on a 63-plot pass, blocks of 16 nodes with overlap 8 end 17 m from
    the one-block solution, 32 with 16 6 m).
    ``init``: initial guess (it changes the iteration count, not the answer: see
    :func:`solver.refine.refine`).
    ``covariance_scale``: multiplies the prior variance of a control change in the Laplace
    covariance (``8 / lambda^2``): real tracks need wider ellipses than tracks that truly have
    piecewise-constant controls; 0.035 covers 97.8 % of those (the calibration test allows at most
    98 %) and 90.5 / 95.5 / 96.7 % of the real dev tracks (seed000 / seed001 / ssr with altitude, 95
    % ellipses). ``switch_threshold``: control changes above it (m/s^2) are kept as switches by the
    polish solve, the rest held at zero (0: no polish); ``polish_penalty_scale`` scales the L1
    weights in that solve. ``ipopt_tol``: IPOPT's convergence tolerance of the solves whose
    answer is the result (chi-square units; against 1e-6, 1e-5 moves the dev tracks by at most
    0.09 m with 5 % fewer iterations, 1e-4 by as much with 2 % fewer still: ``python -m
    benchmarks.refine_profile`` with the first solve at ``first_solve_tol``, 2026-11-26; before
    it, 1e-4 moved a dev track by 10.4 m and a block seam by 0.96 m). ``first_solve_tol``:
    IPOPT's tolerance of the first, cold-started solve when the polish solve follows it
    (``switch_threshold > 0``; never tighter than ``ipopt_tol``): that solve only chooses the
    switches, the wild plots and the sensors' weight scales, and the polish solve, warm-started,
    meets ``ipopt_tol``. 3e-4 against 1e-5: 10 / 10 / 10 % fewer iterations in all on dev seeds
    100-107 (seed000 / seed001 / ssr: 1311 -> 1181, 1267 -> 1138, 1183 -> 1067), RMS position
    unchanged (353.45 / 320.57 -> 320.54 / 72.95 m). Looser gives little more (1e-2: 12 %) and
    lands some blocked solves in another local solution (on the blocked seed-like track of
    tests/test_refine.py, 1.6 m from the one-block solution at 1e-3, 205 m in a 6 m/s^2 turn at
    1e-2; 0.5 m at 3e-4); looser complementarity or constraint tolerances cost the polish solve
    more iterations than they save. Nor does a smoother level penalty in the first solve alone
    (``level_smoothing`` 0.1 / 0.2 there, 0.05 in the polish; dev seeds 100-107): the first solves
    take 15-33 % fewer iterations but the polish solves 1.8-4.2x more, in all -1 / +6 / +15 %
    (0.1) and +19 / +25 / +36 % (0.2), the same RMS to 0.07 m.
    """

    max_node_step_s: float = 20.0
    switch_penalty_u: float = 1.0
    switch_penalty_w: float = 1.25
    level_penalty_u: float = 0.1
    level_penalty_w: float = 0.1
    level_smoothing: float = 0.05
    level_relief_u: float = 1.5
    huber_delta: float | None = 3.0
    outlier_gate: float | None = 5.0
    outlier_max_share: float = 0.2
    block_nodes: int = 2048
    overlap_nodes: int = 1024
    init: Literal["sliding", "smoother"] = "smoother"
    covariance_scale: float = 0.035
    switch_threshold: float = 0.01
    polish_penalty_scale: float = 1.0
    ipopt_tol: float = 1e-5
    first_solve_tol: float = 3e-4

    def validate(self) -> None:
        """Raise :class:`InputError` (located under ``refine``) for values the NLP cannot use:
        the Laplace covariance divides by the switch penalties, the level term needs a positive
        smoothing to stay differentiable, and a block is cut half its overlap before its end, which
        must lie inside it."""
        positive = ("max_node_step_s", "switch_penalty_u", "switch_penalty_w", "level_smoothing",
                    "covariance_scale", "ipopt_tol", "first_solve_tol")
        for name in positive:
            if not getattr(self, name) > 0:  # also rejects NaN
                raise InputError(("refine", name), "must be positive")
        for name in ("level_penalty_u", "level_penalty_w", "level_relief_u", "switch_threshold",
                     "polish_penalty_scale"):
            if not getattr(self, name) >= 0:
                raise InputError(("refine", name), "must be zero or positive")
        for name in ("huber_delta", "outlier_gate"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise InputError(("refine", name), "must be positive or None")
        if not 0 <= self.outlier_max_share <= 1:
            raise InputError(("refine", "outlier_max_share"), "must be between 0 and 1")
        if not MIN_BLOCK_NODES <= self.block_nodes <= MAX_BLOCK_NODES:
            raise InputError(("refine", "block_nodes"),
                             f"must be between {MIN_BLOCK_NODES} and {MAX_BLOCK_NODES}")
        if not 2 <= self.overlap_nodes < 2 * self.block_nodes:
            raise InputError(("refine", "overlap_nodes"),
                             "must be at least 2 and less than 2 * block_nodes")
        if self.init not in ("sliding", "smoother"):
            raise InputError(("refine", "init"), "must be sliding or smoother")


@dataclass(frozen=True)
class ReconstructionConfig:
    """How to reconstruct.

    ``window_plots`` (m) plots per window (the seed used 3-5; 3 was best on hard manoeuvres);
    ``trial_step_s``: spacing of the extra trial start points between plots; ``criterion``: R1
    (least squares) or R2 (ellipse-shaped, default); ``sample_step_s``: spacing of the regular
    samples; ``method``: ``refined`` (the full-track NLP, :mod:`solver.refine`) or
    ``sliding`` (the seed's method alone); ``nlp_solver``: the window NLP's CasADi plugin.
    """

    bounds: Bounds = field(default_factory=Bounds)
    window_plots: int = 3
    trial_step_s: float = 5.0
    criterion: Criterion = "R2"
    sample_step_s: float = 1.0
    method: Method = "refined"
    nlp_solver: NlpSolver = "sqpmethod"
    refine: RefineSettings = field(default_factory=RefineSettings)

    def validate(self) -> None:
        """Raise :class:`InputError` for values no reconstruction can use."""
        self.bounds.validate()
        if self.window_plots < 2:
            raise InputError(("window", "plots"), "must be at least 2")
        if not self.trial_step_s > 0:
            raise InputError(("window", "trial_step_s"), "must be positive")
        if not self.trial_step_s >= MIN_TRIAL_STEP_S:
            raise InputError(("window", "trial_step_s"), f"must be at least {MIN_TRIAL_STEP_S:g} "
                             "s (the time stamps' resolution; trial starts closer than that "
                             "tell no switch time apart)")
        if not 0 < self.sample_step_s < float("inf"):
            raise InputError(("sample_step_s",), "must be positive and finite")
        if self.criterion not in ("R1", "R2"):
            raise InputError(("criterion",), "must be R1 or R2")
        self.refine.validate()
