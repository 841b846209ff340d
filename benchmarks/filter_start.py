"""The filters' judged start (``solver.estimation._from_a_sound_start``): a wild first plot.

A gating filter starts from its first two plots, which its gate cannot judge; the first two
are judged by the causal IMM run backwards over the first ten. Per profile, on the benchmark
tracks' simulated plots (as the report's), each gating filter runs with the judged start
(``run_filter``) and without it (the filter's runner on the plots as they are), on the clean
plots and with the first plot made wild (8 km long and 2 deg off). Reported: RMS horizontal
position error at the genuine plots (the wild one left out of the RMS), and how many runs had
one of their first two plots left out (clean: false alarms; wild: caught). Then starts in a
turn (constant turn from the first plot, 220 m/s) at each profile's scan period: how many runs
had a first plot left out (false alarms).

    python -m benchmarks.filter_start --first-seed 100 --seeds 4   # dev seeds
    python -m benchmarks.filter_start --seeds 4                     # held-out seeds
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from solver import Plots
from solver.estimation import _RUNNERS, GATING_NAMES, START_PLOTS, measurement_set, run_filter

from .profiles import PROFILES
from .run import environment, publish
from .simulate import simulate
from .truth import SYNTHETIC, load_truth, truth_names

WILD_RANGE_M, WILD_AZIMUTH_DEG = 8_000.0, 2.0
TURNS_M_S2 = (5.0, 11.5, 25.0)
TURN_RUNS = 20


def _rms(states, x, z) -> float:
    return float(np.sqrt(np.mean((states.x - x) ** 2 + (states.z - z) ** 2)))


def _wild_first(plots: Plots) -> Plots:
    r, a = plots.range_m.copy(), plots.azimuth_rad.copy()
    r[0] += WILD_RANGE_M
    a[0] -= np.radians(WILD_AZIMUTH_DEG)
    return Plots.from_arrays(plots.t, r, a, plots.altitude_m)


def _turning(period: float, acc: float, sigma_r: float, sigma_psi: float,
             rng: np.random.Generator) -> Plots:
    """30 plots of a constant turn at ``acc`` from the first plot on (220 m/s, 60 km out)."""
    t = np.arange(30) * period
    v = 220.0
    w = acc / v
    x = 60_000.0 + v / w * np.sin(w * t)
    z = 20_000.0 + v / w * (1 - np.cos(w * t))
    return Plots.from_arrays(t, np.hypot(x, z) + rng.normal(0, sigma_r, t.size),
                             np.arctan2(z, x) + rng.normal(0, sigma_psi, t.size))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--profiles", default="seed000,seed001,ssr")
    ap.add_argument("--out", default="filter_start.md", help="results name ('' to only print)")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    md = ["# The filters' judged start: a wild first plot", "",
          f"`python -m benchmarks.filter_start --first-seed {args.first_seed} --seeds "
          f"{args.seeds}` at commit `{environment()['commit']}`, "
          f"{environment()['date_utc']}. Seeds {seeds.start}-{seeds.stop - 1}, the "
          f"{len(truth_names())} benchmark tracks; wild: the first plot "
          f"{WILD_RANGE_M / 1e3:g} km long and {WILD_AZIMUTH_DEG:g} deg off. RMS horizontal "
          "position error (m) at the genuine plots; runs with one of the first "
          f"{START_PLOTS} plots left out, of all runs.", ""]
    for prof in args.profiles.split(","):
        profile = PROFILES[prof]
        radar = profile.radar()
        err: dict[tuple[str, str, str], list[float]] = {}
        out: dict[tuple[str, str, str], int] = {}
        runs = 0
        for name in truth_names():
            for seed in seeds:
                sim = simulate(load_truth(name), profile, seed, drop_in_turns=name == SYNTHETIC)
                x, z = sim.truth.x, sim.truth.z
                runs += 1
                for case, plots in (("clean", sim.plots), ("wild", _wild_first(sim.plots))):
                    sl = slice(1, None) if case == "wild" else slice(None)
                    for f in GATING_NAMES:
                        judged = run_filter(f, plots, radar)
                        plain = _RUNNERS[f](measurement_set(plots, radar))
                        for how, est in (("judged", judged), ("plain", plain)):
                            st = est.states
                            e = np.hypot(st.x[sl] - x[sl], st.z[sl] - z[sl])
                            err.setdefault((f, case, how), []).append(e)
                            out[f, case, how] = out.get((f, case, how), 0) + int(
                                np.asarray(est.info["gated"])[:START_PLOTS].any())
        md += [f"## {prof}", "", "| filter | RMS clean, judged / plain | RMS wild first plot, "
               "judged / plain | start plot left out, clean (false) | start plot left out, "
               "wild (caught) |", "|---|---:|---:|---:|---:|"]
        for f in GATING_NAMES:
            rms = {k: float(np.sqrt(np.mean(np.concatenate(err[(f, *k)]) ** 2)))
                   for k in (("clean", "judged"), ("clean", "plain"), ("wild", "judged"),
                             ("wild", "plain"))}
            md.append(f"| {f} | {rms['clean', 'judged']:.1f} / {rms['clean', 'plain']:.1f} | "
                      f"{rms['wild', 'judged']:.1f} / {rms['wild', 'plain']:.1f} | "
                      f"{out[f, 'clean', 'judged']} of {runs} | "
                      f"{out[f, 'wild', 'judged']} of {runs} |")
        rng = np.random.default_rng([seeds.start, 7])
        md += ["", f"Turning starts ({TURN_RUNS} runs each, scan {profile.scan_s:g} s): runs "
               "with a start plot left out (false alarms), per filter:", "",
               "| turn (m/s^2) | " + " | ".join(GATING_NAMES) + " |",
               "|---:|" + "---:|" * len(GATING_NAMES)]
        for acc in TURNS_M_S2:
            alarms = dict.fromkeys(GATING_NAMES, 0)
            for _ in range(TURN_RUNS):
                plots = _turning(profile.scan_s, acc, profile.sigma_r, profile.sigma_psi, rng)
                for f in GATING_NAMES:
                    alarms[f] += int(np.asarray(run_filter(f, plots, radar).info["gated"])
                                     [:START_PLOTS].any())
            md.append(f"| {acc:g} | " + " | ".join(str(alarms[f]) for f in GATING_NAMES)
                      + " |")
        md.append("")
        print(f"{prof} done ({time.perf_counter() - start:.0f} s)", flush=True)
    md[2] += f" {time.perf_counter() - start:.0f} s."
    publish(args.out, md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
