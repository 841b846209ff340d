"""Accuracy and speed of the sliding windows on a track like seed 000's (issue 2's figures).

    python -m benchmarks.seed_track              # 10 noise seeds, all solvers (~2-4 min)
    python -m benchmarks.seed_track --seeds 3    # quicker

The track (tests/tracks.py): 5057 s, 19-s scans, straight legs, a ~220 deg right turn at
6 m/s^2, a ~180 deg left turn at 5 m/s^2, speed changes, every second plot missing in the turns.
The radar is the seed's (eps_r = 500 m, eps_psi = 1.5 deg, noise sigmas one third of those).
Two variants: ``flat`` (altitude 0, no altitude correction) and ``alt`` (aircraft at 10 km,
slant ranges, the seed's h_max = 15 km and alpha_max = 60 deg correction). Raw = the plot points
at their (slant) range. Errors are horizontal position errors at plot times.

Timing: ``time.perf_counter`` (wall) and ``time.process_time`` (CPU of this process) around one
``reconstruct_sliding`` call after an untimed warm-up (solvers are built once per process); the
median of several repetitions. The machine is shared, so wall time includes waiting for a core;
CPU time does not. Writes benchmarks/results/seed_track.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from solver import window
from solver.config import ReconstructionConfig
from solver.geometry import plot_points, weight_entries
from solver.guess import initial_guess
from solver.inputs import Bounds
from solver.motion import propagate
from solver.results import Diagnostics
from solver.sliding import criterion_data, initial_state, reconstruct_sliding, slide

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from tracks import SEED_RADAR, SEED_RADAR_ALT, make_track

SIGMA_R, SIGMA_PSI = 500.0 / 3, np.deg2rad(0.5)
OUT = Path(__file__).resolve().parent / "results" / "seed_track.md"


def log(msg: str) -> None:
    print(msg, flush=True)


def run(plots, radar, m: int, seed_rule: bool, nlp_solver: str = "sqpmethod"):
    """Reconstruct; with ``seed_rule`` the literal seed candidate set and start."""
    cfg = ReconstructionConfig(window_plots=m, method="sliding", nlp_solver=nlp_solver)
    if not seed_rule:
        return reconstruct_sliding(plots, radar, cfg)
    cx, cz, abc, scale = criterion_data(plots, radar, cfg.criterion)
    start, _ = initial_state(plots.t, cx, cz, cfg.bounds.v)
    diag = Diagnostics()
    from solver.trajectory import evaluate

    segs = slide(plots.t, cx, cz, abc, start, m, cfg, diag, scale, seed_rule=True)

    class Rec:
        at_plots = evaluate(segs, plots.t)
        diagnostics = diag
        segments = segs

    return Rec


def rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a**2)))


def accuracy(seeds: int) -> list[str]:
    lines = ["## Accuracy: RMS horizontal position error at plot times (m)", "",
             f"Mean over {seeds} noise seeds (min-max in brackets). `project` is the default "
             "sliding method; `seed rule` the seed's literal candidate set and start "
             "(`slide(..., seed_rule=True)`).", "",
             "| variant | m | raw plots | project | seed rule | noise-free max, project | "
             "noise-free max, seed rule |", "|---|---|---|---|---|---|---|"]
    for variant, radar, alt in [("flat", SEED_RADAR, 0.0), ("alt", SEED_RADAR_ALT, 10_000.0)]:
        clean = make_track(altitude_m=alt)
        noisy = [make_track(sigma_r=SIGMA_R, sigma_psi=SIGMA_PSI, seed=s, altitude_m=alt)
                 for s in range(seeds)]
        for m in (3, 4, 5):
            raw, ours, seedr = [], [], []
            for tr in noisy:
                px, pz = plot_points(tr.plots)
                raw.append(rms(np.hypot(px - tr.x, pz - tr.z)))
                for rule, acc in ((False, ours), (True, seedr)):
                    rec = run(tr.plots, radar, m, rule)
                    acc.append(rms(np.hypot(rec.at_plots.x - tr.x, rec.at_plots.z - tr.z)))
            nf = []
            for rule in (False, True):
                rec = run(clean.plots, radar, m, rule)
                nf.append(np.hypot(rec.at_plots.x - clean.x, rec.at_plots.z - clean.z).max())

            def fmt(v):
                return f"{np.mean(v):.0f} [{np.min(v):.0f}-{np.max(v):.0f}]"

            lines.append(f"| {variant} | {m} | {fmt(raw)} | {fmt(ours)} | {fmt(seedr)} | "
                         f"{nf[0]:.1f} | {nf[1]:.1f} |")
            log(f"  accuracy {variant} m={m}: raw {np.mean(raw):.0f}  project "
                f"{np.mean(ours):.0f}  seed rule {np.mean(seedr):.0f}  noise-free max "
                f"{nf[0]:.1f} / {nf[1]:.1f}")
    return lines


def timing(reps: int) -> list[str]:
    tr = make_track(sigma_r=SIGMA_R, sigma_psi=SIGMA_PSI, seed=0)
    lines = ["## Speed: the 5057-s, 19-s-scan track (261 plots), window 3, R2", "",
             f"Median of {reps} runs after a warm-up. Seed 000: 6.0-6.3 s on an AMD Athlon "
             "3000+ (2005).", "",
             "| NLP solver | wall s/track | CPU s/track | NLP solves | trial windows | "
             "trial windows/s (wall) | median ms/NLP solve | solver failures | fallbacks | "
             "RMS (m) |", "|---|---|---|---|---|---|---|---|---|---|"]
    variants = [("sqpmethod, exact Hessian (default)", "sqpmethod", "exact"),
                ("sqpmethod, Gauss-Newton", "sqpmethod", "gauss-newton"),
                ("ipopt", "ipopt", "exact")]
    for name, plugin, hess in variants:
        window.use_hessian(hess)
        run(tr.plots, SEED_RADAR, 3, False, plugin)  # warm-up: builds the solvers
        wall, cpu, last = [], [], None
        for _ in range(reps):
            w0, c0 = time.perf_counter(), time.process_time()
            last = run(tr.plots, SEED_RADAR, 3, False, plugin)
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
        d = last.diagnostics
        err = rms(np.hypot(last.at_plots.x - tr.x, last.at_plots.z - tr.z))
        w, c = float(np.median(wall)), float(np.median(cpu))
        lines.append(f"| {name} | {w:.3f} | {c:.3f} | {d.windows_solved} | {d.trial_windows} | "
                     f"{d.trial_windows / w:.0f} | {np.median(d.nlp_solve_ms):.3f} | "
                     f"{d.solver_failures} | {d.fallbacks} | {err:.0f} |")
        log(f"  timing {name}: wall {w:.3f} s, CPU {c:.3f} s, {d.windows_solved} solves, "
            f"median {np.median(d.nlp_solve_ms):.3f} ms/solve, failures {d.solver_failures}")
    window.use_hessian("exact")
    lines += ["", "`median ms/NLP solve`: the trial windows of one step are solved in one mapped "
              "call, whose time is split evenly over them, and so are the switch-time "
              "refinements of a step; the free-start solve is a single call."]
    return lines


def _windows(n: int, m: int, seed: int):
    rng = np.random.default_rng(seed)
    start = np.column_stack([rng.uniform(-1.5e5, 1.5e5, n), rng.uniform(-1.5e5, 1.5e5, n),
                             rng.uniform(0, 2 * np.pi, n), rng.uniform(120, 300, n)])
    t = np.cumsum(rng.uniform(4, 38, (n, m)), axis=1)
    u = rng.uniform(-7, 7, n)
    w = np.clip(rng.uniform(-2, 3, n), (40 - start[:, 3]) / t[:, -1],
                (320 - start[:, 3]) / t[:, -1])
    x, z, _, _ = propagate(start[:, 0:1], start[:, 1:2], start[:, 2:3], start[:, 3:4],
                           u[:, None], w[:, None], t)
    d = np.hypot(x, z)
    psi = np.arctan2(z, x) + SIGMA_PSI * rng.standard_normal(x.shape)
    d = d + SIGMA_R * rng.standard_normal(x.shape)
    cx, cz = d * np.cos(psi), d * np.sin(psi)
    abc = weight_entries(psi.ravel(), np.deg2rad(1.5) * d.ravel(),
                         np.full(n * m, 500.0)).reshape(n, m, 3)
    return start, t, cx, cz, abc


def brute_force(n: int) -> list[str]:
    """NLP optimum against the minimum over a 281 x 201 grid of the feasible (u, w) box."""
    bounds = Bounds()
    lines = ["## Window NLP against brute force", "",
             f"{n} random noisy windows per m (random start, speeds 120-300 m/s, plot spacing "
             "4-38 s, controls anywhere in the bounds, seed radar noise, R2), started from the "
             "analytic guess. `worse` counts windows whose NLP value exceeds the grid minimum by "
             "more than 1e-9 relative (a different, worse local minimum); `gain` is the median "
             "relative improvement of the NLP over the grid minimum.", "",
             "| NLP solver | m | worse than grid | worst excess | median gain | failures | "
             "CPU ms/solve: solve_windows (mapped, with checks) | CPU ms/solve: bare solver, "
             "one call each |",
             "|---|---|---|---|---|---|---|---|"]
    for name, plugin, hess in [("sqpmethod, exact", "sqpmethod", "exact"),
                               ("sqpmethod, Gauss-Newton", "sqpmethod", "gauss-newton"),
                               ("ipopt", "ipopt", "exact")]:
        window.use_hessian(hess)
        for m in (3, 5):
            start, t, cx, cz, abc = _windows(n, m, seed=m)
            lbw, ubw, _ = window.w_box(start[:, 3], t[:, -1], bounds)
            guess, _ = initial_guess(start, t, cx, cz, abc, bounds.u, lbw, ubw)
            window.solve_windows(start, t, cx, cz, abc, guess, lbw, ubw, bounds,
                                 plugin)  # builds the solver and its map over n windows
            c0 = time.process_time()
            fits = window.solve_windows(start, t, cx, cz, abc, guess, lbw, ubw, bounds, plugin)
            mapped_ms = (time.process_time() - c0) * 1e3 / n
            solver = window.window_solver(m, plugin)
            params = window.pack_params(start, t, cx, cz, abc)
            c0 = time.process_time()
            for k in range(n):
                solver(x0=guess[k], p=params[k], lbx=[bounds.u[0], lbw[k]],
                       ubx=[bounds.u[1], ubw[k]])
            single_ms = (time.process_time() - c0) * 1e3 / n
            gu = np.linspace(*bounds.u, 281)
            excess = np.empty(n)
            for k in range(n):
                uu, ww = np.meshgrid(gu, np.linspace(lbw[k], ubw[k], 201))
                vals = window.criterion(np.broadcast_to(start[k], (*uu.shape, 4)), uu, ww,
                                        t[k], cx[k], cz[k], abc[k])
                excess[k] = (fits.value[k] - vals.min()) / vals.min()
            lines.append(f"| {name} | {m} | {int(np.sum(excess > 1e-9))} | "
                         f"{excess.max():.2e} | {-np.median(excess):.2e} | "
                         f"{int(fits.failed.sum())} | {mapped_ms:.3f} | {single_ms:.3f} |")
            log(f"  brute force {name} m={m}: worse {int(np.sum(excess > 1e-9))}/{n}, "
                f"worst {excess.max():.2e}, mapped {mapped_ms:.3f} ms, single {single_ms:.3f} ms")
    window.use_hessian("exact")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10, help="noise seeds for the accuracy table")
    ap.add_argument("--reps", type=int, default=5, help="timed runs per solver")
    ap.add_argument("--windows", type=int, default=200, help="random windows for brute force")
    args = ap.parse_args()
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    log("[1/3] timing")
    tim = timing(args.reps)
    log("[2/3] window NLP vs brute force")
    bf = brute_force(args.windows)
    log("[3/3] accuracy")
    acc = accuracy(args.seeds)
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if "model name" in line)
    except (OSError, StopIteration):
        pass
    head = ["# Sliding windows on a seed-000-like track", "",
            f"Command: `python -m benchmarks.seed_track --seeds {args.seeds} --reps {args.reps} "
            f"--windows {args.windows}`; run {started}.", "",
            f"Machine: {cpu}, {os.cpu_count()} cores shared with other jobs (load average at the "
            f"end {os.getloadavg()[0]:.1f}); Python {platform.python_version()}.", ""]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text("\n".join([*head, *tim, "", *bf, "", *acc, ""]))
    log(f"wrote {OUT}")


if __name__ == "__main__":
    main()
