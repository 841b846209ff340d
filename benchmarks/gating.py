"""Wild plots and the filters' validation gate (``solver.estimation.gating``).

Each run's plots are simulated as in the report (``simulate``), then a share of them (``--wild``,
default 1 %) is replaced by false plots drawn uniformly within +-20 km in range and +-5 deg in
azimuth of the true plot (a reflection, a garbled range, a false plot: what a recording has).
Every gating filter runs on the clean and the wild plots with the gate at each value of
``--gates`` (sigmas; ``none``: no gate), and the reconstruction (its own gate) beside them. RMS
horizontal position error at the genuine plots, pooled over tracks and seeds; the plots a
filter left out, false (genuine plots left out, per 1,000) and caught (false plots left out).
Tune on the dev seeds (100, 101: ``--first-seed 100``), check on held-out ones (0, 1).

    python -m benchmarks.gating --first-seed 100 --seeds 2 --out ''
    python -m benchmarks.gating --seeds 2
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from solver import Plots
from solver.estimation import run_filter
from solver.estimation.gating import GATE_SIGMA
from solver.reconstruct import reconstruct

from .profiles import PROFILES
from .run import environment, publish
from .simulate import SimulatedTrack, simulate
from .truth import SYNTHETIC, load_truth, truth_names

FILTERS = ("imm_smoother", "cv_rts", "imm", "singer", "quasi_optimal", "fuzzy")
RANGE_M, AZIMUTH_DEG = 20_000.0, 5.0


def with_wild_plots(sim: SimulatedTrack, share: float, rng: np.random.Generator
                    ) -> tuple[Plots, np.ndarray]:
    """``sim``'s plots with ``share`` of them (never the first two) replaced by false plots
    (module docstring); returns the plots and the mask of the false ones."""
    p = sim.plots
    n = p.t.size
    wild = rng.uniform(size=n) < share
    wild[:2] = False
    r, az = p.range_m.copy(), p.azimuth_rad.copy()
    k = int(wild.sum())
    r[wild] = np.maximum(r[wild] + rng.uniform(-RANGE_M, RANGE_M, k), 1_000.0)
    az[wild] += np.radians(rng.uniform(-AZIMUTH_DEG, AZIMUTH_DEG, k))
    alt = None if p.altitude_m is None else np.minimum(p.altitude_m, 0.99 * r)
    return Plots.from_arrays(p.t, r, az, alt), wild


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--wild", type=float, default=0.01, help="share of false plots")
    ap.add_argument("--gates", default=f"none,4,5,{GATE_SIGMA:g},8,10",
                    help="comma-separated gates in sigmas; 'none' for no gate")
    ap.add_argument("--profiles", default="seed000,seed001,ssr")
    ap.add_argument("--no-reconstruction", action="store_true")
    ap.add_argument("--declared-sigma-scale", type=float, default=1.0,
                    help="the radar's declared sigmas are the true ones times this (an "
                    "operator's sigmas are seldom exact)")
    ap.add_argument("--out", default="gating.md", help="results name ('' to only print)")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    gates: list[float | None] = [None if g == "none" else float(g) for g in args.gates.split(",")]
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    rows = []
    for prof in args.profiles.split(","):
        profile = PROFILES[prof]
        radar = replace(profile.radar(),
                        range_sigma_m=profile.sigma_r * args.declared_sigma_scale,
                        azimuth_sigma_rad=profile.sigma_psi * args.declared_sigma_scale)
        err: dict[tuple, list[np.ndarray]] = {}
        false_gated: dict[tuple, int] = {}
        caught: dict[tuple, int] = {}
        n_genuine = n_wild = 0
        for k, name in enumerate(truth_names()):
            for seed in seeds:
                sim = simulate(load_truth(name), profile, seed, drop_in_turns=name == SYNTHETIC)
                rng = np.random.default_rng([seed, k, 104729])
                wild_plots, wild = with_wild_plots(sim, args.wild, rng)
                n_genuine += int((~wild).sum())
                n_wild += int(wild.sum())
                for case, plots, mask in (("clean", sim.plots, np.zeros_like(wild)),
                                          ("wild", wild_plots, wild)):
                    runs = [(f, g) for f in FILTERS for g in gates]
                    if not args.no_reconstruction:
                        runs.append(("reconstruction", None))
                    for f, g in runs:
                        if f == "reconstruction":
                            states, left_out = reconstruct(plots, radar).at_plots, None
                        else:
                            est = run_filter(f, plots, radar, gate=g)
                            states, left_out = est.states, est.info["gated"]
                        e = np.hypot(states.x - sim.truth.x, states.z - sim.truth.z)[~wild]
                        err.setdefault((f, g, case), []).append(e)
                        if left_out is not None:
                            false_gated[f, g, case] = false_gated.get((f, g, case), 0) + int(
                                (left_out & ~mask).sum())
                            caught[f, g, case] = caught.get((f, g, case), 0) + int(
                                (left_out & mask).sum())
        for (f, g, case), es in err.items():
            e = np.concatenate(es)
            rows.append((prof, f, g, case, float(np.sqrt(np.mean(e**2))),
                         false_gated.get((f, g, case)), caught.get((f, g, case)),
                         n_genuine, n_wild))
        print(f"{prof} done ({time.perf_counter() - start:.0f} s)", flush=True)
    env = environment()
    md = ["# Wild plots and the filters' validation gate", "",
          f"`python -m benchmarks.gating --first-seed {args.first_seed} --seeds {args.seeds} "
          f"--wild {args.wild:g} --gates {args.gates} --declared-sigma-scale "
          f"{args.declared_sigma_scale:g}` at commit `{env['commit']}`, "
          f"{env['date_utc']}, {time.perf_counter() - start:.0f} s. Seeds "
          f"{seeds.start}-{seeds.stop - 1}, the {len(truth_names())} benchmark tracks; "
          f"'wild': {args.wild:.0%} of the plots replaced by false plots within "
          f"+-{RANGE_M / 1e3:.0f} km and +-{AZIMUTH_DEG:g} deg of the true plot. RMS horizontal "
          "position error (m) at the genuine plots; genuine plots left out per 1,000; false "
          "plots left out of all false plots.", ""]
    for prof in args.profiles.split(","):
        sel = [r for r in rows if r[0] == prof]
        md += [f"## {prof}", "", "| estimator | gate (sigma) | RMS clean | RMS wild | genuine "
               "left out per 1,000, clean / wild | false plots left out |",
               "|---|---:|---:|---:|---:|---:|"]
        keys = sorted({(r[1], r[2]) for r in sel},
                      key=lambda fg: (([*FILTERS, "reconstruction"]).index(fg[0]),
                                      -1.0 if fg[1] is None else fg[1]))
        for f, g in keys:
            c = next(r for r in sel if r[1:4] == (f, g, "clean"))
            w = next(r for r in sel if r[1:4] == (f, g, "wild"))
            gate = "own" if f == "reconstruction" else ("none" if g is None else f"{g:g}")
            fg = "-" if c[5] is None else f"{1000 * c[5] / c[7]:.2f} / {1000 * w[5] / w[7]:.2f}"
            caught = "-" if w[6] is None else f"{w[6]} / {w[8]}"
            md.append(f"| {f} | {gate} | {c[4]:.1f} | {w[4]:.1f} | {fg} | {caught} |")
        md.append("")
    publish(args.out, md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
