"""Run the benchmark: every estimator on the same simulated plots, metrics, report, figures.

    python -m benchmarks.run                 # full run (6 ADS-B tracks + synthetic, 3 profiles)
    python -m benchmarks.run --quick         # < 2 minutes: 2 shortened tracks, 1 seed
    python -m benchmarks.run --profiles ssr --seeds 5 --estimators 'ss-*' 'recon-*'

Each (truth, profile, seed) is simulated once and handed to every estimator. Wall time is
``time.perf_counter`` around one estimator call on one track, after an untimed warm-up call
per estimator (CasADi solvers and imports are built once per process, not per track); CPU
time is ``time.process_time`` (every thread of the process) over the same call, so plots per
CPU-second is the per-core speed whatever threads a library starts.
The speed comparison of the report (``--speed-reps``, default 2) then re-times the smoothers it
compares on every track and seed of the run (the reconstruction's speed differs by up to 2x from
seed to seed on the same tracks): every repetition runs each of them on each track in turn
(the order rotated between repetitions), and each (track, estimator) keeps its least CPU time, so
a burst of other work on this shared machine, which only ever adds time, drops out.
An estimator that raises is recorded as a failure in the report; the run goes on.
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .estimators import DEFAULT_SET, QUICK_SET, Estimate, Estimator, select
from .metrics import RunErrors, errors, summarize
from .profiles import PROFILES, RadarProfile
from .simulate import SimulatedTrack, simulate
from .truth import SYNTHETIC, load_truth, truth_names

RESULTS_DIR = Path(__file__).parent / "results"


def publish(name: str, md: list[str]) -> Path | None:
    """Write the markdown lines ``md`` to ``results/<name>`` and print them (``name`` empty:
    only print them)."""
    if not name:
        print("\n".join(md))
        return None
    out = RESULTS_DIR / name
    out.write_text("\n".join(md) + "\n")
    print("\n".join(md))
    print(f"wrote {out}")
    return out
QUICK_TRUTHS = ("calibration__vienna", SYNTHETIC)
QUICK_T_MAX = 1200.0
FIGURE_CASES = ((SYNTHETIC, "seed000"), ("calibration__kiruna", "seed001"),
                ("featured__belevingsvlucht", "ssr"))


@dataclass
class Failure:
    estimator: str
    profile: str
    truth: str
    seed: int
    error: str


@dataclass
class BenchResult:
    """Everything one run measured."""

    errors: dict[tuple[str, str, str], list[RunErrors]] = field(default_factory=dict)
    failures: list[Failure] = field(default_factory=list)
    n_plots: dict[tuple[str, str], list[int]] = field(default_factory=dict)
    figure_data: dict[tuple[str, str], tuple[SimulatedTrack, SimulatedTrack | None,
                                             dict[str, Estimate]]] = field(default_factory=dict)
    # (profile, estimator) -> plots, least CPU seconds per track summed, each repetition's sum
    speed: dict[tuple[str, str], dict] = field(default_factory=dict)
    speed_reps: int = 0
    elapsed_s: float = 0.0


SPEED_ESTIMATORS = ("ss-cv-rts", "imm-smoother", "recon-refined-m3-R2")


def _simulate_pair(truth_name: str, profile: RadarProfile, seed: int, need_alt: bool,
                   t_max: float | None) -> tuple[SimulatedTrack, SimulatedTrack | None]:
    """The run's plots; with ``need_alt`` the same plots carrying the true altitude."""
    truth = load_truth(truth_name)
    drop = truth_name == SYNTHETIC  # the seed's track lost many plots in its turns
    track = simulate(truth, profile, seed, drop_in_turns=drop, t_max=t_max)
    alt = simulate(truth, profile, seed, with_altitude=True, drop_in_turns=drop,
                   t_max=t_max) if need_alt else None
    return track, alt


def _warm_up(estimators: list[Estimator], profile: RadarProfile) -> None:
    """One untimed call per estimator on a short track (builds solvers, imports modules)."""
    track, alt = _simulate_pair("calibration__vienna", profile, 10_000, True, 300.0)
    for est in estimators:
        sim = alt if est.with_altitude else track
        try:
            est.run(sim.plots, profile.radar(), profile.name)
        except Exception:  # the timed run records the failure
            pass


def run_benchmark(truths: list[str], profiles: list[str], seeds: list[int],
                  estimators: list[Estimator], t_max: float | None = None,
                  figure_cases: tuple[tuple[str, str], ...] = FIGURE_CASES,
                  progress: bool = True, speed_reps: int = 0) -> BenchResult:
    """Simulate every (truth, profile, seed) once and run every applicable estimator on it."""
    res = BenchResult()
    start = time.perf_counter()
    tasks = [(p, tn, s) for p in profiles for tn in truths for s in seeds]
    total = sum(sum(e.applies_to(p) for e in estimators) for p, _, _ in tasks)
    _warm_up(estimators, PROFILES[profiles[0]])
    bar = tqdm(total=total, unit="est", disable=not progress, dynamic_ncols=True)
    for pname, tname, seed in tasks:
        profile = PROFILES[pname]
        active = [e for e in estimators if e.applies_to(pname)]
        track, alt = _simulate_pair(tname, profile, seed, any(e.with_altitude for e in active),
                                    t_max)
        res.n_plots.setdefault((pname, tname), []).append(len(track.plots))
        keep = (tname, pname) in figure_cases and seed == seeds[0]
        kept: dict[str, Estimate] = {}
        for est in active:
            bar.set_postfix_str(f"{pname} {tname[:18]} s{seed} {est.name}", refresh=False)
            sim = alt if est.with_altitude else track
            assert sim is not None
            try:
                t0, c0 = time.perf_counter(), time.process_time()
                out = est.run(sim.plots, profile.radar(), pname)
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                run_err = errors(out.states, sim.truth, sim.manoeuvre, wall, cpu)
            except Exception as exc:  # recorded; the run goes on
                msg = "".join(traceback.format_exception_only(type(exc), exc)).strip()
                res.failures.append(Failure(est.name, pname, tname, seed, msg[:300]))
            else:
                res.errors.setdefault((pname, tname, est.name), []).append(run_err)
                if keep:
                    kept[est.name] = out
            bar.update(1)
        if keep:
            res.figure_data[(tname, pname)] = (track, alt, kept)
    bar.close()
    if speed_reps > 0:
        timed = [e for e in estimators if e.name in SPEED_ESTIMATORS]
        for pname in profiles:
            _time_speed(res, pname, truths, seeds, [e for e in timed if e.applies_to(pname)],
                        speed_reps, t_max)
    res.elapsed_s = time.perf_counter() - start
    return res


def _time_speed(res: BenchResult, pname: str, truths: list[str], seeds: list[int],
                estimators: list[Estimator], reps: int, t_max: float | None) -> None:
    """Least CPU time of each estimator on each track over ``reps`` interleaved repetitions
    (see the module docstring) into ``res.speed``."""
    profile = PROFILES[pname]
    tracks = [_simulate_pair(tn, profile, seed, False, t_max)[0]
              for tn in truths for seed in seeds]
    cpu = np.full((reps, len(estimators), len(tracks)), np.inf)
    for r in range(reps):
        for i, track in enumerate(tracks):
            for j in np.roll(np.arange(len(estimators)), r + i):
                c0 = time.process_time()
                try:
                    estimators[j].run(track.plots, profile.radar(), pname)
                except Exception:  # recorded by the accuracy loop
                    continue
                cpu[r, j, i] = time.process_time() - c0
    plots = sum(len(t.plots) for t in tracks)
    res.speed_reps = reps
    for j, est in enumerate(estimators):
        least = cpu[:, j, :].min(axis=0)
        if np.all(np.isfinite(least)):
            res.speed[(pname, est.name)] = {
                "plots": plots, "cpu_s": float(least.sum()),
                "plots_per_cpu_s": plots / float(least.sum()),
                "rep_cpu_s": [float(c) for c in cpu[:, j, :].sum(axis=1)]}


def summaries(res: BenchResult) -> tuple[dict, dict]:
    """Pooled metrics per profile x estimator (over trajectories and seeds) and per
    profile x trajectory x estimator (over seeds)."""
    by_profile: dict[str, dict[str, list[RunErrors]]] = {}
    per_truth: dict[str, dict[str, dict[str, dict]]] = {}
    for (p, tn, en), runs in res.errors.items():
        by_profile.setdefault(p, {}).setdefault(en, []).extend(runs)
        per_truth.setdefault(p, {}).setdefault(tn, {})[en] = summarize(runs)
    overall = {p: {en: summarize(runs) for en, runs in ests.items()}
               for p, ests in by_profile.items()}
    return overall, per_truth


def _git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True, cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def environment() -> dict[str, str]:
    """Versions and machine, for the report header."""
    import casadi
    import filterpy
    import stonesoup
    return {
        "python": platform.python_version(), "machine": platform.machine(),
        "cpus": str(__import__("os").cpu_count()), "numpy": np.__version__,
        "casadi": casadi.__version__, "stonesoup": stonesoup.__version__,
        "filterpy": filterpy.__version__, "commit": _git_commit(),
        "date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help=f"{len(QUICK_TRUTHS)} tracks cut to {QUICK_T_MAX:.0f} s, 1 seed, "
                    "fewer estimators (under two minutes)")
    ap.add_argument("--profiles", nargs="+", choices=sorted(PROFILES), default=None)
    ap.add_argument("--truths", nargs="+", default=None, help="truth names (default: all)")
    ap.add_argument("--seeds", type=int, default=None, help="Monte Carlo seeds per track "
                    "(default 3, quick 1)")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--estimators", nargs="+", default=None,
                    help="names or glob patterns (default: the standard set)")
    ap.add_argument("--t-max", type=float, default=None, help="cut tracks to this many seconds")
    ap.add_argument("--out", type=Path, default=None,
                    help="output directory (default benchmarks/results, quick: results/quick)")
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--speed-reps", type=int, default=None,
                    help="repetitions of the interleaved speed timing of "
                    f"{', '.join(SPEED_ESTIMATORS)} on every track and seed (default 2, "
                    "quick 1; 0: none)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    from .report import write_outputs

    args = parse_args(argv)
    profiles = args.profiles or list(PROFILES)
    truths = args.truths or (list(QUICK_TRUTHS) if args.quick else truth_names())
    unknown = [t for t in truths if t not in truth_names()]
    if unknown:
        print(f"unknown truth {unknown}; known: {truth_names()}", file=sys.stderr)
        return 2
    n_seeds = args.seeds or (1 if args.quick else 3)
    seeds = list(range(args.first_seed, args.first_seed + n_seeds))
    estimators = select(args.estimators or (QUICK_SET if args.quick else DEFAULT_SET))
    t_max = args.t_max if args.t_max is not None else (QUICK_T_MAX if args.quick else None)
    cases = tuple((t, p) for t, p in FIGURE_CASES if t in truths and p in profiles)
    if not cases:
        cases = ((truths[0], profiles[0]),)
    speed_reps = args.speed_reps if args.speed_reps is not None else (1 if args.quick else 2)
    res = run_benchmark(truths, profiles, seeds, estimators, t_max, cases,
                        progress=not args.no_progress, speed_reps=speed_reps)
    settings = {"command": "python -m benchmarks.run " + " ".join(argv or sys.argv[1:]),
                "profiles": profiles, "truths": truths, "seeds": seeds,
                "estimators": [e.name for e in estimators], "t_max": t_max,
                "quick": args.quick, "speed_reps": speed_reps}
    out = args.out or (RESULTS_DIR / "quick" if args.quick else RESULTS_DIR)
    report = write_outputs(res, settings, environment(), out, figures=not args.no_figures)
    print(f"wrote {report} ({res.elapsed_s:.0f} s, {len(res.failures)} failures)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
