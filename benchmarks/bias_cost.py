"""The cost of estimating many radars' offsets (``estimate_bias``) against the same track
without it.

A tester's request of 16 radars with ``estimate_bias`` and 2,000 plots held a service worker
for its 300-s limit. Here: the ADS-B truth ``calibration__ajaccio`` placed on the earth
(:func:`benchmarks.earth.place`), ``N`` SSRs (4.8 s, 50 m, 0.08 deg, Pd 0.97, Mode C) on a ring
70-130 km about the track's centroid (bearing ``360 k / N``, heights 300 + 50 k m), each with
a range offset of 50-200 m and an azimuth offset of 0.1-0.3 deg (random signs), the track cut
so that the radars make about ``--plots`` plots in all. Each case is reconstructed twice, the
radars' offsets estimated or not, in this process, one after the other; the first solve of a
number of radars builds its solvers (as a service worker's first such request does): CPU
seconds (``time.process_time``) with that build, and again without (a second run).

    python -m benchmarks.bias_cost                      # 2, 4, 8, 16 radars x 2,000 plots
    python -m benchmarks.bias_cost --radars 16 48 --plots 2000

Writes ``results/bias_cost.md`` (``--out`` another name).
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from solver.reconstruct import reconstruct
from solver.sensors import Site

from .earth import GEOD, BiasDraw, EarthTruth, MultiTrack, place, simulate_multi
from .multisensor import PSSR, radar_spec

RESULTS = Path(__file__).parent / "results"
OFFSETS = BiasDraw(range_m=(50.0, 200.0), azimuth_deg=(0.1, 0.3))


def ring_run(radars: int, plots: int, estimate: bool, truth: str = "calibration__ajaccio",
             seed: int = 0) -> MultiTrack:
    """``radars`` offset SSRs on a ring about the truth, about ``plots`` plots in all."""
    et0 = place(truth)
    xc, zc = float(np.mean(et0.truth.x)), float(np.mean(et0.truth.z))
    lat_c, lon_c = et0.frame.to_geodetic(np.array([xc]), np.array([zc]))
    sites = []
    for k in range(radars):
        lon, lat, _ = GEOD.fwd(float(lon_c[0]), float(lat_c[0]), 360.0 * k / radars,
                               70e3 + 30e3 * (k % 3))
        sites.append(Site(round(float(lat), 6), round(float(lon), 6), 300.0 + 50.0 * k))
    et = EarthTruth(et0.truth, et0.frame, tuple(sites))
    t_max = plots / radars * PSSR.scan_s / PSSR.pd
    specs = [radar_spec(f"R{k:02d}", PSSR, k, mode_c=True, bias=OFFSETS, estimate_bias=estimate)
             for k in range(radars)]
    return simulate_multi(et, specs, "bias-cost", seed, t_max=t_max)


def measure(run: MultiTrack) -> dict:
    """One reconstruction: CPU s, wall s, IPOPT iterations, RMS position error (m), offsets
    within 3 of their sigmas."""
    cpu, wall = time.process_time(), time.perf_counter()
    rec = reconstruct(run.table)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    err = np.hypot(rec.at_plots.x - run.truth.x, rec.at_plots.z - run.truth.z)
    within = total = 0
    for r in rec.sensors or []:
        if r.range_bias_m is None:
            continue
        b = run.biases[r.id]
        for est, sig, true in ((r.range_bias_m, r.range_bias_sigma_m, b.range_m),
                               (r.azimuth_bias_rad, r.azimuth_bias_sigma_rad, b.azimuth_rad),
                               (r.time_bias_s, r.time_bias_sigma_s, b.time_s)):
            total += 1
            within += bool(abs(est - true) < 3 * sig)
    return {"cpu": cpu, "wall": wall, "its": rec.diagnostics.extra.get("refine_iterations"),
            "rms": float(np.sqrt(np.mean(err**2))), "within": within, "offsets": total,
            "failures": rec.diagnostics.solver_failures}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bias_cost", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--radars", type=int, nargs="+", default=[2, 4, 8, 16])
    ap.add_argument("--plots", type=int, default=2000)
    ap.add_argument("--out", default="bias_cost")
    a = ap.parse_args(argv)
    started = time.perf_counter()
    rows = []
    for n in a.radars:
        for estimate in (False, True):
            run = ring_run(n, a.plots, estimate)
            first, again = measure(run), measure(run)
            rows.append((n, len(run.table), estimate, first, again))
            print(f"{n} radars, {len(run.table)} plots, estimate_bias {estimate}: "
                  f"{first['cpu']:.1f} / {again['cpu']:.1f} s CPU, {again['its']} iterations",
                  file=sys.stderr, flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, check=False).stdout.strip()
    cmd = "python -m benchmarks.bias_cost " + " ".join(argv if argv is not None else sys.argv[1:])
    lines = [
        "# Cost of estimate_bias with many radars", "",
        f"Command: `{cmd.strip()}`  ",
        f"Commit {commit}, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {platform.machine()}, "
        f"Python {platform.python_version()}; run time {time.perf_counter() - started:.0f} s "
        "(a shared machine: CPU seconds, not wall).", "",
        "Setting in the module docstring (`benchmarks/bias_cost.py`). CPU s: the first solve of "
        "that many radars (with the build of its solvers) / a second solve of the same plots.",
        "", "| radars | plots | estimate_bias | CPU s (first / again) | IPOPT iterations | "
        "RMS position (m) | offsets within 3 sigma | failed solves |",
        "|---:|---:|---|---:|---:|---:|---:|---:|"]
    for n, plots, estimate, first, again in rows:
        within = f"{again['within']} of {again['offsets']}" if estimate else "-"
        lines.append(f"| {n} | {plots} | {'yes' if estimate else 'no'} | {first['cpu']:.1f} / "
                     f"{again['cpu']:.1f} | {again['its']} | {again['rms']:.1f} | {within} | "
                     f"{again['failures']} |")
    (RESULTS / f"{a.out}.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
