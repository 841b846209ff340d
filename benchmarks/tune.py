"""Grid searches on the dev set (the six ADS-B tracks) that fix the frozen settings.

    python -m benchmarks.tune baselines     # q of the CV filter/smoother, IMM grid, per profile
    python -m benchmarks.tune recon         # the reconstruction's window, trial step, criterion,
                                            # solver (one factor at a time around the default)
    python -m benchmarks.tune refine        # the refinement's penalties (one factor at a time
                                            # around RefineSettings(), also with altitude)
    python -m benchmarks.tune refine --grid # the two turn penalties together (REFINE_GRID)
    python -m benchmarks.tune imm_smoother  # the IMM smoother's grid (IMM_SMOOTHER_GRID): the
                                            # product's defaults and the per-profile baseline

Tuning seeds (100, 101 by default) are disjoint from the benchmark's seeds (0, 1, ...), so the
frozen values are not fitted to the very noise they are scored on; the tracks are the same (the
dev set is all there is). The score is the pooled RMS horizontal position error. Results go to
``results/tuning_<part>.json`` and, rendered, to ``results/tuning.md`` (which the report
includes). The chosen baseline values are then copied by hand into ``baselines.TUNED``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from dataclasses import asdict, replace
from pathlib import Path

from .baselines import ImmTuning, filterpy_imm, stonesoup_cv
from .estimators import Estimate, Estimator, recon_config, recon_runner
from .run import RESULTS_DIR, run_benchmark, summaries
from .truth import SYNTHETIC, truth_names

Q_GRID = (1.0, 3.0, 10.0, 30.0, 100.0, 300.0)
IMM_GRID = {"q_cv": (0.3, 3.0), "q_ct": (10.0, 30.0, 100.0), "q_omega": (1e-6, 1e-5, 1e-4),
            "sojourn_s": (60.0, 300.0)}
IMM_SMOOTHER_GRID = {"q_cv": (1.0, 3.0, 10.0, 30.0), "q_ct": (10.0, 30.0, 100.0),
                     "omega_deg": (1.0, 2.0, 3.0), "sojourn": ((60.0, 30.0), (200.0, 60.0))}
"""``solver.estimation.imm_smoother``: white-acceleration densities of the CV and turn models
(m^2/s^3), the turn models' rate (deg/s), and the mean sojourn times ``(tau_cv, tau_ct)`` (s)."""
IMM_SMOOTHER_FINE = {"q_cv": (1.0, 3.0), "q_ct": (30.0,), "omega_deg": (0.5, 1.0, 1.5),
                     "sojourn": ((200.0, 60.0), (600.0, 60.0), (200.0, 180.0), (600.0, 180.0))}
"""Second stage (``--fine``): around the coarse grid's best point, which sat at the coarse grid's
edges in the turn rate and the sojourn times."""
RECON_DEFAULT = {"window_plots": 3, "trial_step_s": 5.0, "criterion": "R2",
                 "nlp_solver": "sqpmethod"}
RECON_AXES = {"window_plots": (3, 4, 5), "trial_step_s": (2.5, 5.0, 10.0, 20.0),
              "criterion": ("R2", "R1"), "nlp_solver": ("sqpmethod", "ipopt")}
# The refinement starts from the CV smoother by default, which makes it independent of the four
# settings above; starting it from the sliding windows brings the window length back into play.
REFINE_INIT_POINTS = ({"refine_init": "sliding", "window_plots": 3},
                      {"refine_init": "sliding", "window_plots": 5})
# The refinement's penalties (solver.config.RefineSettings), one at a time around the default.
REFINE_AXES = {"switch_penalty_u": (0.7, 1.4), "switch_penalty_w": (0.6, 2.5, 5.0),
               "level_penalty_u": (0.05, 0.2), "level_penalty_w": (0.05, 0.2)}
# The two penalties on turning, together: is there one setting better on every profile?
REFINE_GRID = {"level_penalty_u": (0.0, 0.02, 0.05, 0.1), "switch_penalty_u": (0.5, 0.7, 1.0)}


def dev_set() -> list[str]:
    return [n for n in truth_names() if n != SYNTHETIC]


def _cv(q: float, smooth: bool) -> Estimator:
    name = f"{'ss-cv-rts' if smooth else 'ss-cv-kf'} q={q:g}"
    return Estimator(name, "baseline",
                     lambda p, r, _: Estimate(stonesoup_cv(p, r, q=q, smooth=smooth)))


def _imm(t: ImmTuning) -> Estimator:
    name = f"fp-imm {t.q_cv:g}/{t.q_ct:g}/{t.q_omega:g}/{t.sojourn_s:g}"
    return Estimator(name, "baseline", lambda p, r, _: Estimate(filterpy_imm(p, r, t)))


def _recon(settings: dict, method: str) -> Estimator:
    from solver.config import RefineSettings

    extra = {}
    if "refine_init" in settings:
        extra["refine"] = RefineSettings(init=settings["refine_init"])
    cfg = recon_config(method, settings["window_plots"], settings["criterion"],
                       trial_step_s=settings["trial_step_s"], nlp_solver=settings["nlp_solver"],
                       **extra)
    label = " ".join(f"{k}={v}" for k, v in settings.items())
    return Estimator(f"{method} {label}", "recon", recon_runner(cfg))


def tune_baselines(profiles: list[str], seeds: list[int]) -> dict:
    """Pooled RMS position error of every grid point, per profile, and the best of each family."""
    imm_points = [ImmTuning(*v) for v in itertools.product(*IMM_GRID.values())]
    ests = ([_cv(q, False) for q in Q_GRID] + [_cv(q, True) for q in Q_GRID]
            + [_imm(t) for t in imm_points])
    res = run_benchmark(dev_set(), profiles, seeds, ests, figure_cases=())
    overall, _ = summaries(res)
    out: dict = {"seeds": seeds, "tracks": dev_set(), "q_grid": Q_GRID,
                 "imm_grid": IMM_GRID, "profiles": {}}
    for p in profiles:
        scores = {n: m["rms_pos"] for n, m in overall[p].items()}
        best = {}
        for family, key in (("ss-cv-kf", "q_kf"), ("ss-cv-rts", "q_rts")):
            cand = {q: scores[f"{family} q={q:g}"] for q in Q_GRID}
            best[key] = min(cand, key=cand.get)
        imm_scores = {i: scores[_imm(t).name] for i, t in enumerate(imm_points)}
        best["imm"] = asdict(imm_points[min(imm_scores, key=imm_scores.get)])
        out["profiles"][p] = {"scores": scores, "best": best}
    return out


def imm_smoother_points(grid: dict | None = None) -> list[dict]:
    """Every point of ``grid`` (default :data:`IMM_SMOOTHER_GRID`) as ``run_imm_smoother``
    keyword arguments."""
    pts = []
    for q_cv, q_ct, om, (tau_cv, tau_ct) in itertools.product(
            *(grid or IMM_SMOOTHER_GRID).values()):
        pts.append({"q_cv": q_cv, "q_ct": q_ct, "omega_deg": om, "tau_cv": tau_cv,
                    "tau_ct": tau_ct})
    return pts


def _imm_smoother(params: dict, kim: bool = False) -> Estimator:
    from solver.estimation import run_filter

    name = "imm-smoother " + "/".join(f"{v:g}" for v in params.values())
    return Estimator(name, "baseline", lambda p, r, _: Estimate(
        run_filter("imm_smoother", p, r, future_modes=not kim, **params).states))


def tune_imm_smoother(profiles: list[str], seeds: list[int], fine: bool = False,
                      kim: bool = False) -> dict:
    """Pooled RMS position and speed errors of every grid point per profile; the best point per
    profile (the benchmark's ``imm-smoother`` baseline) and the point with the lowest mean over
    the profiles of RMS / the profile's best RMS (the product's defaults). ``fine``: the second
    stage :data:`IMM_SMOOTHER_FINE`; ``kim``: Kim's backward mode weights."""
    grid = IMM_SMOOTHER_FINE if fine else IMM_SMOOTHER_GRID
    points = imm_smoother_points(grid)
    ests = [_imm_smoother(pt, kim) for pt in points]
    res = run_benchmark(dev_set(), profiles, seeds, ests, figure_cases=())
    overall, _ = summaries(res)
    out: dict = {"seeds": seeds, "tracks": dev_set(), "grid": grid, "fine": fine, "kim": kim,
                 "points": points, "profiles": {}}
    rel = [0.0] * len(points)
    for p in profiles:
        rows = [{k: overall[p][e.name][k] for k in ("rms_pos", "rms_speed", "rms_pos_man",
                                                    "coverage95", "plots_per_cpu_s")}
                for e in ests]
        best = min(range(len(points)), key=lambda i: rows[i]["rms_pos"])
        for i, r in enumerate(rows):
            rel[i] += r["rms_pos"] / rows[best]["rms_pos"] / len(profiles)
        out["profiles"][p] = {"rows": rows, "best": points[best]}
    common = min(range(len(points)), key=lambda i: rel[i])
    out["mean_relative_rms"] = rel
    out["common"] = points[common]
    out["failures"] = [f.__dict__ for f in res.failures]
    return out


def tune_recon(profiles: list[str], seeds: list[int], t_max: float | None,
               method: str, only_init: bool = False) -> dict:
    """One factor at a time around :data:`RECON_DEFAULT` for one method (``only_init``: just the
    default and the refinement started from the sliding windows)."""
    points = [dict(RECON_DEFAULT)]
    if not only_init:
        for axis, values in RECON_AXES.items():
            points += [{**RECON_DEFAULT, axis: v} for v in values if v != RECON_DEFAULT[axis]]
    if method == "refined":
        points += [{**RECON_DEFAULT, **pt} for pt in REFINE_INIT_POINTS]
    ests = [_recon(pt, method) for pt in points]
    res = run_benchmark(dev_set(), profiles, seeds, ests, t_max=t_max, figure_cases=())
    overall, _ = summaries(res)
    rows = []
    for pt, est in zip(points, ests, strict=True):
        row = {"settings": pt}
        for p in profiles:
            m = overall.get(p, {}).get(est.name)
            row[p] = None if m is None else {k: m[k] for k in
                                             ("rms_pos", "rms_pos_man", "rms_speed",
                                              "wall_s_per_track", "plots_per_s")}
        rows.append(row)
    failures = [f.__dict__ for f in res.failures]
    return {"method": method, "seeds": seeds, "tracks": dev_set(), "t_max": t_max,
            "default": RECON_DEFAULT,
            "axes": RECON_AXES, "rows": rows, "failures": failures}


def tune_refine(profiles: list[str], seeds: list[int], t_max: float | None,
                grid: bool = False) -> dict:
    """One factor of :data:`REFINE_AXES` at a time around ``RefineSettings()`` (or, ``grid``,
    every point of :data:`REFINE_GRID`): pooled RMS position error and 95 % ellipse coverage per
    profile, and on the ssr plots with their altitude."""
    from solver.config import RefineSettings

    default = RefineSettings()
    points: list[dict] = [{}]
    if grid:
        points += [pt for pt in (dict(zip(REFINE_GRID, vals, strict=True))
                                 for vals in itertools.product(*REFINE_GRID.values()))
                   if any(v != getattr(default, k) for k, v in pt.items())]
    for axis, values in ({} if grid else REFINE_AXES).items():
        points += [{axis: v} for v in values if v != getattr(default, axis)]
    ests = []
    for pt in points:
        cfg = recon_config("refined", 3, "R2", refine=replace(default, **pt))
        label = " ".join(f"{k}={v}" for k, v in pt.items()) or "default"
        for alt in (False, True):
            ests.append(Estimator(f"refine {label}{'+alt' if alt else ''}", "recon",
                                  recon_runner(cfg), with_altitude=alt))
    res = run_benchmark(dev_set(), profiles, seeds, ests, t_max=t_max, figure_cases=())
    overall, _ = summaries(res)
    rows = []
    for i, pt in enumerate(points):
        row: dict = {"settings": pt}
        for est in ests[2 * i: 2 * i + 2]:
            for p in profiles:
                m = overall.get(p, {}).get(est.name)
                if est.applies_to(p):
                    key = p + ("+alt" if est.with_altitude else "")
                    row[key] = None if m is None else {k: m[k] for k in ("rms_pos", "coverage95")}
        rows.append(row)
    axes = REFINE_GRID if grid else REFINE_AXES
    return {"seeds": seeds, "tracks": dev_set(), "t_max": t_max, "grid": grid,
            "default": {k: getattr(default, k) for k in REFINE_AXES}, "axes": axes,
            "rows": rows, "failures": [f.__dict__ for f in res.failures]}


def render(out_dir: Path) -> str:
    """Markdown of the tuning results present in ``out_dir``."""
    md = ["## Tuning on the dev set", ""]
    base = out_dir / "tuning_baselines.json"
    if base.exists():
        b = json.loads(base.read_text())
        md += [f"Baselines (`python -m benchmarks.tune baselines`): the six ADS-B tracks, seeds "
               f"{b['seeds']}, pooled RMS position error (m). CV white-acceleration density "
               f"`q` (m²/s³) over {b['q_grid']}; IMM over q_cv x q_ct x q_omega x sojourn = "
               f"{' x '.join(str(list(v)) for v in b['imm_grid'].values())}.", "",
               "| profile | " + " | ".join(f"q={q:g} KF / RTS" for q in b["q_grid"])
               + " | chosen KF, RTS | best IMM (q_cv/q_ct/q_omega/sojourn) | its RMS |",
               "|---|" + "---:|" * len(b["q_grid"]) + "---|---|---:|"]
        for p, d in b["profiles"].items():
            s = d["scores"]
            cells = [f"{s[f'ss-cv-kf q={q:g}']:.0f} / {s[f'ss-cv-rts q={q:g}']:.0f}"
                     for q in b["q_grid"]]
            imm = d["best"]["imm"]
            iname = (f"fp-imm {imm['q_cv']:g}/{imm['q_ct']:g}/{imm['q_omega']:g}/"
                     f"{imm['sojourn_s']:g}")
            md.append(f"| {p} | " + " | ".join(cells) + f" | {d['best']['q_kf']:g}, "
                      f"{d['best']['q_rts']:g} | {iname.split(' ')[1]} | {s[iname]:.0f} |")
        md.append("")
    for method in ("sliding", "refined"):
        rec = out_dir / f"tuning_recon_{method}.json"
        if rec.exists():
            md += _render_recon(json.loads(rec.read_text()))
    for name in ("tuning_imm_smoother.json", "tuning_imm_smoother_fine.json",
                 "tuning_imm_smoother_kim.json"):
        if (out_dir / name).exists():
            md += _render_imm_smoother(json.loads((out_dir / name).read_text()))
    for name in ("tuning_refine.json", "tuning_refine_grid.json"):
        if (out_dir / name).exists():
            md += _render_refine(json.loads((out_dir / name).read_text()))
    return "\n".join(md)


def _render_imm_smoother(r: dict) -> list[str]:
    """The best grid points per profile and the common one (the product's defaults)."""
    profiles = list(r["profiles"])
    pts = r["points"]
    grid = "; ".join(f"{k} {list(v)}" for k, v in r["grid"].items())
    fine = (" --fine" if r.get("fine") else "") + (" --kim" if r.get("kim") else "")
    how = " with Kim's backward mode weights" if r.get("kim") else ""
    md = [f"IMM smoother (`python -m benchmarks.tune imm_smoother{fine}`): {len(pts)} points of "
          f"{grid}{how}; "
          f"the six ADS-B tracks, seeds {r['seeds']}. RMS position error (m), RMS speed "
          "error (m/s), 95 % ellipse coverage. Rows: the best point of each profile and the "
          "point with the lowest mean RMS relative to each profile's best. The choices over the "
          "stages (per profile: `baselines.TUNED`, estimators `imm-smoother`, "
          "`imm-smoother-kim`; common: the defaults of `solver.estimation.imm_smoother`) are in "
          "the tuning notes." + (f" Note: {r['note']}." if r.get("note") else ""), "",
          "| point (q_cv/q_ct/omega_deg/tau_cv/tau_ct) | chosen for | " + " | ".join(profiles)
          + " | mean RMS / best |", "|---|---|" + "---|" * len(profiles) + "---:|"]
    chosen: dict[int, list[str]] = {}
    for p in profiles:
        chosen.setdefault(pts.index(r["profiles"][p]["best"]), []).append(p)
    chosen.setdefault(pts.index(r["common"]), []).append("defaults")
    for i, why in chosen.items():
        cells = []
        for p in profiles:
            m = r["profiles"][p]["rows"][i]
            cells.append(f"{m['rms_pos']:.1f} m, {m['rms_speed']:.2f} m/s, "
                         f"{100 * m['coverage95']:.0f} %")
        label = "/".join(f"{v:g}" for v in pts[i].values())
        md.append(f"| {label} | {', '.join(why)} | " + " | ".join(cells)
                  + f" | {r['mean_relative_rms'][i]:.3f} |")
    md.append("")
    return md


def _render_refine(r: dict) -> list[str]:
    cols = [k for k in r["rows"][0] if k != "settings"]
    how = (f"the grid {r['axes']}, with the other penalties at" if r.get("grid") else
           "one at a time around")
    md = [f"Refinement penalties (`python -m benchmarks.tune refine"
          f"{' --grid' if r.get('grid') else ''}`): {how} {r['default']}; the six ADS-B tracks"
          + (f" cut to {r['t_max']:.0f} s" if r["t_max"] else "")
          + f", seeds {r['seeds']}. RMS position error (m) and 95 % ellipse coverage; `+alt`: "
          "the plots carry the true altitude.", "",
          "| changed | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for row in r["rows"]:
        changed = ", ".join(f"{k}={v}" for k, v in row["settings"].items()) or "(default)"
        cells = ["failed" if row[c] is None else
                 f"{row[c]['rms_pos']:.1f} ({100 * row[c]['coverage95']:.1f} %)" for c in cols]
        md.append(f"| {changed} | " + " | ".join(cells) + " |")
    if r["failures"]:
        md += ["", f"{len(r['failures'])} failed runs."]
    md.append("")
    return md


def _render_recon(r: dict) -> list[str]:
    profiles = [k for k in r["rows"][0] if k != "settings"]
    md = [f"Reconstruction (`python -m benchmarks.tune recon --method {r['method']}`): one "
          f"factor at a time around {r['default']}; the six ADS-B tracks"
           + (f" cut to {r['t_max']:.0f} s" if r["t_max"] else "")
           + f", seeds {r['seeds']}. RMS position error (m) [manoeuvres] and plots/s.", "",
           "| changed | " + " | ".join(profiles) + " |", "|---|" + "---|" * len(profiles)]
    for row in r["rows"]:
        changed = [f"{k}={v}" for k, v in row["settings"].items()
                   if r["default"].get(k) != v]
        cells = []
        for p in profiles:
            m = row[p]
            cells.append("failed" if m is None else
                         f"{m['rms_pos']:.0f} [{m['rms_pos_man']:.0f}], "
                         f"{m['plots_per_s']:.0f}/s")
        md.append(f"| {', '.join(changed) or '(default)'} | " + " | ".join(cells) + " |")
    if r["failures"]:
        md += ["", f"{len(r['failures'])} failed runs: "
               + "; ".join(sorted({f['estimator'] + ': ' + f['error'].splitlines()[-1]
                                   for f in r['failures']}))[:1500]]
    md.append("")
    return md


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.tune", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("part", choices=("baselines", "recon", "refine", "imm_smoother", "render"))
    ap.add_argument("--profiles", nargs="+", default=["seed000", "seed001", "ssr"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[100, 101])
    ap.add_argument("--t-max", type=float, default=None)
    ap.add_argument("--method", choices=("sliding", "refined"), default="refined")
    ap.add_argument("--only-init", action="store_true",
                    help="recon: only the default and the refinement's start variants")
    ap.add_argument("--grid", action="store_true",
                    help="refine: the grid REFINE_GRID instead of one factor at a time")
    ap.add_argument("--fine", action="store_true",
                    help="imm_smoother: the second-stage grid IMM_SMOOTHER_FINE")
    ap.add_argument("--kim", action="store_true",
                    help="imm_smoother: with Kim's backward mode weights (future_modes=False)")
    ap.add_argument("--out", type=Path, default=RESULTS_DIR)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.part == "baselines":
        data = tune_baselines(args.profiles, args.seeds)
        (args.out / "tuning_baselines.json").write_text(json.dumps(data, indent=1))
        for p, d in data["profiles"].items():
            b = d["best"]
            print(f'    "{p}": Tuning(q_kf={b["q_kf"]:g}, q_rts={b["q_rts"]:g}, '
                  f'imm={replace(ImmTuning(), **b["imm"])!r}),')
    elif args.part == "recon":
        data = tune_recon(args.profiles, args.seeds, args.t_max, args.method, args.only_init)
        path = args.out / f"tuning_recon_{args.method}.json"
        if args.only_init and path.exists():  # merge into the full table
            old = json.loads(path.read_text())
            known = [r["settings"] for r in old["rows"]]
            old["rows"] += [r for r in data["rows"] if r["settings"] not in known]
            old["failures"] += data["failures"]
            data = old
        path.write_text(json.dumps(data, indent=1))
    elif args.part == "imm_smoother":
        data = tune_imm_smoother(args.profiles, args.seeds, args.fine, args.kim)
        name = ("tuning_imm_smoother_kim.json" if args.kim else
                "tuning_imm_smoother_fine.json" if args.fine else "tuning_imm_smoother.json")
        (args.out / name).write_text(json.dumps(data, indent=1))
        for p, d in data["profiles"].items():
            print(f'    "{p}": {d["best"]},')
        print("defaults:", data["common"])
    elif args.part == "refine":
        data = tune_refine(args.profiles, args.seeds, args.t_max, args.grid)
        name = "tuning_refine_grid.json" if args.grid else "tuning_refine.json"
        (args.out / name).write_text(json.dumps(data, indent=1))
    (args.out / "tuning.md").write_text(render(args.out))
    print(render(args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
