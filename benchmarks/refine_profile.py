"""Where a refinement's time goes, and what IPOPT's tolerance buys (issue 6, speed target).

    python -m benchmarks.refine_profile                     # 3 profiles, seed 100 (~3 min)
    python -m benchmarks.refine_profile --tols 1e-6 1e-5 --profiles ssr

For every dev track and profile, the refinement runs once per tolerance (after an untimed call
that builds that tolerance's solvers) and reports IPOPT's iterations and how far the positions
at the plots move against the first tolerance; for the default tolerance, the time split
into IPOPT's own work, the model evaluations it asks for (CasADi functions: dynamics, their
derivatives, the criterion), and everything outside IPOPT (constant-velocity start, covariance,
sampling). Writes benchmarks/results/refine_profile.md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from tqdm import tqdm

from solver import compiled
from solver.config import ReconstructionConfig, RefineSettings
from solver.reconstruct import reconstruct

from .profiles import PROFILES
from .run import publish
from .simulate import simulate
from .truth import SYNTHETIC, load_truth, truth_names

DEFAULT_TOL = RefineSettings.ipopt_tol


def profile_track(name: str, profile: str, seed: int, tols: list[float]) -> dict:
    sim = simulate(load_truth(name), PROFILES[profile], seed)
    radar = PROFILES[profile].radar()
    out: dict = {"name": name, "profile": profile, "plots": len(sim.plots.t), "runs": []}
    ref = None
    for tol in tols:
        cfg = ReconstructionConfig(refine=RefineSettings(ipopt_tol=tol))
        reconstruct(sim.plots, radar, cfg)  # builds this tolerance's solvers
        t0 = time.perf_counter()
        rec = reconstruct(sim.plots, radar, cfg)
        wall = time.perf_counter() - t0
        pos = np.column_stack([rec.at_plots.x, rec.at_plots.z])
        ref = pos if ref is None else ref
        moved = np.hypot(*(pos - ref).T)
        ex = rec.diagnostics.extra
        out["runs"].append({
            "tol": tol, "iterations": int(ex["refine_iterations"]), "wall_s": wall,
            "ipopt_s": ex["refine_ipopt_ms"] / 1e3, "model_s": ex["refine_model_ms"] / 1e3,
            "moved_max": float(moved.max()), "moved_p95": float(np.percentile(moved, 95))})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=100, help="noise seed (default: dev seed 100)")
    ap.add_argument("--profiles", nargs="+", default=["seed000", "seed001", "ssr"],
                    choices=sorted(PROFILES))
    ap.add_argument("--tols", nargs="+", type=float, default=[1e-6, DEFAULT_TOL, 1e-4],
                    help="IPOPT tolerances; positions are compared with the first")
    args = ap.parse_args(argv)
    if DEFAULT_TOL not in args.tols:
        args.tols.append(DEFAULT_TOL)
    names = [n for n in truth_names() if n != SYNTHETIC]
    jobs = [(n, p) for p in args.profiles for n in names]
    t0 = time.perf_counter()
    rows = [profile_track(n, p, args.seed, args.tols)
            for n, p in tqdm(jobs, desc="tracks", unit="track")]
    tol_head = " | ".join(f"{t:g}" for t in args.tols)
    md = [
        "# Refinement: time split and IPOPT tolerance", "",
        f"`python -m benchmarks.refine_profile --seed {args.seed} --profiles "
        f"{' '.join(args.profiles)} --tols {' '.join(f'{t:g}' for t in args.tols)}` "
        f"({time.perf_counter() - t0:.0f} s, motion model "
        f"{'compiled' if compiled.is_compiled('motion') else 'interpreted'}). "
        "Time of one reconstruction (`time.perf_counter`; one thread) at the default tolerance "
        f"{DEFAULT_TOL:g}, split into IPOPT's own work, the model evaluations IPOPT asks for, "
        "and the rest of the pipeline; iterations (both solves) and the largest and 95th-"
        f"percentile move of the positions at the plots against tolerance {args.tols[0]:g}.", "",
        "## Time split (default tolerance)", "",
        "| profile | track | plots | time (s) | IPOPT own | model evaluations | outside IPOPT |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    totals = np.zeros(4)
    for r in rows:
        run = next(x for x in r["runs"] if x["tol"] == DEFAULT_TOL)
        own, model = run["ipopt_s"] - run["model_s"], run["model_s"]
        rest = run["wall_s"] - run["ipopt_s"]
        totals += (run["wall_s"], own, model, rest)
        md.append(f"| {r['profile']} | {r['name'].split('__')[-1]} | {r['plots']} | "
                  f"{run['wall_s']:.3f} | {own / run['wall_s']:.0%} | "
                  f"{model / run['wall_s']:.0%} | {rest / run['wall_s']:.0%} |")
    md.append(f"| all | | | {totals[0]:.2f} | {totals[1] / totals[0]:.0%} | "
              f"{totals[2] / totals[0]:.0%} | {totals[3] / totals[0]:.0%} |")
    md += ["", "## Tolerance", "",
           f"| profile | track | iterations at {tol_head} | max / p95 move (m) at {tol_head} |",
           "|---|---|---|---|"]
    its = np.zeros(len(args.tols))
    for r in rows:
        its += [x["iterations"] for x in r["runs"]]
        md.append(f"| {r['profile']} | {r['name'].split('__')[-1]} | "
                  + " / ".join(str(x["iterations"]) for x in r["runs"]) + " | "
                  + " ; ".join(f"{x['moved_max']:.2f} / {x['moved_p95']:.2f}" for x in r["runs"])
                  + " |")
    worst = [max(r["runs"][i]["moved_max"] for r in rows) for i in range(len(args.tols))]
    md.append("| all | | " + " / ".join(f"{v:.0f}" for v in its) + " | "
              + " ; ".join(f"{v:.2f} max" for v in worst) + " |")
    publish("refine_profile.md", md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
