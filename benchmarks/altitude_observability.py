"""Can the refinement estimate an unknown altitude from 2-D plots? (issue 6, ssr target)

    python -m benchmarks.altitude_observability            # ssr profile, seed 0 (~2 min)
    python -m benchmarks.altitude_observability --seed 1

Without Mode C the ground range ``sqrt(r^2 - h^2)`` is unknown; taking the slant range puts the
track ``h^2 / 2r`` too far out (up to ~100 m RMS on two dev tracks of the ssr profile). If the
altitude were observable, the fit criterion would prefer the true altitude. For every dev track
this hands the refinement the same plots with a hypothesised constant altitude ``h`` from a grid
and reports the final criterion (chi-square units: the objective's data term) and the RMS
position error against the truth. A criterion flat to a fraction of one unit while the error
doubles means the data cannot tell the altitudes apart: the track bends to fit any of them.
Writes benchmarks/results/altitude_observability.md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from tqdm import tqdm

from solver.config import ReconstructionConfig
from solver.inputs import Plots
from solver.reconstruct import reconstruct

from .profiles import PROFILES
from .run import publish
from .simulate import simulate
from .truth import SYNTHETIC, load_truth, truth_names

ALTITUDES_M = (0.0, 1000.0, 2000.0, 3000.0, 4000.0, 6000.0, 8000.0)


def scan(name: str, seed: int, altitudes: tuple[float, ...]) -> dict:
    """Criterion and RMS error of the refinement for each hypothesised constant altitude."""
    sim = simulate(load_truth(name), PROFILES["ssr"], seed, with_altitude=True)
    radar = PROFILES["ssr"].radar()
    crit, rms = [], []
    for h in altitudes:
        plots = Plots.from_arrays(sim.plots.t, sim.plots.range_m, sim.plots.azimuth_rad,
                                  np.full(len(sim.plots.t), h))
        rec = reconstruct(plots, radar, ReconstructionConfig())
        err = np.hypot(rec.at_plots.x - sim.truth.x, rec.at_plots.z - sim.truth.z)
        crit.append(rec.diagnostics.criterion_values[0])
        rms.append(float(np.sqrt(np.mean(err**2))))
    alt = sim.altitude
    return {"name": name, "plots": len(sim.plots.t), "h_mean": float(alt.mean()),
            "h_min": float(alt.min()), "h_max": float(alt.max()), "crit": crit, "rms": rms}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    names = [n for n in truth_names() if n != SYNTHETIC]
    t0 = time.perf_counter()
    rows = [scan(n, args.seed, ALTITUDES_M) for n in tqdm(names, desc="tracks")]
    head = " | ".join(f"{h / 1000:g} km" for h in ALTITUDES_M)
    md = [
        "# Is a constant unknown altitude observable from 2-D plots?", "",
        f"`python -m benchmarks.altitude_observability --seed {args.seed}` "
        f"({time.perf_counter() - t0:.0f} s): ssr profile, refinement given the plots with a "
        "hypothesised constant altitude. Criterion: chi-square of the fit minus its value at "
        "the hypothesis with the lowest one (a difference below ~1 cannot select an altitude); "
        "RMS: horizontal position error (m) against the truth.", "",
        f"| track | plots | true altitude (m) | | {head} |",
        "|---|---:|---|---|" + "---:|" * len(ALTITUDES_M),
    ]
    for r in rows:
        c = np.array(r["crit"])
        true_h = f"{r['h_mean']:.0f} ({r['h_min']:.0f}-{r['h_max']:.0f})"
        short = r["name"].split("__")[-1]
        md.append(f"| {short} | {r['plots']} | {true_h} | criterion | "
                  + " | ".join(f"{v:+.2f}" for v in c - c.min()) + " |")
        md.append("| | | | RMS (m) | " + " | ".join(f"{v:.0f}" for v in r["rms"]) + " |")
    publish("altitude_observability.md", md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
