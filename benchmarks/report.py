"""Write a benchmark run: ``report.md`` (tables), ``results.json`` (every number), figures."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .estimators import registry
from .profiles import PROFILES
from .run import BenchResult, summaries

TUNING_MD = "tuning.md"  # written by `python -m benchmarks.tune`, included when present
TUNING_NOTES = "tuning_notes.md"  # the choices drawn from it (hand-written), included too
ISSUE6_REFERENCE = {  # sanity figures quoted in issue 6 (RMS horizontal position, m)
    "raw": {"seed000": 782},
    "ss-cv-rts": {"seed000": 443, "seed001": 398, "ssr": 79},
    "ss-cv-rts+alt": {"ssr": 55},
}


def best_baselines(overall: dict[str, dict[str, dict]]) -> dict[str, tuple[str, float]]:
    """Per profile, the baseline (without altitude) with the lowest RMS position error."""
    kinds = {n: e.kind for n, e in registry().items()}
    out = {}
    for p, ests in overall.items():
        cand = [(m["rms_pos"], n) for n, m in ests.items()
                if kinds.get(n) == "baseline" and not n.endswith("+alt")
                and math.isfinite(m["rms_pos"])]
        if cand:
            rms, name = min(cand)
            out[p] = (name, rms)
    return out


def _f(v: float, digits: int = 0) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:,.{digits}f}".replace(",", " ")


def _x(ratio: float) -> str:
    """A ratio as ``0.95x`` (``-`` when not finite)."""
    return _f(ratio, 2) + "x" if math.isfinite(ratio) else "-"


def headline_table(overall: dict[str, dict[str, dict]], best: dict[str, tuple[str, float]],
                   profile: str) -> str:
    """Markdown table of one profile, estimators sorted by RMS position error."""
    rows = sorted(overall[profile].items(), key=lambda kv: kv[1]["rms_pos"])
    b = best.get(profile, ("", float("nan")))[1]
    lines = [
        "| estimator | RMS pos (m) | / best baseline | p95 pos (m) | RMS speed (m/s) "
        "| RMS pos, manoeuvres (m) | p95 pos, man. (m) | RMS speed, man. (m/s) "
        "| 95 % ellipse coverage | ms / track | plots / s | plots / CPU-s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, m in rows:
        cov = m["coverage95"]
        cov_s = _f(100 * cov, 1) + " %" if math.isfinite(cov) else "-"
        lines.append(
            f"| {name} | {_f(m['rms_pos'])} | {_f(m['rms_pos'] / b, 2)} | {_f(m['p95_pos'])} "
            f"| {_f(m['rms_speed'], 1)} | {_f(m['rms_pos_man'])} | {_f(m['p95_pos_man'])} "
            f"| {_f(m['rms_speed_man'], 1)} | {cov_s} "
            f"| {_f(1e3 * m['wall_s_per_track'], 1)} | {_f(m['plots_per_s'])} "
            f"| {_f(m['plots_per_cpu_s'])} |")
    return "\n".join(lines)


def per_truth_table(per_truth: dict, profile: str, estimators: list[str]) -> str:
    """RMS position error (m) per trajectory for one profile."""
    truths = sorted(per_truth.get(profile, {}))
    short = [t.split("__")[-1] for t in truths]
    lines = ["| estimator | " + " | ".join(short) + " |",
             "|---|" + "---:|" * len(truths)]
    for name in estimators:
        vals = [per_truth[profile][t].get(name, {}).get("rms_pos", float("nan")) for t in truths]
        if all(not math.isfinite(v) for v in vals):
            continue
        lines.append(f"| {name} | " + " | ".join(_f(v) for v in vals) + " |")
    return "\n".join(lines)


def _spread(speed: dict | None) -> str:
    """How much slower the slowest repetition was than the fastest, in all."""
    if not speed:
        return "-"
    reps = speed["rep_cpu_s"]
    return f"{max(reps) / min(reps) - 1:.0%}"


def speed_table(res: BenchResult, overall: dict, profiles: list[str]
                ) -> list[str]:
    """Plots per CPU-second of the Stone Soup CV smoother, the IMM smoother and the refined
    reconstruction: from the interleaved speed timing when the run made it, with the single
    timed calls of the accuracy loop beside it."""
    names = ("ss-cv-rts", "imm-smoother", "recon-refined-m3-R2")
    md = [""]
    if res.speed:
        md += [f"Speed per core (plots per CPU-second, all threads counted), least CPU time of "
               f"each estimator on each track and seed over {res.speed_reps} interleaved "
               "repetitions (the order rotated, so other work on the machine drops out); the "
               "last column is the ratio from the accuracy loop's single timed calls for "
               "comparison:", "",
               "| profile | ss-cv-rts | imm-smoother | recon-refined-m3-R2 | ratio to ss-cv-rts "
               "| ratio to imm-smoother | repetitions' spread (recon / imm) | single calls: "
               "ratio to imm-smoother |", "|---|---:|---:|---:|---:|---:|---|---:|"]
    else:
        md += ["Speed per core (plots per CPU-second, all threads counted) against the Stone "
               "Soup CV smoother and the IMM smoother of the same run:", "",
               "| profile | ss-cv-rts | imm-smoother | recon-refined-m3-R2 | ratio to ss-cv-rts "
               "| ratio to imm-smoother |", "|---|---:|---:|---:|---:|---:|"]
    for p in profiles:
        one = [overall[p].get(n, {}).get("plots_per_cpu_s", float("nan")) for n in names]
        if not res.speed:
            ref, imm, rec = one
            md.append(f"| {p} | {_f(ref)} | {_f(imm)} | {_f(rec)} | {_x(rec / ref)} "
                      f"| {_x(rec / imm)} |")
            continue
        sp = [res.speed.get((p, n)) for n in names]
        ref, imm, rec = (s["plots_per_cpu_s"] if s else float("nan") for s in sp)
        md.append(f"| {p} | {_f(ref)} | {_f(imm)} | {_f(rec)} | {_x(rec / ref)} "
                  f"| {_x(rec / imm)} | {_spread(sp[2])} / {_spread(sp[1])} "
                  f"| {_x(one[2] / one[1])} |")
    return md


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def write_outputs(res: BenchResult, settings: dict, env: dict[str, str], out: Path,
                  figures: bool = True) -> Path:
    """Write ``results.json``, ``report.md`` and ``figures/*.png`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    overall, per_truth = summaries(res)
    best = best_baselines(overall)
    profiles = [p for p in settings["profiles"] if p in overall]
    fig_names: list[tuple[str, str]] = []
    if figures:
        fig_names = _figures(res, overall, {p: best[p][1] for p in best}, out / "figures")
    data = {"settings": settings, "environment": env, "elapsed_s": res.elapsed_s,
            "best_baseline": {p: {"name": n, "rms_pos": v} for p, (n, v) in best.items()},
            "overall": overall, "per_truth": per_truth,
            "n_plots": {f"{p}/{t}": n for (p, t), n in res.n_plots.items()},
            "speed": {f"{p}/{e}": v for (p, e), v in res.speed.items()},
            "speed_reps": res.speed_reps,
            "failures": [f.__dict__ for f in res.failures]}
    (out / "results.json").write_text(json.dumps(_jsonable(data), indent=1))

    md = ["# Benchmark report", ""]
    md += [f"`{settings['command'].strip()}` — {env['date_utc']}, commit `{env['commit']}`, "
           f"{res.elapsed_s / 60:.1f} min on {env['cpus']} CPUs ({env['machine']}, shared), "
           f"Python {env['python']}, CasADi {env['casadi']}, Stone Soup {env['stonesoup']}, "
           f"FilterPy {env['filterpy']}.", ""]
    md += [f"Tracks: {', '.join(settings['truths'])}"
           + (f" (cut to {settings['t_max']:.0f} s)" if settings["t_max"] else "")
           + f"; Monte Carlo seeds {settings['seeds']}; the same simulated plots for every "
           "estimator of a (track, profile, seed). Errors at the plot times against the "
           "interpolated truth, pooled over tracks and seeds. `+alt` rows get the true altitude "
           "with each plot (ssr only); `/ best baseline` compares them with the best baseline "
           "without altitude. Wall time per track after one untimed warm-up call per "
           "estimator, on a shared machine (other jobs running): compare speeds within this "
           "run only.", ""]
    md += ["## Radar profiles", "", "| profile | scan (s) | sigma_r (m) | sigma_psi (deg) | Pd "
           "| eps_r (m) | eps_psi (deg) | h_max (m) | alpha_max (deg) |",
           "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for p in profiles:
        pr = PROFILES[p]
        md.append(f"| {p} | {pr.scan_s} | {pr.sigma_r:.1f} | {np.degrees(pr.sigma_psi):.3f} "
                  f"| {pr.pd} | {pr.eps_r:.0f} | {np.degrees(pr.eps_psi):.3f} | {pr.h_max:.0f} "
                  f"| {np.degrees(pr.alpha_max):.0f} |")
    md += ["", "## Headline: reconstruction against the best baseline", "",
           "| profile | best baseline | its RMS pos (m) | " + " | ".join(
               n for n in ("recon-refined-m3-R2", "recon-sliding-m3-R2")) + " |",
           "|---|---|---:|---:|---:|"]
    for p in profiles:
        if p not in best:
            continue
        bn, bv = best[p]
        cells = []
        for n in ("recon-refined-m3-R2", "recon-sliding-m3-R2"):
            m = overall[p].get(n)
            cells.append(f"{_f(m['rms_pos'])} m ({_f(m['rms_pos'] / bv, 2)}x)" if m else "-")
        md.append(f"| {p} | {bn} | {_f(bv)} | " + " | ".join(cells) + " |")
    md += ["", "Against the two smoothers side by side (RMS position error, RMS speed error; the "
           "IMM smoother `imm-smoother` is the strongest baseline, tuned per profile on the dev "
           "seeds):", "",
           "| profile | ss-cv-rts | imm-smoother | recon-refined-m3-R2 | recon / imm-smoother |",
           "|---|---:|---:|---:|---:|"]
    for p in profiles:
        ms = [overall[p].get(n) for n in ("ss-cv-rts", "imm-smoother", "recon-refined-m3-R2")]
        cells = [f"{_f(m['rms_pos'])} m, {_f(m['rms_speed'], 1)} m/s" if m else "-" for m in ms]
        ratio = _x(ms[2]["rms_pos"] / ms[1]["rms_pos"]) if ms[1] and ms[2] else "-"
        md.append(f"| {p} | " + " | ".join(cells) + f" | {ratio} |")
    md += speed_table(res, overall, profiles)
    for p in profiles:
        md += ["", f"## Profile `{p}`", "", headline_table(overall, best, p), "",
               "RMS position error (m) per track:", "",
               per_truth_table(per_truth, p, settings["estimators"])]
    md += ["", "## Sanity check against issue 6's baseline figures", "",
           "| estimator | profile | issue 6 (m) | this run (m) |", "|---|---|---:|---:|"]
    for n, ref in ISSUE6_REFERENCE.items():
        for p, v in ref.items():
            got = overall.get(p, {}).get(n, {}).get("rms_pos", float("nan"))
            md.append(f"| {n} | {p} | {v} | {_f(got)} |")
    md += ["", "## Failures", ""]
    if res.failures:
        md += ["| estimator | profile | track | seed | error |", "|---|---|---|---:|---|"]
        md += [f"| {f.estimator} | {f.profile} | {f.truth} | {f.seed} | "
               f"{f.error.splitlines()[-1].replace('|', '/')} |" for f in res.failures[:60]]
        if len(res.failures) > 60:
            md.append(f"\n... and {len(res.failures) - 60} more (results.json).")
    else:
        md.append("None.")
    if fig_names:
        md += ["", "## Figures", ""]
        md += [f"![{title}](figures/{name})\n\n*{title}*\n" for name, title in fig_names]
    from .run import RESULTS_DIR

    for extra in (TUNING_MD, TUNING_NOTES):
        for folder in dict.fromkeys((out, RESULTS_DIR)):
            if (folder / extra).exists():
                md += ["", (folder / extra).read_text().strip()]
                break
    report = out / "report.md"
    report.write_text("\n".join(md) + "\n")
    return report


def _figures(res: BenchResult, overall: dict, best: dict[str, float],
             fig_dir: Path) -> list[tuple[str, str]]:
    from . import figures

    fig_dir.mkdir(parents=True, exist_ok=True)
    made = []
    for (tname, pname), (track, _alt, ests) in res.figure_data.items():
        stem = f"{tname.split('__')[-1]}_{pname}"
        for kind, fn, title in (
                ("trajectory", figures.trajectory, "trajectory, plots with ellipses, estimates"),
                ("controls", figures.controls, "control histories u(t), w(t)"),
                ("errors", figures.error_history, "position error against time")):
            name = f"{kind}_{stem}.png"
            fn(track, ests, fig_dir / name)
            made.append((name, f"{title}: {tname}, {pname}, seed {track.seed}"))
    if best:
        figures.summary_bars({p: overall[p] for p in best}, best, fig_dir / "summary.png")
        made.insert(0, ("summary.png", "RMS position error relative to the best baseline"))
    return made
