"""How far can the refinement's penalty weights take its accuracy? (issue 6, accuracy targets)

    python -m benchmarks.penalty_oracle                 # dev seeds 100 and 101 (~2 min)
    python -m benchmarks.penalty_oracle --seeds 100 --scales 0.5 0.7 1 1.4 2

Every dev track is refined with all four penalties (switch and level, ``u`` and ``w``) scaled
together by each factor of ``--scales``. Pooled RMS position error (m) at the plots, against the
truth, for: the default weights; the best single scale per profile (what a per-radar setting
could give); the best scale per track, chosen with the truth (an oracle no selection rule can
beat, e.g. an evidence or cross-validation choice of the weights per track); and the mean of the
tracks refined at 0.7, 1 and 1.4 (averaging neighbouring solutions); beside them issue 6's
target on the same runs (0.75 times the Stone Soup CV smoother's error; 45 m with altitude).
Writes benchmarks/results/penalty_oracle.md.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from tqdm import tqdm

from solver.config import ReconstructionConfig, RefineSettings
from solver.reconstruct import reconstruct

from .estimators import registry
from .profiles import PROFILES
from .run import publish
from .simulate import simulate
from .truth import SYNTHETIC, load_truth, truth_names

PROFILE_NAMES = ("seed000", "seed001", "ssr", "ssr+alt")
ENSEMBLE = (0.7, 1.0, 1.4)
ALT_TARGET = 45.0  # m, issue 6's bound for the ssr profile with altitude


def scaled(scale: float) -> RefineSettings:
    """The default settings with the four penalty weights multiplied by ``scale``."""
    d = RefineSettings()
    return replace(d, switch_penalty_u=d.switch_penalty_u * scale,
                   switch_penalty_w=d.switch_penalty_w * scale,
                   level_penalty_u=d.level_penalty_u * scale,
                   level_penalty_w=d.level_penalty_w * scale)


def squared_errors(profile: str, names: list[str], seeds: list[int], scales: list[float],
                   progress: bool = True, t_max: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per run (track, seed): summed squared position errors at each scale ``(runs, scales)``,
    of the ensemble mean and of the Stone Soup CV smoother ``(runs,)``, and the plot counts
    (``t_max``: the first that many seconds of each track). ``scales`` must hold ``ENSEMBLE``."""
    if not set(ENSEMBLE) <= set(scales):
        raise ValueError(f"the scales must include {ENSEMBLE} (the ensemble's)")
    base, alt = profile.removesuffix("+alt"), profile.endswith("+alt")
    radar = PROFILES[base].radar()
    smoother = registry()["ss-cv-rts+alt" if alt else "ss-cv-rts"]
    jobs = [(n, s) for n in names for s in seeds]
    sse = np.zeros((len(jobs), len(scales)))
    sse_mean = np.zeros(len(jobs))
    sse_ss = np.zeros(len(jobs))
    plots = np.zeros(len(jobs))
    for i, (name, seed) in enumerate(tqdm(jobs, desc=profile, unit="run", disable=not progress)):
        sim = simulate(load_truth(name), PROFILES[base], seed, with_altitude=alt, t_max=t_max)
        truth = np.column_stack([sim.truth.x, sim.truth.z])
        pos = {}
        for j, sc in enumerate(scales):
            at = reconstruct(sim.plots, radar, ReconstructionConfig(refine=scaled(sc))).at_plots
            pos[sc] = np.column_stack([at.x, at.z])
            sse[i, j] = np.sum((pos[sc] - truth) ** 2)
        mean = sum(pos[sc] for sc in ENSEMBLE) / len(ENSEMBLE)
        sse_mean[i] = np.sum((mean - truth) ** 2)
        ss = smoother.run(sim.plots, radar, base).states
        sse_ss[i] = np.sum((np.column_stack([ss.x, ss.z]) - truth) ** 2)
        plots[i] = sim.plots.t.size
    return sse, sse_mean, sse_ss, plots


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[100, 101],
                    help="noise seeds (default: the dev seeds 100 and 101)")
    ap.add_argument("--scales", type=float, nargs="+",
                    default=[0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8],
                    help="penalty scale factors (must include 0.7, 1 and 1.4)")
    ap.add_argument("--profiles", nargs="+", default=list(PROFILE_NAMES), choices=PROFILE_NAMES)
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if not set(ENSEMBLE) <= set(args.scales):
        ap.error(f"--scales must include {' '.join(map(str, ENSEMBLE))} (the ensemble's)")
    names = [n for n in truth_names() if n != SYNTHETIC]
    t0 = time.perf_counter()
    rows = []
    for profile in args.profiles:
        sse, sse_mean, sse_ss, plots = squared_errors(profile, names, args.seeds, args.scales,
                                                      not args.no_progress)
        n = plots.sum()
        per_scale = np.sqrt(sse.sum(axis=0) / n)
        best = int(np.argmin(per_scale))
        chosen = [args.scales[k] for k in np.argmin(sse, axis=1)]
        target = ALT_TARGET if profile.endswith("+alt") else 0.75 * np.sqrt(sse_ss.sum() / n)
        rows.append(
            f"| {profile} | {target:.1f} | {per_scale[args.scales.index(1.0)]:.1f} "
            f"| {per_scale[best]:.1f} (x{args.scales[best]:g}) "
            f"| {np.sqrt(sse.min(axis=1).sum() / n):.1f} | {np.sqrt(sse_mean.sum() / n):.1f} "
            f"| {', '.join(f'{c:g}' for c in chosen)} |")
    md = [
        "# How far the penalty weights can take the refinement", "",
        f"`python -m benchmarks.penalty_oracle --seeds {' '.join(map(str, args.seeds))}` "
        f"({time.perf_counter() - t0:.0f} s): the six dev tracks refined with the four penalty "
        f"weights scaled together by {', '.join(f'{s:g}' for s in args.scales)}. Pooled RMS "
        "position error (m) at the plots. Per-track oracle: the best scale of each track, "
        "chosen with the truth (no rule choosing the weights per track can do better); "
        f"ensemble: the mean position of the solutions at scales "
        f"{', '.join(f'{s:g}' for s in ENSEMBLE)}. Issue 6's target: 0.75 times the Stone Soup "
        "CV smoother's error on the same runs (with altitude: 45 m).", "",
        "| profile | issue 6 target | default | best scale per profile "
        "| per-track oracle | ensemble | oracle's scale per run (tracks x seeds) |",
        "|---|---:|---:|---:|---:|---:|---|",
        *rows,
    ]
    publish("penalty_oracle.md", md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
