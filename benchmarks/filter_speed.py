"""How fast each recursive filter runs, in plots per CPU-second of this process.

    python -m benchmarks.filter_speed                         # 3 profiles, dev seed 100 (~1 min)
    python -m benchmarks.filter_speed --filters imm_smoother --reps 7 --out ''   # print only

For every dev track (the six ADS-B tracks and the seed-like one) and profile, each filter runs
once untimed (imports, compiled functions built or loaded), then ``--reps`` times; a track's
time is its least CPU time (``time.process_time``, all threads), so bursts of other work on a
shared machine drop out. Pooled: all plots over the sum of those times. Writes
``benchmarks/results/<--out>`` (default ``filter_speed.md``).
"""

from __future__ import annotations

import argparse
import subprocess
import time
from functools import partial

from solver.estimation import SINGLE_SENSOR_NAMES, run_filter

from .profiles import PROFILES
from .run import publish
from .simulate import simulate
from .truth import SYNTHETIC, load_truth, truth_names


def least_cpu(fn, reps: int) -> float:
    """The least CPU seconds of ``reps`` calls of ``fn``."""
    best = float("inf")
    for _ in range(reps):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=100, help="noise seed (default: dev seed 100)")
    ap.add_argument("--profiles", nargs="+", default=["seed000", "seed001", "ssr"],
                    choices=sorted(PROFILES))
    ap.add_argument("--filters", nargs="+", default=list(SINGLE_SENSOR_NAMES),
                    choices=list(SINGLE_SENSOR_NAMES))
    ap.add_argument("--reps", type=int, default=5, help="timed calls per track (least counts)")
    ap.add_argument("--out", default="filter_speed.md", help="results file ('' to only print)")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    rate: dict[tuple[str, str], float] = {}
    for profile in args.profiles:
        p = PROFILES[profile]
        sims = [simulate(load_truth(n), p, args.seed, drop_in_turns=(n == SYNTHETIC))
                for n in truth_names()]
        plots = sum(len(s.plots.t) for s in sims)
        for name in args.filters:
            total = 0.0
            for s in sims:
                run_filter(name, s.plots, p.radar())  # untimed: builds what it needs
                total += least_cpu(partial(run_filter, name, s.plots, p.radar()), args.reps)
            rate[profile, name] = plots / total
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip() or "unknown"
    md = ["# Recursive filters: plots per CPU-second", "",
          f"`python -m benchmarks.filter_speed --seed {args.seed} --reps {args.reps}` at "
          f"commit `{commit}`, {time.perf_counter() - start:.0f} s: the {len(truth_names())} "
          "dev tracks per profile, each filter's least CPU time of the repetitions per track, "
          "pooled (all plots over the sum of those times). A shared machine: compare within "
          "one run.", "",
          "| filter | " + " | ".join(args.profiles) + " |",
          "|---|" + "---:|" * len(args.profiles)]
    md += [f"| {name} | " + " | ".join(f"{rate[pr, name]:,.0f}" for pr in args.profiles) + " |"
           for name in args.filters]
    publish(args.out, md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
