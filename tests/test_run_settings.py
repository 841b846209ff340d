"""A command-line run's settings beside its outputs (``run.json``): parsed from ``--bounds``,
kept on the first run, the same settings resume, others are refused naming what differs."""

from __future__ import annotations

import json

import pytest

from solver.inputs import Bounds, InputError
from solver.run_settings import RUN_FILE, RunSettings, keep, parse_bounds, stored


def test_bounds_parse_to_the_model_bounds_and_bad_ones_name_the_field():
    assert parse_bounds([]) == Bounds()
    got = parse_bounds(["v=15,250", "u=-10,10"])
    assert got == Bounds(u=(-10.0, 10.0), v=(15.0, 250.0))
    for items, where in ((["x=1,2"], "bounds "), (["v=15"], "bounds.v "),
                         (["v=a,b"], "bounds.v "), (["w=1,3"], "bounds.w must contain 0"),
                         (["v=250,15"], "bounds.v is inverted"),
                         (["v=nan,300"], "bounds.v must be finite")):
        with pytest.raises(InputError) as e:
            parse_bounds(items)
        assert str(e.value).startswith(where), (items, str(e.value))


def test_a_run_keeps_its_settings_and_resumes_only_the_same(tmp_path):
    first = RunSettings("refined", Bounds(v=(15.0, 250.0)), ("cv_rts", "singer"))
    assert stored(tmp_path) is None
    keep(tmp_path, first)
    assert stored(tmp_path) == first
    assert json.loads((tmp_path / RUN_FILE).read_text())["bounds"]["v"] == [15.0, 250.0]
    keep(tmp_path, RunSettings("refined", Bounds(v=(15.0, 250.0)), ("singer", "cv_rts")))
    # no track finished yet: nothing to resume, other settings take the place of these
    keep(tmp_path / "unfinished", first)
    keep(tmp_path / "unfinished", RunSettings("sliding"))
    assert stored(tmp_path / "unfinished") == RunSettings("sliding")
    (tmp_path / "progress.jsonl").write_text(json.dumps({"aircraft": "A"}) + "\n")  # one
    for other, named in ((RunSettings("sliding", first.bounds, first.filters), "method"),
                         (RunSettings("refined", Bounds(), first.filters), "bounds"),
                         (RunSettings("refined", first.bounds, ("cv_rts",)), "filters"),
                         (RunSettings("refined", first.bounds, first.filters, 2.0),
                          "sample_step_s"),
                         (RunSettings("refined", first.bounds, first.filters, window_plots=4),
                          "window"),
                         (RunSettings("refined", first.bounds, first.filters, criterion="R1"),
                          "criterion"),
                         (RunSettings("refined", first.bounds, first.filters,
                                      filter_gate_sigma=None), "filter_gate_sigma")):
        with pytest.raises(InputError) as e:
            keep(tmp_path, other)
        assert f"holds a run made with {named} " in str(e.value)
    assert stored(tmp_path) == first  # the refused run changed nothing
    sampled = RunSettings(sample_step_s=2.0)
    keep(tmp_path / "sampled", sampled)
    assert stored(tmp_path / "sampled") == sampled
    assert sampled.config().sample_step_s == 2.0
    windows = RunSettings("sliding", window_plots=5, trial_step_s=2.5, criterion="R1")
    keep(tmp_path / "windows", windows)
    assert stored(tmp_path / "windows") == windows
    config = windows.config()
    assert (config.window_plots, config.trial_step_s, config.criterion) == (5, 2.5, "R1")
    # a run.json written before the sample step and the windows were kept: a run without
    # samples, with the default windows
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / RUN_FILE).write_text(json.dumps(
        {"method": "refined", "filters": [], "bounds": {"v": [30.0, 330.0]}}))
    assert stored(tmp_path / "old") == RunSettings()
    keep(tmp_path / "old", RunSettings())
    ungated = RunSettings(filter_gate_sigma=None)
    keep(tmp_path / "ungated", ungated)
    assert stored(tmp_path / "ungated") == ungated
    assert json.loads((tmp_path / "ungated" / RUN_FILE).read_text())["filter_gate_sigma"] is None
    for bad in (0.0, -1.0, float("inf"), float("nan"), True, "6"):
        with pytest.raises(InputError) as e:
            RunSettings(filter_gate_sigma=bad)  # type: ignore[arg-type]
        assert e.value.loc == ("filter_gate_sigma",)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / RUN_FILE).write_text(json.dumps({"filter_gate_sigma": -1}))
    with pytest.raises(InputError, match="is not a run's settings"):
        stored(tmp_path / "bad")
    (tmp_path / RUN_FILE).write_text("[1, 2]")
    with pytest.raises(InputError, match="is not a run's settings"):
        stored(tmp_path)
