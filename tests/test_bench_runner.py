"""A tiny end-to-end benchmark run: simulation, estimators, failure recording, report files."""

from __future__ import annotations

import json

import numpy as np

from benchmarks import run as bench_run
from benchmarks.estimators import Estimator, select
from benchmarks.report import best_baselines, write_outputs


def _broken(plots, radar, profile):
    raise RuntimeError("solver exploded")


def _offset(plots, radar, profile):
    """Raw plots shifted 1 km north: a known, large error."""
    est = select(["raw"])[0].run(plots, radar, profile)
    est.states.x = est.states.x + 1000.0
    return est


def test_tiny_run_writes_report_json_and_records_failures(tmp_path):
    ests = [*select(["raw", "ss-cv-rts"]),
            Estimator("broken", "recon", _broken),
            Estimator("offset", "filter", _offset)]
    truths = ["calibration__vienna"]
    res = bench_run.run_benchmark(truths, ["ssr"], [0, 1], ests, t_max=240.0,
                                  figure_cases=(("calibration__vienna", "ssr"),),
                                  progress=False)
    assert [f.estimator for f in res.failures] == ["broken", "broken"]
    assert "solver exploded" in res.failures[0].error
    runs = res.errors[("ssr", "calibration__vienna", "offset")]
    assert len(runs) == 2
    # a 1 km northward shift of the plot points: error |(1000, 0) + plot error| ~ 1000 m
    assert np.all(np.abs(runs[0].pos - 1000.0) < 300.0)
    overall, _ = bench_run.summaries(res)
    assert overall["ssr"]["ss-cv-rts"]["rms_pos"] < overall["ssr"]["raw"]["rms_pos"]
    assert best_baselines(overall)["ssr"][0] == "ss-cv-rts"
    assert overall["ssr"]["ss-cv-rts"]["n_runs"] == 2

    settings = {"command": "python -m benchmarks.run (test)", "profiles": ["ssr"],
                "truths": truths, "seeds": [0, 1], "estimators": [e.name for e in ests],
                "t_max": 240.0, "quick": False}
    env = {k: "x" for k in ("python", "machine", "cpus", "numpy", "casadi", "stonesoup",
                            "filterpy", "commit", "date_utc")}
    report = write_outputs(res, settings, env, tmp_path, figures=True)
    text = report.read_text()
    assert "| ss-cv-rts |" in text and "solver exploded" in text
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["best_baseline"]["ssr"]["name"] == "ss-cv-rts"
    assert data["overall"]["ssr"]["offset"]["rms_pos"] > 900
    assert len(data["failures"]) == 2
    pngs = sorted(p.name for p in (tmp_path / "figures").glob("*.png"))
    assert pngs == ["controls_vienna_ssr.png", "errors_vienna_ssr.png", "summary.png",
                    "trajectory_vienna_ssr.png"]


def test_same_plots_for_every_estimator_of_a_run(monkeypatch):
    seen = []

    def spy(plots, radar, profile):
        seen.append(plots.range_m.copy())
        return select(["raw"])[0].run(plots, radar, profile)

    ests = [Estimator("a", "baseline", spy), Estimator("b", "baseline", spy)]
    bench_run.run_benchmark(["calibration__bornholm"], ["seed001"], [5], ests, t_max=200.0,
                            figure_cases=(), progress=False)
    # warm-up calls (2) on their own track, then the timed calls (2) on the same plots
    assert len(seen) == 4
    np.testing.assert_array_equal(seen[2], seen[3])


def test_cli_quick_arguments_parse():
    args = bench_run.parse_args(["--quick", "--profiles", "ssr", "--estimators", "ss-*"])
    assert args.quick and args.profiles == ["ssr"] and args.estimators == ["ss-*"]
    names = [e.name for e in select(["ss-*"])]
    assert names == ["ss-cv-kf", "ss-cv-rts", "ss-cv-rts+alt"]


def test_speed_stage_interleaves_and_keeps_the_least_cpu_time(tmp_path):
    """The speed stage times the compared smoothers on every track and seed, each repetition
    in a rotated order, and keeps each (track, estimator)'s least CPU time."""
    calls: list[str] = []

    def spy(name):
        def fn(plots, radar, profile):
            calls.append(name)
            return select(["raw"])[0].run(plots, radar, profile)
        return fn

    ests = [Estimator(n, "baseline", spy(n)) for n in bench_run.SPEED_ESTIMATORS]
    truths = ["calibration__vienna", "calibration__bornholm"]
    res = bench_run.run_benchmark(truths, ["ssr"], [4, 5], ests, t_max=200.0, figure_cases=(),
                                  progress=False, speed_reps=3)
    timed = calls[len(ests) * (1 + len(truths) * 2):]  # after the warm-up and accuracy loop
    assert len(timed) == 3 * len(truths) * 2 * len(ests)
    firsts = [timed[k * len(ests)] for k in range(3 * len(truths) * 2)]
    assert len(set(firsts)) == len(ests)  # every estimator goes first somewhere
    plots = sum(len(bench_run._simulate_pair(t, bench_run.PROFILES["ssr"], seed, False,
                                             200.0)[0].plots) for t in truths for seed in (4, 5))
    for n in bench_run.SPEED_ESTIMATORS:
        s = res.speed[("ssr", n)]
        assert s["plots"] == plots and len(s["rep_cpu_s"]) == 3
        assert s["cpu_s"] <= min(s["rep_cpu_s"]) + 1e-12
        assert s["plots_per_cpu_s"] == plots / s["cpu_s"]
    settings = {"command": "test", "profiles": ["ssr"], "truths": truths, "seeds": [4, 5],
                "estimators": list(bench_run.SPEED_ESTIMATORS), "t_max": 200.0,
                "quick": False, "speed_reps": 3}
    env = {k: "x" for k in ("python", "machine", "cpus", "numpy", "casadi", "stonesoup",
                            "filterpy", "commit", "date_utc")}
    text = write_outputs(res, settings, env, tmp_path, figures=False).read_text()
    assert "on each track and seed over 3 interleaved repetitions" in text
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["speed_reps"] == 3 and "ssr/imm-smoother" in data["speed"]
